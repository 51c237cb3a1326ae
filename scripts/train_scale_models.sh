#!/usr/bin/env bash
# The x2 and x8 networks of the upscale-factor sweep (`isosr bench --models`), on one GPU:
# the default model's data and recipe at another factor, then scored with the oracles.
#   bash scripts/train_scale_models.sh WORKDIR [TRAIN_MINUTES]
# x8 renders a 64-pixel low-res frame (512 high-res) to keep its ground truth affordable, and
# its steps cost about 6x those of x4, hence fewer steps.
set -euo pipefail
work=${1:-work}
minutes=${2:-8}
isosr() { python3 -m isosr_cli.main "$@"; }
isosr datagen configs/datagen.json -o "$work/data_x2" --upscale 2
isosr datagen configs/datagen.json -o "$work/data_x8" --upscale 8 --lowres-size 64
isosr train configs/train_l1_normal.json --upscale 2 --data "$work/data_x2" --out "$work/run_x2" --steps 3000 \
  --time-limit-minutes "$minutes"
isosr train configs/train_l1_normal.json --upscale 8 --data "$work/data_x8" --out "$work/run_x8" --steps 1000 \
  --time-limit-minutes "$minutes"
for s in 2 8; do
  isosr datagen configs/datagen_eval.json -o "$work/eval_x$s" --upscale "$s"
  isosr eval --model "$work/run_x$s/best" --data "$work/eval_x$s" --device cuda --oracles --json "$work/eval_x$s.json"
done
echo "sweep them: isosr bench --only knobs --out benchmarks/results --models \"L1-normal x2=$work/run_x2/best,L1-normal x8=$work/run_x8/best\""
