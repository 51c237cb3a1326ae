"""The ``auto`` view mode's policy: the best frame method for a session's share of the device.

With N view sessions and a target of F frames a second each, a frame gets ``1000 / (N F)`` ms of
device time; :func:`isosr_net.budget.choose_method` picks the method of the best expected quality
whose probe time fits that budget less its headroom. The probe's quality scores are cached per
volume, iso and size, and its timings per volume, iso, size and method, so a re-choice after N
changes costs no new probe; a choice is cached per (volume, iso, size, AO radius, N). The probe
runs on the session's current view (a still camera: the view to be shown).

The first choice for a scene and size runs the probe on the device thread: every candidate's
frames at a quarter of the frame's side and the timed ones at the frame's size (``probe_seconds``
of the choice says how long; the server logs it).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import warnings

from isosr_net.budget import BudgetChoice, BudgetConfig, QualityProbe, choose_method, default_candidates, \
    probe_quality
from isosr_net.frame_methods import FrameMethod, FrameRunner, Networks
from isosr_net.reconstructor import Reconstructor, recon_limits
from isosr_render import Camera, Renderer

log = logging.getLogger("isosr.server")
# The probe's frames (a still camera needs few), timed by the wall clock: the device thread's
# cost per frame, host work included (on an H100 at 1080p it exceeds the GPU's for cheap methods).
# Headroom 0.75: under load a frame costs the device thread more than alone (its encoding's
# hand-off, the event loop's share of the host): on an H100 at 1080p, 16 sessions of full
# frames ran at 2.7 ms each where one alone took 1.5 ms of the device thread.
PROBE = dict(probe_frames=1, warmup_frames=1, timing_frames=2, clock="wall", headroom=0.75)


def served_factor(runner: type[FrameRunner], factor: int) -> int:
    """The factor the service gives a method of ``runner``: its upscaler's ``factor`` to low-res
    kinds, 1 to the others (its reconstruction renders at full resolution)."""
    return factor if runner.low_res else 1


class AutoPolicy:
    """Chooses and caches the auto mode's methods for one server.

    Args:
        candidates: the methods to choose from (the server's models and precision).
        target_fps: frames a second each session should get.
        networks: the server's loaded networks (the probe's runners use them).
    """

    def __init__(self, candidates: tuple[FrameMethod, ...], target_fps: float, networks: Networks):
        if not target_fps > 0:
            raise ValueError(f"target_fps must be positive, got {target_fps!r}")
        self.candidates, self.target_fps, self.networks = candidates, float(target_fps), networks
        self._quality: dict[tuple, QualityProbe] = {}
        self._timings: dict[tuple, dict] = {}
        self._chosen: dict[tuple, BudgetChoice] = {}

    @classmethod
    def for_server(cls, device: str, precision: str, factor: int, models: dict, target_fps: float,
                   networks: Networks, x2_model: str | os.PathLike | None = None) -> "AutoPolicy":
        """The default candidates with the server's precision, upscale factor and model folders
        (``models``: network class -> (folder or None, name), as in the views' context), and the
        reconstruction at twice the sides by ``x2_model`` (None: none)."""
        recon_folder = models.get(Reconstructor, (None, None))[0]
        limits = None if recon_folder is None else recon_limits(recon_folder)
        candidates = []
        for m in default_candidates(device, precision, limits, x2_model):
            if m.learned and m.model is None:  # a server model's method (the x2 one names its own)
                folder, name = models.get(m.runner.network_class, (None, m.model_name))
                m = dataclasses.replace(m, model=None if folder is None else str(folder), model_name=name,
                                        factor=served_factor(m.runner, factor))
            candidates.append(m)
        return cls(tuple(candidates), target_fps, networks)

    def budget_ms(self, sessions: int) -> float:
        """A frame's share of device time with ``sessions`` sessions served."""
        return 1000.0 / (max(1, sessions) * self.target_fps)

    def choose(self, renderer: Renderer, scene: str, iso: float, width: int, height: int, camera: Camera,
               sessions: int, ao_radius: float) -> BudgetChoice:
        """The method for this scene, size and session count (device thread; probes on first use)."""
        scene_key = (scene, round(float(iso), 6), width, height, float(ao_radius))
        key = scene_key + (max(1, sessions),)
        if key in self._chosen:
            return self._chosen[key]
        config = BudgetConfig(candidates=self.candidates, ao_radius=ao_radius, **PROBE)
        cameras = [camera] * config.probe_frames
        if scene_key not in self._quality:
            self._quality[scene_key] = probe_quality(renderer, iso, width, height, config, cameras, self.networks)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # "nothing fits" is in the choice and the log
            choice = choose_method(renderer, iso, width, height, self.budget_ms(sessions), config, cameras,
                                   self.networks, quality=self._quality[scene_key],
                                   timings=self._timings.setdefault(scene_key, {}))
        log.info("auto mode, %s at %dx%d, %d session(s): %s", scene, width, height, sessions, choice.summary())
        self._chosen[key] = choice
        return choice
