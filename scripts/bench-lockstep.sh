#!/usr/bin/env bash
# Lockstep throughput: runs the default scenario N times (three processes each) and reports
# the wall time of the simulated 2.5 s and the real-time factor per run, then the median.
set -euo pipefail
cd "$(dirname "$0")/.."
n=${1:-10}
cargo build --release -q
exe=target/release/stepdrive
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
for i in $(seq 1 "$n"); do
  "$exe" run --method proposed,lyapunov --json "$tmp/$i.json" >/dev/null 2>&1
  python3 - "$tmp/$i.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
print(" ".join(f"{r['method']}: {r['wall_time_s']:.3f} s ({r['sim_time_s']/r['wall_time_s']:.1f}x)" for r in d["runs"]))
PY
done | tee "$tmp/all"
python3 - "$tmp" "$n" <<'PY'
import json, sys, statistics
tmp, n = sys.argv[1], int(sys.argv[2])
walls = {}
for i in range(1, n + 1):
    for r in json.load(open(f"{tmp}/{i}.json"))["runs"]:
        walls.setdefault(r["method"], []).append(r["wall_time_s"])
for m, w in walls.items():
    med = statistics.median(w)
    print(f"{m}: median {med:.3f} s for 2.5 s simulated = {2.5/med:.1f}x real time (min {min(w):.3f}, max {max(w):.3f})")
PY
