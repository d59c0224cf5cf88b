#!/usr/bin/env bash
# Run training jobs one after another, resuming any that has a checkpoint.
#   scripts/run_queue.sh RUNS_DIR JOBS_FILE [--report]
# JOBS_FILE: one job a line, "<run name> <zeus_ros.learning_tools.train arguments...>" (no --out,
# no --resume: the queue adds them). Start two queues (two lanes) for two cores;
# each job trains with one torch thread. A job whose run directory holds
# DONE is skipped, so a killed queue restarted with the same file picks up
# where it stopped, losing at most one checkpoint interval. With --report, each
# finished run also gets its adaptation report (adaptation.json and .txt, 2
# episodes per value, as the committed results) before the next job starts.
set -uo pipefail
runs="$1"; jobs="$2"; report="${3:-}"
cd "$(dirname "$0")/.."
source scripts/ros_env.sh && source "$ZEUS_VENV/bin/activate"
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
report_run() {   # $1 name, $2 run directory
  [[ "$report" == --report && ! -f "$2/adaptation.json" ]] || return 0
  python -m zeus_ros.learning_tools.adaptation --weights "$2" --episodes 2 --json "$2/adaptation.json" \
    >"$2/adaptation.txt" 2>&1 </dev/null
  echo "[$(date +%T)] $1: report exit $?" | tee -a "$runs/queue.log"
}
while read -r name args; do
  [[ -z "$name" || "$name" == \#* ]] && continue
  out="$runs/$name"
  if [[ -f "$out/DONE" ]]; then report_run "$name" "$out"; continue; fi
  resume=(); [[ -f "$out/checkpoint/metadata.json" ]] && resume=(--resume)
  mkdir -p "$out"
  echo "[$(date +%T)] $name: $args ${resume[*]}" | tee -a "$runs/queue.log"
  # shellcheck disable=SC2086
  python -m zeus_ros.learning_tools.train --out "$out" $args "${resume[@]}" --quiet --set num_threads=1 \
    >>"$out/stdout.log" 2>&1 </dev/null
  rc=$?
  echo "[$(date +%T)] $name: exit $rc" | tee -a "$runs/queue.log"
  [[ $rc -eq 0 ]] && touch "$out/DONE" && report_run "$name" "$out"
  [[ $rc -eq 130 ]] && exit 130   # interrupted: stop the lane, resume later
done < "$jobs"
