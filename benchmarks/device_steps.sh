#!/usr/bin/env bash
# A GPU training run's steps with and without session 39's changes (issue 4, BENCHMARKS.md
# "Targets prepared on the host; longer epochs tried"): render 1,000 default 384 px
# frames on the machine's cores, then
#   1. benchmarks/bench_loop.py: the step with the loss's targets prepared on the device (as
#      before) and on the host (YOLOLoss.prepare, what a Lightning run does now);
#   2. configs/small_relu_gpu.yaml on those renders for RUN_S seconds each: the code of git
#      BASE (unpacked here in $BASE_DIR, with this tree's callbacks.py for TrainingRate), this
#      tree, and this tree with --model.compile true (COMPILE_S seconds: compilation comes
#      first). Session 39 ran a fourth, a trial --data.epoch_repeats 10 (not kept: slower).
# Each run prints its steps and the last train/images_per_s of TrainingRate (50-step windows,
# validation off).
#
#   git archive BASE lunarnav_ml train.py configs ':!lunarnav_ml/weights' | tar -x -C s39_base
#   OUT=outputs/gpu_steps SITE=$PWD/.gpu/site BASE_DIR=s39_base bash benchmarks/device_steps.sh
#   (carry .gpu; s39_base is an untracked folder and travels with the tree)
set -u
OUT=${OUT:?set OUT to the folder for the results}
BASE_DIR=${BASE_DIR:?set BASE_DIR to the unpacked baseline tree}
RUN_S=${RUN_S:-60}
COMPILE_S=${COMPILE_S:-150}
PY=${PY:-python3}
source "$(dirname "$0")/device_render1000.sh"
cp lunarnav_ml/training/callbacks.py "$BASE_DIR/lunarnav_ml/training/callbacks.py"
cp configs/small_relu_gpu.yaml "$BASE_DIR/configs/"  # the same config, with TrainingRate
$PY benchmarks/bench_loop.py --train data/gpu/train/annotations.json --device cuda \
  --workers 14 --batch 64 --init-from lunarnav_ml/weights/small.pt --loader-batches 20 \
  --steps 30 2>&1 | tee $OUT/bench_loop.txt | grep -v Warning
root=$PWD
run() {  # name, tree, seconds, extra train.py arguments
  local name=$1 tree=$2 secs=$3; shift 3
  rm -rf $tree/runs/small_relu_gpu
  nvidia-smi --query-gpu=utilization.gpu --format=csv,noheader,nounits -l 1 > $OUT/util_$name.txt 2>&1 &
  local smi=$! t1=$(date +%s)
  (cd $tree && PYTHONPATH="${SITE:-}:$PWD" $PY train.py fit --config configs/small_relu_gpu.yaml \
    --model.init_from $root/lunarnav_ml/weights/small.pt \
    --data.train $root/data/gpu/train/annotations.json --data.val $root/data/gpu/val/annotations.json \
    --data.read_sizes null --data.weights null --data.num_workers ${WORKERS:-14} \
    --trainer.max_time $(printf '00:00:%02d:%02d' $((secs / 60)) $((secs % 60))) \
    --trainer.enable_progress_bar false --trainer.check_val_every_n_epoch 1000 ${EXTRA:-} "$@") > $OUT/train_$name.txt 2>&1
  kill $smi
  rm -f $OUT/metrics_$name.csv; cp $tree/runs/small_relu_gpu/csv/*/metrics.csv $OUT/metrics_$name.csv
  $PY - "$name" "$(( $(date +%s) - t1 ))" $OUT/metrics_$name.csv <<'EOP'
import csv, sys
name, wall, path = sys.argv[1:]
rows = list(csv.DictReader(open(path)))
steps = max((int(r["step"]) for r in rows if r.get("step")), default=0)
rates = [float(r["train/images_per_s"]) for r in rows if r.get("train/images_per_s")]
print(f"{name:9s} wall {wall} s, {steps} steps; images/s, last 50-step windows: "
      + ", ".join(f"{x:.0f}" for x in rates[-4:]))
EOP
  echo "  GPU: $(awk '$1 > 0' $OUT/util_$name.txt | wc -l) of $(wc -l < $OUT/util_$name.txt) 1-s samples with a kernel running"
}
run base $BASE_DIR $RUN_S
run host $root $RUN_S
run compiled $root $COMPILE_S --model.compile true
tail -n 30 $OUT/train_compiled.txt | grep -iE "error|Traceback" | head -5
