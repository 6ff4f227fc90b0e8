#!/usr/bin/env bash
# Every benchmark once, quick settings (each about a minute on a quiet 2-core machine), with the load
# average before each. Figures are only comparable when the load stays below the benchmark's threads (2):
# every script flags its figures otherwise. Before each benchmark the script waits until the 1-minute load
# average has fallen below SETTLE_LOAD (default 1.0), at most SETTLE_MAX seconds (default 90): run back to
# back, each benchmark would start with the load its predecessor's own threads left in that average.
# Every load line also gives the hypervisor's steal share since the previous check (flagged STOLEN above 10 %).
# The side-by-side runs against the public models (issue 17 items 3 and 4) measure only where the public model
# files are brought in: HORIZONNET_REF_DIR and FREDSNET_REF_DIR (see benchmarks/public_models.py); without
# them their lines say so. The benchmarks are judged on glibc's default allocator: a run made with another
# (MALLOC_* variables, GLIBC_TUNABLES, a preloaded allocator, THP_MEM_ALLOC_ENABLE) says so on its target lines
# (benchmarks/_timing.allocator_tag). benchmarks/gpu.py measures only on a CUDA machine (here it says so).
# Usage: [HORIZONNET_REF_DIR=DIR] [FREDSNET_REF_DIR=DIR] bash benchmarks/run_all.sh [OUT_DIR]
set -u
cd "$(dirname "$0")/.."
out="${1:-benchmarks/results/run_all}"
mkdir -p "$out"
settle() {
  local waited=0 load
  while [ "$waited" -lt "${SETTLE_MAX:-90}" ]; do
    load=$(cut -d' ' -f1 /proc/loadavg 2>/dev/null) || return 0
    awk -v l="$load" -v t="${SETTLE_LOAD:-1.0}" 'BEGIN { exit !(l < t) }' && break
    sleep 5
    waited=$((waited + 5))
  done
  [ "$waited" -gt 0 ] && echo "(waited ${waited} s for the load to settle)"
  return 0
}
run() {
  local name="$1"; shift
  settle
  echo "=== $name: $* ($(date -u +%H:%M:%S) UTC, $(cut -d' ' -f1-4 /proc/loadavg 2>/dev/null || uptime))"
  "$@" 2>&1 | tee "$out/$name.txt"
}
run projected_conv python benchmarks/projected_conv.py --reps 5
run gyroscope      python benchmarks/gyroscope.py speed --reps 5
run contention     python benchmarks/contention.py --reps 5
run synth          python benchmarks/synth.py --reps 5 --seeds 3 11
run fredsnet       python benchmarks/fredsnet.py --reps 5
run fredsnet_scale python benchmarks/fredsnet.py --scaling --reps 3
run public_hnet    python benchmarks/public_models.py horizonnet --reps 5
run public_fdsnet  python benchmarks/public_models.py fredsnet --reps 5
run layout         python benchmarks/layout.py --reps 10
run gpu            python benchmarks/gpu.py
grep -h "^TARGET\|LOADED\|STOLEN" "$out"/*.txt > "$out/summary.txt"
echo "=== summary: $out/summary.txt"; cat "$out/summary.txt"
