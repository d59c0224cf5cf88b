#!/usr/bin/env bash
# A two-node Ray cluster on this machine, loopback only, with token authentication:
#   scripts/ray_local_cluster.sh [WORK_DIR]     (a new directory; default: a mktemp one)
# Starts a head and a second node (one CPU each), checks that every listening
# socket is on 127.0.0.1 and that a wrong token is refused, runs a two-trial
# sweep (tiny budget) across them, kills the driver mid-run, resumes it to the
# end, and stops the cluster. The cluster commands are the docs' (training page, "Sweeps on
# a Ray cluster"), with HEAD = NODE = 127.0.0.1. Exits non-zero on any failure.
#
# Why namespaces: on Linux, `ray start` replaces 127.0.0.1 (in --node-ip-address
# and --address) by the address of the interface with the default route, and
# then listens on all interfaces (Ray 2.60, ray/_private/services.py:
# resolve_ip_for_localhost); there is no option to keep it. In a network
# namespace holding only `lo` that address is 127.0.0.1, so Ray binds loopback
# and no traffic can leave. The PID namespace makes `ray stop` see only this
# cluster (it stops every Ray process it can see) and kills whatever is left
# when the script ends, even on failure; the mount namespace gives a private
# /etc/hosts (Ray falls back to the host name when no route exists) and
# /tmp/ray (Ray's default temp dir), kept under WORK_DIR for the logs.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"

if [[ -z "${ZEUS_RAY_NAMESPACED:-}" ]]; then
  userns=(); [[ $(id -u) -eq 0 ]] || userns=(--map-root-user)
  ns=(unshare "${userns[@]}" --net --pid --mount-proc --fork --kill-child)
  if ! "${ns[@]}" true 2>/dev/null; then
    echo "ray_local_cluster: needs network, PID and mount namespaces (unshare ${ns[*]:1})" >&2
    exit 2
  fi
  if [[ -n "${1:-}" ]]; then mkdir -p "$1" && work="$(cd "$1" && pwd)"
  else work="$(mktemp -d /tmp/zeus_ray_cluster.XXXXXX)"; fi
  if [[ -n "$(ls -A "$work")" ]]; then
    echo "ray_local_cluster: $work is not empty (give a new directory)" >&2
    exit 2
  fi
  ZEUS_RAY_NAMESPACED=1 exec nice -n 10 "${ns[@]}" bash "$0" "$work"
fi

work="$1"
log() { echo "[ray_local_cluster $(date +%T)] $*"; }
fail() { echo "ray_local_cluster: FAILED: $*" >&2; exit 1; }
ip link set lo up
printf '127.0.0.1 localhost %s\n::1 localhost\n' "$(hostname)" >"$work/hosts"
mount --bind "$work/hosts" /etc/hosts
mkdir -p "$work/ray_tmp" /tmp/ray && mount --bind "$work/ray_tmp" /tmp/ray
cd "$repo"
source scripts/ros_env.sh && source "$ZEUS_VENV/bin/activate"
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
trap 'ray stop --force >/dev/null 2>&1 || true' EXIT   # only this namespace's Ray

HEAD=127.0.0.1 NODE=127.0.0.1 CPUS=1 TOKEN=$work/ray_token SWEEP=$work/cluster_smoke.yaml
steps=240
cat >"$SWEEP" <<EOF
# Two trials, one CPU each: one on the head, one on the second node.
name: cluster_smoke
storage: $work/sweeps
families: [finger-spin-v0]
methods: [sac]
seeds: [1, 2]
steps: $steps
max_concurrent: 2
train: {eval_every: 120, eval_max_steps: 20, checkpoint_every: 20, log_every: 10}
overrides: {hidden_dim: 32, batch_size_per_task: 4, replay_capacity: 3000, init_steps: 40,
            episode_steps: 60, context_length: 5}
EOF
runs="$work/sweeps/cluster_smoke/runs"

# Every listening socket in this namespace (Ray's only) is on loopback, the GCS among them.
assert_loopback_only() {
  local sockets; sockets="$(ss -Hltun)"
  grep -Eq '(127\.0\.0\.1|\[::ffff:127\.0\.0\.1\]):6380 ' <<<"$sockets" || fail "no GCS on 127.0.0.1:6380"
  local outside; outside="$(awk '{a=$5; sub(/:[^:]*$/, "", a)}
    a != "127.0.0.1" && a != "[::ffff:127.0.0.1]" && a != "[::1]"' <<<"$sockets")"
  [[ -z "$outside" ]] || fail "listening beyond loopback ($1):"$'\n'"$outside"
  log "listening on loopback only ($1): $(wc -l <<<"$sockets") sockets"
}
timestep() {   # the run's checkpointed timestep, 0 before its first checkpoint
  python -c 'import json, sys; print(json.load(open(sys.argv[1]))["steps"]["timestep"])' \
    "$runs/finger-spin-v0.sac.s$1/checkpoint/metadata.json" 2>/dev/null || echo 0
}
wait_for() {   # $1 seconds, $2 what, then a command that succeeds when it is done
  local deadline=$((SECONDS + $1)) what="$2"; shift 2
  until "$@"; do ((SECONDS < deadline)) || fail "timed out waiting for $what"; sleep 1; done
}
cluster_cpus_free() { ray status --address=$HEAD:6380 2>/dev/null | grep -q ' 0.0/2.0 CPU'; }
two_nodes_up() { [[ $(ray status --address=$HEAD:6380 2>/dev/null | grep -c ' node_') -eq 2 ]]; }
both_checkpointed() { [[ -f $runs/finger-spin-v0.sac.s1/checkpoint/metadata.json &&
                        -f $runs/finger-spin-v0.sac.s2/checkpoint/metadata.json ]]; }

log "cluster in $work"
# --- the docs' cluster commands (HEAD = NODE = 127.0.0.1) ---
export RAY_AUTH_MODE=token RAY_AUTH_TOKEN_PATH=$TOKEN RAY_USAGE_STATS_ENABLED=0
(umask 077 && python -c 'import secrets; print(secrets.token_hex(32))' > "$RAY_AUTH_TOKEN_PATH")
ray start --head --node-ip-address=$HEAD --port=6380 --num-cpus=$CPUS --include-dashboard=false
ray start --address=$HEAD:6380 --node-ip-address=$NODE --num-cpus=$CPUS
wait_for 60 "the second node" two_nodes_up
assert_loopback_only "two nodes"
refused() {   # the command fails, and for want of the right token
  local out; if out="$(timeout 90 "$@" 2>&1)"; then return 1; fi
  grep -q InvalidAuthToken <<<"$out"
}
refused env RAY_AUTH_TOKEN=0000 ray status --address=$HEAD:6380 \
  || fail "a client with a wrong token was not refused"
refused env -u RAY_AUTH_MODE -u RAY_AUTH_TOKEN_PATH HOME="$work" \
  ray start --address=$HEAD:6380 --node-ip-address=$NODE --num-cpus=$CPUS \
  || fail "a node without the token was not refused"
log "a client with a wrong token and a node without one are refused (InvalidAuthToken)"

python -m zeus_ros.learning_tools.sweep run $SWEEP --address $HEAD:6380 >"$work/driver_killed.log" 2>&1 &
driver=$!
wait_for 600 "both trials' first checkpoint" both_checkpointed
assert_loopback_only "sweep running"
kill -KILL $driver && wait $driver || true
t1=$(timestep 1) t2=$(timestep 2)
((t1 < steps && t2 < steps)) || fail "the trials finished before the driver was killed"
log "driver killed mid-run (checkpoints at timestep $t1 and $t2 of $steps)"
wait_for 120 "the killed driver's trials to end" cluster_cpus_free

python -m zeus_ros.learning_tools.sweep run $SWEEP --address $HEAD:6380 --resume >"$work/driver_resumed.log" 2>&1 \
  || fail "the resumed sweep exited $? (log: $work/driver_resumed.log)"
(( $(timestep 1) == steps && $(timestep 2) == steps )) || fail "resumed runs did not reach $steps"
log "resumed sweep finished both trials at timestep $steps"
nodes="$(python -c 'import json, pathlib, sys
print(len({json.loads(line).get("node") for f in pathlib.Path(sys.argv[1]).glob("*/result.json")
           for line in open(f) if line.strip()}))' "$work/sweeps/cluster_smoke/tune")"
[[ "$nodes" == 2 ]] || fail "the trials reported $nodes node(s), not the cluster's 2"
log "the trials trained on both nodes"
ray stop
# --- end of the docs' commands ---
left="$(ps -eo pid=,args= | grep -E '[r]aylet|[g]cs_server|[r]ay::|[s]ite-packages/ray|[z]eus_ros\.sweep' || true)"
[[ -z "$left" ]] || fail "Ray processes left after ray stop:"$'\n'"$left"
log "cluster stopped, no Ray process left; results in $work/sweeps/cluster_smoke"
