#!/usr/bin/env bash
# The GPU figures of the README in one run on a CUDA machine that has jax, flax, optax, orbax, OpenCV
# and PyTorch but no network and no ../shared: loop efficiency (bench_train_loop.py) for both
# methods at 240×376, batch 8, then the side-by-side against PyTorch eager and compiled
# (bench_vs_torch.py). Each part writes its output as it goes, so a part cut short by its time limit
# leaves what it measured.
#
# Prepare beside the checkout, in folders git ignores:
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux2014_x86_64 \
#       -d .whl tensorboardX                    # the one dependency such images tend to lack
#   cp -r ../shared/bench/torch_reference .device/
# then run `bash benchmarks/gpu_check.sh` there with `.whl` and `.device` carried; the outputs go to
# $OUT (default ./gpu_out). BUDGET (seconds, default 540) bounds the whole run.
#
# QUICK=1 runs the same steps on any machine, a CPU included, in a minute or two: the --smoke network at
# 32×48, batch 2, two steps; the side-by-side only where PyTorch imports (CI runs it so, so that a moved
# module breaks CI and not a GPU hour).
set -uo pipefail
export PYTHONUNBUFFERED=1
OUT="${OUT:-gpu_out}"
BUDGET="${BUDGET:-540}"
QUICK="${QUICK:-0}"
mkdir -p "$OUT"
if [ "$QUICK" = 1 ]; then
    LOOP_ARGS=(--preset small --smoke-network --size 32x48 --batch 2 --steps 2 --rounds 1 --correct-frames 8
               --workers 1)
    TORCH_ARGS=(--size 64 96 --torch-device cpu --torch-variants eager --torch-timeout 60 --pairs 1 --reps 2
                --warmup 1 --only mono-infer-1 stereo-infer-1)
else
    LOOP_ARGS=(--steps "${LOOP_STEPS:-40}" --rounds 3 --workers 4)
    TORCH_ARGS=(--torch-device cuda --torch-variants eager compiled --compiled-only mono-infer-1 mono-train-8
                --torch-timeout 90 --pairs 1 --reps 20 --warmup 3
                --only mono-train-8 stereo-train-8 mono-infer-1 stereo-infer-1)
fi
if compgen -G ".whl/*.whl" > /dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
        .whl/*.whl || exit 3
    export PYTHONPATH="/tmp/site:$PWD"
else
    export PYTHONPATH="$PWD"
fi
# One persistent cache: the benchmarks' processes compile some of the same programs.
export JAX_COMPILATION_CACHE_DIR="${JAX_COMPILATION_CACHE_DIR:-/tmp/jaxcache}" JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
start=$SECONDS
left() { echo $(( BUDGET - (SECONDS - start) )); }
{
    if command -v nvidia-smi > /dev/null; then
        nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    else
        echo "no nvidia-smi: no CUDA device"
    fi
    python3 -c "import jax, flax, optax; print('jax', jax.__version__, jax.devices(), 'flax', \
flax.__version__, 'optax', optax.__version__)"
    nproc
    date -u
} 2>&1 | tee "$OUT/device.txt"
for method in stereo_dpc ss_dpc; do
    timeout "${LOOP_TIMEOUT:-170}" python3 benchmarks/bench_train_loop.py --method "$method" \
        "${LOOP_ARGS[@]}" --json "$OUT/loop_$method.json" 2>&1 | tee "$OUT/loop_$method.txt"
    echo "elapsed $((SECONDS - start)) s"
done
if python3 -c "import torch; print('torch', torch.__version__)" 2> /dev/null | tee -a "$OUT/device.txt"; then
    timeout "$(left)" python3 benchmarks/bench_vs_torch.py \
        --torch-python python3 --torch-bench .device/torch_reference/bench_torch.py --wait-quiet 0 \
        "${TORCH_ARGS[@]}" 2>&1 | tee "$OUT/vs_torch.md"
else
    echo "no PyTorch here: the side-by-side against it is skipped" | tee "$OUT/vs_torch.md"
fi
echo "elapsed $((SECONDS - start)) s"
