#!/usr/bin/env bash
# Issue 49 item 3: the stem with a pixel tail (configs/train_recon_stem_pixel.json: from checkpoints/recon_stem_geometry/
# best, recon_4k's 8-frame sequences, the shipped model as teacher), resumed from checkpoints/recon_stem_pixel/last
# where that is kept. With CONTROL=1 the same config with pixel_tail 0 (runs/recon_stem_notail) trains beside it from
# the same start: the A/B of 2026-12-03 (benchmarks/results/pareto_stem_pixel_cuda.json), two runs side by side on one
# GPU at no cost in speed (a run is bound by its host).
# On the device, from the project root with scripts/gpu/env.sh sourced:  bash scripts/gpu/train_stems.sh MINUTES
# [STEPS] (STEPS: the cosine schedules' length, default the config's). The first call renders recon_4k's data where
# data/recon_4k is missing (about 380 s on an H200) and trains for what is left of MINUTES; later calls on the warm
# machine resume each run from its runs/NAME/last. The logs and runs/*/{last,best} come back in $OUT (runs.tgz).
set -euo pipefail
minutes=${1:?usage: train_stems.sh MINUTES [STEPS]}
start=$SECONDS
isosr() { python3 -m isosr_cli.main "$@"; }
if [ ! -f data/recon_4k/manifest.json ]; then
    isosr datagen configs/datagen_recon_4k.json -o data/recon_4k > "$OUT/datagen.log" 2>&1
    tail -1 "$OUT/datagen.log"
fi
left=$(python3 -c "left = $minutes - ($SECONDS - $start) / 60
print(round(left, 2)) if left >= 1 else exit('under a minute left for training after the data')")
pixel=configs/train_recon_stem_pixel.json
if [ ! -d runs/recon_stem_pixel/last ] && [ -d checkpoints/recon_stem_pixel/last ]; then
    mkdir -p runs/recon_stem_pixel && cp -r checkpoints/recon_stem_pixel/{last,best} runs/recon_stem_pixel/
    chmod -R u+w runs/recon_stem_pixel  # the carried tree's files are read-only
fi
steps=(${2:+--steps "$2"})
names=(pixel ${CONTROL:+notail})
isosr train "$pixel" "${steps[@]}" --time-limit-minutes "$left" > "$OUT/pixel.log" 2>&1 &
if [ -n "${CONTROL:-}" ]; then  # the same config without the tail
    notail=/tmp/train_recon_stem_notail.json
    python3 -c 'import json, sys; c = json.load(open(sys.argv[1])); c["model"]["pixel_tail"] = 0
c["out"] = "runs/recon_stem_notail"; json.dump(c, open(sys.argv[2], "w"), indent=1)' "$pixel" "$notail"
    isosr train "$notail" "${steps[@]}" --time-limit-minutes "$left" > "$OUT/notail.log" 2>&1 &
fi
wait
for name in "${names[@]}"; do
    echo "$name:"
    tr '\r' '\n' < "$OUT/$name.log" | grep -a '^step \|"steps"\|"train_s"\|Error' | tail -4 | cut -c1-150 || true
done
tar czf "$OUT/runs.tgz" $(ls -d runs/recon_stem_{pixel,notail}/{last,best} 2>/dev/null)
