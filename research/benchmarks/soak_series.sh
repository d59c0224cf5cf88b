#!/usr/bin/env bash
# Consecutive soaks (issue #39: the goals must hold in 10 consecutive 10-minute
# runs beside two trainings). Each run is research/benchmarks/soak.py with its
# own ROS domain; its JSON and printed report land in OUT_DIR, with the load
# and the trainings running beside it. Stops at the first run that misses a
# goal only with --stop-on-fail; otherwise runs them all and the summary
# (soak_summary.py) counts the consecutive passes.
#   bash research/benchmarks/soak_series.sh RUNS MINUTES OUT_DIR [--stop-on-fail]
set -uo pipefail
runs="$1"; minutes="$2"; out="$3"; stop="${4:-}"
cd "$(dirname "$0")/../.."
# colcon's setup scripts read unset variables (COLCON_TRACE): source them without -u.
set +u
source scripts/ros_env.sh && source "$ZEUS_VENV/bin/activate" && source install/setup.bash
set -u
mkdir -p "$out"
for i in $(seq 1 "$runs"); do
  # Outside 20-99, the pool the tests and demos claim theirs from; the soak
  # itself refuses a domain that already carries a loop.
  export ROS_DOMAIN_ID=$((110 + i % 10))
  {
    echo "run $i of $runs, $(date -u +%FT%TZ), ROS_DOMAIN_ID $ROS_DOMAIN_ID"
    echo "load before: $(cut -d' ' -f1-3 /proc/loadavg)"
    echo "trainings beside it: $(pgrep -fc 'zeus_ros.*train --out' || true)"
  } >"$out/run_$i.txt"
  python research/benchmarks/soak.py --minutes "$minutes" --json "$out/run_$i.json" \
    >>"$out/run_$i.txt" 2>&1 </dev/null
  rc=$?
  # Counted again at the end: a lane that was writing a report at the start
  # may have begun its next training during the run.
  {
    echo "exit $rc; load after: $(cut -d' ' -f1-3 /proc/loadavg)"
    echo "trainings beside it at the end: $(pgrep -fc 'zeus_ros.*train --out' || true)"
  } >>"$out/run_$i.txt"
  echo "[$(date +%T)] soak run $i: exit $rc"
  [[ $rc -ne 0 && "$stop" == --stop-on-fail ]] && exit "$rc"
done
exit 0
