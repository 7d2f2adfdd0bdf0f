# Sourced by benchmarks/device_layout.sh, device_loop.sh and device_steps.sh (the lent GPU
# machine): puts SITE (the --target folder of packages its python3 lacks) and the working tree
# on PYTHONPATH, defines `lunarnav`, and renders the 1,000 default 384 px training frames
# (seed 0) and the 48 validation frames (seed 1,000,003) of configs/small_relu_gpu.yaml's
# data/gpu/ on its cores.
[ -n "${SITE:-}" ] && export PYTHONPATH="$SITE:${PYTHONPATH:-}"
export PYTHONPATH="$PWD:${PYTHONPATH:-}"
mkdir -p "$OUT"
lunarnav() { python3 -c 'import sys; from lunarnav_ml.cli import main; sys.exit(main())' "$@"; }
t0=$(date +%s)
lunarnav synth data/gpu/val --n 48 --seed 1000003 --config configs/synth/default.yaml --size 384 --no-stereo --quiet --workers 4 > $OUT/synth_val.log 2>&1 &
lunarnav synth data/gpu/train --n 1000 --seed 0 --config configs/synth/default.yaml --size 384 --no-stereo --quiet --workers 12 > $OUT/synth.log 2>&1
wait
echo "rendered in $(( $(date +%s) - t0 )) s"
