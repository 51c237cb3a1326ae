#!/usr/bin/env bash
# Issue 49 item 3: whether a pixel tail closes the stem's AO gap, as an A/B on one GPU (a run is bound by its host:
# two side by side cost no speed). Both start from checkpoints/recon_stem_geometry/best with the same recipe and
# steps (configs/train_recon_stem_pixel.json, recon_4k's 8-frame sequences):
#   pixel    with its pixel tail of 16 (a path from each pixel's own previous AO: docs/measurements.md, "Where the
#            stem loses at 4 rays a pixel")
#   notail   the same config with pixel_tail 0 (runs/recon_stem_notail): what the steps alone buy
# On the device, from the project root with scripts/gpu/env.sh sourced:  bash scripts/gpu/train_stems.sh MINUTES
# [STEPS] (STEPS: both cosine schedules' length, default the config's). The first call renders recon_4k's data where
# data/recon_4k is missing (about 350 s on an H200) and trains for what is left of MINUTES; later calls on the warm
# machine resume each run from its runs/NAME/last. The logs and runs/*/{last,best} come back in $OUT (runs.tgz).
# (Until 2026-12-03 this script compared the stem's first three recipes: benchmarks/results/train_stem_gpu_runs.json;
# then the geometry run resumed beside the pixel tail.)
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
pixel=configs/train_recon_stem_pixel.json notail=/tmp/train_recon_stem_notail.json
python3 -c 'import json, sys; c = json.load(open(sys.argv[1])); c["model"]["pixel_tail"] = 0
c["out"] = "runs/recon_stem_notail"; json.dump(c, open(sys.argv[2], "w"), indent=1)' "$pixel" "$notail"
steps=(${2:+--steps "$2"})
isosr train "$pixel" "${steps[@]}" --time-limit-minutes "$left" > "$OUT/pixel.log" 2>&1 &
isosr train "$notail" "${steps[@]}" --time-limit-minutes "$left" > "$OUT/notail.log" 2>&1 &
wait
for name in pixel notail; do
    echo "$name:"
    tr '\r' '\n' < "$OUT/$name.log" | grep -a '^step \|"steps"\|"train_s"\|Error' | tail -4 | cut -c1-150 || true
done
tar czf "$OUT/runs.tgz" $(ls -d runs/recon_stem_{pixel,notail}/{last,best} 2>/dev/null)
