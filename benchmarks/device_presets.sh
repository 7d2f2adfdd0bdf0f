#!/usr/bin/env bash
# Training throughput of every preset on the lent GPU (issue 4, "Training throughput per preset
# on CPU, and on GPU when one is lent"): benchmarks/bench_train.py on random batches (no
# loader), float32 and bf16 autocast, one line per preset and precision, into $OUT/presets.txt.
#
#   OUT=outputs/gpu_presets SITE=$PWD/.gpu/site bash benchmarks/device_presets.sh   (carry .gpu)
#
# Environment: OUT (required), PY (default python3), DEVICE (default cuda; cpu for a smoke run
# here), SIZE / BATCH (default 416 / 64: the reference YOLOv4's side), BIG_SIZE / BIG_BATCH
# (default 608 / 32: the full YOLOv4 preset at its large side), STEPS (default 20), LAYOUTS
# (default "nchw channels-last": each preset in both memory layouts).
set -euo pipefail
OUT=${OUT:?set OUT to the folder for the results}
PY=${PY:-python3}
DEVICE=${DEVICE:-cuda}
SIZE=${SIZE:-416}
BATCH=${BATCH:-64}
BIG_SIZE=${BIG_SIZE:-608}
BIG_BATCH=${BIG_BATCH:-32}
STEPS=${STEPS:-20}
LAYOUTS=${LAYOUTS:-nchw channels-last}
[ -n "${SITE:-}" ] && export PYTHONPATH="$SITE:${PYTHONPATH:-}"
export PYTHONPATH="$PWD:${PYTHONPATH:-}"
mkdir -p "$OUT"
if command -v nvidia-smi >/dev/null; then
    nvidia-smi -L | tee "$OUT/device.txt"
fi
bench() {
    "$PY" benchmarks/bench_train.py --device "$DEVICE" --precision 32 bf16 --steps "$STEPS" \
        --warmup 5 "$@" 2>&1 | tee -a "$OUT/presets.txt"
}
for layout in $LAYOUTS; do
    flag=(); [ "$layout" = channels-last ] && flag=(--channels-last)
    echo "layout $layout" | tee -a "$OUT/presets.txt"
    bench --presets nano tiny small small-relu medium yolov4 --size "$SIZE" --batch "$BATCH" \
        "${flag[@]}"
    bench --presets yolov4 --size "$BIG_SIZE" --batch "$BIG_BATCH" "${flag[@]}"
done
