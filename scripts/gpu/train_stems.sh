#!/usr/bin/env bash
# Issue 49 item 3: train the stem of stride 2 on, three ways side by side on one GPU, each resumed from
# checkpoints/recon_stem/last (or from its own runs/NAME/last on a warm machine's later call):
#   stem_a    the same recipe (batch 8): whether the gap to the shipped model closes with steps
#   stem_kd   batch 8, also distilled from the shipped model (configs/train_recon_stem_distil.json; on a CPU it
#             gained 1-1.5 dB of validation color at equal steps, docs/measurements.md)
#   stem_kd32 the same at batch 32, validated as often in steps: whether the GPU (idle under one run of batch 8)
#             trains faster
# On the device, after recon_4k's data (isosr datagen configs/datagen_recon_4k.json -o data/recon_4k), from the
# project root with scripts/gpu/env.sh sourced:  bash scripts/gpu/train_stems.sh MINUTES [STEPS]
# Run on 2026-12-03 (benchmarks/results/train_stem_gpu_runs.json): stem_kd32 led, and checkpoints/recon_stem holds its
# lineage since, so a run of this script now compares the three recipes from there.
# Each run stops, validated and saved, after MINUTES; the cosine schedules run over STEPS (default 12000). The logs and
# runs/*/{last,best} come back in $OUT (runs.tgz).
set -euo pipefail
minutes=${1:?usage: train_stems.sh MINUTES [STEPS]}
steps=${2:-12000}
train() {
    local name=$1; shift
    if [ ! -d "runs/$name/last" ]; then
        mkdir -p "runs/$name" && cp -r checkpoints/recon_stem/last checkpoints/recon_stem/best "runs/$name/"
        chmod -R u+w "runs/$name"  # the carried tree's files are read-only
    fi
    python3 -m isosr_cli.main train "$@" --out "runs/$name" --steps "$steps" --time-limit-minutes "$minutes" \
        > "$OUT/$name.log" 2>&1
}
train stem_a configs/train_recon_stem.json &
train stem_kd configs/train_recon_stem_distil.json --batch-size 8 --validate-every 0 &
train stem_kd32 configs/train_recon_stem_distil.json &
wait
for name in stem_a stem_kd stem_kd32; do
    echo "$name: $(grep -a -m1 'resuming from' "$OUT/$name.log" || true)"
    tr '\r' '\n' < "$OUT/$name.log" | grep -a '^step \|"steps"\|"train_s"\|Error' | tail -4 | cut -c1-150 || true
done
tar czf "$OUT/runs.tgz" runs/stem_*/last runs/stem_*/best
