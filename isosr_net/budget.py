"""``quality="auto"``: the best way to make frames of one scene within a frame-time budget.

    choice = choose_method(renderer, iso, 1920, 1080, budget_ms=8.0)
    choice.method.name, choice.ms, choice.expected_psnr   # e.g. "full, AO 4, spp 1", 6.1, 30.2
    frame, choice = render_within_budget(renderer, camera, iso, 1920, 1080, budget_ms=8.0)

A short probe on the scene decides (its cost is ``choice.probe_seconds``):

1. Quality, at a reduced probe size (a quarter of the frame's rows, ``probe_scale``, and at least
   ``probe_height``: 540 on GPUs, 96 on CPUs; the frame's aspect):
   a high-effort reference per probe frame (4 rays per pixel, 512 AO rays) and every
   candidate's frames in sequence, scored by color PSNR on the scene's region, the same pixels for every
   candidate (:func:`color_psnr`). An estimate: classic and
   learned upscalers lose more at a small size than at the target size, where a pixel holds less
   detail, and a filter or network sees AO rays that reach further in pixels. At 96 rows the
   probe ranked the a-trous filter against supersampling wrongly at 4K (up to 6.4 dB short of
   the best fixed setting, H100); a quarter of the frame's side keeps the probe to 1/16 of its
   pixels. At 272 rows (a quarter of 1080p) it ranked the reconstruction with 16 AO rays at spp 4
   below the plain render with as many rays on bonsai (35.1 against 36.3 dB; at 544 rows 37.1
   against 36.3, at 1080p itself 38.4 against 36.1), so no probe on a GPU has fewer than 540
   rows. On CPUs, where a network frame of 540 rows takes seconds, the probe keeps 96.
2. Whether AO matters: the reference shaded with and without its AO, color PSNR on the covered
   region. At or above ``ao_matters_db`` (40 dB: an RMS change of 1% of the color range, about
   2.5 of 255 display levels, below what a moving view shows) the scene gets no AO candidates
   at all (a convex shape, the hydrogen volume's smooth blobs): AO rays would cost time and
   change nothing visible.
3. Time, at the target size on the renderer's device: candidates in order of expected quality,
   each after ``warmup_frames`` and over ``timing_frames`` (device time from CUDA events on
   GPUs, wall time on CPUs), until the first whose mean frame time fits within ``headroom``
   of the budget (90%: frame times vary by view and run, and a budget is a ceiling; :func:`fits`); it
   is the choice. Probe the views that will be shown: frame time grows with the covered pixels. A
   candidate stops being timed once one frame takes more than twice the budget.
   On CPUs, step 1's frames at the probe size are timed too: scaled to the frame's pixels, half
   of that is a candidate's floor (:func:`floor_ms`), and one whose floor is over twice the
   budget is not timed at all (on a 2-core CPU at 1080p, where frames take seconds, that skips
   most candidates). On GPUs, where a first frame at a new size captures graphs and tunes
   kernels, every candidate is timed. If none fits, the fastest timed is chosen, ``fits`` is
   False and a warning says so.

A scheduler that must not stop for the probe (the server's ``auto`` mode) runs it as a
generator, :func:`probe_quality_steps` and :func:`choose_method_steps`: each yields before every
unit of device work (the references, a candidate's scoring, a candidate's timed frame, whose ray
cast is sliced by ``slice_ms``), so its work interleaves with other jobs; the plain functions
run them to their end.

An image without any covered pixel (iso outside the data) has no PSNR (NaN): every candidate
ties, and the cheapest in the candidate list that fits is chosen.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import time
import warnings
from collections.abc import Generator
from dataclasses import dataclass, field
from pathlib import Path

import torch

from isosr_render import Camera, FrameBuffers, Renderer, RenderRequest, orbit_path
from isosr_render.clip import Clip
from isosr_render.sequence import sequence_cameras
from isosr_render.shading import ShadingParams, shade
from isosr_render.conventions import AO_RADIUS
from isosr_render.shapes import check_int
from isosr_render.surfaces import Surfaces
from isosr_net.methods import RUNNERS, FrameMethod, FrameRunner, Networks, finish_steps, make_runner
from isosr_net.metrics import masked_psnr, scene_region
from isosr_net.reconnet import RayLimits
from isosr_net.reconstructor import RECON_X2_MODEL

# Color PSNR of no-AO against many-ray AO above which a scene gets no AO rays (see above).
AO_MATTERS_DB = 40.0
# The quality reference: rays per pixel, AO rays per hit, and an AO seed no method uses (the
# methods' default is 0), so that no method's AO rays are a subset of the reference's. Its
# subpixel pattern is fixed, though: a 4-ray-per-pixel method has the reference's geometry.
REFERENCE_SPP = 4
REFERENCE_AO_RAYS = 512
REFERENCE_SEED = 1
# Row bands of the reference on CPUs, a unit of device work each (seconds for the whole on 2 cores).
REFERENCE_BANDS_CPU = 8
# A candidate's timing stops once one frame takes this many budgets (a frame alone before its batch: times the batch).
OVER_BUDGET_STOP = 2.0
# The share of a candidate's time at the probe size, scaled to the frame's pixels, counted on
# as its floor (:func:`floor_ms`): fixed costs per frame make small frames dearer per pixel.
FLOOR_SHARE = 0.5


def default_candidates(device: str, precision: str | None = None, limits: RayLimits | None = None,
                       x2_model: str | os.PathLike | None = RECON_X2_MODEL) -> tuple[FrameMethod, ...]:
    """The methods the policy considers: those of every registered kind that can run here
    (:meth:`FrameRunner.candidates`), roughly cheapest first by their ranks (the order breaks
    ties). The networks run in ``precision`` (None: each at its fastest); ``limits``: the
    reconstruction model's ray limits (None: the shipped model's); ``x2_model``: the model of the
    reconstruction that also upscales x2 (None: none)."""
    ranked = [c for cls in RUNNERS.values() if cls.unavailable() is None
              for c in cls.candidates(device, precision, limits, x2_model)]
    return tuple(m for _, m in sorted(ranked, key=lambda c: c[0]))


@dataclass(frozen=True)
class BudgetConfig:
    """The probe's knobs.

    Attributes:
        candidates: the methods to choose from; None: :func:`default_candidates`.
        probe_scale: the quality probe's side over the frame's (its width follows the frame's
            aspect; both multiples of 8).
        probe_height: the fewest rows the quality probe has; frames no taller are probed at
            their own size; None: :func:`default_probe_height` of the renderer's device.
        probe_frames: frames of the quality probe (an orbit unless cameras are given).
        warmup_frames, timing_frames: frames per timed candidate, before and while timing. Three
            warm-up frames: a reconstruction in motion replays three CUDA graphs (the first
            frame's, then one per buffer of its ray-history pair), each captured on its first
            frame; with two, the first timed frame was a capture, which made the reconstruction
            look up to twice as slow as it is (the Pareto study's policy rows, H100, ca82b1b).
        ao_matters_db: the AO test's threshold, dB.
        headroom: the fraction of the budget a candidate's probe time may take.
        clock: what a frame's time is on GPUs: ``"device"``, the GPU's (CUDA events: the Pareto
            study's scale), or ``"wall"``, the host's to the frame's end (a serving thread's cost,
            where the host's work per frame can exceed the GPU's).
        ao_radius: AO ray length, world units.
        shading: material and light.
        batch: streams a candidate's timed frames are made for at once, by its kind's ``make_batch``
            (a frame's time: their batch's wall time over ``batch``): what a frame costs a service
            that makes many sessions' frames together; 1: each frame alone.
        clip: the scene's clip planes, crop box and caps: references and candidates are rendered,
            scored and timed clipped (a clip changes what a frame costs and shows).
    """

    candidates: tuple[FrameMethod, ...] | None = None
    probe_scale: float = 0.25
    probe_height: int | None = None
    probe_frames: int = 3
    warmup_frames: int = 3
    timing_frames: int = 3
    ao_matters_db: float = AO_MATTERS_DB
    headroom: float = 0.9
    clock: str = "device"
    ao_radius: float = AO_RADIUS
    shading: ShadingParams = field(default_factory=ShadingParams)
    batch: int = 1
    clip: Clip = field(default_factory=Clip)

    def __post_init__(self):
        for name, low in (("probe_frames", 1), ("warmup_frames", 0), ("timing_frames", 1), ("batch", 1)):
            check_int(getattr(self, name), name, low, where="BudgetConfig")
        if self.probe_height is not None:
            check_int(self.probe_height, "probe_height", 16, where="BudgetConfig")
        if not (isinstance(self.probe_scale, (int, float)) and 0 < self.probe_scale <= 1):
            raise ValueError(f"BudgetConfig.probe_scale must be in (0, 1], got {self.probe_scale!r}")
        if self.clock not in ("device", "wall"):
            raise ValueError(f"BudgetConfig.clock must be 'device' or 'wall', got {self.clock!r}")
        if not 0 < self.headroom <= 1:
            raise ValueError(f"BudgetConfig.headroom must be in (0, 1], got {self.headroom!r}")
        if self.candidates is not None and not self.candidates:
            raise ValueError("BudgetConfig.candidates is empty: give at least one method, or None for the defaults")


@dataclass(frozen=True)
class ProbeRow:
    """One candidate as the probe saw it: expected PSNR (dB, NaN without coverage) and mean
    frame time (ms; None where not timed, because a better candidate fit first; its floor,
    ``floored``, where the floor was over twice the budget: :func:`floor_ms`)."""

    method: FrameMethod
    expected_psnr: float
    ms: float | None
    floored: bool = False


@dataclass(frozen=True)
class BudgetChoice:
    """What the policy chose and why.

    Attributes:
        method: the chosen method.
        ms: its mean frame time in the probe, ms.
        expected_psnr: its color PSNR on the covered region at the probe size, dB.
        fits: whether ``ms`` is within the budget's headroom (False: nothing fit, the fastest was taken).
        budget_ms: the budget.
        ao_effect_db: color PSNR of the reference without AO against with AO (NaN: nothing covered).
        ao_matters: whether AO candidates were considered.
        probe_size: (width, height) of the quality probe.
        probe_seconds: wall time of the whole probe.
        table: every candidate considered, best expected quality first.
    """

    method: FrameMethod
    ms: float
    expected_psnr: float
    fits: bool
    budget_ms: float
    ao_effect_db: float
    ao_matters: bool
    probe_size: tuple[int, int]
    probe_seconds: float
    table: tuple[ProbeRow, ...]

    def summary(self) -> str:
        """One line for logs."""
        fit = "within" if self.fits else "NOTHING FITS, the fastest, over"
        return (f"{self.method.name}: {self.ms:.2f} ms ({fit} the budget of {self.budget_ms:g} ms), expected color "
                f"PSNR {self.expected_psnr:.1f} dB; AO changes colors by {self.ao_effect_db:.1f} dB PSNR "
                f"({'AO candidates considered' if self.ao_matters else 'no AO'}); probe {self.probe_size[0]}x"
                f"{self.probe_size[1]}, {self.probe_seconds:.1f} s")


# The committed cost tables, one per device class (``cuda.json``; written by ``isosr_bench.report --docs``).
PRIORS_DIR = Path(__file__).parent / "priors"


def method_key(method: FrameMethod) -> tuple[str, int, int, int]:
    """What a cost table knows a method by: its kind and counts (not its model's display name)."""
    return method.kind, method.ao_rays, method.spp, method.factor


def _row_key(row: dict) -> tuple[str, int, int, int]:
    """A result row's :func:`method_key`."""
    return row["kind"], row["ao_rays"], row["spp"], row["factor"]


def front_psnr(row: dict) -> float | None:
    """The PSNR a Pareto study row is ranked by (its fronts, dominance, scorecard and best fixed setting; the cost
    table): on the scene's region, the same pixels for every row of a scene (``color_psnr_scene``); ``color_psnr``
    in rows written before that score was. None: nothing covered."""
    return row["color_psnr_scene"] if "color_psnr_scene" in row else row["color_psnr"]


@dataclass(frozen=True)
class CostTable:
    """A device class's committed costs, the prior before a probe: per method (:func:`method_key`)
    its frame time over a plain first-hit frame's (``full``, no AO, same volume and size) and its
    color PSNR, medians over the Pareto study's volumes and sizes.

    Attributes:
        device, commit: where and from which commit the study measured them.
        rows: method key -> (cost in first-hit frames, color PSNR dB).
    """

    device: str
    commit: str
    rows: dict[tuple[str, int, int, int], tuple[float, float]]

    @classmethod
    def for_device(cls, device: str) -> CostTable | None:
        """The committed table of ``device``'s class (``cuda`` or ``cpu``), or None where there is none."""
        path = PRIORS_DIR / f"{'cuda' if str(device).startswith('cuda') else 'cpu'}.json"
        if not path.is_file():
            return None
        record = json.loads(path.read_text())
        rows = {_row_key(r): (r["cost"], r["color_psnr"]) for r in record["rows"]}
        return cls(record["device"], record["commit"], rows)

    @staticmethod
    def from_pareto(rows: list[dict]) -> list[dict]:
        """A table's rows from Pareto study rows (each with volume, size, kind, counts, ms and a
        :func:`front_psnr`): per method the medians over the (volume, size) pairs that have a first-hit row,
        of each pair's fastest variant (e.g. of a network's precisions)."""
        first_hit = {(r["volume"], r["size"]): r["ms"] for r in rows if _row_key(r) == ("full", 0, 1, 1)}
        fastest: dict[tuple, tuple[float, float]] = {}  # (ms, score) of each method's fastest variant per scene
        for r in rows:
            at = (*_row_key(r), r["volume"], r["size"])
            if (r["volume"], r["size"]) in first_hit and (psnr := front_psnr(r)) is not None and math.isfinite(psnr):
                if at not in fastest or r["ms"] < fastest[at][0]:
                    fastest[at] = r["ms"], psnr
        by_method: dict[tuple, list[tuple[float, float]]] = {}
        for (*key, volume, size), (ms, psnr) in fastest.items():
            by_method.setdefault(tuple(key), []).append((ms / first_hit[volume, size], psnr))
        return [{"kind": k[0], "ao_rays": k[1], "spp": k[2], "factor": k[3],
                 "cost": round(statistics.median(c for c, _ in v), 3),
                 "color_psnr": round(statistics.median(p for _, p in v), 2), "scenes": len(v)}
                for k, v in sorted(by_method.items())]

    def choose(self, candidates: tuple[FrameMethod, ...], first_hit_ms: float, budget_ms: float, headroom: float
               ) -> tuple[FrameMethod, float, float] | None:
        """The candidate of the best tabled PSNR whose predicted time (its cost times
        ``first_hit_ms``, this scene's first-hit frame) :func:`fits` ``budget_ms``, with that time and PSNR;
        None where none of the tabled ones fits."""
        fitting = [(self.rows[method_key(m)][1], -self.rows[method_key(m)][0], m) for m in candidates
                   if method_key(m) in self.rows and fits(self.rows[method_key(m)][0] * first_hit_ms, budget_ms,
                                                          headroom)]
        if not fitting:
            return None
        psnr, minus_cost, method = max(fitting, key=lambda f: f[:2])
        return method, -minus_cost * first_hit_ms, psnr


def default_probe_height(device: str) -> int:
    """The quality probe's fewest rows on ``device``: 540 on GPUs, 96 on CPUs (module docstring)."""
    return 540 if str(device).startswith("cuda") else 96


def probe_size(width: int, height: int, probe_height: int, probe_scale: float = 0.0) -> tuple[int, int]:
    """The quality probe's size: the frame's own if it is at most ``probe_height`` rows, else
    ``probe_scale`` of its rows but at least ``probe_height`` (rounded to a multiple of 8), and
    the frame's aspect (width a multiple of 8)."""
    rows = max(probe_height, probe_scale * height)
    if height <= rows:
        return width, height
    h = 8 * max(2, round(rows / 8))
    return 8 * max(2, round(h * width / height / 8)), h


def _check_size_and_budget(width: int, height: int, budget_ms: float) -> None:
    check_int(width, "width", 1, where="the frame to probe")
    check_int(height, "height", 1, where="the frame to probe")
    if not (isinstance(budget_ms, (int, float)) and math.isfinite(budget_ms) and budget_ms > 0):
        raise ValueError(f"budget_ms must be a positive finite number of milliseconds, got {budget_ms!r}")


def reference_frames(renderer: Renderer, iso: float, size: tuple[int, int], cameras: list[Camera],
                     ao_radius: float = AO_RADIUS, shading: ShadingParams = ShadingParams(),
                     flow: bool = False, clip: Clip = Clip(),
                     surfaces: Surfaces | None = None, spp: int = REFERENCE_SPP) -> list[FrameBuffers]:
    """High-effort reference frames along a camera path: mask, normal, AO (``spp`` rays per pixel, 512
    AO rays, the reference's own AO seed) and color with AO, cut by ``clip`` (its cut faces shaded
    as the methods shade them); with ``flow``, each frame's flow from the previous camera too
    (zeros for the first); with ``surfaces``, of theirs (the colour the renderer's: translucent ones'
    two layers composited). The renderer's subpixel pattern is fixed, its first samples every frame's:
    a frame of as many rays per pixel has the reference's geometry exactly.

    Shape:
        Per frame: mask, ao (H, W); normal, color (H, W, 3); flow (H, W, 2).
    """
    return finish_steps(reference_frames_steps(renderer, iso, size, cameras, ao_radius, shading, flow, clip=clip,
                                               surfaces=surfaces, spp=spp))


def reference_frames_steps(renderer: Renderer, iso: float, size: tuple[int, int], cameras: list[Camera],
                           ao_radius: float = AO_RADIUS, shading: ShadingParams = ShadingParams(),
                           flow: bool = False, bands: int = 1,
                           clip: Clip = Clip(), surfaces: Surfaces | None = None,
                           spp: int = REFERENCE_SPP) -> Generator[None, None, list[FrameBuffers]]:
    """:func:`reference_frames` in ``bands`` row bands per frame, yielding between them (a band's
    pixels are the whole frame's, bit for bit: each pixel's rays depend on its index alone)."""
    frames = []
    for camera, prev in sequence_cameras(cameras):
        outputs = (("mask", "normal", "ao") + (("flow",) if flow and prev is not None else ())
                   + (("cap",) if clip.capped else ()) + (("color",) if surfaces is not None else ()))
        request = RenderRequest(*size, iso, outputs, spp=spp, ao_samples=REFERENCE_AO_RAYS,
                                ao_radius=ao_radius, seed=REFERENCE_SEED, prev_camera=prev if flow else None,
                                shading=shading, clip=clip, surfaces=surfaces)
        edges = [round(size[1] * k / bands) for k in range(bands + 1)]
        ref = None
        for start, stop in zip(edges, edges[1:]):
            band = renderer.render(camera, request, rows=None if bands == 1 else (start, stop))
            if ref is None:
                ref = band
            else:
                for name in outputs:
                    getattr(ref, name)[start:stop] = getattr(band, name)[start:stop]
            if stop < size[1]:
                yield
        ref.color = shade(ref.mask, ref.normal, ref.ao, shading, cap=ref.cap) if surfaces is None else ref.color
        if flow and ref.flow is None:
            ref.flow = torch.zeros(*ref.mask.shape, 2, device=ref.mask.device)
        frames.append(ref)
    return frames


def color_psnr(frame: FrameBuffers, reference: FrameBuffers) -> float:
    """Color PSNR (dB) of a frame against a reference on the scene's region
    (:func:`isosr_net.metrics.scene_region`: the same pixels for every candidate, as the Pareto study ranks);
    NaN where the reference covers no pixel."""
    region = scene_region(reference.mask[None, None])
    return float(masked_psnr(frame.color.permute(2, 0, 1)[None], reference.color.permute(2, 0, 1)[None], region)[0])


def _nanmean(values: list[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return sum(finite) / len(finite) if finite else float("nan")


def ao_effect_db(references: list[FrameBuffers], shading: ShadingParams = ShadingParams()) -> float:
    """Color PSNR (dB) of the references shaded without AO against with it, on their covered
    region, averaged over frames; NaN if nothing is covered."""
    scores = []
    for ref in references:
        bare = FrameBuffers(mask=ref.mask, color=shade(ref.mask, ref.normal, None, shading, cap=ref.cap))
        scores.append(color_psnr(bare, ref))
    return _nanmean(scores)


def _frame_ms(runner: FrameRunner, camera: Camera, prev: Camera | None, clock: str) -> float:
    """One frame's time in ms: on GPUs with the ``device`` clock CUDA events (the GPU's time),
    else wall time to the frame's end (on GPUs synchronized: the host's and the GPU's together)."""
    if runner.renderer.device.is_cuda and clock == "device":
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        runner.frame(camera, prev)
        end.record()
        torch.cuda.synchronize()
        return start.elapsed_time(end)
    t0 = time.perf_counter()
    runner.frame(camera, prev)
    return _synced_ms(runner, t0)


def first_hit_ms_steps(renderer: Renderer, iso: float, width: int, height: int, camera: Camera,
                       ao_radius: float = AO_RADIUS, networks: Networks | None = None,
                       clip: Clip = Clip()) -> Generator[None, None, float]:
    """The wall time (ms) of a plain first-hit frame (``full``, no AO) of this scene (cut by ``clip``)
    and size after a warm-up frame, a frame a unit: the unit a :class:`CostTable`'s costs are in."""
    runner = make_runner(FrameMethod.of("full"), renderer, iso, width, height, ao_radius=ao_radius, networks=networks,
                         clip=clip)
    yield
    runner.frame(camera)
    yield
    return _frame_ms(runner, camera, None, "wall")


def _sliced_frame_ms(runner: FrameRunner, camera: Camera, prev: Camera | None,
                     slice_ms: float | None) -> Generator[None, None, float]:
    """One frame's time in ms, made in slices of about ``slice_ms`` (:meth:`FrameRunner.steps`):
    the wall time of its own slices, each synchronized at its end, what runs between them left
    out (without ``slice_ms``, one slice)."""
    steps, ms = runner.steps(camera, prev, slice_ms), 0.0
    while True:
        start = time.perf_counter()
        try:
            next(steps)
        except StopIteration:
            return ms + _synced_ms(runner, start)
        ms += _synced_ms(runner, start)
        yield


def _synced_ms(runner: FrameRunner, start: float) -> float:
    """Milliseconds from ``start`` to the end of the runner's device work."""
    if runner.renderer.device.is_cuda:
        torch.cuda.synchronize()
    return (time.perf_counter() - start) * 1e3


def _time_candidate_steps(runner: FrameRunner, cameras: list[Camera], config: BudgetConfig, budget_ms: float,
                          slice_ms: float | None = None) -> Generator[None, None, float]:
    """Mean frame time of a runner in sequence over ``cameras`` (cycled), after warm-up; stops
    early once a frame takes more than ``OVER_BUDGET_STOP`` budgets (on CPUs a warm-up frame
    too). Yields before each frame."""
    pairs = sequence_cameras(cameras)
    for i in range(config.warmup_frames):
        yield
        ms = yield from _sliced_frame_ms(runner, *pairs[i % len(pairs)], slice_ms)
        if not runner.renderer.device.is_cuda and ms > OVER_BUDGET_STOP * budget_ms:
            return ms  # on CPUs a first frame has no one-off costs (graph captures, kernel tuning)
    times = []
    for i in range(config.timing_frames):
        yield
        camera, prev = pairs[(config.warmup_frames + i) % len(pairs)]
        times.append(_frame_ms(runner, camera, prev, config.clock) if slice_ms is None
                     else (yield from _sliced_frame_ms(runner, camera, prev, slice_ms)))
        if times[-1] > OVER_BUDGET_STOP * budget_ms:
            break
    return sum(times) / len(times)


# Warm-up batches of a timed batch: a first one, then two that carry it (the service's reconstruction captures
# its batched network's graph at a shape's second use: Reconstructor's batch_graphs).
BATCH_WARMUP = 3


def _time_batch_steps(runners: list[FrameRunner], cameras: list[Camera],
                      config: BudgetConfig) -> Generator[None, None, float]:
    """Mean wall time of a frame made with ``len(runners)`` streams' at once (their kind's
    ``make_batch``, each stream along ``cameras``, cycled): a batch's time over its frames, after
    :data:`BATCH_WARMUP` warm-up batches. Yields before each batch.

    Raises:
        Exception: a stream's frame failed (the candidate cannot be timed).
    """
    pairs, kind, times = sequence_cameras(cameras), type(runners[0]), []
    for i in range(BATCH_WARMUP + config.timing_frames):
        yield
        camera, prev = pairs[i % len(pairs)]
        start = time.perf_counter()
        results = kind.make_batch([(runner, camera, prev) for runner in runners])
        ms = _synced_ms(runners[0], start) / len(runners)
        for result in results:
            if isinstance(result, Exception):
                raise result
            result.checked()
        times.append(ms)
    return sum(times[BATCH_WARMUP:]) / config.timing_frames


@dataclass(frozen=True)
class QualityProbe:
    """The budget-independent part of the probe: expected PSNR per candidate and the AO test.

    Attributes:
        size: (width, height) the candidates were scored at.
        psnr: expected color PSNR per candidate, dB (NaN: nothing covered).
        ao_effect_db: color PSNR of the reference without AO against with AO.
        ao_matters: whether AO candidates were kept.
        seconds: wall time of this part.
        ms: wall time of a frame per candidate at the probe size, ms (on CPUs; GPUs: empty).
    """

    size: tuple[int, int]
    psnr: dict
    ao_effect_db: float
    ao_matters: bool
    seconds: float
    ms: dict = field(default_factory=dict)


def probe_quality(renderer: Renderer, iso: float, width: int, height: int, config: BudgetConfig = BudgetConfig(),
                  cameras: list[Camera] | None = None, networks: Networks | None = None) -> QualityProbe:
    """Steps 1 and 2 of the module docstring: the AO test, then every remaining candidate scored
    at the probe size against the reference (:func:`probe_quality_steps` to its end)."""
    return finish_steps(probe_quality_steps(renderer, iso, width, height, config, cameras, networks))


def probe_quality_steps(renderer: Renderer, iso: float, width: int, height: int,
                        config: BudgetConfig = BudgetConfig(), cameras: list[Camera] | None = None,
                        networks: Networks | None = None) -> Generator[None, None, QualityProbe]:
    """:func:`probe_quality` as a generator that yields before each unit of device work (the
    references, each candidate's frames).

    Raises:
        ValueError: a zero-size or non-integer frame, or no candidate whose upscaling factor
            divides the frame and probe sizes.
    """
    _check_size_and_budget(width, height, 1.0)
    start = time.perf_counter()
    rows = config.probe_height or default_probe_height(str(renderer.device))
    size = probe_size(width, height, rows, config.probe_scale)
    cameras = cameras or _probe_cameras(config)
    networks = Networks() if networks is None else networks
    candidates = [m for m in config.candidates or default_candidates(str(renderer.device))
                  if not (width % m.factor or height % m.factor or size[0] % m.factor or size[1] % m.factor)]
    if not candidates:
        raise ValueError(f"no candidate method's upscaling factor divides the frame size {width}x{height} "
                         f"and the probe size {size[0]}x{size[1]}")
    yield
    bands = 1 if renderer.device.is_cuda else REFERENCE_BANDS_CPU
    references = yield from reference_frames_steps(renderer, iso, size, cameras, config.ao_radius, config.shading,
                                                   bands=bands, clip=config.clip)
    effect = ao_effect_db(references, config.shading)
    ao_matters = effect < config.ao_matters_db  # False for NaN: nothing covered, no AO to see
    if not ao_matters and any(m.ao_rays == 0 for m in candidates):
        candidates = [m for m in candidates if m.ao_rays == 0]
    psnr, ms = {}, {}
    for m in candidates:
        yield
        runner = make_runner(m, renderer, iso, *size, shading=config.shading, ao_radius=config.ao_radius,
                             networks=networks, clip=config.clip)
        frames, spent = [], 0.0
        for k, (camera, prev) in enumerate(sequence_cameras(cameras)):
            if k:
                yield  # a frame a unit: a candidate's first frame may carry one-off costs (compiles, tuning)
            began = time.perf_counter()
            frames.append(runner.frame(camera, prev).buffers.clone())
            spent += _synced_ms(runner, began)
        if not renderer.device.is_cuda:
            ms[m] = spent / len(cameras)
        psnr[m] = _nanmean([color_psnr(f, r) for f, r in zip(frames, references)])
    return QualityProbe(size, psnr, effect, ao_matters, time.perf_counter() - start, ms)


def _probe_cameras(config: BudgetConfig) -> list[Camera]:
    return orbit_path(config.probe_frames, yaw0=30.0, yaw_step=3.0, pitch=20.0, distance=1.8)


def choose_method(renderer: Renderer, iso: float, width: int, height: int, budget_ms: float,
                  config: BudgetConfig = BudgetConfig(), cameras: list[Camera] | None = None,
                  networks: Networks | None = None, quality: QualityProbe | None = None,
                  timings: dict | None = None) -> BudgetChoice:
    """Pick the method with the best expected quality whose probe frame time fits ``budget_ms``.

    Args:
        renderer: the scene's renderer (its device is where the candidates are timed).
        iso: normalized iso-value.
        width, height: the frame size to choose for.
        budget_ms: frame-time budget in milliseconds.
        config: the probe's knobs.
        cameras: the probe's camera path (default a short orbit at distance 1.8).
        networks: the loaded networks, shared with later runners (see :class:`Networks`).
        quality: a :func:`probe_quality` of the same scene and frame size, reused across budgets.
        timings: frame times (ms) by method of earlier calls on the same scene and size, reused
            and filled: pass one dict to calls from the largest budget down (a time cut short
            above twice a budget is above any smaller budget too).

    Returns:
        The choice with the probe's table (see the module docstring for how it is made).

    Raises:
        ValueError: a zero-size or non-integer frame, a budget that is not a positive finite number,
            or no candidate whose upscaling factor divides the frame and probe sizes.
    """
    return finish_steps(choose_method_steps(renderer, iso, width, height, budget_ms, config, cameras, networks,
                                            quality, timings))


def choose_method_steps(renderer: Renderer, iso: float, width: int, height: int, budget_ms: float,
                        config: BudgetConfig = BudgetConfig(), cameras: list[Camera] | None = None,
                        networks: Networks | None = None, quality: QualityProbe | None = None,
                        timings: dict | None = None, slice_ms: float | None = None,
                        warn: bool = True) -> Generator[None, None, BudgetChoice]:
    """:func:`choose_method` as a generator that yields before each unit of device work, so that
    where ``quality`` and ``timings`` already decide it, it returns without yielding. A timed
    frame's ray cast runs in slices of about ``slice_ms``; ``warn=False`` leaves the warning
    that nothing fits to the choice's ``fits``.
    """
    _check_size_and_budget(width, height, budget_ms)
    cameras = cameras or _probe_cameras(config)
    networks = Networks() if networks is None else networks
    quality = quality or (yield from probe_quality_steps(renderer, iso, width, height, config, cameras, networks))
    start = time.perf_counter()
    psnr = quality.psnr
    order = quality_order(psnr)
    timings = {} if timings is None else timings
    floors: dict[FrameMethod, float] = {}  # this budget's candidates too dear to time, by their floor
    while True:
        untimed, chosen, considered = _pick(order, timings | floors, budget_ms, config.headroom)
        if untimed is None and chosen in floors:  # nothing fits, the fastest known by its floor alone: time it
            untimed = chosen
            del floors[chosen]
        elif (untimed is not None
              and (floor := floor_ms(untimed, quality, width, height)) > OVER_BUDGET_STOP * budget_ms):
            floors[untimed] = floor
            continue
        if untimed is None:
            break
        runners = [make_runner(untimed, renderer, iso, width, height, shading=config.shading,
                               ao_radius=config.ao_radius, networks=networks if k == 0 else networks.fork(),
                               clip=config.clip)
                   for k in range(config.batch)]
        # A batch shares at most all of a frame's work: a frame alone of up to `batch` budgets may still fit.
        alone_budget_ms = budget_ms * config.batch
        timings[untimed] = yield from _time_candidate_steps(runners[0], cameras, config, alone_budget_ms, slice_ms)
        if config.batch > 1 and timings[untimed] <= OVER_BUDGET_STOP * alone_budget_ms:
            timings[untimed] = yield from _time_batch_steps(runners, cameras, config)
    ms = {m: timings[m] for m in considered if m in timings}
    fitting = fits(ms[chosen], budget_ms, config.headroom)
    if not fitting and warn:
        warnings.warn(f"no method fits the budget of {budget_ms:g} ms at {width}x{height}: the fastest, "
                      f"{chosen.name}, takes {ms[chosen]:.2f} ms", RuntimeWarning, stacklevel=2)
    table = tuple(ProbeRow(m, psnr[m], ms.get(m, floors.get(m)), m in floors) for m in order)
    return BudgetChoice(chosen, ms[chosen], psnr[chosen], fitting, float(budget_ms), quality.ao_effect_db,
                        quality.ao_matters, quality.size, time.perf_counter() - start + quality.seconds, table)


def floor_ms(method: FrameMethod, quality: QualityProbe, width: int, height: int) -> float:
    """A method's expected least frame time at ``width`` x ``height``: :data:`FLOOR_SHARE` of its
    probe-size frame's time scaled to the pixels (0 where the probe timed none: on GPUs)."""
    probe_pixels = quality.size[0] * quality.size[1]
    return FLOOR_SHARE * quality.ms.get(method, 0.0) * width * height / probe_pixels


def quality_order(psnr: dict[FrameMethod, float]) -> list[FrameMethod]:
    """The candidates of ``psnr`` best expected quality first (NaN: no coverage, last), ties in its order."""
    return sorted(psnr, key=lambda m: -psnr[m] if not math.isnan(psnr[m]) else math.inf)  # a stable sort


def fits(ms: float, budget_ms: float, headroom: float) -> bool:
    """Whether a frame of ``ms`` fits a budget of ``budget_ms``: it takes at most ``headroom`` of it (the policy's
    one test; NaN fits nothing)."""
    return ms <= headroom * budget_ms


def best_timed(quality: QualityProbe, timings: dict, budget_ms: float, headroom: float) -> FrameMethod | None:
    """Of the candidates timed already, the best expected quality within ``headroom`` of the budget; None where
    none is. A choice without device work."""
    return next((m for m in quality_order(quality.psnr) if fits(timings.get(m, math.inf), budget_ms, headroom)), None)


def _pick(order: list[FrameMethod], timings: dict, budget_ms: float, headroom: float
          ) -> tuple[FrameMethod | None, FrameMethod | None, list[FrameMethod]]:
    """Step 3 of the module docstring on the times known: ``(method to time next, None, [])``
    where they do not decide it, else ``(None, the choice, the methods considered)``: the first
    in ``order`` within ``headroom`` of the budget, or the fastest of all where none is."""
    for i, m in enumerate(order):
        if m not in timings:
            return m, None, []
        if fits(timings[m], budget_ms, headroom):
            return None, m, order[:i + 1]
    return None, min(order, key=timings.__getitem__), list(order)


def render_within_budget(renderer: Renderer, camera: Camera, iso: float, width: int, height: int, budget_ms: float,
                         config: BudgetConfig = BudgetConfig()) -> tuple[FrameBuffers, BudgetChoice]:
    """One frame made by the method :func:`choose_method` picks for the budget, and the choice.

    Shape:
        The frame's color: (H, W, 3) in [0, 1] (see :meth:`FrameRunner.frame`).
    """
    networks = Networks()
    still = [camera] * config.probe_frames  # the view to be shown is the one to probe
    choice = choose_method(renderer, iso, width, height, budget_ms, config, cameras=still, networks=networks)
    runner = make_runner(choice.method, renderer, iso, width, height, shading=config.shading,
                         ao_radius=config.ao_radius, networks=networks, clip=config.clip)
    return runner.frame(camera).buffers, choice
