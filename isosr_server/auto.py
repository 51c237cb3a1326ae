"""The ``auto`` view mode's policy: the best frame method for a session's share of the device.

With N view sessions and a target of F frames a second each, a frame gets ``1000 / (N F)`` ms of
device time (``1000 S / (N F)`` for a replica with a share S of a GPU that others use too, until its
frames' cost in service is measured: below);
:func:`isosr_net.budget.choose_method` picks the method of the best expected quality whose probe
time fits that budget less its headroom. The probe's quality scores are cached per
volume, iso and size, and its timings per volume, iso, size and method, so a re-choice after N
changes costs no new probe; a choice is cached per (volume, iso, size, AO radius, clip, N). The probe
runs on the session's current view (a still camera: the view to be shown) as clipped (a clip
changes what a frame costs and shows): its references and candidates are rendered with the clip.

On GPUs with 4 sessions or more, a candidate is timed as their frames are made under load, several
sessions' at once (the frame methods' ``make_batch``: the reconstruction's network then runs once
for all), each frame costing its share of the batch (:func:`probe_batch`).

A choice is then held to what its frames cost in service (:meth:`AutoPolicy.served`): a probe times
its candidates at the load of its moment, and on a replica sharing a GPU the others' frames may be
cheaper then than once every replica makes its choice (on an H200, four replicas with a quarter
each: budgets cut to the share chose plain frames at 29.6 frames/s a session, whole budgets chose
the reconstruction at 2 rays a pixel and got 25.3). The budget is the session's whole share over
the measured load, ``1000 / (N F L)``, with ``L`` what its frames cost the device thread in service
over the probe's time, both by the wall clock (``1 / S`` until measured): the choice is made again
where ``L`` moves. ``L`` is the latest measure; a method's own measure holds for :data:`LOAD_HOLD_S`
where it is higher (its probe time counts at its own load): a method that proved dear is not tried
again at once, while a spike that one method met (on an H200, four replicas probing at once: 13-17
times the probe, a minute of budgets under 0.6 ms when the scene's load held it) does not keep the
others from the budget. While a probe chooses again, a choice that no longer fits the budget gives way at once to
the best candidate timed already that does, else to the prior at that budget (:meth:`AutoPolicy._meanwhile`).
The log says a choice where its method changes; a re-choice that keeps the method (a load measured on either side
of :data:`DRIFT`: on an H200's replicas, loads of 1.0 and 1.3-1.4 in turn, a re-choice a second) only at DEBUG.

Under load a session gives up rate before AO: where that budget leaves only a frame without AO
(or with too few rays to gain over none) in a scene where AO matters, the cheapest candidate with AO
rays that gains :data:`KEEP_AO_DB` and fits the budget at ``min_fps`` (of those timed already, and of
the first :data:`KEEP_AO_TRIES` not yet timed) takes its place: many viewers of one GPU get a (learned)
frame with AO at a lower rate, not a plain frame without it at the target rate.

No frame waits for a probe. Until the probe of a scene and size has run, frames use the prior:
first the cheapest candidate (no AO, one ray per pixel), the frame that reaches the viewer
first; once the probe's first units timed this scene's plain first-hit frame, the device class's
committed cost table (:class:`isosr_net.budget.CostTable`) picks the best tabled method whose
cost in first-hit frames fits the budget. The probe runs in the background as generator steps
(:func:`isosr_net.budget.choose_method_steps`) that the engine interleaves with frames on the device thread, a
unit of work at a time, and that shutdown drops between two units. On GPUs a candidate's first frame at a new size
carries one-off costs (fused kernels tuned for the size's class, shading compiled for its inputs): the
server pays them at start for its common window sizes and their probes (:meth:`AutoPolicy.warm`),
and logs a unit that still held the device thread for long. What a probe learns is kept per device, volume, iso and
size in ``probe_cache`` (a JSON file), so that a restarted server chooses without probing.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Generator
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

from isosr_net.budget import (BudgetChoice, BudgetConfig, CostTable, QualityProbe, best_timed, choose_method_steps,
                              default_candidates, default_probe_height, first_hit_ms_steps, fits, floor_ms,
                              probe_quality_steps, probe_size)
from isosr_net.methods import FrameMethod, FrameRunner, Networks, make_runner
from isosr_net.reconstructor import Reconstructor, recon_limits
from isosr_render import Camera, Renderer
from isosr_render.clip import Clip
from isosr_render.atomic import atomic_write
from isosr_render.camera import orbit_path
from isosr_render.sequence import sequence_cameras
from isosr_server.core.config import check_gpu_share, check_min_fps

log = logging.getLogger("isosr.server")
# The probe's frames (a still camera needs few), timed by the wall clock: the device thread's
# cost per frame, host work included (on an H100 at 1080p it exceeds the GPU's for cheap methods).
# Headroom 0.75: under load a frame costs the device thread more than alone (its encoding's
# hand-off, the event loop's share of the host): on an H100 at 1080p, 16 sessions of full
# frames ran at 2.7 ms each where one alone took 1.5 ms of the device thread.
PROBE = dict(probe_frames=1, warmup_frames=1, timing_frames=2, clock="wall", headroom=0.75)
# On GPUs under load a candidate is timed as the service makes it: a batch of streams' frames at once
# (BudgetConfig.batch), each frame costing its share; batches of at most this many.
PROBE_BATCH = 8
# A choice held to what its frames cost in service: after this many of them, their device-thread time over its probe's
# time (the service's load: other replicas on the GPU, the host) rescales the budget; a change beyond DRIFT
# re-chooses (AutoPolicy.served).
SERVICE_FRAMES = 64
DRIFT = 1.25
# A method's measured load holds this long for it where the scene's latest is lower (no ping-pong back to a method that
# proved dear); then its probe time counts at the scene's load again.
LOAD_HOLD_S = 60.0
# What a frame must gain over the target rate's choice, one without AO where AO matters, for auto to give up rate
# (down to min_fps) for it: 3 dB, half the error's power.
KEEP_AO_DB = 3.0
# Candidates with AO not yet timed that auto times for that trade, cheapest first (each a probe unit or two of device
# time); those timed already cost nothing to weigh and are all weighed.
KEEP_AO_TRIES = 3


def drops_ao(choice: BudgetChoice, quality: QualityProbe) -> bool:
    """Whether a choice shows none of the AO: a frame without AO rays, or one whose rays gain nothing over the
    best frame without (1 noisy ray a pixel scored below none on an H200's probes)."""
    plain = [psnr for m, psnr in quality.psnr.items() if not m.ao_rays and math.isfinite(psnr)]
    return not choice.method.ao_rays or bool(plain) and choice.expected_psnr <= max(plain)


def served_factor(runner: type[FrameRunner], factor: int) -> int:
    """The factor the service gives a method of ``runner``: its upscaler's ``factor`` to low-res
    kinds, 1 to the others (its reconstruction renders at full resolution)."""
    return factor if runner.low_res else 1


def probe_batch(renderer: Renderer, sessions: int) -> int:
    """The streams a probe times a candidate's frames for at once: on GPUs, the power of two up to
    half the ``sessions`` (closed-loop viewers: about half wait on the wire while the others' frames
    are made; measured batch means 8.4 of 16 sessions in one process, 1.8 of 4 a replica), at most
    :data:`PROBE_BATCH`; 1 (frames alone) below 4 sessions and on CPUs."""
    if not renderer.device.is_cuda or sessions < 4:
        return 1
    return min(PROBE_BATCH, 1 << (sessions // 2).bit_length() - 1)


def prior_method(candidates: tuple[FrameMethod, ...]) -> FrameMethod:
    """The method of the frames before a probe: the cheapest candidate at full resolution (fewest
    rays, no network), where there is one: a sharp first look, if not the fastest one."""
    return min(candidates, key=lambda m: (m.ao_rays * m.spp, m.spp, m.learned, m.factor))


class Chosen(NamedTuple):
    """A choice as the policy holds it: the choice, the load it was made for, its method's probe time (ms; the
    choice's own may count a held load) and until when the held loads that shaped it hold (by the policy's clock)."""

    choice: BudgetChoice
    load: float
    probe_ms: float
    until: float


class ProbeCache:
    """What probes learned (quality scores and frame times by method name), per device, volume,
    iso and size, in a JSON file read at start and rewritten whole after each probe; ``None``:
    kept in memory only. A file that cannot be read is ignored (and overwritten), with a notice."""

    def __init__(self, path: Path | None, device: str):
        self.path, self.device = path, device
        self.entries: dict[str, dict] = {}
        if path is not None and path.is_file():
            try:
                self.entries = json.loads(path.read_text())
            except (OSError, ValueError) as e:
                log.warning("the auto mode's probe cache %s cannot be read (%s): probing anew", path, e)

    def _key(self, scene_key: tuple) -> str:
        return json.dumps([self.device, *scene_key])

    def get(self, scene_key: tuple, candidates: tuple[FrameMethod, ...]) -> tuple[QualityProbe, dict] | None:
        """The probe's quality and timings for this scene, by the candidates of these names."""
        entry = self.entries.get(self._key(scene_key))
        by_name = {m.name: m for m in candidates}
        if entry is None or not set(entry["psnr"]) <= set(by_name) or "probe_ms" not in entry:
            return None
        psnr = {by_name[n]: (math.nan if v is None else v) for n, v in entry["psnr"].items()}
        probe_ms = {by_name[n]: ms for n, ms in entry["probe_ms"].items()}
        quality = QualityProbe(tuple(entry["size"]), psnr, entry["ao_effect_db"], entry["ao_matters"], 0.0, probe_ms)
        return quality, {by_name[n]: ms for n, ms in entry["timings"].items() if n in by_name}

    def put(self, scene_key: tuple, quality: QualityProbe, timings: dict) -> None:
        self.entries[self._key(scene_key)] = {
            "size": list(quality.size), "ao_effect_db": quality.ao_effect_db, "ao_matters": quality.ao_matters,
            "psnr": {m.name: (None if math.isnan(v) else v) for m, v in quality.psnr.items()},
            "probe_ms": {m.name: ms for m, ms in quality.ms.items()},
            "timings": {m.name: ms for m, ms in timings.items()}}
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            text = json.dumps(self.entries, indent=1).encode()
            atomic_write(self.path, lambda f: f.write(text))


class AutoPolicy:
    """Chooses and caches the auto mode's methods for one server.

    Args:
        candidates: the methods to choose from (the server's models and precision).
        target_fps: frames a second each session should get.
        networks: the server's loaded networks (the probe's runners use them).
        cache: where probes' results are kept (default: in memory).
        slice_ms: device time a unit of the probe's timed frames aims at (None: whole frames).
        costs: the device class's committed cost table, the prior before a probe (None: the
            cheapest candidate until the probe decides).
        gpu_share: the part of the device this server's frames get (a replica sharing a GPU with
            others: its part); a frame's budget is its session's share of that part until what its
            frames cost in service is measured (:meth:`load`).
        min_fps: the least frame rate a session is given to keep AO that the target rate would drop
            (:meth:`_keeping_ao`); None: ``target_fps`` (rate is never given up).

    Attributes:
        pending: probes to run (generators of device-thread steps), taken by the engine.

    :meth:`served` runs on the event loop, the rest on the device thread: only it writes the loads and
    the served counts, each a single dict store.
    """

    def __init__(self, candidates: tuple[FrameMethod, ...], target_fps: float, networks: Networks,
                 cache: ProbeCache | None = None, slice_ms: float | None = None, costs: CostTable | None = None,
                 gpu_share: float = 1.0, min_fps: float | None = None):
        if not target_fps > 0:
            raise ValueError(f"target_fps must be positive, got {target_fps!r}")
        self.candidates, self.target_fps, self.networks = candidates, float(target_fps), networks
        self.min_fps = check_min_fps(target_fps if min_fps is None else min_fps, target_fps)
        self.gpu_share = check_gpu_share(gpu_share)
        self.cache, self.slice_ms = cache or ProbeCache(None, ""), slice_ms
        self.pending: list[Generator[None, None, BudgetChoice]] = []
        self._quality: dict[tuple, QualityProbe] = {}
        self._timings: dict[tuple, dict] = {}
        self._chosen: dict[tuple, Chosen] = {}
        self._probing: set[tuple] = set()
        self._load: dict[tuple, float] = {}  # scene key -> its frames' latest cost in service over their probe's time
        self._own: dict[tuple, dict[FrameMethod, tuple[float, float]]] = {}  # scene key -> method -> (its load, when)
        self.clock = time.monotonic
        self._served: dict[tuple, tuple[int, float]] = {}  # key -> frames of its choice served, their summed ms
        self.costs = costs
        self._first_hit: dict[tuple, float] = {}  # scene key -> a plain first-hit frame's ms

    @classmethod
    def for_server(cls, device: str, precision: str, factor: int, models: dict, target_fps: float,
                   networks: Networks, x2_model: str | os.PathLike | None = None, cache: ProbeCache | None = None,
                   slice_ms: float | None = None, gpu_share: float = 1.0, min_fps: float | None = None
                   ) -> "AutoPolicy":
        """The default candidates with the server's precision, upscale factor and model folders
        (``models``: network class -> (folder or None, name), as in the views' context), and the
        reconstruction at twice the sides by ``x2_model`` (None: none)."""
        recon_folder = models.get(Reconstructor, (None, None))[0]
        limits = None if recon_folder is None else recon_limits(recon_folder)
        candidates = []
        for m in default_candidates(device, precision, limits, x2_model):
            if m.learned and m.options.model is None:  # a server model's method (the x2 one names its own)
                folder, name = models.get(m.runner.network_class, (None, m.options.model_name))
                m = m.replace(model=None if folder is None else str(folder), model_name=name,
                              factor=served_factor(m.runner, factor))
            candidates.append(m)
        return cls(tuple(candidates), target_fps, networks, cache, slice_ms, CostTable.for_device(device), gpu_share,
                   min_fps)

    def warm(self, renderer: Renderer, sizes: tuple[tuple[int, int], ...]) -> None:
        """Make two frames of every candidate at each ``(height, width)`` and at its probe's size
        (device thread, at start): what a candidate's first frame at a new size costs once (kernels
        tuned for the size's class, shading compiled for its inputs) is paid before any viewer waits,
        not in a probe unit between the sessions' frames."""
        pairs = sequence_cameras(orbit_path(2))
        rows = default_probe_height(str(renderer.device))
        for width, height in {(w, h) for h, w in sizes} | {probe_size(w, h, rows) for h, w in sizes}:
            for m in self.candidates:
                if not (width % m.factor or height % m.factor):
                    runner = make_runner(m, renderer, 0.5, width, height, networks=self.networks)
                    for camera, prev in pairs:
                        runner.frame(camera, prev)

    def budget_ms(self, sessions: int) -> float:
        """A frame's share of device time with ``sessions`` sessions served (of this server's ``gpu_share``)."""
        return 1000.0 * self.gpu_share / (max(1, sessions) * self.target_fps)

    def load(self, scene_key: tuple) -> float:
        """What the service's load makes a probed frame of ``scene_key`` cost, in probe times: measured by
        :meth:`served`, else ``1 / gpu_share`` (a replica's probe timed with the GPU's other users idle)."""
        return self._load.get(scene_key, 1.0 / self.gpu_share)

    def _budget_at(self, sessions: int, load: float) -> float:
        """A frame's budget in probe time: the session's whole share over the ``load``."""
        return self.budget_ms(sessions) / (self.gpu_share * load)

    def _timings_of(self, scene_key: tuple, batch: int) -> dict:
        """A scene's probe times of frames alone (kept in the cache), or in batches of ``batch`` (kept for this run:
        measured again after a start)."""
        return self._timings.setdefault(scene_key if batch == 1 else scene_key + (batch,), {})

    def _seen(self, scene_key: tuple, load: float, timings: dict) -> tuple[dict, float]:
        """``timings`` with the dear methods at their own held load (:meth:`_held`; one timed only now, at a new
        batch size, counts at the scene's), and until when the first of those holds."""
        factors, until = self._held(scene_key, load)
        return timings | {m: ms * factors[m] for m, ms in timings.items() if m in factors}, until

    def _held(self, scene_key: tuple, load: float) -> tuple[dict[FrameMethod, float], float]:
        """The methods whose own measured load still holds above ``load`` (each: over it), and until when the first
        of them holds (inf: none)."""
        now, factors, until = self.clock(), {}, math.inf
        for method, (own, when) in self._own.get(scene_key, {}).items():
            if own > load and now - when < LOAD_HOLD_S:
                factors[method], until = own / load, min(until, when + LOAD_HOLD_S)
        return factors, until

    def served(self, scene: str, iso: float, width: int, height: int, sessions: int, ao_radius: float, clip: Clip,
               method: FrameMethod, thread_ms: float) -> None:
        """A frame of a probed choice cost the device thread ``thread_ms`` in service (its share of its batch's wall
        time: the probe's clock; event loop). Every
        :data:`SERVICE_FRAMES` such frames, their mean over the probe's time (at least 1) is the scene's
        :meth:`load` and the method's own, which holds for it :data:`LOAD_HOLD_S` where higher (a method that proved
        dear is not tried again at once). A load that moved by more than :data:`DRIFT` has :meth:`choose` choose
        again."""
        scene_key, key = self._keys(scene, iso, width, height, sessions, ao_radius, clip)
        chosen = self._chosen.get(key)
        if (chosen is None or not chosen.choice.table or chosen.choice.method != method or not chosen.probe_ms > 0
                or not 0 < thread_ms < math.inf):
            return  # a prior's, another mode's, or no time (none, non-finite): no measure of the probe's choice
        frames, total = self._served.get(key, (0, 0.0))
        frames, total = frames + 1, total + thread_ms
        if frames < SERVICE_FRAMES:
            self._served[key] = frames, total
            return
        self._served.pop(key, None)
        measured = max(1.0, total / frames / chosen.probe_ms)
        self._load[scene_key] = measured
        self._own.setdefault(scene_key, {})[method] = measured, self.clock()
        if not self._holds(scene_key, chosen):
            log.debug("auto mode, %s at %dx%d, %d sessions: %s costs %.3g ms in service, %.2f times its probe's time "
                      "(load %.2f, chosen at %.2f): choosing again", scene, width, height, key[-1], method.name,
                      total / frames, total / frames / chosen.probe_ms, measured, chosen.load)

    def _holds(self, scene_key: tuple, chosen: Chosen) -> bool:
        """Whether a choice still holds: the scene's :meth:`load` within DRIFT of the one it was made for, and the
        methods' own loads that shaped it still held."""
        return 1 / DRIFT < self.load(scene_key) / chosen.load < DRIFT and self.clock() < chosen.until

    @staticmethod
    def _keys(scene: str, iso: float, width: int, height: int, sessions: int, ao_radius: float,
              clip: Clip) -> tuple[tuple, tuple]:
        """A scene's key (its probe's) and a choice's (the scene's at a session count)."""
        cut = (repr(clip),) if clip.active else ()  # a clip's own probe; unclipped keys as before (the cache's)
        scene_key = (scene, round(float(iso), 6), width, height, float(ao_radius)) + cut
        return scene_key, scene_key + (max(1, sessions),)

    def choose(self, renderer: Renderer, scene: str, iso: float, width: int, height: int, camera: Camera,
               sessions: int, ao_radius: float, clip: Clip = Clip()) -> BudgetChoice:
        """The method for this scene (as ``clip`` cuts it), size and session count, at once (device
        thread): the probe's choice where what probes learned decides it, else the prior while the
        probe waits in :attr:`pending` (choosing again: :meth:`_meanwhile`, said in the log where it differs)."""
        scene_key, key = self._keys(scene, iso, width, height, sessions, ao_radius, clip)
        chosen = self._chosen.get(key)
        if chosen is not None and self._holds(scene_key, chosen):
            return chosen.choice
        started = key not in self._probing
        if started:
            probe = self._probe(renderer, scene_key, key, camera, clip)
            try:
                next(probe)
            except StopIteration as decided:  # earlier probes' results decide it: no device work
                return decided.value
            self._probing.add(key)
            self.pending.append(probe)
        if chosen is None:
            return self.prior(self.budget_ms(sessions), scene_key)
        meanwhile = self._meanwhile(scene_key, key, chosen, probe_batch(renderer, sessions))
        if started and meanwhile.method != chosen.choice.method:
            log.info("auto mode, %s at %dx%d, %d sessions: %s no longer fits %.3g ms; %s until the probe chooses",
                     scene, width, height, key[-1], chosen.choice.method.name, meanwhile.budget_ms,
                     meanwhile.method.name)
        return meanwhile

    def _meanwhile(self, scene_key: tuple, key: tuple, chosen: Chosen, batch: int) -> BudgetChoice:
        """While a probe chooses again: the held choice where it still fits the budget at the scene's :meth:`load`,
        else the best candidate timed already that does, else the prior at that budget (:meth:`prior`), without
        device work: a choice that proved dear is not served for the seconds the probe takes (on an H200 under four
        replicas, probes whose budget nothing fit took 13.6-13.9 s, and in a reverted experiment a choice that cost
        21 times its probe's time was served for the 30 s its next probe took)."""
        load = self.load(scene_key)
        budget_ms = self._budget_at(key[-1], load)
        seen, _ = self._seen(scene_key, load, self._timings_of(scene_key, batch))
        held = chosen.choice
        if fits(seen.get(held.method, chosen.probe_ms), budget_ms, PROBE["headroom"]) or scene_key not in self._quality:
            return held
        quality = self._quality[scene_key]
        method = best_timed(quality, seen, budget_ms, PROBE["headroom"])
        if method is None:
            return self.prior(budget_ms, scene_key)
        return replace(held, method=method, ms=seen[method], expected_psnr=quality.psnr[method], fits=True,
                       budget_ms=budget_ms)

    def _keeping_ao(self, renderer: Renderer, iso: float, width: int, height: int, choice: BudgetChoice,
                    config: BudgetConfig, cameras: list[Camera], quality: QualityProbe,
                    timings: dict) -> Generator[None, None, tuple[BudgetChoice, str]]:
        """``choice`` (the target rate's), or where it drops AO that matters (:func:`drops_ao`), the first candidate
        (the cheapest) with AO rays that gains :data:`KEEP_AO_DB` over it and keeps :attr:`min_fps`, of such
        candidates whose floor allows it: every one timed already (``timings``), and the first
        :data:`KEEP_AO_TRIES` of the others, timed in turn: rate given up for AO, no more of it than the cheapest
        such frame needs. With it, why (for the log; empty where AO was not at stake)."""
        if not choice.ao_matters or self.min_fps == self.target_fps or not drops_ao(choice, quality):
            return choice, ""
        floor_budget = choice.budget_ms * self.target_fps / self.min_fps
        gains = [m for m in self.candidates if m.ao_rays and floor_ms(m, quality, width, height) <= floor_budget
                 and quality.psnr.get(m, math.nan) >= choice.expected_psnr + KEEP_AO_DB]  # CPUs: floors untimed
        untimed = [m for m in gains if m not in timings]
        weighed = [m for m in gains if m in timings or m in untimed[:KEEP_AO_TRIES]]
        for method in weighed:
            only = replace(quality, psnr={method: quality.psnr[method]})
            kept = yield from choose_method_steps(renderer, iso, width, height, floor_budget, config, cameras,
                                                  self.networks, only, timings, self.slice_ms, warn=False)
            if kept.fits:
                return kept, (f"auto mode: {choice.method.name} ({choice.expected_psnr:.1f} dB) drops the AO the scene "
                              f"shows; at {self.min_fps:g} frames/s a session: {kept.summary()}")
        tried = ", ".join(f"{m.name} {quality.psnr[m]:.1f} dB {timings.get(m, math.nan):.2f} ms"
                          for m in weighed)
        return choice, (f"auto mode: {choice.method.name} ({choice.expected_psnr:.1f} dB) drops the AO the scene "
                        f"shows; none with AO keeps {self.min_fps:g} frames/s a session within "
                        f"{floor_budget * config.headroom:.3g} ms ({tried or f'none gains {KEEP_AO_DB:g} dB'})")

    def prior(self, budget_ms: float, scene_key: tuple | None = None) -> BudgetChoice:
        """The choice before a probe: the cost table's where this scene's first-hit time is known
        (predicted time and PSNR), else :func:`prior_method` (nothing measured)."""
        first_hit = self._first_hit.get(scene_key)
        if self.costs is not None and first_hit is not None:
            picked = self.costs.choose(self.candidates, first_hit, budget_ms, PROBE["headroom"])
            if picked is not None:
                method, ms, psnr = picked
                return BudgetChoice(method, ms, psnr, True, budget_ms, math.nan, False, (0, 0), 0.0, ())
        return BudgetChoice(prior_method(self.candidates), math.nan, math.nan, False, budget_ms, math.nan, False,
                            (0, 0), 0.0, ())

    def _probe(self, renderer: Renderer, scene_key: tuple, key: tuple, camera: Camera,
               clip: Clip) -> Generator[None, None, BudgetChoice]:
        """The choice for ``key`` as device-thread steps (a failed probe keeps the prior, logged)."""
        _, iso, width, height, ao_radius = scene_key[:5]
        batch = probe_batch(renderer, key[-1])
        load = self.load(scene_key)
        budget_ms = self._budget_at(key[-1], load)
        config = BudgetConfig(candidates=self.candidates, ao_radius=ao_radius, batch=batch, clip=clip, **PROBE)
        cameras = [camera] * config.probe_frames
        if scene_key not in self._quality and (cached := self.cache.get(scene_key, self.candidates)):
            self._quality[scene_key], self._timings[scene_key] = cached
        timings = self._timings_of(scene_key, batch)
        probes_quality, timed_before = scene_key not in self._quality, len(timings)
        try:
            if scene_key not in self._quality and self.costs is not None and scene_key not in self._first_hit:
                self._first_hit[scene_key] = yield from first_hit_ms_steps(renderer, iso, width, height, camera,
                                                                           ao_radius, self.networks, clip)
            if scene_key not in self._quality:
                self._quality[scene_key] = yield from probe_quality_steps(renderer, iso, width, height, config,
                                                                          cameras, self.networks)
            seen, until = self._seen(scene_key, load, timings)
            choice = yield from choose_method_steps(renderer, iso, width, height, budget_ms, config, cameras,
                                                    self.networks, self._quality[scene_key], seen,
                                                    self.slice_ms, warn=False)
            choice, why = yield from self._keeping_ao(renderer, iso, width, height, choice, config, cameras,
                                                      self._quality[scene_key], seen)
            timings.update({m: ms for m, ms in seen.items() if m not in timings})  # timed now
        except ValueError as e:  # the scene or size admits no candidate: say why, keep the prior
            log.warning("auto mode, %s at %dx%d: no probe (%s); frames stay %s", scene_key[0], width, height, e,
                        prior_method(self.candidates).name)
            choice, until = self.prior(self.budget_ms(key[-1]), scene_key), math.inf
        else:  # said where the method changes; a load's drift that keeps it, only when debugging
            before = self._chosen.get(key)
            level = logging.INFO if before is None or before.choice.method != choice.method else logging.DEBUG
            if why:
                log.log(level, "%s", why)
            log.log(level, "auto mode, %s at %dx%d, budget %.3g ms: %s", scene_key[0], width, height, budget_ms,
                    choice.summary())
            if probes_quality or len(timings) > timed_before:  # something was measured: keep it
                self.cache.put(scene_key, self._quality[scene_key], self._timings.get(scene_key, {}))
        finally:
            self._probing.discard(key)
        self._chosen[key] = Chosen(choice, load, timings.get(choice.method, choice.ms), until)
        return choice
