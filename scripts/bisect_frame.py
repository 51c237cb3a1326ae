"""Time the reconstructed frame of several commits on one machine, interleaved: an A/B of a change.

    python scripts/bisect_frame.py stage REV...        # here: .bisect_frame/<short hash>/ (git-ignored)
    python scripts/bisect_frame.py run --base HASH --out R.json [--rounds 3] [--frames 40] [--cases ...]

Each staged tree holds a commit's ``isosr_render``, ``isosr_net`` and ``isosr_bench``, its model
folders linked to the working tree's (the same weights: a change of a model is not what this
times). ``run`` starts a fresh interpreter per tree and round, the trees in turn within each
round (a machine's drift then reaches every tree alike), reversed every other round (the trees
that ran first in every round of one A/B had up to 0.3 ms more idle time in some rounds: the
order could not be told from the tree), and times each case, the reconstruction at 1 AO ray
through its runner (``Reconstructor.fastest``: on CUDA the fused fp16 kernels in one CUDA graph)
over the Pareto study's orbit, after its warm-up frames:

- ``pareto_ms``: as the study times a frame (CUDA events around each call, a sync after it);
- ``back_to_back_ms``: the frames in a row, one sync at the end;
- ``gpu_busy_ms`` (CUDA): the kernels' and copies' time per frame under ``torch.profiler``, and
  ``idle_ms = pareto_ms - gpu_busy_ms``: what the call spends with the GPU waiting (the host's
  work, launch latency, gaps between kernels).

The result keeps every row and, per case, each tree's medians over rounds and their ratio to
``--base``. A case is ``volume:size:model`` (``model`` x1, the shipped model, x2, or a model folder
under the project root, e.g. ``checkpoints/recon_stem_pixel/best``); on a CPU
use the study's smoke volumes and size (``cloud:smoke:x1``). The API timed is the one every commit
with ``Reconstructor.fastest`` and ``bench_recon_path.recon_method`` shares.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGE = ROOT / ".bisect_frame"
PACKAGES = ("isosr_render", "isosr_net", "isosr_bench")
CASES = "avg152t1:1080p:x1,ct_pitch:1080p:x1,avg152t1:1080p:x2,ct_pitch:4k:x1"
MEASURES = ("pareto_ms", "back_to_back_ms", "gpu_busy_ms", "idle_ms")


def stage(commits: list[str], stage_dir: Path = STAGE) -> list[Path]:
    """Export each commit's packages into ``stage_dir/<commit>/``, its model folders linked to the
    working tree's; the stage folder is git-ignored (``.git/info/exclude``)."""
    exclude = ROOT / ".git" / "info" / "exclude"
    entry = f"/{stage_dir.relative_to(ROOT)}/" if stage_dir.is_relative_to(ROOT) else None
    if entry and entry not in (exclude.read_text().split() if exclude.is_file() else []):
        exclude.parent.mkdir(parents=True, exist_ok=True)
        with exclude.open("a") as f:
            f.write(entry + "\n")
    trees = []
    for rev in commits:
        commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=7", rev], check=True,
                                capture_output=True, text=True).stdout.strip()
        target = stage_dir / commit
        target.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit, *PACKAGES], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(target)], input=archive, check=True)
        for model in (p for p in (target / "isosr_net").iterdir() if (p / "config.json").is_file()):
            subprocess.run(["rm", "-rf", str(model)], check=True)
            model.symlink_to(os.path.relpath(ROOT / "isosr_net" / model.name, model.parent))
        print(f"staged {rev} as {target}")
        trees.append(target)
    return trees


def child(tree: str, cases: str, frames: int, device: str) -> None:
    """In a fresh interpreter with ``tree`` first on the path: time the cases, print JSON rows."""
    sys.path.insert(0, tree)
    import torch

    from isosr_bench.bench_pareto import SIZES, SMOKE_SIZES, WARMUP, bench_cameras, load
    from isosr_bench.bench_recon_path import recon_method
    from isosr_bench.common import time_frames
    from isosr_net.methods import Networks, make_runner
    from isosr_net.reconstructor import DEFAULT_RECON_MODEL, RECON_X2_MODEL, Reconstructor
    from isosr_render import Renderer
    from isosr_render.sequence import sequence_cameras

    pairs, rows = sequence_cameras(bench_cameras(max(frames, WARMUP))), []
    cuda = device.startswith("cuda")
    for case in cases.split(","):
        volume_name, size, model = case.split(":")
        volume, iso = load(volume_name, device)
        renderer = Renderer(volume, device)
        path = {"x1": DEFAULT_RECON_MODEL, "x2": RECON_X2_MODEL}.get(model, ROOT / model)
        if not (path / "config.json").is_file():
            raise SystemExit(f"case {case}: the model is x1, x2 or a model folder under {ROOT}, got {model}")
        recon = Reconstructor.fastest(path, device=device)
        method = recon_method(str(path), 1, 1, recon.precision)
        runner = make_runner(method, renderer, iso, *{**SIZES, **SMOKE_SIZES}[size],
                             networks=Networks(lambda *_: recon))
        row = {"case": case, "method": method.name}
        row["pareto_ms"] = time_frames(lambda i: runner.frame(*pairs[i]), frames, device, warmup=WARMUP).get(
            "gpu_ms" if cuda else "wall_ms")
        if cuda:
            torch.cuda.synchronize()
        start = time.perf_counter()
        for i in range(frames):
            runner.frame(*pairs[i])
        if cuda:
            torch.cuda.synchronize()
        row["back_to_back_ms"] = (time.perf_counter() - start) / frames * 1e3
        if cuda:
            with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as profile:
                for i in range(frames):
                    runner.frame(*pairs[i])
                torch.cuda.synchronize()
            kernels: dict[str, float] = {}
            for e in profile.events():
                if e.device_type == torch.autograd.DeviceType.CUDA:
                    kernels[e.name[:60]] = kernels.get(e.name[:60], 0.0) + e.time_range.elapsed_us() / frames
            row["gpu_busy_ms"] = sum(kernels.values()) / 1e3
            row["idle_ms"] = row["pareto_ms"] - row["gpu_busy_ms"]
            row["kernels_us"] = {k: round(v, 1) for k, v in sorted(kernels.items(), key=lambda kv: -kv[1])}
        rows.append(row)
    print("ROWS " + json.dumps(rows))


def summary(rows: list[dict], base: str | None) -> list[dict]:
    """Per case and tree the medians over rounds; with ``base``, each measure's ratio to its tree's."""
    out = []
    for case in dict.fromkeys(r["case"] for r in rows):
        medians = {}
        for tree in dict.fromkeys(r["tree"] for r in rows):
            mine = [r for r in rows if r["case"] == case and r["tree"] == tree]
            medians[tree] = {m: statistics.median(r[m] for r in mine) for m in MEASURES if m in mine[0]}
        for tree, values in medians.items():
            line = {"case": case, "tree": tree, "rounds": sum(r["case"] == case and r["tree"] == tree for r in rows),
                    **{f"median_{m}": round(v, 4) for m, v in values.items()}}
            if base in medians and tree != base:
                line.update({f"ratio_{m}": round(v / medians[base][m], 4) for m, v in values.items()
                             if medians[base].get(m)})
            out.append(line)
    return out


def round_order(trees: list, r: int) -> list:
    """The trees in the order round ``r`` runs them: as given, reversed every other round."""
    return trees if r % 2 == 0 else trees[::-1]


def run(out: Path, base: str | None, rounds: int, frames: int, cases: str, device: str,
        stage_dir: Path = STAGE) -> dict:
    """Every staged tree once a round, a fresh interpreter each, for ``rounds`` rounds; write ``out``."""
    trees = sorted(p for p in stage_dir.iterdir() if all((p / pkg).is_dir() for pkg in PACKAGES))
    if base is not None and base not in [t.name for t in trees]:
        raise SystemExit(f"--base {base}: not a staged tree ({', '.join(t.name for t in trees) or 'none'})")
    rows, errors = [], {}
    for r in range(rounds):
        for tree in round_order(trees, r):
            done = subprocess.run([sys.executable, __file__, "child", str(tree), "--cases", cases, "--frames",
                                   str(frames), "--device", device], capture_output=True, text=True)
            line = [x for x in done.stdout.splitlines() if x.startswith("ROWS ")]
            if not line:
                errors[f"{tree.name} round {r}"] = done.stderr[-2000:]
                print(f"{tree.name} round {r}: failed\n{done.stderr[-2000:]}", flush=True)
                continue
            for row in json.loads(line[0][5:]):
                rows.append({"tree": tree.name, "round": r, **row})
                print(json.dumps({k: v for k, v in rows[-1].items() if k != "kernels_us"}), flush=True)
    import torch
    name = torch.cuda.get_device_name() if device.startswith("cuda") else "cpu"
    record = {"benchmark": "bisect_frame", "device": name, "command": " ".join(sys.argv), "base": base,
              "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "summary": summary(rows, base),
              "rows": rows, "errors": errors}
    out.write_text(json.dumps(record, indent=1))
    return record


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("stage", "run", "child"))
    parser.add_argument("args", nargs="*")
    parser.add_argument("--out", type=Path, default=Path(os.environ.get("OUT", ".")) / "bisect_frame.json")
    parser.add_argument("--base", help="the staged tree (short hash) the others are compared with")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--cases", default=CASES, help="comma-separated volume:size:model (default: %(default)s)")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--stage-dir", type=Path, default=STAGE)
    a = parser.parse_args(argv)
    if a.rounds < 1 or a.frames < 1:
        parser.error("--rounds and --frames must be at least 1")
    if a.what == "stage":
        stage(a.args, a.stage_dir)
    elif a.what == "run":
        run(a.out, a.base, a.rounds, a.frames, a.cases, a.device, a.stage_dir)
    else:
        child(a.args[0], a.cases, a.frames, a.device)


if __name__ == "__main__":
    main()
