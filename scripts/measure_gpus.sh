#!/usr/bin/env bash
# The several-GPU measurements (docs/several-gpus.md) on one host with 4 GPUs, one step per call
# of at most 10 minutes, from the project root. The cluster steps add their rows to one result
# file under $CL (default /tmp/cl; each run keeps the other servers' rows) and copy it to $OUT:
#   bash scripts/measure_gpus.sh cluster 0 16,32,64   # the plain server on GPU 0 (fills the kernel caches)
#   bash scripts/measure_gpus.sh cluster 1 16,32,64   # one replica on GPU 0
#   bash scripts/measure_gpus.sh cluster 2 16,32,64   # two replicas on GPUs 0-1, then failover (32 sessions)
#   bash scripts/measure_gpus.sh cluster 4 16,32,64   # four replicas on GPUs 0-3, then failover
#   bash scripts/measure_gpus.sh one-gpu              # 1, 2 and 4 replicas sharing GPU 0, 16 sessions
#   ENC=h264 CASES=full:0,reconstruct:1 bash scripts/measure_gpus.sh mps 16,32   # 4 replicas on GPU 0 under MPS
#       behind HAProxy (SETTLE: untimed seconds first, e.g. 20 for auto; SW: the switch interval, ms)
#   bash scripts/measure_gpus.sh datagen              # training data (GPU 3 unless GPU is set)
#   bash scripts/measure_gpus.sh train SEED           # training on 1 and on 2 GPUs at once (GPUs 0-2, or GPUS)
#   COMPILE=default bash scripts/measure_gpus.sh train SEED   # the same with a compiled step
#   CONCURRENT=0 GPUS=1,2 bash scripts/measure_gpus.sh train SEED   # 1 GPU, then 2, one after the other
# GPUS (CUDA_VISIBLE_DEVICES) moves a cluster or training step to other GPUs, so that steps share a host.
# LEASE names the machine's lease for every call in it (default: the first call's hour; rows are
# compared within one lease). CASES (default: the bench's full:0,reconstruct:1,auto:0) narrows the cases of a cluster
# step; DRAG (Hz) makes its sessions dragging viewers (bench_cluster --drag-hz) instead of closed loops.
# A step took, on 4 H200s: about 45-70 s to start a server or Ray with its replicas (warm kernel
# caches), 25-50 s a case, 15 s a failover.
# On the lab's lent machines, Ray and the server's wheels arrive split over several calls (64 MiB
# a call; scripts/stage_gpu_extras.sh): `kit` joins the parts of Ray parked in /tmp/kit.
set -euo pipefail
OUT=${OUT:-/tmp/gpus_out}
CL=${CL:-/tmp/cl}
[ -f /tmp/lease ] || date -u "+%Y-%m-%d %H:00" > /tmp/lease
LEASE=${LEASE:-$(cat /tmp/lease)}
VOLUME=${VOLUME:-bonsai}
mkdir -p "$OUT" "$CL"
cluster() {
    python3 -m isosr_bench.bench_cluster --device cuda --volume "$VOLUME" --seconds "${SECONDS_PER_CASE:-3}" \
        --out "$CL" --lease "$LEASE" ${CASES:+--cases "$CASES"} ${DRAG:+--drag-hz "$DRAG"} "$@"
}
gpus_for() { case "$1" in 0|1) echo 0 ;; 2) echo 0,1 ;; *) echo 0,1,2,3 ;; esac; }
case "${1:?step: kit, cluster N SESSIONS, one-gpu, mps SESSIONS, datagen or train SEED}" in
    kit)
        mkdir -p /tmp/raysite
        cat /tmp/kit/raysite.part-* | python3 -c "import sys,tarfile; tarfile.open(fileobj=sys.stdin.buffer, mode='r|xz').extractall('/tmp/raysite', filter='data')"
        echo "ray unpacked: $(du -sh /tmp/raysite | cut -f1)" ;;
    cluster)
        n=${2:?replicas (0: the plain server)}
        failover=$([ "$n" -ge 2 ] && echo 32 || echo 0)
        CUDA_VISIBLE_DEVICES=${GPUS:-$(gpus_for "$n")} cluster --gpus-per-replica 1 --replicas "$n" \
            --sessions "${3:-16,32,64}" --failover-sessions "$failover" ;;
    one-gpu) CUDA_VISIBLE_DEVICES=0 cluster --gpus-per-replica split --replicas 1,2,4 --sessions 16 --failover-sessions 0 ;;
    mps)
        export CUDA_MPS_PIPE_DIRECTORY=/tmp/nvidia-mps CUDA_MPS_LOG_DIRECTORY=/tmp/nvidia-mps-log
        mkdir -p "$CUDA_MPS_PIPE_DIRECTORY" "$CUDA_MPS_LOG_DIRECTORY"
        pgrep -f nvidia-cuda-mps-control >/dev/null || CUDA_VISIBLE_DEVICES=0 nvidia-cuda-mps-control -d
        ISOSR_SWITCH_INTERVAL_MS=${SW:-1} CUDA_VISIBLE_DEVICES=0 SECONDS_PER_CASE=${SECONDS_PER_CASE:-10} cluster \
            --gpus-per-replica split --replicas 4 --sessions "${2:-16}" --failover-sessions 0 --ingress haproxy \
            --client-processes 4 --encoding "${ENC:-jpeg}" --settle "${SETTLE:-0}" ;;
    datagen)
        # configs/datagen_recon_history.json over the volumes present (ISOSR_SHARED_VOLUMES).
        python3 - <<'PY'
import json
from isosr_render.catalog import manifest
present = {e["name"] for e in manifest()}
config = json.load(open("configs/datagen_recon_history.json"))
config["volumes"] = [v for v in config["volumes"] if not v.startswith("shared:") or v[7:] in present]
json.dump(config, open("/tmp/datagen_scaling.json", "w"), indent=1)
print("datagen volumes:", config["volumes"])
PY
        CUDA_VISIBLE_DEVICES=${GPU:-3} python3 -m isosr_cli.main datagen /tmp/datagen_scaling.json -o /tmp/data/scaling ;;
    train)
        CUDA_VISIBLE_DEVICES=${GPUS:-0,1,2} python3 -m isosr_bench.bench_train --device cuda \
            --config configs/train_recon_history.json --data /tmp/data/scaling --gpus 1,2 $([ "${CONCURRENT:-1}" = 1 ] && echo --concurrent) \
            --steps "${STEPS:-600}" --batch-size "${BATCH:-32}" --seeds "${2:?seed}" --runs /tmp/bt --out "$CL" \
            ${COMPILE:+--compile "$COMPILE"} ;;
    *) echo "unknown step $1" >&2; exit 2 ;;
esac
cp "$CL"/*.json "$OUT"/ 2>/dev/null || true
