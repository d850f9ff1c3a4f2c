#!/usr/bin/env bash
# The GPU figures of the README in one run on a CUDA machine that has jax, flax, optax, orbax, OpenCV
# and PyTorch but no network and no ../shared: loop efficiency (bench_train_loop.py) for both
# methods, then the side-by-side against PyTorch eager and compiled (bench_vs_torch.py).
#
# Prepare beside the checkout, in folders git ignores:
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux2014_x86_64 \
#       -d .whl tensorboardX                    # the one dependency such images tend to lack
#   cp -r ../shared/bench/torch_reference .device/
# then run `bash benchmarks/gpu_check.sh` there with `.whl` and `.device` carried; the outputs go to
# $OUT (default ./gpu_out). BUDGET (seconds, default 540) bounds the PyTorch comparison.
set -uo pipefail
export PYTHONUNBUFFERED=1
OUT="${OUT:-gpu_out}"
mkdir -p "$OUT"
if compgen -G ".whl/*.whl" > /dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
        .whl/*.whl || exit 3
    export PYTHONPATH="/tmp/site:$PWD"
else
    export PYTHONPATH="$PWD"
fi
# One persistent cache: the benchmarks' processes compile some of the same programs.
export JAX_COMPILATION_CACHE_DIR=/tmp/jaxcache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/device.txt"
start=$SECONDS
for method in stereo_dpc ss_dpc; do
    timeout 200 python3 benchmarks/bench_train_loop.py --method "$method" --steps 60 --rounds 3 \
        --json "$OUT/loop_$method.json" 2>&1 | tee "$OUT/loop_$method.txt"
done
timeout $(( ${BUDGET:-540} - (SECONDS - start) )) python3 benchmarks/bench_vs_torch.py \
    --torch-python python3 --torch-bench .device/torch_reference/bench_torch.py --torch-device cuda \
    --wait-quiet 0 --torch-variants eager compiled --compiled-only mono-train-8 stereo-infer-1 mono-infer-1 \
    --torch-timeout 100 --pairs 1 --reps 20 --warmup 3 \
    --only stereo-train-8 mono-train-8 stereo-infer-1 mono-infer-1 2>&1 | tee "$OUT/vs_torch.md"
