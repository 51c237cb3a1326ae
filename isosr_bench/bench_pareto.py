"""What accuracy costs in time, on one scale: every way to make a frame, timed and scored.

    python -m isosr_bench.bench_pareto --device cuda                        # every volume, 1080p and 4K
    python -m isosr_bench.bench_pareto --device cuda --volumes ct_pitch,hydrogen --sizes 1080p
    python -m isosr_bench.bench_pareto --device cpu --smoke                 # small, in the test suite
    python -m isosr_bench.bench_pareto --device cuda --volumes avg152t1 --sizes 4k \
        --kinds reconstruct,svgf --models tuned=runs/recon_4k/best     # an A/B of two models, in minutes
    python -m isosr_bench.bench_pareto --device cuda --sizes 1080p --kinds full,reconstruct \
        --spp 4 --ao-rays 16,32,64                                      # the top of the front alone
    python -m isosr_bench.bench_pareto --device cuda --sizes 1080p --budget-only \
        --out benchmarks/results       # the policy anew, scored by the methods' rows that file holds

Every method of :mod:`isosr_net.methods` (full resolution with 0-128 AO rays and 1, 2, 4
rays per pixel; the a-trous filter, the SVGF temporal filter and OIDN (fast and high, where
``pyoidn`` is installed; else a line says why not) over 1, 2, 4 AO rays; the shipped
reconstruction networks (full size, and x2 from a half-size render: :data:`SHIPPED_MODELS`) over
0-16 AO rays (to each model's limits) at 1, 2, 4 rays per pixel, fp16 on CUDA; x2,
x4, x8 nearest, bilinear, bicubic; every upscaling network at fp32, bf16, fp16 on CUDA; fp32 on
CPUs) is timed as a whole path (render, reconstruction, shading) per frame, in sequence over an
8-frame orbit so that recurrent state (the networks', SVGF's history) is real, after warm-up
(CUDA events on GPUs, wall time on CPUs), and each of those frames is scored against a
reference rendered for it with 4 rays per pixel (``--reference-spp``) and 512 AO rays:

- ``color_psnr``, ``color_ssim``: shaded color on the covered region (either mask > 0.5);
  ``image_psnr``, ``image_ssim``: the same on the whole image; ``color_psnr_8bit``: ``color_psnr`` of the
  colors a viewer receives, both quantized to 8 bits (within half a level everywhere: the ceiling, 100 dB;
  one level off everywhere: 48.1 dB); ``color_psnr_scene``: on the scene's region, the same pixels for
  every method (:func:`isosr_net.metrics.scene_region`: the reference's covered pixels and their
  neighbours), which compares a scene's rows like with like: the fronts, the scorecard and the
  best fixed setting rank by it (:func:`front_psnr`);
- ``ao_rmse``: RMS AO error where both cover (a method without AO counts as AO 1; one that casts
  AO rays but gives only a color, OIDN, has none: null);
- ``flicker``: :func:`isosr_net.metrics.color_instability` of the frames' colors along the
  reference's flow: the mean absolute color change from the previous frame warped to this one;
  ``flicker_reference`` is the reference's own, and ``flicker_ratio`` the method's over it (1:
  as steady as the reference).

The reference's AO rays have their own seed, but its subpixel pattern is the renderer's fixed
one: the ``spp 4`` rows have the reference's geometry exactly, so their scores measure AO error
alone and are optimistic against a truly converged image. ``--reference-spp 16`` scores a
selection against references of 16 rays per pixel, of which a frame's 4 are the first (rows:
``reference_spp``).

A row's scores are of one draw of the AO rays (the service's seeds) unless ``--draws K`` (a selection only) scores
each method over K draws of the same frames (:class:`~isosr_net.methods.FrameRunner`'s ``draw``; the first timed):
the scores are their means, and ``color_psnr_scene_draws`` lists each draw's. Where a few rays decide a pixel's
error (hydrogen: nearly unoccluded, rare hits), one draw's score moves by a decibel or two from seed to seed
(measurements.md, "What one draw can tell").

An empty covered region (iso outside the data) has no PSNR or SSIM: written as null, and left
out of the Pareto fronts. Rows (``part: pareto``): one per (volume, size, method). The budget
part (``part: budget``) runs the policy of :mod:`isosr_net.budget` at 4, 8, 16 and 33 ms and
sets the PSNR this run measured for its choice against the best fixed setting that fits the
budget here (the best row with ``ms`` at most the budget). ``--budget-only`` runs that part
alone, scored by the methods' rows the result file holds for each scene (measured on this kind
of device; ``rows_commit`` names their commit), without timing the methods again.

Volumes: the val volumes of the catalog, a simulation (hydrogen), and bonsai resampled to
1024^3. ``--volumes`` and ``--sizes`` select; their rows replace those of the same volume and
size in an existing ``pareto_<kind>.json`` and the others are kept, so a long run can be split.
``--sizes`` also takes ``WxH`` (a small CPU run: ``--sizes 256x256``).

Translucent surfaces (``--translucent A``): each scene's methods again on two surfaces, the volume's iso at opacity
``A`` over the iso :data:`INNER_ISO_STEP` above it (the normalized scale; opaque: bone under skin), scored against
references of the same surfaces (their two layers composited by the renderer), as rows of ``part: layers``
(``surfaces``: ``[[iso, opacity], ...]``) beside the single surface's: what the second layer costs every method
(each runs on both layers apart, then composites; ``full`` composites in its render).
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from pathlib import Path

import torch

from isosr_render import Renderer, Volume, open_volume, orbit_path, resolve_iso
from isosr_render.catalog import entry, manifest
from isosr_render.images import quantize
from isosr_render.renderer import MAX_SPP
from isosr_render.sequence import sequence_cameras
from isosr_render.shapes import frame_size
from isosr_render.surfaces import PALETTE, Surfaces
from isosr_net.budget import (REFERENCE_AO_RAYS, REFERENCE_SPP, BudgetConfig, choose_method, front_psnr, probe_quality,
                              reference_frames)
from isosr_net.flow_warp import warp_by_flow
from isosr_net.methods import RUNNERS, FrameMethod, Networks, make_runner, run_sequence, unavailable_kinds
from isosr_net.metrics import color_instability, eval_region, masked_psnr, masked_ssim, scene_region
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, RECON_X2_MODEL
from isosr_net.upscaler import DEFAULT_MODEL

from .bench_knobs import parse_models
from .bench_pipeline import resampled
from .common import (bench_parser, commit, device_name, kept_rows, mean_ms, print_table, time_frames,
                     write_result)

NAME = "pareto"
SELECT_NAME = "pareto_select"  # runs of some method kinds (--kinds), such as a quick A/B of two models
SIZES = {"1080p": (1920, 1080), "4k": (3840, 2160)}
SMOKE_SIZES = {"smoke": (96, 64)}
# The inner surface of --translucent: this much above the volume's iso (normalized scale).
INNER_ISO_STEP = 0.1
EXTRA_VOLUMES = ("hydrogen", "bonsai1024")
SMOKE_VOLUMES = {"sphere": "proc:sphere@32", "cloud": "proc:cloud:7@48"}
FRAMES, SMOKE_FRAMES = 8, 3
MAX_DRAWS = 64  # --draws: each a whole run of the method's frames
WARMUP = 3  # a compiled network with CUDA graphs compiles, then records, then replays
SMOKE_WARMUP = 1  # eager on the CPU: one call loads what it needs
BUDGETS, SMOKE_BUDGETS = (4.0, 8.0, 16.0, 33.0), (3.0, 30.0)
# The top of the budget ladder of :func:`learned_scorecard`.
GOAL_TOP_MS = 50.0
# Cost of a primary ray in AO rays, for the time estimate only (README: 1080p first hit vs AO 128).
PRIMARY_IN_AO_RAYS = 6
# The non-learned filters over few AO rays the reconstruction is compared with at the same rays.
BASELINE_KINDS = ("atrous", "svgf", "oidn")
# The shipped networks, measured by default (those the server's auto mode chooses among).
SHIPPED_MODELS = {"network": DEFAULT_MODEL, "recon": DEFAULT_RECON_MODEL, "recon_x2": RECON_X2_MODEL}


def methods(smoke: bool, device: str, models: dict[str, Path]) -> list[FrameMethod]:
    """The methods measured: every registered kind's that can run here
    (:meth:`~isosr_net.methods.FrameRunner.bench_methods`; a line says why a kind is left out),
    fewer settings in smoke mode: first the kinds without a network, then per model the learned
    kinds' settings of it."""
    missing = unavailable_kinds()
    for kind, reason in missing.items():
        print(f"{kind} left out: {reason}", flush=True)
    runners = [cls for kind, cls in RUNNERS.items() if kind not in missing]
    out = [m for cls in runners if cls.network_class is None for m in cls.bench_methods(smoke, device)]
    for model in models.items():
        out += [m for cls in runners if cls.network_class is not None for m in cls.bench_methods(smoke, device, model)]
    return out


def volume_names(smoke: bool) -> list[str]:
    """The volumes measured by default."""
    if smoke:
        return list(SMOKE_VOLUMES)
    return [e["name"] for e in manifest() if e["split"] == "val"] + list(EXTRA_VOLUMES)


def load(name: str, device: str) -> tuple[Volume, float]:
    """``(volume, normalized iso)`` by name: a smoke volume, ``bonsai1024``, or a catalog volume."""
    if name in SMOKE_VOLUMES:
        volume = open_volume(SMOKE_VOLUMES[name])
        return volume, resolve_iso(SMOKE_VOLUMES[name], volume)
    e = entry("bonsai" if name == "bonsai1024" else name)
    volume = open_volume(str(e["path"]))
    if name == "bonsai1024":
        volume = resampled(volume, 1024, device)
    return volume, e["otsu_iso_normalized"]


def finite(x: float) -> float | None:
    """JSON has no NaN: an undefined score is null."""
    return None if math.isnan(x) else x


def scores(frames: list, references: list, ao_rays: int = 0) -> dict:
    """Mean scores of a method's frames against the references (see the module docstring); ``ao_rays``:
    the method's (a frame without AO counts as AO 1 only where it cast none)."""
    per = {k: [] for k in ("color_psnr", "color_ssim", "image_psnr", "image_ssim", "ao_rmse", "color_psnr_8bit",
                           "color_psnr_scene")}
    for f, r in zip(frames, references):
        pred, ref = f.color.permute(2, 0, 1)[None], r.color.permute(2, 0, 1)[None]
        region = eval_region(f.mask[None, None], r.mask[None, None])
        whole = torch.ones_like(region)
        per["color_psnr"].append(float(masked_psnr(pred, ref, region)[0]))
        per["color_psnr_scene"].append(float(masked_psnr(pred, ref, scene_region(r.mask[None, None]))[0]))
        per["color_ssim"].append(float(masked_ssim(pred, ref, region)[0]))
        shown, truth = (quantize(c).float() / 255 for c in (pred, ref))
        per["color_psnr_8bit"].append(float(masked_psnr(shown, truth, region)[0]))
        per["image_psnr"].append(float(masked_psnr(pred, ref, whole)[0]))
        per["image_ssim"].append(float(masked_ssim(pred, ref, whole)[0]))
        both = (f.mask > 0.5) & (r.mask > 0.5)
        ao = f.ao if f.ao is not None else None if ao_rays else torch.ones_like(f.mask)
        per["ao_rmse"].append(float((ao - r.ao)[both].square().mean().sqrt()) if ao is not None and both.any()
                              else math.nan)
    out = {k: finite(torch.tensor(v, dtype=torch.float64).nanmean().item()) for k, v in per.items()}
    out["flicker"] = finite(flicker(frames, references)) if len(frames) > 1 else None
    return out


def frames_of(runner, cameras: list, warmup: int) -> list:
    """The buffers of the frames along ``cameras`` (copies), after ``warmup`` frames along their first as
    :func:`time_frames` makes them: a timed run's frames, untimed."""
    run_sequence(runner, cameras[:warmup])
    return run_sequence(runner, cameras)


def drawn_scores(draws: list[dict]) -> dict:
    """Scores over draws of the same frames' rays: each score's mean over the draws that have it (null: none),
    and ``color_psnr_scene_draws``, each draw's."""
    mean = {k: finite(torch.tensor([d[k] for d in draws if d[k] is not None], dtype=torch.float64).mean().item())
            for k in draws[0]}
    return {**mean, "color_psnr_scene_draws": [d["color_psnr_scene"] for d in draws]}


def flicker(frames: list, references: list) -> float:
    """:func:`isosr_net.metrics.color_instability` of the frames' colors along the references' flow."""
    colors = torch.stack([f.color.permute(2, 0, 1) for f in frames])[:, None]
    masks = torch.stack([f.mask for f in frames])[:, None, None]
    flows = torch.stack([r.flow.permute(2, 0, 1) for r in references])[:, None]
    return float(color_instability(colors, masks, flows, warp_by_flow)[0])


def work(method: FrameMethod) -> float:
    """A method's ray work relative to one primary ray per pixel (for the time estimate only)."""
    return method.spp * (1.0 + method.ao_rays / PRIMARY_IN_AO_RAYS) / method.factor ** 2


def bench_cameras(frames: int):
    """The orbit every method is timed and scored on; the budget policy probes the same views."""
    return orbit_path(frames, yaw0=20.0, yaw_step=3.0, pitch=20.0, distance=1.6)


def pareto_rows(renderer: Renderer, iso: float, volume: str, size: tuple[int, int], size_name: str,
                measured: list[FrameMethod], frames: int, warmup: int, device: str, networks: Networks,
                surfaces: Surfaces | None = None, reference_spp: int = REFERENCE_SPP, draws: int = 1) -> list[dict]:
    """One row per method on one volume and size (with ``surfaces``: of them, ``part: layers``), scored against
    references of ``reference_spp`` rays per pixel, over ``draws`` draws of the AO rays (the first timed). A
    network's captured graphs are freed after its last method here, so that one model's at most are held."""
    cameras = bench_cameras(frames)
    pairs = sequence_cameras(cameras)
    start = time.perf_counter()
    refs = reference_frames(renderer, iso, size, cameras, flow=True, surfaces=surfaces, spp=reference_spp)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    ref_s = time.perf_counter() - start
    reference_work = work(FrameMethod.of("full", ao_rays=REFERENCE_AO_RAYS, spp=reference_spp))
    estimate = ref_s * (1 + (warmup + frames) / frames * sum(work(m) for m in measured) / reference_work)
    print(f"{volume} {size_name}: references {ref_s:.1f} s; estimated {estimate:.0f} s for the methods "
          f"(plus compiling networks on first use)", flush=True)
    flicker_reference = scores(refs, refs)["flicker"]
    stamp = run_stamp(device)
    part = {"part": "pareto"} if surfaces is None else {
        "part": "layers", "surfaces": [[s.iso, s.opacity] for s in surfaces.items]}
    rows, held = [], None
    for method in measured:
        runner = make_runner(method, renderer, iso, *size, networks=networks, surfaces=surfaces)
        if held is not None and runner.net is not held:  # a model's methods are measured together (methods())
            held.drop_graphs()  # its graphs go before the next model's are captured
        held = runner.net
        outs = [None] * frames
        t = time_frames(lambda i: runner.frame(*pairs[i]).buffers, frames, device, warmup=warmup,
                        keep=lambda i, buffers: outs.__setitem__(i, buffers.clone()))
        scored = scores(outs, refs, method.ao_rays)
        if draws > 1:
            scored = drawn_scores([scored] + [scores(frames_of(make_runner(
                method, renderer, iso, *size, networks=networks, surfaces=surfaces, draw=d), cameras, warmup), refs,
                method.ao_rays) for d in range(1, draws)])
        ratio = None if scored["flicker"] is None or not flicker_reference else scored["flicker"] / flicker_reference
        rows.append({**part, "volume": volume, "size": size_name, "pixels": f"{size[0]}x{size[1]}",
                     "method": method.name, "kind": method.kind, "learned": method.learned,
                     "ao_rays": method.ao_rays, "spp": method.spp, "factor": method.factor,
                     "ms": mean_ms(t), "wall_ms": t["wall_ms"],
                     **scored, "flicker_reference": flicker_reference, "flicker_ratio": ratio,
                     "coverage": float(sum(float((r.mask > 0.5).float().mean()) for r in refs) / frames),
                     "reference_spp": reference_spp, "draws": draws, **stamp})
    if held is not None:
        held.drop_graphs()
    print(f"{volume} {size_name}: {time.perf_counter() - start:.0f} s", flush=True)
    return rows


def budget_rows(renderer: Renderer, iso: float, volume: str, size: tuple[int, int], size_name: str,
                measured: list[FrameMethod], rows: list[dict], budgets, networks: Networks, smoke: bool) -> list[dict]:
    """The policy's choice per budget, scored by this run's rows, against the best fixed setting that fits."""
    precision = "bf16" if str(renderer.device).startswith("cuda") else "fp32"
    config = BudgetConfig(candidates=tuple(m for m in measured if not m.runner.low_res or not m.learned
                                          or m.options.precision == precision),
                          **(dict(warmup_frames=SMOKE_WARMUP, timing_frames=2) if smoke else {}))
    cameras = bench_cameras(SMOKE_FRAMES if smoke else FRAMES)
    quality = probe_quality(renderer, iso, *size, config, cameras, networks=networks)
    by_name = {r["method"]: r for r in rows}
    stamp = run_stamp(str(renderer.device))
    timings: dict = {}
    out = []
    for budget in sorted(budgets, reverse=True):  # largest first, so that the timings carry over
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # recorded as fits: false
            choice = choose_method(renderer, iso, *size, budget, config, cameras, networks=networks,
                                   quality=quality, timings=timings)
        fitting = [r for r in rows if r["ms"] <= budget and front_psnr(r) is not None]
        best = max(fitting, key=front_psnr, default=None)
        auto = by_name[choice.method.name]
        auto_psnr = front_psnr(auto)
        out.append({"part": "budget", "volume": volume, "size": size_name, "pixels": f"{size[0]}x{size[1]}",
                    "budget_ms": budget, "method": choice.method.name, "learned": choice.method.learned,
                    "fits": choice.fits, "probe_ms": choice.ms, "expected_psnr": finite(choice.expected_psnr),
                    "ao_effect_db": finite(choice.ao_effect_db), "ao_matters": choice.ao_matters,
                    "probe_seconds": choice.probe_seconds, "ms": auto["ms"], "color_psnr": auto["color_psnr"],
                    "color_psnr_scene": auto.get("color_psnr_scene"),
                    "best_fixed": best and best["method"], "best_fixed_ms": best and best["ms"],
                    "best_fixed_psnr": best and front_psnr(best),
                    "psnr_gap": None if best is None or auto_psnr is None else front_psnr(best) - auto_psnr, **stamp,
                    "rows_commit": auto.get("commit")})  # the methods' rows' (another with --budget-only)
    return out


def pareto_front(points: list[tuple[float, float | None]]) -> list[bool]:
    """Which ``(ms, psnr)`` points are on the Pareto front: no other point is at least as fast
    and at least as good, and better in one. Points without a PSNR (None or NaN) are never on it."""
    valid = [p[1] is not None and not math.isnan(p[1]) for p in points]
    return [ok and not any(v and q[0] <= p[0] and q[1] >= p[1] and (q[0] < p[0] or q[1] > p[1])
                           for q, v in zip(points, valid))
            for p, ok in zip(points, valid)]


def dominator(row: dict, rows: list[dict]) -> dict | None:
    """The fastest row at least as fast and at least as good as ``row`` and better in one, or None."""
    psnr = front_psnr(row)
    if psnr is None:
        return None
    better = [r for r in rows if (q := front_psnr(r)) is not None and r["ms"] <= row["ms"] and q >= psnr
              and (r["ms"] < row["ms"] or q > psnr)]
    return min(better, key=lambda r: r["ms"], default=None)


def budget_ladder(cheapest_ms: float, top_ms: float = GOAL_TOP_MS) -> list[float]:
    """Frame-time budgets from 1.5 times the cheapest full-resolution frame up to ``top_ms``,
    each sqrt(2) times the one before, and ``top_ms`` itself."""
    budgets, b = [], 1.5 * cheapest_ms
    while b < top_ms:
        budgets.append(b)
        b *= math.sqrt(2.0)
    return budgets + [top_ms]


def learned_scorecard(rows: list[dict]) -> dict:
    """Where the learned methods of one scene win, checked against every other method's rows.

    Returns:
        ``budgets``: per budget of :func:`budget_ladder`, the best method that fits and the best
        learned one (None where none fits). ``baselines``: per row of a non-learned filter
        (:data:`BASELINE_KINDS`: a-trous, SVGF, OIDN), the best reconstruction at the same AO rays
        and spp, with both times, PSNRs and flicker ratios. ``ao64``: the 64-ray AO frame (spp 1)
        and the fastest learned method at least as good, with the time ratio.
    """
    scored = [r for r in rows if front_psnr(r) is not None]
    full = [r for r in scored if r["kind"] == "full"]
    if not full:
        return {"budgets": [], "baselines": [], "ao64": None}
    best = lambda cands: max(cands, key=front_psnr, default=None)  # noqa: E731
    budgets = []
    for budget in budget_ladder(min(r["ms"] for r in full)):
        fits = [r for r in scored if r["ms"] <= budget]
        top, learned = best(fits), best([r for r in fits if r["learned"]])
        budgets.append({"budget_ms": budget, "best": top and top["method"], "best_psnr": top and front_psnr(top),
                        "learned": learned and learned["method"], "learned_psnr": learned and front_psnr(learned),
                        "learned_best": learned is not None and front_psnr(learned) >= front_psnr(top)})
    baselines = []
    for a in (r for r in scored if r["kind"] in BASELINE_KINDS):
        same = best([r for r in scored if r["kind"] == "reconstruct" and r["ao_rays"] == a["ao_rays"]
                     and r["spp"] == a["spp"]])
        if same is not None:
            baselines.append({"kind": a["kind"], "method": a["method"], "ao_rays": a["ao_rays"], "ms": a["ms"],
                              "psnr": front_psnr(a), "flicker_ratio": a.get("flicker_ratio"),
                              "recon": same["method"], "recon_ms": same["ms"], "recon_psnr": front_psnr(same),
                              "recon_flicker_ratio": same.get("flicker_ratio")})
    ao64 = next((r for r in full if r["ao_rays"] == 64 and r["spp"] == 1), None)
    match = None
    if ao64 is not None:
        match = min((r for r in scored if r["learned"] and front_psnr(r) >= front_psnr(ao64)),
                    key=lambda r: r["ms"], default=None)
    return {"budgets": budgets, "baselines": baselines,
            "ao64": ao64 and {"ms": ao64["ms"], "psnr": front_psnr(ao64), "learned": match and match["method"],
                              "learned_ms": match and match["ms"], "learned_psnr": match and front_psnr(match),
                              "speedup": match and ao64["ms"] / match["ms"]}}


def run_stamp(device: str) -> dict:
    """What each row says of the run that measured it: the device's name and the commit (a merged
    file holds scenes of several runs)."""
    return {"device": device_name(device), "commit": commit()}


def measured_scene(path: Path, volume: str, size_name: str, device: str) -> list[dict]:
    """The methods' rows of one scene in the result file at ``path``, measured on this kind of
    device: what ``--budget-only`` scores the policy by.

    Raises:
        ValueError: the file holds none, or they were measured on another kind of device (the
            policy's times and theirs must come from one).
    """
    rows = kept_rows(path, lambda r: r["part"] == "pareto" and (r["volume"], r["size"]) == (volume, size_name),
                     stamp=("device", "commit"))
    if not rows:
        raise ValueError(f"{path} holds no measured rows of {volume} at {size_name}: run the study for it first")
    here = device_name(device)
    if others := sorted({r["device"] for r in rows} - {here}):
        raise ValueError(f"the rows of {volume} at {size_name} in {path} were measured on {', '.join(others)}, "
                         f"not this {here}: the policy's times and theirs must come from one kind of device")
    return rows


def merge(path: Path, rows: list[dict]) -> list[dict]:
    """``rows`` plus the rows of an existing result file at ``path`` for other (volume, size) pairs
    (those without a device of their own get the file's)."""
    new = {(r["volume"], r["size"]) for r in rows}
    return kept_rows(path, lambda r: (r["volume"], r["size"]) not in new) + rows


def main(argv=None) -> list[dict]:
    parser = bench_parser(__doc__)
    parser.add_argument("--volumes", default="", help="comma-separated volume names (default: all)")
    parser.add_argument("--sizes", default="", help=f"comma-separated sizes of {','.join(SIZES)} or WxH "
                        "(default: all named)")
    parser.add_argument("--models", default="", help="more networks: NAME=MODEL_FOLDER,...")
    parser.add_argument("--kinds", default="", help="comma-separated method kinds to measure (default: all); a "
                        f"selection (this, --spp, --ao-rays) skips the budget part and is written to "
                        f"{SELECT_NAME}_<device>.json")
    parser.add_argument("--spp", default="", help="comma-separated rays per pixel: only methods with those")
    parser.add_argument("--ao-rays", default="", help="comma-separated AO rays per hit: only methods with those")
    parser.add_argument("--translucent", type=float, default=None, metavar="A",
                        help="also measure each scene with the iso at opacity A over a surface inside it (rows of "
                        "part layers; default: none)")
    parser.add_argument("--reference-spp", type=int, default=REFERENCE_SPP,
                        help=f"rays per pixel of the references the methods' rows are scored against (default "
                        f"{REFERENCE_SPP}, which frames of as many rays match in geometry exactly; more, with a "
                        "selection only: a truer converged image)")
    parser.add_argument("--draws", type=int, default=1,
                        help="score each method over this many draws of its AO rays (means; the first draw timed), "
                        "a selection only (default 1: the service's seeds)")
    parser.add_argument("--budget-only", action="store_true",
                        help="only the policy's part, scored by the methods' rows of each scene that the result "
                        "file in --out holds (measured on this kind of device; its budget rows name their commit)")
    args = parser.parse_args(argv)
    kinds = {k.strip() for k in args.kinds.split(",") if k.strip()}
    if kinds - set(RUNNERS):
        parser.error(f"unknown kinds {sorted(kinds - set(RUNNERS))}; choose from {', '.join(RUNNERS)}")
    try:
        counts = {name: {int(n) for n in getattr(args, name).split(",") if n.strip()} for name in ("spp", "ao_rays")}
    except ValueError as e:
        parser.error(f"--spp and --ao-rays take comma-separated integers: {e}")
    sizes = SMOKE_SIZES if args.smoke else SIZES
    size_names = [s.strip().lower() for s in args.sizes.split(",") if s.strip()] or list(sizes)
    names = [s.strip() for s in args.volumes.split(",") if s.strip()] or volume_names(args.smoke)
    unknown = [s for s in size_names if s not in sizes and "x" not in s]
    if unknown:
        parser.error(f"unknown sizes {unknown}; choose from {', '.join(sizes)} or WxH")
    try:
        sizes = {**sizes, **{s: frame_size(s) for s in size_names if s not in sizes}}
    except argparse.ArgumentTypeError as e:
        parser.error(f"--sizes: {e}")
    if args.translucent is not None and not 0.0 <= args.translucent < 1.0:
        parser.error(f"--translucent must be in [0, 1) (an opacity below 1), got {args.translucent}")
    if args.translucent is not None and args.budget_only:
        parser.error("--budget-only scores the policy on one surface: give no --translucent")
    known = list(SMOKE_VOLUMES) if args.smoke else [e["name"] for e in manifest()] + ["bonsai1024"]
    unknown = [n for n in names if n not in known]
    if unknown:
        parser.error(f"unknown volumes {unknown}; choose from {', '.join(known)}")
    try:
        models = {**SHIPPED_MODELS, **parse_models(args.models)}
    except ValueError as e:
        parser.error(str(e))
    if args.device.startswith("cuda"):
        # Each network precision compiles per frame size (two sizes and the probe's): more variants
        # of one code object than dynamo's default limit of 8, past which it would run them eagerly.
        torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
    measured = [m for m in methods(args.smoke, args.device, models) if (not kinds or m.kind in kinds)
                and all(not values or getattr(m, name) in values for name, values in counts.items())]
    selection = bool(kinds or counts["spp"] or counts["ao_rays"])
    if selection and args.budget_only:
        parser.error("--budget-only runs the policy over every method: give no --kinds, --spp or --ao-rays")
    if args.reference_spp != REFERENCE_SPP and not selection:
        parser.error(f"--reference-spp {args.reference_spp}: the policy's part scores against its own references "
                     f"({REFERENCE_SPP} rays per pixel): give a selection (--kinds, --spp or --ao-rays)")
    if args.draws != 1 and not selection:
        parser.error(f"--draws {args.draws}: the policy's part scores one draw: give a selection (--kinds, --spp or "
                     "--ao-rays)")
    if not 1 <= args.draws <= MAX_DRAWS:
        parser.error(f"--draws must lie in [1, {MAX_DRAWS}], got {args.draws}")
    if not 1 <= args.reference_spp <= MAX_SPP:
        parser.error(f"--reference-spp must lie in [1, {MAX_SPP}], got {args.reference_spp}")
    kind = "cuda" if args.device.startswith("cuda") else "cpu"
    # With --budget-only, every scene's measured rows are found before any volume is loaded.
    measured_rows = {(name, size_name): measured_scene(args.out / f"{NAME}_{kind}.json", name, size_name, args.device)
                     for name in names for size_name in size_names} if args.budget_only else {}
    frames = SMOKE_FRAMES if args.smoke else FRAMES
    networks = Networks()
    rows = []
    for name in names:
        volume, iso = load(name, args.device)
        renderer = Renderer(volume, args.device)
        for size_name in size_names:
            size = sizes[size_name]
            fitting = [m for m in measured if size[0] % m.factor == 0 and size[1] % m.factor == 0]
            if args.budget_only:
                scene = measured_rows[(name, size_name)]
                fitting = [m for m in fitting if m.name in {r["method"] for r in scene}]
            else:
                scene = pareto_rows(renderer, iso, name, size, size_name, fitting, frames,
                                    SMOKE_WARMUP if args.smoke else WARMUP, args.device, networks,
                                    reference_spp=args.reference_spp, draws=args.draws)
            rows += scene
            if args.translucent is not None:
                surfaces = Surfaces.of([(iso, PALETTE[0], args.translucent),
                                        (min(1.0, iso + INNER_ISO_STEP), PALETTE[1])])
                rows += pareto_rows(renderer, iso, name, size, size_name, fitting, frames,
                                    SMOKE_WARMUP if args.smoke else WARMUP, args.device, networks, surfaces,
                                    args.reference_spp, args.draws)
            if not selection:  # the policy chooses among every method
                rows += budget_rows(renderer, iso, name, size, size_name, fitting, scene,
                                    SMOKE_BUDGETS if args.smoke else BUDGETS, networks, args.smoke)
        del renderer, volume
    name = SELECT_NAME if selection else NAME  # the study's own file keeps whole scenes
    merged = merge(args.out / f"{name}_{kind}.json", rows)
    print_table([r for r in rows if r["part"] in ("pareto", "layers")],
                ["volume", "size", "part", "method", "ms", "color_psnr", "color_psnr_scene", "color_ssim", "image_psnr",
                 "ao_rmse", "flicker", "flicker_ratio"])
    print_table([r for r in rows if r["part"] == "budget"],
                ["volume", "size", "budget_ms", "method", "fits", "probe_ms", "color_psnr_scene", "best_fixed",
                 "best_fixed_psnr"])
    print(f"wrote {write_result(name, args.device, merged, args.out)}")
    return rows


if __name__ == "__main__":
    main()
