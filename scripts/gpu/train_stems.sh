#!/usr/bin/env bash
# Issue 49 item 3: the stem's next two runs, side by side on one GPU (a run is bound by its host: two cost no speed):
#   geo    checkpoints/recon_stem_geometry resumed (configs/train_recon_stem_geometry.json), its cosine schedule
#          restarted over GEO_STEPS (default 9000): whether more steps win its AO back
#   pixel  its best with a pixel tail of 16 (configs/train_recon_stem_pixel.json, over the config's 4000 steps):
#          whether a path from each pixel's own previous AO closes the rest of its gap (the AO along a sequence:
#          docs/measurements.md, "Where the stem loses at 4 rays a pixel")
# On the device, from the project root with scripts/gpu/env.sh sourced:  bash scripts/gpu/train_stems.sh MINUTES
# The first call renders recon_4k's data where data/recon_4k is missing (about 350 s on an H200) and trains for what
# is left of MINUTES; later calls on the warm machine resume each run from its runs/NAME/last. The logs and
# runs/*/{last,best} come back in $OUT (runs.tgz). (Until 2026-12-03 this script compared the stem's first three
# recipes: benchmarks/results/train_stem_gpu_runs.json.)
set -euo pipefail
minutes=${1:?usage: train_stems.sh MINUTES}
start=$SECONDS
isosr() { python3 -m isosr_cli.main "$@"; }
if [ ! -f data/recon_4k/manifest.json ]; then
    isosr datagen configs/datagen_recon_4k.json -o data/recon_4k > "$OUT/datagen.log" 2>&1
    tail -1 "$OUT/datagen.log"
fi
left=$(python3 -c "left = $minutes - ($SECONDS - $start) / 60
print(round(left, 2)) if left >= 1 else exit('under a minute left for training after the data')")
if [ ! -d runs/recon_stem_geometry/last ]; then
    mkdir -p runs/recon_stem_geometry && cp -r checkpoints/recon_stem_geometry/{last,best} runs/recon_stem_geometry/
    chmod -R u+w runs/recon_stem_geometry  # the carried tree's files are read-only
fi
isosr train configs/train_recon_stem_geometry.json --steps "${GEO_STEPS:-9000}" --time-limit-minutes "$left" \
    > "$OUT/geo.log" 2>&1 &
isosr train configs/train_recon_stem_pixel.json --time-limit-minutes "$left" > "$OUT/pixel.log" 2>&1 &
wait
for name in geo pixel; do
    echo "$name:"
    tr '\r' '\n' < "$OUT/$name.log" | grep -a '^step \|"steps"\|"train_s"\|Error' | tail -4 | cut -c1-150 || true
done
tar czf "$OUT/runs.tgz" $(ls -d runs/recon_stem_geometry/{last,best} runs/recon_stem_pixel/{last,best} 2>/dev/null)
