#!/usr/bin/env bash
# How the shipped default model (isosr_net/default_model) is made, on one GPU:
# render training data, train the paper's L1-normal network, render full-frame evaluation
# sequences of the validation volumes, and score the network against the classic upscalers.
#   bash scripts/train_default_model.sh WORKDIR [TRAIN_MINUTES]
set -euo pipefail
work=${1:-work}
minutes=${2:-5}
isosr() { python3 -m isosr_cli.main "$@"; }
isosr datagen configs/datagen.json -o "$work/data"
isosr train configs/train_l1_normal.json --data "$work/data" --out "$work/run" --time-limit-minutes "$minutes"
isosr datagen configs/datagen_eval.json -o "$work/eval_data"
isosr eval --model "$work/run/best" --data "$work/eval_data" --device cuda --json "$work/eval.json"
