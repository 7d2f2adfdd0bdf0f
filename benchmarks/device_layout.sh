#!/usr/bin/env bash
# Channels-last on the GPU in a real training run (issue 4, BENCHMARKS.md "GPU throughput per
# preset"): render 1,000 default 384 px frames on the machine's cores, then run
# configs/small_relu_gpu.yaml on them for 90 s with the NCHW layout and 90 s with channels-last
# (--model.channels_last false / true); the step counts are the last rows of the metrics files.
#
#   OUT=outputs/gpu_layout SITE=$PWD/.gpu/site bash benchmarks/device_layout.sh   (carry .gpu)
set -u
OUT=${OUT:?set OUT to the folder for the results}
source "$(dirname "$0")/device_render1000.sh"
for cl in false true; do
  rm -rf runs/small_relu_gpu
  t1=$(date +%s)
  python3 train.py fit --config configs/small_relu_gpu.yaml --data.train data/gpu/train/annotations.json \
    --data.read_sizes null --data.weights null --data.num_workers 14 --trainer.max_time 00:00:01:30 \
    --trainer.enable_progress_bar false --trainer.check_val_every_n_epoch 1000 --model.channels_last $cl > $OUT/train_$cl.txt 2>&1
  tail -n 1 runs/small_relu_gpu/csv/*/metrics.csv | cut -d, -f1,4 | sed "s/^/channels_last $cl: epoch,step /"
  echo "wall $(( $(date +%s) - t1 )) s"; tail -n 3 $OUT/train_$cl.txt
  cp runs/small_relu_gpu/csv/*/metrics.csv $OUT/metrics_$cl.csv 2>/dev/null
done
