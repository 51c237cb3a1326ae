#!/usr/bin/env bash
# Issue 49 item 4 on one GPU, one step a call of at most 10 minutes, from the project root (docs/training.md, "A
# fine-tune held to its start"; docs/measurements.md, "Half the sequences at 4 rays a pixel"):
#   bash scripts/measure_item4.sh datagen           # v6's data anew (seed 1): 325-393 s on an H200
#   bash scripts/measure_item4.sh train             # recon_model_v7 fine-tuned whole, held to it (MINUTES, 7)
#   bash scripts/measure_item4.sh bench SCENE...    # e.g. hydrogen:1080p chest_lidc:4k: beside the shipped model
# bench measures the run's best/ as "held" (or as $NAME; RUN may be any folder with a best/, e.g.
# checkpoints/recon_stem_cpu) and MODELS (LABEL=FOLDER,..., e.g. v6=isosr_net/recon_model_v6) at 1 and 4 rays a
# pixel and 1-64 AO rays (SPP, AO override): 40-190 s a scene on an H200 (SPP=1 AO=1,2,4: 25-90 s). The item's
# filters (SVGF, OIDN) need not run again: with MODELS=v7=isosr_net/recon_model_v7 its rows repeat the "recon" rows of
# benchmarks/results/pareto_filters_v6_cuda.json, whose SVGF and OIDN rows are then those frames'. Results land in $OUT
# (default /tmp/item4_out).
# NARROWS_PAST=N benches instead a copy of the run's best/ whose interval narrows past N rays
# ("ao_interval_narrows_past", a weightless field) as "heldN". The run of 2026-12-02 with N = 16 is the shipped
# isosr_net/recon_model; the model it started from, isosr_net/recon_model_v7, is its config's init and teacher.
set -euo pipefail
OUT=${OUT:-/tmp/item4_out}
DATA=${DATA:-/tmp/recon_4k_seed1}
RUN=${RUN:-/tmp/run_teacher}
mkdir -p "$OUT"
case "${1:?step: datagen, train or bench SCENE...}" in
    datagen)
        python3 -m isosr_cli.main datagen configs/datagen_recon_4k_seed1.json -o "$DATA" > "$OUT/datagen.log" 2>&1
        tail -2 "$OUT/datagen.log" ;;
    train)
        python3 -m isosr_cli.main train configs/train_recon_teacher_4k.json --data "$DATA" --out "$RUN" \
            --time-limit-minutes "${MINUTES:-7}" > "$OUT/train.log" 2>&1
        tr '\r' '\n' < "$OUT/train.log" | grep -v "^train:" | tail -4
        mkdir -p "$OUT/best" && cp -r "$RUN/best/." "$OUT/best/" ;;
    bench)
        shift
        models="${NAME:-held}=$RUN/best"
        if [ -n "${NARROWS_PAST:-}" ]; then
            copy=/tmp/held$NARROWS_PAST && rm -rf "$copy" && cp -r "$RUN/best" "$copy"
            python3 -c 'import json, sys; p = sys.argv[1] + "/config.json"; c = json.load(open(p))
c["model"]["ao_interval_narrows_past"] = float(sys.argv[2])
json.dump(c, open(p, "w"), indent=1)' "$copy" "$NARROWS_PAST"
            models="held$NARROWS_PAST=$copy"
        fi
        for scene in "$@"; do
            volume=${scene%:*} size=${scene#*:}
            python3 -m isosr_bench.bench_pareto --device cuda --volumes "$volume" --sizes "$size" \
                --kinds full,reconstruct --spp "${SPP:-1,4}" --ao-rays "${AO:-1,2,4,16,64}" \
                --models "$models${MODELS:+,$MODELS}" --out "$OUT/$volume-$size" > "$OUT/$volume-$size.log" 2>&1
            echo "$scene: $(tail -1 "$OUT/$volume-$size.log")"
        done ;;
    *) echo "unknown step $1 (datagen, train or bench)" >&2; exit 2 ;;
esac
