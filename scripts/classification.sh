#!/usr/bin/env bash
# Motion classification under noise (issue 2): for each preset, N seeded sessions at
# σ px through `rigcal synth` and `rigcal calibrate`, counting the reported motion class
# and status. Usage: scripts/classification.sh [N=200] [SIGMA=1] [PRESET...]
# Needs a release build (cargo build --release) and python3 (to read the JSON).
set -euo pipefail
n=${1:-200}
sigma=${2:-1}
shift $(( $# > 2 ? 2 : $# ))
presets=("$@")
[ ${#presets[@]} -gt 0 ] || presets=(car-planar car-planar-uturn car-planar-loop lebraly-5.1 car-bump)
bin=${RIGCAL:-target/release/rigcal}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
echo "| preset | class | status |"
echo "|---|---|---|"
for p in "${presets[@]}"; do
  : > "$work/$p.txt"
  for ((s = 3000; s < 3000 + n; s++)); do
    "$bin" synth --preset "$p" --seed "$s" --noise "$sigma" --out "$work/s" > /dev/null 2>&1
    "$bin" calibrate "$work/s/session.json" > "$work/r.json" || true
    python3 -c '
import json, sys
r = json.load(open(sys.argv[1]))
codes = ",".join(sorted({x["code"] for x in r.get("reasons", [])}))
print(r["singularity"]["motion_class"] if r.get("singularity") else "none", r["status"] + (" (" + codes + ")" if codes else ""))
' "$work/r.json" >> "$work/$p.txt"
  done
  classes=$(cut -d' ' -f1 "$work/$p.txt" | sort | uniq -c | awk '{printf "%s%s %s", sep, $1, $2; sep=", "}')
  statuses=$(cut -d' ' -f2- "$work/$p.txt" | sort | uniq -c | awk '{c=$1; $1=""; printf "%s%s%s", sep, c, $0; sep=", "}')
  echo "| $p | $classes | $statuses |"
done
