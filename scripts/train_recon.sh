#!/usr/bin/env bash
# Render a reconstruction model's data (configs/datagen_$RUN.json) and train it
# (configs/train_$RUN.json), on the GPU machine, from the project root:
#   [RUN=recon2] bash scripts/train_recon.sh OUT_DIR [FROM_DIR]
# RUN: recon2 (default; the model over the input rays: 0-16 AO rays, 1-4 rays per pixel, frames of
# 512, 1024 and 2048 pixels), recon_x2 (the same, rendered at half the sides: it also upscales x2) or
# recon_history (recon2's data with each frame's AO rays accumulated along the flow, as at inference;
# its training fine-tuned recon_model_v2 into isosr_net/recon_model_v3) or recon_x2_history
# (the same for the x2 model: fine-tunes isosr_net/recon_x2_model) or recon_4k (recon_history's data with
# frames of 1024, 2048 and 4096 pixels, so that crops also show 4K's pixel scale: fine-tuned recon_model_v3 into
# the shipped isosr_net/recon_model) or recon_blend (recon_4k's data: fine-tunes the shipped model into one that
# blends its AO with the input rays' mean by the rays each stands for, ao_prior "blend": issue 49) or
# recon_blend_geo (the same data: fine-tunes checkpoints/recon_blend/best with its geometry corrections gated
# by rays per pixel, geometry_gate).
# DATA names another run's data (configs/datagen_$DATA.json into data/$DATA) for a run that shares it, as its train
# config's "data" says: RUN=recon_stem DATA=recon_4k (the stem of stride 2, issue 49 item 3, trained from scratch) or
# RUN=recon_stem_distil DATA=recon_4k (the same distilled from the shipped model at batch 32: checkpoints/recon_stem)
# or RUN=recon_stem_geometry DATA=recon_4k (checkpoints/recon_stem/best fine-tuned with its gates held open:
# checkpoints/recon_stem_geometry) or RUN=recon_stem_pixel DATA=recon_4k (that one fine-tuned with a pixel tail).
# FROM_DIR: a previous run's OUT_DIR; training resumes from its last/ (the trainer resumes from
# runs/$RUN/last) and keeps its best/ unless it does better. Data goes to data/$RUN and the run to
# runs/$RUN (both git-ignored; the same config renders the same data again); the logs, last/ (the
# resume checkpoint: weights, config, optimizer state) and best/ go to OUT_DIR.
# To train past the config's steps when resuming, set STEPS (the cosine schedule restarts over it);
# MINUTES overrides the training's time limit (the whole script must fit one 10-minute device run).
set -euo pipefail
run=${RUN:-recon2}
out=${1:?usage: [RUN=recon2|...|recon_blend|recon_blend_geo: the configs above] train_recon.sh OUT_DIR [FROM_DIR]}
from=${2:-}
isosr() { python3 -m isosr_cli.main "$@"; }
mkdir -p "$out" data runs
if [ -n "$from" ]; then
    rm -rf "runs/$run" && mkdir -p "runs/$run"
    cp -r "$from/last" "runs/$run/last"
    if [ -d "$from/best" ]; then cp -r "$from/best" "runs/$run/best"; fi
    chmod -R u+w "runs/$run"  # files fetched from a device run come back read-only
fi
data=${DATA:-$run}
isosr datagen "configs/datagen_$data.json" -o "data/$data" > "$out/datagen_$data.log" 2>&1
isosr train "configs/train_$run.json" ${STEPS:+--steps "$STEPS"} ${MINUTES:+--time-limit-minutes "$MINUTES"} \
    > "$out/train_$run.log" 2>&1
rm -rf "$out/last" "$out/best"
cp -r "runs/$run/last" "$out/last"
if [ -d "runs/$run/best" ]; then cp -r "runs/$run/best" "$out/best"; fi
du -sh "$out"/*
