# Device side of a measuring session on a lent GPU machine (source it from the project root): the GPU kit
# (../shared/gpu/README.md: part a parked by an earlier run, part b carried, or installed already), the server's
# wheels (.gpu/s, scripts/stage_gpu_extras.sh s, installed into /tmp/ssite by the first run), the staged volumes
# (.vols, scripts/stage_gpu_volumes.py bonsai), kernel caches kept under /tmp for the machine's next runs, and
# `pack`: those caches back under $OUT in parts under the 16 MiB a returned file may have.
# A session's runs, each carrying what it names (64 MiB a run, the working tree included: thin it with
# scripts/gpu/trim.sh out, and `back` after):
#   1. carry [".gpu/a", ".gpu/s"]:  bash .gpu/a/stage.sh && python3 -m pip install -q --no-index --no-deps --target /tmp/ssite .gpu/s/*.whl
#   2. carry [".gpu/b", ".gpu/HEAD"]:   source scripts/gpu/env.sh && <command>   (not .vols: beside part b and the
#      tree they pass 64 MiB, so this run takes work that reads no shared volume, e.g. the fused checks; a datagen
#      of shared volumes, recon_4k's, fails here)
#   3. later, warm:  carry [".gpu/b/env.sh", ".gpu/HEAD", ".vols"] and the same.
source .gpu/b/env.sh || return 3
export PYTHONPATH=$PYTHONPATH:/tmp/ssite
export ISOSR_SHARED_VOLUMES=$PWD/.vols
export WARP_CACHE_PATH=/tmp/wcache
export ISOSR_COMMIT=${ISOSR_COMMIT:-$(cat .gpu/HEAD 2>/dev/null || echo unknown)}  # the copy has no .git
export OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
pack() {
    tar czf - -C / $(cd / && ls -d tmp/wcache root/.triton/cache 2>/dev/null) | split -b 15M - "$OUT/caches.tgz.part-"
    ls -la "$OUT"/caches.tgz.part-*
}
