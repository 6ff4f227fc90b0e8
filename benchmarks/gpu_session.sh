#!/usr/bin/env bash
# One lease of a GPU machine (issue 17, item 8), as one prepared command:
#     bash benchmarks/gpu_session.sh [OUTDIR]        (OUTDIR: $OUT, else ./gpu_out)
# 1. the CUDA tests: `pytest -m cuda` over the GPU test files (every camera, ProjectedConv2d against
#    deform_conv2d on CUDA, every model forward/backward/eval against the CPU, autocast, gyroscope, layout
#    hooks, renderer) and the tests taking the `device` fixture with --device cuda;
#    then every model's CUDA tests again with ProjectedConv2d's fused Triton kernels on (OMNIDL_TRITON=1);
# 2. benchmarks/gpu.py (FreDSNet fps, ProjectedConv2d vs cuDNN beside both CUDA backends, a training step) and a
#    CUDA profile.
# Logs go to OUTDIR; the last lines printed are the summary. The steps' time limits (GPU_TEST_S 180, GPU_DEVICE_S
# 60, GPU_TRITON_S 100, GPU_BENCH_S 220 seconds) add up to 560 s, within one device call's 600 s. Python packages
# the machine lacks travel as wheels in ./.whl (git-ignored; see the device tool's notes) and are installed to
# /tmp/site first.
set -u
OUTDIR=${1:-${OUT:-gpu_out}}
mkdir -p "$OUTDIR"
export PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1
if ls .whl/*.whl >/dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        && export PYTHONPATH=/tmp/site:$PWD || { echo "wheel install failed"; exit 2; }
else
    export PYTHONPATH=$PWD
fi
nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem,temperature.gpu --format=csv | tee "$OUTDIR/gpu.txt"
python3 -c "import torch, sys; print('python', sys.version.split()[0], 'torch', torch.__version__, torch.cuda.get_device_name())"
T0=$(date +%s)
timeout "${GPU_TEST_S:-180}" python3 -m pytest -p no:cacheprovider -m cuda -q -rfE --tb=short --timeout 120 \
    tests/nn/test_cuda.py tests/models/test_cuda_models.py tests/postprocess/test_cuda.py tests/synth/test_cuda.py \
    > "$OUTDIR/pytest_cuda.log" 2>&1
echo "pytest -m cuda: rc=$? in $(( $(date +%s) - T0 )) s: $(tail -1 "$OUTDIR/pytest_cuda.log")"
T0=$(date +%s)
timeout "${GPU_DEVICE_S:-60}" python3 -m pytest -p no:cacheprovider --device cuda -k cuda -q -rfE --tb=short --timeout 60 \
    tests/engine/test_forward.py tests/nn/test_unfold_conv.py > "$OUTDIR/pytest_device.log" 2>&1
echo "pytest --device cuda: rc=$? in $(( $(date +%s) - T0 )) s: $(tail -1 "$OUTDIR/pytest_device.log")"
T0=$(date +%s)
OMNIDL_TRITON=1 timeout "${GPU_TRITON_S:-100}" python3 -m pytest -p no:cacheprovider -m cuda -q -rfE --tb=short \
    --timeout 120 tests/models/test_cuda_models.py > "$OUTDIR/pytest_cuda_triton.log" 2>&1
echo "pytest -m cuda, models with the fused Triton kernels on (OMNIDL_TRITON=1): rc=$? in $(( $(date +%s) - T0 )) s: \
$(tail -1 "$OUTDIR/pytest_cuda_triton.log")"
T0=$(date +%s)
timeout "${GPU_BENCH_S:-220}" python3 benchmarks/gpu.py --reps "${GPU_REPS:-20}" --profile "$OUTDIR/profile.txt" \
    > "$OUTDIR/gpu_bench.log" 2>&1
echo "benchmarks/gpu.py: rc=$? in $(( $(date +%s) - T0 )) s"
echo "== failures"; grep -E "^(FAILED|ERROR)" "$OUTDIR"/pytest_*.log | cut -c1-300 | head -40
echo "== benchmark"; grep -vE "^\s*$" "$OUTDIR/gpu_bench.log" | tail -25
