#!/usr/bin/env bash
# Render the training data and train, side by side on one GPU, the reconstruction network
# (the first model, shipped as isosr_net/recon_model_v1) and the small subpixel upscaler (measured, not shipped).
#   bash scripts/train_recon_model.sh OUT_DIR        (from the project root, on the GPU machine)
# Data goes to data/, runs to runs/ (both git-ignored), logs to OUT_DIR, and the trained
# model folders (runs/*/best) into OUT_DIR/models.tar.
set -euo pipefail
out=${1:?usage: train_recon_model.sh OUT_DIR}
isosr() { python3 -m isosr_cli.main "$@"; }
mkdir -p "$out" data runs
isosr datagen configs/datagen_recon.json -o data/recon > "$out/datagen_recon.log" 2>&1 &
recon_data=$!
isosr datagen configs/datagen.json -o data/train --sequences 4 > "$out/datagen_x4.log" 2>&1
isosr train configs/train_srnet_small.json > "$out/train_srnet_small.log" 2>&1 &
wait $recon_data
isosr train configs/train_recon.json > "$out/train_recon.log" 2>&1
wait
tar cf "$out/models.tar" runs/*/best
