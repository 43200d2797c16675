#!/usr/bin/env bash
# The cost of an axis (issue 25): the default realtime stack of 1, 2, 4 and 8 axes (each the
# paper's motor running the scenario's trajectory), one run of each, the proposed method.
# Prints one row per axis count: deadline misses (all, and outside the host's holds of the
# current loop's CPU), sensor-to-actuator p99, each loop's compute per cycle, and the CPU
# time the stack used per second of run; writes the runs' JSON and the table to OUT.
#
#   scripts/scale-axes.sh [SECONDS] [OUT] [AXIS COUNTS]      # defaults: 60 /tmp/scale-axes "1 2 4 8"
#
# A measurement, not a test: run it on an otherwise idle machine, nothing compiling.
set -euo pipefail
seconds="${1:-60}"
out="${2:-/tmp/scale-axes}"
counts="${3:-1 2 4 8}"
exe="${STEPDRIVE_EXE:-$(dirname "$0")/../target/release/stepdrive}"
mkdir -p "$out"
for n in $counts; do
  scenario="$out/axes-$n.toml"
  echo "name = \"axes-$n\"" > "$scenario"
  # One axis: the plain file (today's path); more: one [[axis]] table each.
  if [ "$n" -gt 1 ]; then
    for ((i = 0; i < n; i++)); do printf '[[axis]]\nname = "a%d"\n' "$i" >> "$scenario"; done
  fi
  python3 - "$exe" "$scenario" "$seconds" "$out/axes-$n.json" <<'PY'
import resource, subprocess, sys, time
exe, scenario, seconds, json_out = sys.argv[1:]
t0 = time.monotonic()
rc = subprocess.run([exe, "run", "--mode", "realtime", "--method", "proposed",
                     "--scenario", scenario, "--duration", seconds, "--json", json_out],
                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
wall = time.monotonic() - t0
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
open(json_out + ".cpu", "w").write(f"{rc} {wall} {ru.ru_utime + ru.ru_stime}\n")
PY
done
python3 - "$out" "$counts" <<'PY' | tee "$out/table.md"
import json, sys
out, counts = sys.argv[1], sys.argv[2].split()
print("| axes | exit | misses | outside host holds | s→a p99 µs | current loop compute p50/p99 µs (per axis p50) | plant compute p50/p99 µs | position loop compute p50/p99 µs | CPU s per s |")
print("|---|---|---|---|---|---|---|---|---|")
for n in counts:
    rc, wall, cpu = open(f"{out}/axes-{n}.json.cpu").read().split()
    try:
        d = json.load(open(f"{out}/axes-{n}.json"))
    except (OSError, ValueError):
        print(f"| {n} | {rc} | no JSON | | | | | | |")
        continue
    t = d["runs"][0]["timing"]
    h = t.get("host_holds") or {}
    c, p, q = t["current_loop"]["compute"], t["plant"]["compute"], t["position_loop"]["compute"]
    # A current-loop cycle serves the axes whose states are in; its compute per axis is
    # its compute time over the axes it stepped on average.
    per_cycle = int(n) * t["plant"]["cycles"] / max(t["current_loop"]["cycles"], 1)
    sim = d["runs"][0]["sim_time_s"]
    print(f"| {n} | {rc} | {t['deadline_miss_pct']:.3f} % | {h.get('deadline_miss_pct_outside_holds', float('nan')):.3f} % "
          f"| {t['sensor_to_actuator']['p99_us']:.1f} | {c['p50_us']:.1f} / {c['p99_us']:.1f} ({c['p50_us'] / per_cycle:.2f}) "
          f"| {p['p50_us']:.1f} / {p['p99_us']:.1f} | {q['p50_us']:.1f} / {q['p99_us']:.1f} | {float(cpu) / max(sim, 1e-9):.2f} |")
PY
