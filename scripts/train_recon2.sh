#!/usr/bin/env bash
# Render the data of the reconstruction model over the input rays (configs/datagen_recon2.json:
# 0-16 AO rays, 1-4 rays per pixel, frames of 512, 1024 and 2048 pixels) and train it
# (configs/train_recon2.json), on the GPU machine, from the project root:
#   bash scripts/train_recon2.sh OUT_DIR [FROM_DIR]
# FROM_DIR: a previous run's OUT_DIR; training resumes from its last/ (the trainer resumes from
# runs/recon2/last) and keeps its best/ unless it does better. Data goes to data/recon2 and the
# run to runs/recon2 (both git-ignored; the same config renders the same data again); the logs,
# last/ (the resume checkpoint: weights, config, optimizer state) and best/ go to OUT_DIR.
# To train past the config's steps when resuming, set STEPS (the cosine schedule restarts over it);
# MINUTES overrides the training's time limit (the whole script must fit one 10-minute device run).
set -euo pipefail
out=${1:?usage: train_recon2.sh OUT_DIR [FROM_DIR]}
from=${2:-}
isosr() { python3 -m isosr_cli.main "$@"; }
mkdir -p "$out" data runs
if [ -n "$from" ]; then
    rm -rf runs/recon2 && mkdir -p runs/recon2
    cp -r "$from/last" runs/recon2/last
    if [ -d "$from/best" ]; then cp -r "$from/best" runs/recon2/best; fi
    chmod -R u+w runs/recon2  # files fetched from a device run come back read-only
fi
isosr datagen configs/datagen_recon2.json -o data/recon2 > "$out/datagen_recon2.log" 2>&1
isosr train configs/train_recon2.json ${STEPS:+--steps "$STEPS"} ${MINUTES:+--time-limit-minutes "$MINUTES"} \
    > "$out/train_recon2.log" 2>&1
rm -rf "$out/last" "$out/best"
cp -r runs/recon2/last "$out/last"
if [ -d runs/recon2/best ]; then cp -r runs/recon2/best "$out/best"; fi
du -sh "$out"/*
