"""Time the renderer of several commits on one machine: a regression's bisection.

    python scripts/bisect_render.py stage REV...               # here: .bisect/<short hash>/isosr_render (git-ignored)
    python scripts/bisect_render.py run --out R.json [--frames 8]   # device: every staged tree, one at a time

Each tree's `isosr_render` runs in a fresh interpreter (the same module names, other code). Its
kernels are compiled first, all trees at once; then, one tree after another, the cases below
are timed over an orbit at 1920x1080: ``call_ms`` (CUDA events around each
``Renderer.render``, new buffers) and ``kernel_ms`` (the render kernels alone, Warp's timing:
``render_kernel`` up to 283f2bc, ``first_hit_kernel`` and a surface kernel after).
The API used is the one every commit since 877f0f0 shares.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGE = ROOT / ".bisect"
FIRST_HIT = ("mask", "normal", "depth")
# The render's kernels in any tree (in their timing names).
RENDER_KERNELS = ("render_kernel", "first_hit_kernel", "surface_kernel", "surface_samples_kernel")
# (volume, case, outputs, AO rays, with a previous camera, rays per pixel)
CASES = [("ct_pitch", "first hit", FIRST_HIT, 1, False, 1),
         ("ct_pitch", "AO 1 + flow", FIRST_HIT + ("ao", "flow"), 1, True, 1),
         ("ct_pitch", "AO 1 + flow, spp 4", FIRST_HIT + ("ao", "flow"), 1, True, 4),
         ("ct_pitch", "AO 64", ("mask", "normal", "ao"), 64, False, 1),
         ("bonsai", "first hit", FIRST_HIT, 1, False, 1),
         ("bonsai", "AO 64", ("mask", "normal", "ao"), 64, False, 1)]


def stage(commits: list[str]) -> None:
    """Export each commit's isosr_render into .bisect/<commit>/ (git-ignored through .git/info/exclude)."""
    exclude = ROOT / ".git" / "info" / "exclude"
    if "/.bisect/" not in (exclude.read_text().split() if exclude.is_file() else []):
        exclude.parent.mkdir(parents=True, exist_ok=True)
        with exclude.open("a") as f:
            f.write("/.bisect/\n")
    for rev in commits:
        commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=7", rev], check=True,
                                capture_output=True, text=True).stdout.strip()
        target = STAGE / commit
        target.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit, "isosr_render"], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(target)], input=archive, check=True)
        print(f"staged {rev} as {target.relative_to(ROOT)}")


def child(tree: str, frames: int, compile_only: bool) -> None:
    """In a fresh interpreter with ``tree`` first on the path: time the cases, print JSON rows."""
    sys.path.insert(0, tree)
    import torch
    import warp as wp

    from isosr_render import Renderer, RenderRequest, open_volume, orbit_path, resolve_iso
    from isosr_render import kernels

    wp.init()
    if compile_only:
        wp.load_module(kernels, device="cuda")
        return
    rows, renderers = [], {}
    path = orbit_path(frames + 3, yaw0=20.0, yaw_step=3.0, pitch=20.0, distance=1.8)
    for name, case, outputs, ao, flow, spp in CASES:
        if name not in renderers:
            volume = open_volume(f"shared:{name}")
            renderers[name] = (Renderer(volume, "cuda"), resolve_iso(f"shared:{name}", volume))
        renderer, iso = renderers[name]

        def render(i: int):
            request = RenderRequest(1920, 1080, iso, outputs, ao_samples=ao, ao_radius=0.02,
                                    prev_camera=path[i] if flow else None, spp=spp)
            return renderer.render(path[i + 1], request)

        for i in range(2):
            render(i)
        torch.cuda.synchronize()
        starts = [torch.cuda.Event(enable_timing=True) for _ in range(frames)]
        ends = [torch.cuda.Event(enable_timing=True) for _ in range(frames)]
        for i in range(frames):
            starts[i].record()
            render(i + 2)
            ends[i].record()
        torch.cuda.synchronize()
        call = sum(s.elapsed_time(e) for s, e in zip(starts, ends)) / frames
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
        for i in range(frames):
            render(i + 2)
        results = wp.timing_end()
        kernel = sum(r.elapsed for r in results if any(k in r.name for k in RENDER_KERNELS)) / frames
        rows.append({"volume": name, "case": case, "call_ms": round(call, 3), "kernel_ms": round(kernel, 3)})
    print("ROWS " + json.dumps(rows))


def run(out: Path, frames: int) -> None:
    """Compile every staged tree at once, then time them one after another."""
    trees = sorted(p for p in STAGE.iterdir() if (p / "isosr_render").is_dir())
    me = [sys.executable, __file__, "child"]
    began = time.perf_counter()
    compiles = [subprocess.Popen(me + [str(t), "--compile"]) for t in trees]
    for p in compiles:
        p.wait()
    print(f"compiled {len(trees)} trees in {time.perf_counter() - began:.0f} s", flush=True)
    record = {"device": None, "frames": frames, "command": " ".join(sys.argv), "trees": {}}
    for tree in trees:
        done = subprocess.run(me + [str(tree), "--frames", str(frames)], capture_output=True, text=True)
        line = [x for x in done.stdout.splitlines() if x.startswith("ROWS ")]
        record["trees"][tree.name] = json.loads(line[0][5:]) if line else {"error": done.stderr[-2000:]}
        print(tree.name, json.dumps(record["trees"][tree.name]), flush=True)
    import torch
    record["device"] = torch.cuda.get_device_name()
    out.write_text(json.dumps(record, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("stage", "run", "child"))
    parser.add_argument("args", nargs="*")
    parser.add_argument("--out", type=Path, default=Path(os.environ.get("OUT", ".")) / "bisect_render.json")
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--compile", action="store_true")
    a = parser.parse_args()
    if a.what == "stage":
        stage(a.args)
    elif a.what == "run":
        run(a.out, a.frames)
    else:
        child(a.args[0], a.frames, a.compile)


if __name__ == "__main__":
    main()
