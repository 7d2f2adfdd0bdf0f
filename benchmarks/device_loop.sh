#!/usr/bin/env bash
# Where a GPU training run's time goes (issue 4, BENCHMARKS.md "Where a GPU run's time goes"):
# render 1,000 default 384 px frames on the machine's cores, then
#   1. benchmarks/bench_loop.py: the loader alone, the step on real batches kept on the GPU,
#      with the EMA update, and with each batch copied from pinned memory;
#   2. configs/small_relu_gpu.yaml on those renders for RUN_S seconds with Lightning's simple
#      profiler (time per hook) and the GPU's utilisation sampled each second;
#   3. the same at batch 128 (a run held by per-step work, not per-image work, gains images/s).
#
#   OUT=outputs/gpu_loop SITE=$PWD/.gpu/site bash benchmarks/device_loop.sh   (carry .gpu)
# EXTRA: more `train.py fit` arguments for the two Lightning runs (e.g. "--model.compile true").
set -u
OUT=${OUT:?set OUT to the folder for the results}
RUN_S=${RUN_S:-75}
source "$(dirname "$0")/device_render1000.sh"
python3 benchmarks/bench_loop.py --train data/gpu/train/annotations.json --device cuda \
  --workers 14 7 0 --batch 64 --init-from lunarnav_ml/weights/small.pt --loader-batches 30 \
  --steps 30 2>&1 | tee $OUT/bench_loop.txt | grep -v Warning
for batch in 64 128; do
  rm -rf runs/small_relu_gpu
  nvidia-smi --query-gpu=utilization.gpu --format=csv,noheader,nounits -l 1 > $OUT/util_$batch.txt 2>&1 &
  smi=$!
  t1=$(date +%s)
  python3 train.py fit --config configs/small_relu_gpu.yaml --data.train data/gpu/train/annotations.json \
    --data.read_sizes null --data.weights null --data.num_workers 14 --data.batch_size $batch \
    --trainer.max_time $(printf '00:00:%02d:%02d' $((RUN_S / 60)) $((RUN_S % 60))) --trainer.enable_progress_bar false \
    --trainer.check_val_every_n_epoch 1000 --trainer.profiler simple ${EXTRA:-} > $OUT/train_$batch.txt 2>&1
  kill $smi
  echo "batch $batch: wall $(( $(date +%s) - t1 )) s; last epoch,step: $(tail -n 1 runs/small_relu_gpu/csv/*/metrics.csv | cut -d, -f1,4)"
  echo "  GPU utilisation, 1 s samples (start-up included): $(awk '$1 > 0' $OUT/util_$batch.txt | wc -l) of $(wc -l < $OUT/util_$batch.txt) with a kernel running, mean $(awk '{s += $1} END {printf "%.0f", s / NR}' $OUT/util_$batch.txt) %"
  grep -E "run_training_batch|train_dataloader_next|optimizer_step|training_step|backward|batch_to_device|Total  " $OUT/train_$batch.txt | tr -s " \t" " " | head -10
  cp runs/small_relu_gpu/csv/*/metrics.csv $OUT/metrics_$batch.csv 2>/dev/null
done
