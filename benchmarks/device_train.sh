#!/usr/bin/env bash
# One GPU, one wall-clock budget: render configs/small_relu_gpu.yaml's sources on the machine's
# cores, fine-tune on the GPU until the budget is spent, and leave the slim weights, the logs and
# the metrics in $OUT (BENCHMARKS.md, issue 4, "One GPU").
#
#   OUT=outputs/gpu BUDGET_S=540 bash benchmarks/device_train.sh
#
# Made for the lent device machine (nothing installed from a registry there): its python3
# (CPython 3.12) holds torch and Lightning; the packages it lacks come as a --target folder on
# PYTHONPATH (SITE), built here and carried (18 MB with the .so files stripped):
#   uv pip install --target .gpu/site --python-version 3.12 --python-platform x86_64-manylinux_2_28 \
#       --no-deps albumentations==2.0.8 albucore==0.0.24 pydantic==2.14.3 pydantic-core==2.50.4 \
#       annotated-types typing-inspection simsimd stringzilla pycocotools==2.0.11 \
#       jsonargparse==4.53.0 docstring-parser typeshed-client importlib-resources
#   find .gpu/site -name '*.so' -exec strip --strip-unneeded {} +
# The working tree travels too: it must stay under the device's 64 MiB with that folder.
# Session 30 (H200, BUDGET_S=560): rendering 168 s, training 5 min 17 s, 878 steps.
# Session 31 (H200, BUDGET_S=570, the loader and loss fixes): 1,597 steps in 4 min 58 s.
# Session 43 (H100, BUDGET_S=565, the real cameras' renders at 0.35): rendering 270 s, training
# 3 min 34 s, 891 steps (shipped until session 48).
# Session 53 (H200, BUDGET_S=570, the CPU runs' two sources, the paper's grid left out; shipped in
# session 53, the start of sessions 54's and 55's CPU runs): rendering 176 s, training 4 min 24 s,
# 1,069 steps:
#   OUT=$OUT BUDGET_S=570 SITE=$PWD/.gpu/site N_TRAIN=4000 N_TRANSFER=1700 MONO_N=8 BENCH=0 \
#       SEED_TRAIN=23000001 SEED_TRANSFER=25000011 SEED_MONO=9300007 TRAIN_ARGS="--data.train \
#       [data/gpu/train/annotations.json,data/gpu/transfer/annotations.json] \
#       --data.read_sizes [null,null] --data.weights [0.7,0.3]" bash benchmarks/device_train.sh
# (MONO_N=8: the grid's eight frames render in seconds and go unused; the start was the tree's
# small.pt then, git 67e91fa's: to redo it, put that file at lunarnav_ml/weights/small.pt.)
# Session 59 (H200, BUDGET_S=570; the same command from session 57's small.pt with
# SEED_TRAIN=36000001 SEED_TRANSFER=37000011 and --data.weights [0.4,0.6]; not shipped, it lost
# real craters): rendering 223 s, training 4 min 29 s, 1,103 steps.
# Ready for the next lent GPU (session 63; CPU smoke runs only): the stride-2 student of issue 8
# (BENCHMARKS.md "The teacher's weight in the labelled loss"), its stem distilled from the
# shipped small.pt and every weight on its detections (DISTILL_STEPS: `lunarnav distill-stem`
# on the GPU, on the training renders), then trained with labels and small.pt as a second
# target; nothing carried but .gpu/site (DISTILL_FROM=outputs/s62/kd.pt, carried, would start
# from session 62's CPU student instead); size DISTILL_STEPS to about a third of the budget:
#   OUT=$OUT BUDGET_S=570 SITE=$PWD/.gpu/site BENCH=0 SEED_TRAIN=38000001 \
#       SEED_TRANSFER=39000011 DISTILL_STEPS=2000 EXTRA="--model.preset small-relu-s2 \
#       --model.init_from null" TRAIN_ARGS="--model.teacher lunarnav_ml/weights/small.pt \
#       --model.teacher_weight 0.01" bash benchmarks/device_train.sh
# (init_from null: the smoke run's start, whose anchors are not the teacher's, hence the teacher
# in TRAIN_ARGS; the real run starts from the distilled student.) The CPU smoke:
# PY=.venv/bin/python WORKERS=2 N_TRAIN=16 N_TRANSFER=16 MONO_N=2 BUDGET_S=300
# DISTILL_IMAGES=32 DISTILL_BATCH=4 DISTILL_FEATURE_STEPS=2 DISTILL_OUTPUT_STEPS=2
# DISTILL_STEPS=2, "--trainer.accelerator cpu --trainer.precision 32 --data.batch_size 4" added
# to EXTRA.
# Use new seeds next time (renders up to 37,000,011 are taken; 38000001 / 39000011 are not).
# Environment: BUDGET_S (whole script, default 540), WORKERS (rendering processes, default
# nproc), N_TRAIN / N_TRANSFER / MONO_N (render counts; MONO_N empty = the whole shard),
# SEED_TRAIN / SEED_TRANSFER / SEED_MONO (the sources' render seeds, default the CPU runs' 0,
# 5000011 and 9100003; session 51 rendered new ones), BENCH (0 skips the model-only speed),
# PY (default python3), EXTRA (more `train.py fit` arguments for both runs, e.g. for a CPU smoke
# run), TRAIN_ARGS (more arguments for the real run only, e.g. other --data.weights),
# DISTILL_STEPS (default 0: none), DISTILL_FROM (the small-relu-s2 student to start it from;
# unset: a new stem distilled from the shipped small.pt first, DISTILL_FEATURE_STEPS (default
# 1500) and DISTILL_OUTPUT_STEPS (400) of `distill-stem`'s stem phases),
# DISTILL_IMAGES (renders it holds in memory, default 4000), DISTILL_BATCH (default 64),
# DISTILL_LR (default 1e-4).
set -euo pipefail
t0=$(date +%s)
BUDGET_S=${BUDGET_S:-540}
OUT=${OUT:?set OUT to the folder for the results}
PY=${PY:-python3}
WORKERS=${WORKERS:-$(nproc)}
N_TRAIN=${N_TRAIN:-3000}
N_TRANSFER=${N_TRANSFER:-1200}
MONO_N=${MONO_N:-}
SEED_TRAIN=${SEED_TRAIN:-0}
SEED_TRANSFER=${SEED_TRANSFER:-5000011}
SEED_MONO=${SEED_MONO:-9100003}
DATA=data/gpu  # where configs/small_relu_gpu.yaml reads its sources
RUN=runs/small_relu_gpu  # the config's logger and checkpoint folder
[ -n "${SITE:-}" ] && export PYTHONPATH="$SITE:${PYTHONPATH:-}"
export PYTHONPATH="$PWD:${PYTHONPATH:-}"
mkdir -p "$OUT" "$DATA"
log() { echo "[$(($(date +%s) - t0)) s] $*" | tee -a "$OUT/log.txt"; }
lunarnav() { "$PY" -c 'import sys; from lunarnav_ml.cli import main; sys.exit(main())' "$@"; }

log "imports"
"$PY" - <<'EOF' 2>&1 | tee -a "$OUT/log.txt"
import lunarnav_ml  # first: it turns albumentations' PyPI update check off
import albumentations, jsonargparse, pycocotools, torch, lightning, cv2, numba
from lightning.pytorch.cli import LightningCLI  # needs jsonargparse[signatures]
import lunarnav_ml.training.lightning_cli
print("torch", torch.__version__, "lightning", lightning.__version__, "cuda",
      torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
EOF
if command -v nvidia-smi >/dev/null; then
    nvidia-smi -L | tee -a "$OUT/log.txt"
    nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader -l 15 \
        >"$OUT/gpu_util.txt" 2>&1 &
fi

synth() {  # name, then lunarnav synth arguments
    local name=$1; shift
    lunarnav synth "$DATA/$name" --size 384 --no-stereo --quiet "$@" >"$DATA/$name.log" 2>&1
}
log "render validation and training sources, $WORKERS processes each"
synth val --n 48 --seed 1000003 --config configs/synth/default.yaml --workers 2 &
p0=$!
mono_n=(); [ -n "$MONO_N" ] && mono_n=(--n "$MONO_N")
synth train --n "$N_TRAIN" --seed "$SEED_TRAIN" --config configs/synth/default.yaml \
    --workers "$WORKERS" &
p1=$!
synth transfer --n "$N_TRANSFER" --seed "$SEED_TRANSFER" --config configs/synth/transfer.yaml \
    --workers "$WORKERS" &
p2=$!
synth mono1024 --protocol paper-mono --seed "$SEED_MONO" --shard 0/4 "${mono_n[@]}" --size 1024 \
    --workers "$WORKERS" &
p3=$!
fail() { log "$1"; tail -n 30 "$2"; kill $p1 $p2 $p3 2>/dev/null; exit 1; }
wait $p0 || fail "rendering failed" "$DATA/val.log"
log "smoke run on the validation renders while the others render"
"$PY" train.py fit --config configs/small_relu_gpu.yaml --data.train "$DATA/val/annotations.json" \
    --data.read_sizes null --data.weights null --data.val "$DATA/val/annotations.json" \
    --data.batch_size 16 --data.num_workers 2 --trainer.max_steps 3 \
    --trainer.check_val_every_n_epoch 1 --trainer.enable_progress_bar false ${EXTRA:-} \
    >"$OUT/smoke.txt" 2>&1 || fail "smoke run failed" "$OUT/smoke.txt"
rm -rf "$RUN"
# the GPU is idle while the others render: its model-only speed
if [ -z "${EXTRA:-}" ] && [ "${BENCH:-1}" != 0 ]; then
    log "model-only training speed on the GPU (no loader), batch 64 and 128"
    for b in 64 128; do
        "$PY" benchmarks/bench_train.py --device cuda --presets small-relu --size 384 \
            --batch $b --precision bf16 --steps 30 --warmup 10 2>&1 | tee -a "$OUT/bench_cuda.txt"
    done
fi
wait $p1 && wait $p2 && wait $p3 || fail "rendering failed" "$DATA/train.log"
log "rendered: $(du -sh "$DATA" | cut -f1)"

init=()
if [ "${DISTILL_STEPS:-0}" -gt 0 ]; then
    if [ -n "${DISTILL_FROM:-}" ]; then  # a student trained before: the third phase alone
        phases=(--student "$DISTILL_FROM" --feature-steps 0 --output-steps 0)
    else  # the stem from the shipped small.pt first (session 61's steps)
        phases=(--feature-steps "${DISTILL_FEATURE_STEPS:-1500}"
                --output-steps "${DISTILL_OUTPUT_STEPS:-400}")
    fi
    log "distil: ${phases[*]}, then $DISTILL_STEPS steps on the teacher's detections"
    lunarnav distill-stem "${phases[@]}" --images "$DATA/train" "$DATA/transfer" \
        --max-images "${DISTILL_IMAGES:-4000}" \
        --whole-steps "$DISTILL_STEPS" --batch "${DISTILL_BATCH:-64}" \
        --whole-lr "${DISTILL_LR:-1e-4}" --bf16 --seed "$SEED_TRAIN" --quiet \
        --out "$OUT/distilled.pt" >"$OUT/distill.txt" 2>&1 || fail "distillation failed" \
        "$OUT/distill.txt"
    tail -n 1 "$OUT/distill.txt" | tee -a "$OUT/log.txt"
    init=(--model.init_from "$OUT/distilled.pt")
fi

left=$((BUDGET_S - ($(date +%s) - t0) - 60))  # a minute for start-up, the last save, export
[ "$left" -gt 30 ] || { log "no time left to train"; exit 1; }
max_time=$(printf '00:00:%02d:%02d' $((left / 60)) $((left % 60)))
log "train, max_time $max_time"
"$PY" train.py fit --config configs/small_relu_gpu.yaml --data.num_workers $((WORKERS - 2)) \
    --trainer.max_time "$max_time" --trainer.enable_progress_bar false ${EXTRA:-} ${TRAIN_ARGS:-} \
    "${init[@]}" \
    >"$OUT/train.txt" 2>&1 || { log "training failed"; tail -n 30 "$OUT/train.txt"; }
log "export"
"$PY" - "$RUN" "$OUT" <<'EOF' 2>&1 | tee -a "$OUT/log.txt"
import glob, shutil, sys
from lunarnav_ml.training.api import load_detector
run, out = sys.argv[1:]
load_detector(f"{run}/checkpoints/last.ckpt").save(f"{out}/small_gpu.pt", half=True)
for f in sorted(glob.glob(f"{run}/csv/*/metrics.csv"))[-1:]:
    shutil.copy(f, f"{out}/metrics.csv")
print("saved", f"{out}/small_gpu.pt")
EOF
log "done"
