#!/usr/bin/env bash
# Lockstep throughput on an idle and on a busy machine, in one run: the default scenario
# (2.5 s simulated, one method) as three processes, N times with 0, 1, 2 ... CPU hogs
# (`yes > /dev/null`, one per count) beside it, then the in-process simulation (the
# ceiling: same laws, no processes, no IPC). Prints the median wall time and real-time
# factor of each, with every run's figure.
#
#   scripts/bench-lockstep.sh [RUNS (5)] [HOG COUNTS ("0 2")]
#   STEPDRIVE_EXE=/other/build/stepdrive scripts/bench-lockstep.sh   (an A/B against a build)
#   RUN_ARGS="--nice 0" scripts/bench-lockstep.sh                     (options for every run)
set -euo pipefail
cd "$(dirname "$0")/.."
runs=${1:-5}
hog_counts=${2:-"0 2"}
exe=${STEPDRIVE_EXE:-}
read -ra run_args <<<"${RUN_ARGS:-}"
if [ -z "$exe" ]; then
  cargo build --release -q
  exe=target/release/stepdrive
fi
tmp=$(mktemp -d)
hogs=()
stop_hogs() {
  for p in "${hogs[@]}"; do kill "$p" 2>/dev/null || true; done
  hogs=()
}
trap 'stop_hogs; rm -rf "$tmp"' EXIT

# Prints "label median-wall factor runs..." from the wall times in $tmp/walls.
summarize() {
  python3 - "$1" "$tmp/walls" <<'PY'
import statistics, sys
label, path = sys.argv[1], sys.argv[2]
w = [float(x) for x in open(path).read().split()]
m = statistics.median(w)
print(f"| {label:<22} | {m:8.3f} s | {2.5 / m:6.1f}x | {' '.join(f'{x:.3f}' for x in w)} |")
PY
}

wall_of() {
  python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['runs'][0]['wall_time_s'])" "$1"
}

echo "| lockstep, default scenario, proposed | median wall | real-time factor | runs |"
echo "|---|---|---|---|"
for n in $hog_counts; do
  for _ in $(seq 1 "$n"); do
    yes >/dev/null &
    hogs+=($!)
  done
  : >"$tmp/walls"
  for i in $(seq 1 "$runs"); do
    if ! "$exe" run --method proposed "${run_args[@]}" --instance "bench-lockstep-$$" --json "$tmp/run.json" >/dev/null 2>&1; then
      echo "run $i with $n hog(s) failed" >&2
      exit 1
    fi
    wall_of "$tmp/run.json" >>"$tmp/walls"
  done
  stop_hogs
  summarize "run, $n CPU hog(s)"
done
: >"$tmp/walls"
for i in $(seq 1 "$runs"); do
  "$exe" simulate --method proposed --json "$tmp/sim.json" >/dev/null 2>&1
  wall_of "$tmp/sim.json" >>"$tmp/walls"
done
summarize "simulate (in-process)"
