#!/usr/bin/env bash
# Thin the working tree under what a device run carries (64 MiB with the GPU kit's part b): `trim.sh out` parks
# what the GPU runs do not read (results, docs, checkpoints, earlier models) in /tmp/isosr-trimmed, `trim.sh back`
# returns it; `out` also writes the commit into .gpu/HEAD, which the runs carry for their results (the copy there
# has no .git). Commit nothing in between. The shipped models travel (isosr_net/recon_model, and recon_model_v4
# that the fused checks read; the upscaler's default_model that the Pareto study reads), and the stem's run that
# scripts/gpu/train_stems.sh resumes (checkpoints/recon_stem_pixel; its CONTROL=1 run starts from
# checkpoints/recon_stem_geometry/best, parked here: move it back from /tmp/isosr-trimmed for that run).
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
parked=(checkpoints/recon_4k checkpoints/recon_blend checkpoints/recon_gates checkpoints/recon_shipped_gates
        checkpoints/recon_psnr_control checkpoints/recon_stem checkpoints/recon_stem_cpu
        checkpoints/recon_stem_pixel_cpu checkpoints/recon_stem_notail checkpoints/recon_stem_geometry
        benchmarks docs examples deploy isosr_net/recon_model_v1 isosr_net/recon_model_v2
        isosr_net/recon_model_v3 isosr_net/recon_model_v5 isosr_net/recon_model_v6)
case "${1:?out or back}" in
    out) for p in "${parked[@]}"; do  # a path parked already would be moved into it, and come back nested
             [ ! -e "/tmp/isosr-trimmed/$p" ] || { echo "/tmp/isosr-trimmed/$p exists: 'back' first" >&2; exit 2; }
         done
         mkdir -p .gpu && git rev-parse --short HEAD > .gpu/HEAD
         for p in "${parked[@]}"; do mkdir -p "$(dirname "/tmp/isosr-trimmed/$p")"; [ ! -e "$p" ] || mv "$p" "/tmp/isosr-trimmed/$p"; done ;;
    back) for p in "${parked[@]}"; do [ ! -e "/tmp/isosr-trimmed/$p" ] || mv "/tmp/isosr-trimmed/$p" "$p"; done ;;
    *) echo "unknown step $1 (out or back)" >&2; exit 2 ;;
esac
# What travels: tracked and untracked-not-ignored files that are here (parked ones are not).
echo "the tree that travels: $(git ls-files -z --cached --others --exclude-standard | xargs -0 du -cb 2>/dev/null | tail -1 \
    | awk '{printf "%.1fM", $1 / 1048576}')"
