#!/usr/bin/env bash
# The 240×376 cells of the detection-limit study (configs/detection_limit.py, profile "gpu") on a CUDA
# machine that has jax, OpenCV and numpy but no network and no ../shared.
#
# Prepare beside the checkout, in folders git ignores:
#   mkdir -p .device && cp WORKDIR/reference.json .device/     # the CPU run's libviso2-s reference
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux2014_x86_64 \
#       -d .whl tensorboardX filelock protobuf tqdm            # installed only where missing
# then run `bash experiments/studies/detection_limit_gpu.sh` there with `.device` and `.whl` carried.
# The cells, the table and the log go to $OUT (default ./gpu_out); BUDGET (seconds, default 520)
# bounds the study, whose finished cells survive a cut (one JSON each). Tabulate them with the CPU
# cells: detection_limit.py --workdir WORKDIR --include OUT_COPY (a folder holding cells/).
set -uo pipefail
export PYTHONUNBUFFERED=1
OUT="${OUT:-gpu_out}"
BUDGET="${BUDGET:-520}"
WORK="${WORK:-/tmp/detection_limit_gpu}"
mkdir -p "$OUT" "$WORK"
cp .device/reference.json "$WORK/reference.json" || exit 3
for pair in tensorboardX:tensorboardx filelock:filelock google.protobuf:protobuf tqdm:tqdm; do
    module="${pair%%:*}" wheel="${pair##*:}"
    if ! python3 -c "import $module" 2>/dev/null; then
        python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/"$wheel"-*.whl
    fi
done
export PYTHONPATH="/tmp/site:$PWD"
{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    python3 -c "import jax; print('jax', jax.__version__, jax.devices())"
    nproc
    date -u
} 2>&1 | tee "$OUT/device.txt"
timeout "$BUDGET" python3 experiments/studies/detection_limit.py --workdir "$WORK" --profile gpu 2>&1 \
    | grep -v "Given directory is read only" | tee "$OUT/log.txt"
mkdir -p "$OUT/cells"
cp "$WORK"/cells/*.json "$OUT/cells/" 2>/dev/null
cp "$WORK"/detection_limit.md "$WORK"/detection_limit.csv "$OUT/" 2>/dev/null
du -sh "$WORK"/* 2>/dev/null | tee -a "$OUT/log.txt"
