#!/usr/bin/env bash
# Batched frames (issue 50) measured on one GPU, in one lease: the plain server of the tree before
# batching (BASE) against this tree's, alternating by round, at 16 and 32 view sessions of 1080p in
# `reconstruct` (1 AO ray) and `full`; then a py-spy profile of this tree's server at 16 sessions.
#   bash scripts/measure_batching.sh stage [BASE]   # here: .ab/base = BASE's packages (default 736ccbe)
#   bash scripts/measure_batching.sh run [ROUNDS]   # on the GPU machine, from the project root
#   TREES=head PROFILE=0 bash scripts/measure_batching.sh run 1   # one tree, no profile
#   CASES=reconstruct:1,full:0,auto:0 SESSIONS=16,32 ...          # the cases (default: as here, without auto)
# Results under $OUT (default /tmp/ab_out): ab_<base|head>_<round>/bench_cluster_1080p_cuda.json (the
# rows: frames/s, p50/p99, stage times, GPU busy, the server's cores) and profile_server_*.json.
# On the lab's lent machines .ab/ (git-ignored, a few MB) travels as a carried path beside the kit
# (../shared/gpu/README.md), and py-spy as .venv/bin/py-spy copied onto PATH.
set -euo pipefail
OUT=$(realpath -m "${OUT:-/tmp/ab_out}")
VOLUME=${VOLUME:-bonsai}
case "${1:?stage or run}" in
    stage)
        rm -rf .ab/base && mkdir -p .ab/base
        git archive "${2:-736ccbe}" isosr_render isosr_net isosr_server isosr_client isosr_bench isosr_cli \
            | tar -x -C .ab/base
        git rev-parse --short "${2:-736ccbe}" > .ab/base/COMMIT  # the results' commit (the copy has no .git)
        echo "staged $(git rev-parse --short "${2:-736ccbe}") in .ab/base ($(du -sh .ab/base | cut -f1))" ;;
    run)
        for round in $(seq "${2:-2}"); do
            for tree in ${TREES:-base head}; do
                root=$([ "$tree" = head ] && pwd || echo "$PWD/.ab/$tree")
                # from the tree's own folder: `python -m` puts the working directory first on sys.path
                stamp=$(cat "$root/COMMIT" 2>/dev/null || echo "${ISOSR_COMMIT:-$(git rev-parse --short HEAD)}")
                (cd "$root" && ISOSR_COMMIT=$stamp PYTHONPATH="$root:${PYTHONPATH:-}" python3 -m isosr_bench.bench_cluster \
                    --device cuda --volume "$VOLUME" --replicas 0 --sessions "${SESSIONS:-16,32}" \
                    --cases "${CASES:-reconstruct:1,full:0}" --seconds 5 --failover-sessions 0 --out "$OUT/ab_${tree}_${round}")
            done
        done
        [ "${PROFILE:-1}" = 0 ] || python3 scripts/profile_server.py --device cuda --volume "$VOLUME" --mode reconstruct \
            --ao 1 --sessions 16 --seconds 8 --out "$OUT" ;;
    *) echo "unknown step $1" >&2; exit 2 ;;
esac
