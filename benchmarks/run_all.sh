#!/usr/bin/env bash
# Every benchmark once, quick settings (each about a minute on a quiet 2-core machine), with the load
# average before each. Figures are only comparable when the load stays below the benchmark's threads (2):
# every script flags its figures otherwise. Usage: bash benchmarks/run_all.sh [OUT_DIR]
set -u
cd "$(dirname "$0")/.."
out="${1:-benchmarks/results/run_all}"
mkdir -p "$out"
run() {
  local name="$1"; shift
  echo "=== $name: $* ($(date -u +%H:%M:%S) UTC, $(cut -d' ' -f1-4 /proc/loadavg 2>/dev/null || uptime))"
  "$@" 2>&1 | tee "$out/$name.txt"
}
run projected_conv python benchmarks/projected_conv.py --reps 5
run gyroscope      python benchmarks/gyroscope.py speed --reps 5
run contention     python benchmarks/contention.py --reps 5
run synth          python benchmarks/synth.py --reps 5 --seeds 3 11
run fredsnet       python benchmarks/fredsnet.py --reps 3
run layout         python benchmarks/layout.py --reps 10
run gpu            python benchmarks/gpu.py
grep -h "^TARGET\|LOADED" "$out"/*.txt > "$out/summary.txt"
echo "=== summary: $out/summary.txt"; cat "$out/summary.txt"
