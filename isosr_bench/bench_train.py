"""Data-parallel training's scaling: one training config on 1 GPU and on N GPUs (`torchrun`).

    python -m isosr_bench.bench_train --config configs/train_recon_x2_history.json --steps 2000 --gpus 1,2
    python -m isosr_bench.bench_train --config C --gpus 1,2 --concurrent    # each count on its own GPUs at once
    python -m isosr_bench.bench_train --config C --gpus 1,2 --seeds 0,1     # and the spread of two seeds
    python -m isosr_bench.bench_train --config C --gpus 1,2 --batch-size 32 # a larger global batch

Results: ``OUT/bench_train_<device>.json``. Each run trains ``--config`` from its
start (its own run folder under ``--runs``; the same data, steps and global batch: each of N
processes takes 1/N of every batch) and is read back from its ``last/`` checkpoint: the steps,
their wall seconds without validation and saving (``Trainer.timing``), ms per step after the
first ``WARMUP_STEPS`` (``warmup_s``: their seconds, where a compiled step compiles), training
sequences per second, and the validation scores at the end and of ``best/``. Against the 1-GPU
run: ``speedup`` (its ms per step over this run's) and ``efficiency`` (speedup over N).
``--seeds``: each count once per seed (default: the config's seed); against the 1-GPU run of the
same seed, and ``spread_db`` per count, the range of its runs' final color PSNR over the seeds.
``--concurrent`` starts the runs together on disjoint GPUs (they share the host's CPUs and PCIe):
it saves device time and is said in the result. On CPUs, N is the number of processes (gloo).
A later run with other ``--seeds`` keeps the rows of the result file's other seeds for the same
config, steps and batch (each with its own device and commit), so seeds may run in separate calls.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import torch

from isosr_bench.common import bench_parser, kept_rows, print_table, write_result
from isosr_net.configs import load_config
from isosr_net.train import WARMUP_STEPS, TrainConfig


def train_command(config: str, out: Path, steps: int | None, batch_size: int | None, seed: int,
                  processes: int, data: str | None = None, compile_mode: str | None = None) -> list[str]:
    """`isosr train` for one run: a plain process, or ``processes`` under torchrun (``--standalone``:
    each run's rendezvous on a free port, so that concurrent runs do not meet)."""
    launcher = ([sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={processes}"]
                if processes > 1 else [sys.executable])
    return [*launcher, "-m", "isosr_cli.main", "train", config, "--out", str(out), "--time-limit-minutes", "0",
            "--seed", str(seed), *(["--steps", str(steps)] if steps else []),
            *(["--batch-size", str(batch_size)] if batch_size else []), *(["--data", data] if data else []),
            *(["--compile", compile_mode] if compile_mode is not None else [])]


def gpu_sets(counts: list[int], concurrent: bool, available: int) -> list[list[int]]:
    """The GPUs of each run: disjoint when ``concurrent``, else each from GPU 0."""
    if not concurrent:
        if max(counts) > available:
            raise ValueError(f"{max(counts)} GPUs asked, {available} present")
        return [list(range(n)) for n in counts]
    if sum(counts) > available:
        raise ValueError(f"--concurrent runs need {sum(counts)} GPUs together, {available} present")
    starts = [sum(counts[:i]) for i in range(len(counts))]
    return [list(range(s, s + n)) for s, n in zip(starts, counts)]


def run_row(out: Path, processes: int, gpus: list[int]) -> dict:
    """One finished run as a result row, from its checkpoints."""
    last = json.loads((out / "last" / "config.json").read_text())
    best = json.loads((out / "best" / "config.json").read_text())
    timing, batch = last["timing"], last["training"]["batch_size"]
    warm, steady = timing.get("warmup_s"), timing["steps"] - WARMUP_STEPS
    ms = 1000.0 * (timing["train_s"] - warm) / steady if warm is not None and steady > 0 else \
        1000.0 * timing["train_s"] / timing["steps"]
    return {"processes": processes, "gpus": gpus, "steps": last["step"], "batch_size": batch,
            "train_s": timing["train_s"], "warmup_s": warm, "ms_per_step": ms, "sequences_per_s": batch * 1000.0 / ms,
            "val_color_psnr": last["validation"]["color_psnr"], "val_ao_psnr": last["validation"].get("ao_psnr"),
            "best_step": best["step"], "best_color_psnr": best["validation"]["color_psnr"]}


def main(argv: list[str] | None = None) -> list[dict]:
    parser = bench_parser(__doc__)
    parser.add_argument("--config", required=True, help="a TrainConfig JSON (its data must exist)")
    parser.add_argument("--steps", type=int, help="optimizer steps of every run (default: the config's)")
    parser.add_argument("--batch-size", type=int, help="global batch of every run (default: the config's)")
    parser.add_argument("--data", help="the datagen folder of every run (default: the config's)")
    parser.add_argument("--gpus", default="1,2", help="GPU (CPU: process) counts, comma-separated; 1 is the baseline")
    parser.add_argument("--seeds", help="seeds, comma-separated: every count runs once per seed "
                        "(default: the config's)")
    parser.add_argument("--concurrent", action="store_true", help="start the runs together on disjoint GPUs")
    parser.add_argument("--compile", help="every run's torch.compile mode of a step (TrainConfig.compile; "
                                          "default: the config's)")
    parser.add_argument("--runs", type=Path, default=Path("runs/bench_train"), help="the runs' folders")
    args = parser.parse_args(argv)
    counts = [int(n) for n in args.gpus.split(",") if n]
    if 1 not in counts or min(counts) < 1:
        parser.error(f"--gpus {args.gpus}: give the 1-GPU baseline and counts of 1 or more")
    config = load_config(TrainConfig, args.config)  # a bad config fails here, not in N processes
    seeds = [int(k) for k in args.seeds.split(",")] if args.seeds else [config.seed]
    runs = [(n, seed) for seed in seeds for n in counts]
    cuda = args.device.startswith("cuda")
    try:
        sets = gpu_sets([n for n, _ in runs], args.concurrent,
                        torch.cuda.device_count() if cuda else sum(n for n, _ in runs))
    except ValueError as e:
        parser.error(str(e))
    jobs = [start_run(args, n, seed, gpus if cuda else []) for (n, seed), gpus in zip(runs, sets)]
    mode = config.compile if args.compile is None else args.compile
    rows = [dict(finish_run(*job), seed=seed, concurrent=args.concurrent, config=args.config, compile=mode)
            for job, (_, seed) in zip(jobs, runs)]
    rows = with_other_seeds(args.out / f"bench_train_{'cuda' if cuda else 'cpu'}.json", rows)
    for r in rows:
        base = next(b for b in rows if b["processes"] == 1 and (b["seed"], b.get("compile", "")) ==
                    (r["seed"], r.get("compile", "")))
        r["speedup"] = base["ms_per_step"] / r["ms_per_step"]
        r["efficiency"] = r["speedup"] / r["processes"]
        psnrs = [o["val_color_psnr"] for o in rows if o["processes"] == r["processes"]]
        r["spread_db"] = max(psnrs) - min(psnrs) if len(psnrs) > 1 else None
    print_table(rows, ["processes", "seed", "steps", "ms_per_step", "sequences_per_s", "speedup", "efficiency",
                       "val_color_psnr", "best_color_psnr", "spread_db"])
    print(f"wrote {write_result('bench_train', args.device, rows, args.out)}")
    return rows


def with_other_seeds(path: Path, rows: list[dict]) -> list[dict]:
    """``rows`` after the rows of the result at ``path`` for the same study (config, steps, batch and
    compile mode) and other seeds, each with its own device and commit: seeds may run in separate calls."""
    def study(r: dict) -> tuple:
        return r.get("config"), r["steps"], r["batch_size"], r.get("compile", "")
    same, seeds = {study(r) for r in rows}, {r["seed"] for r in rows}
    return kept_rows(path, lambda r: study(r) in same and r["seed"] not in seeds, stamp=("device", "commit")) + rows


def start_run(args, processes: int, seed: int, gpus: list[int]) -> tuple:
    """Start one run from scratch in its own folder (waiting for it unless ``--concurrent``)."""
    out = args.runs / f"processes{processes}_seed{seed}"
    shutil.rmtree(out, ignore_errors=True)  # every run from its start: no resume
    out.mkdir(parents=True)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if gpus:
        env["CUDA_VISIBLE_DEVICES"] = ",".join(map(str, gpus))
    command = [*train_command(args.config, out, args.steps, args.batch_size, seed, processes, args.data,
                              args.compile),
               "--device", args.device.split(":")[0]]
    with open(out / "train.log", "w") as log:
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)
    if not args.concurrent:
        process.wait()
    return processes, gpus, out, process


def finish_run(processes: int, gpus: list[int], out: Path, process: subprocess.Popen) -> dict:
    """Wait for a run and read its row; a failed run stops the study with its log's end."""
    code = process.wait()
    if code != 0:
        raise SystemExit(f"the {processes}-process run failed ({code}): "
                         f"{(out / 'train.log').read_text(errors='replace')[-3000:]}")
    return run_row(out, processes, gpus)


if __name__ == "__main__":
    main()
