#!/usr/bin/env bash
# The cost of an axis (issue 25): the default realtime stack of 1, 2, 4 and 8 axes (each the
# paper's motor running the scenario's trajectory), one run of each, the proposed method.
# Prints one row per axis count: deadline misses (all, and outside the host's holds of the
# current loop's CPU), sensor-to-actuator p99, each loop's compute per cycle, and the CPU
# time the stack used per second of run; writes the runs' JSON and the table to OUT.
#
#   scripts/scale-axes.sh [SECONDS] [OUT] [AXIS COUNTS]      # defaults: 60 /tmp/scale-axes "1 2 4 8"
#   TABLE_ONLY=1 scripts/scale-axes.sh 60 OUT                 # the table and figure of OUT's runs again
#
# A measurement, not a test: run it on an otherwise idle machine, nothing compiling.
set -euo pipefail
seconds="${1:-60}"
out="${2:-/tmp/scale-axes}"
counts="${3:-1 2 4 8}"
exe="${STEPDRIVE_EXE:-$(dirname "$0")/../target/release/stepdrive}"
mkdir -p "$out"
for n in $counts; do
  [ -n "${TABLE_ONLY:-}" ] && break
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
# (and $out/cost-of-an-axis.svg: the same figures against the axis count)
import json, sys
out, counts = sys.argv[1], sys.argv[2].split()
print("| axes | exit | misses | outside host holds | s→a p99 µs | current loop compute p50/p99 µs (per axis p50) | plant compute p50/p99 µs | position loop compute p50/p99 µs | CPU s per s |")
print("|---|---|---|---|---|---|---|---|---|")
rows = []
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
    rows.append((int(n), t["deadline_miss_pct"], h.get("deadline_miss_pct_outside_holds", 0.0),
                 t["sensor_to_actuator"]["p99_us"], p["p50_us"], c["p50_us"] * int(n) / per_cycle, q["p50_us"]))

# The cost of an axis, drawn: two panels against the axis count (log-log), each series a
# polyline with its points marked and labelled.
def panel(x0, title, unit, series, ymin):
    W, H, L, B = 420, 300, 60, 40
    xs = [r[0] for r in rows]
    ys = [v for _, _, vals in series for v in vals if v > 0]
    if not xs or not ys:
        return ""
    import math
    # Head room: the legend sits in the top left, above the lines.
    lo, hi = math.log10(max(min(ys), ymin)), math.log10(max(ys) * 12)
    hi = max(hi, lo + 1)
    X = lambda v: x0 + L + (math.log2(v) / max(math.log2(max(xs)), 1)) * (W - L - 20)
    Y = lambda v: 20 + (hi - math.log10(max(v, ymin))) / (hi - lo) * (H - B - 20)
    g = [f'<text x="{x0 + W / 2}" y="14" text-anchor="middle" font-size="13">{title}</text>',
         f'<line x1="{x0 + L}" y1="{H - B}" x2="{x0 + W - 20}" y2="{H - B}" stroke="black"/>',
         f'<line x1="{x0 + L}" y1="20" x2="{x0 + L}" y2="{H - B}" stroke="black"/>',
         f'<text x="{x0 + W / 2}" y="{H - 8}" text-anchor="middle" font-size="12">axes</text>',
         f'<text x="{x0 + 14}" y="{(H - B) / 2}" font-size="12" transform="rotate(-90 {x0 + 14} {(H - B) / 2})" text-anchor="middle">{unit}</text>']
    for v in xs:
        g.append(f'<text x="{X(v)}" y="{H - B + 15}" text-anchor="middle" font-size="11">{v}</text>')
    for e in range(math.ceil(lo), math.floor(hi) + 1):
        g.append(f'<text x="{x0 + L - 4}" y="{Y(10 ** e) + 4}" text-anchor="end" font-size="11">1e{e}</text>')
        g.append(f'<line x1="{x0 + L}" y1="{Y(10 ** e)}" x2="{x0 + W - 20}" y2="{Y(10 ** e)}" stroke="#ddd"/>')
    for k, (name, colour, vals) in enumerate(series):
        pts = " ".join(f"{X(x)},{Y(v)}" for x, v in zip(xs, vals))
        g.append(f'<polyline points="{pts}" fill="none" stroke="{colour}" stroke-width="2"/>')
        for x, v in zip(xs, vals):
            g.append(f'<circle cx="{X(x)}" cy="{Y(v)}" r="3" fill="{colour}"/>')
        g.append(f'<text x="{x0 + L + 8}" y="{34 + 14 * k}" font-size="11" fill="{colour}">{name}</text>')
    return "\n".join(g)

svg = ['<svg xmlns="http://www.w3.org/2000/svg" width="860" height="300" font-family="sans-serif">',
       '<rect width="860" height="300" fill="white"/>',
       panel(0, "deadline misses and sensor → actuator p99", "% / µs", [
           ("misses, all [%]", "#c0392b", [r[1] for r in rows]),
           ("misses outside host holds [%]", "#e67e22", [r[2] for r in rows]),
           ("sensor → actuator p99 [µs]", "#2c3e50", [r[3] for r in rows])], 1e-3),
       panel(430, "compute per cycle (p50)", "µs", [
           ("plant, all axes", "#27ae60", [r[4] for r in rows]),
           ("current loop, all axes", "#2980b9", [r[5] for r in rows]),
           ("position loop tick, all axes", "#8e44ad", [r[6] for r in rows])], 1e-1),
       '</svg>']
open(f"{out}/cost-of-an-axis.svg", "w").write("\n".join(svg))
PY
