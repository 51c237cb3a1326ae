"""The one conformance test every frame method keeps (issue 46), as diffusers' ``SchedulerCommonTest``
and kornia's filter testers share their checks: :class:`MethodContract` holds the tests, and a
method's test is a subclass that names the method and its options (``tests/test_method_contract.py``):

    class TestFull(MethodContract):
        method = FrameMethod.of("full", ao_rays=2)

The name has no ``Test`` prefix, so pytest collects only the subclasses. Every check runs the class's
``method`` on a small volume on :data:`conftest.DEVICE` (the CPU in CI): a sphere resting on a floor,
with a second ball beside it, so that AO rays of radius :data:`AO_RADIUS` are occluded near the
contacts and AO depends on the rays' seed; frames of :data:`SIZE`. A learned method runs a tiny
randomly initialized network of its kind and factor (:func:`tiny_model`), not the shipped one,
unless its class sets ``shipped_model = True``: the checks hold for any weights.

The checks:

- frames: a 3-frame sequence; every buffer float32, finite, at the frame size (an unshaded low-res
  kind's at the render's), only the buffers the method makes (``makes``, color where shaded, flow
  where continued), mask (and AO) in [0, 1], color in [0, 1] where shaded, something hit (not
  asked of a tiny random network's mask), per-stage times, ``continued`` only on a recurrent
  kind's continued frames;
- determinism: two runners along the same cameras give the same frames, bit for bit on the CPU
  (within 1e-5 on CUDA, where compiled kernels and graphs need not be);
- batches: three streams made together by the kind's ``make_batch`` (each along its own cameras,
  one cutting mid-way) give each stream the frames it makes alone; a stream whose frame fails
  gets its error as its result, and its batch mates their frames;
- draws: draw 0 casts the service's AO seeds, draw 1 others (:data:`DRAW_SEEDS` on): another frame where the
  method casts AO rays, the same frame where it casts none; a negative draw is refused naming it;
- reset: a frame without a previous camera after a sequence equals a new runner's first frame of
  that camera (a kind with ``fresh_rays`` numbers its AO seeds by the frames it made, a stream's
  ray sequence rather than its recurrent state: the new runner is set to the same count);
- options: the kind's options type (``FrameRunner.options_type``) is a frozen, hashable dataclass
  whose defaults are valid; each count is accepted at its bounds (``MethodOptions.bounds``) and
  refused one past either, each choice refused another value, by a ValueError that names the
  field and its bounds or choices (the options type's own, and the method's naming the kind); a
  kind without a count reads its neutral value (``FrameMethod.ao_rays``, ``spp``, ``factor``); a
  knob the kind does not take is refused naming it and those it takes;
- hard cases: the camera inside the volume, rays grazing the sphere and rays grazing the volume's
  box, an iso at either end of the data's range and one past it (nothing hit: exactly the
  background wherever the mask is 0 and ``|color - background| <= mask`` everywhere, an empty mask
  for unlearned kinds),
  a 2x2 frame (where the factor divides 2), an anisotropic volume: finite and bounded;
- clipping: a plane through the sphere with caps puts cut faces in the frame (its ``cap`` buffer, at
  the frame size, an unshaded low-res kind's at the render's); planes that keep nothing leave only the background,
  as an empty iso;
- bench row: the method's name (its runner's ``describe``) and its runner's label are non-empty;
  the Pareto study's method list (``bench_pareto.methods``, smoke) has the kind exactly where the
  kind shades (a study of colors), and for a shaded kind
  :func:`isosr_bench.bench_pareto.pareto_rows` makes its complete row on the smoke volume, size,
  frames and warm-up (the references, the same for every method, are made once per session).

A check a method fails is a finding: the class lists it in ``known_failures`` (test name, with its
parameter, to the exact reason) and it runs as a strict xfail.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import torch
from conftest import DEVICE, field_volume
from net_fixtures import tiny_model_dir

from isosr_net.methods import DRAW_SEEDS, FIRST_TEMPORAL_SEED, FrameMethod, MethodOptions, Networks, make_runner
from isosr_net.model import save_pretrained
from isosr_net.timing import StageTimer
from isosr_net.reconnet import ReconNet, ReconNetConfig
from isosr_net.reconstructor import Reconstructor
from isosr_net.upscaler import Upscaler
from isosr_render import Camera, FrameBuffers, Renderer, RenderRequest, orbit_path
from isosr_render.clip import Clip
from isosr_render.color_field import ColorField
from isosr_render.coloring import GRADIENT, Coloring
from isosr_render.conventions import BACKGROUND_RGB
from isosr_render.sequence import sequence_cameras
from isosr_render.shading import composite
from isosr_render.surfaces import Surfaces

SIZE = (32, 24)  # width, height: every factor up to 8 divides it
AO_RADIUS = 0.15  # world units: occluded near the contacts (the default, 0.05, barely occludes a 24^3 volume)
# A capped cut through the scene (its inside is below the plane): cut faces in the frame.
CAPPED = Clip(planes=[((0.0, 0.0, 0.05), (0.0, 0.0, -1.0))], cap="below")
CAMERAS = orbit_path(3, yaw0=20.0, yaw_step=4.0, pitch=25.0, distance=1.3)
# The hard cases' cameras (the scene: sphere of radius 0.22 at the origin, floor at y = -0.22).
INSIDE = Camera(eye=(0.0, 0.05, 0.0), target=(0.3, 0.0, 0.1))  # inside the sphere, the field's inside
GRAZING_SURFACE = Camera(eye=(-2.0, 0.0, 0.22), target=(2.0, 0.0, 0.22), fov_y=8.0)  # along the sphere's silhouette
GRAZING_BOX = Camera(eye=(-2.0, 0.5, 0.0), target=(2.0, 0.5, 0.0))  # along the volume box's top face
TINY = Camera(eye=(0.0, 0.1, 1.5), target=(0.0, 0.1, 0.0), fov_y=5.0)  # a 2x2 frame's rays all on the sphere
HARD_CASES = ("inside", "grazing_surface", "grazing_box", "iso_at_min", "iso_at_max", "iso_past_max", "tiny_2x2",
              "anisotropic")
EMPTY_ISOS = {"iso_at_min": 0.0, "iso_at_max": 1.0, "iso_past_max": 2.0}  # normalized: nothing hit
TINY_RECONNET = {"widths": (4, 4, 8, 8), "blocks": 1}  # net_fixtures.TINY_RECON_MODEL's size
UNREAD_VALUES = {"ao_rays": 1, "spp": 2, "factor": 2, "interpolation": "bicubic", "model": "elsewhere",
                 "model_name": "other", "precision": "bf16", "quality": "fast"}  # a value per knob of any kind
NEUTRAL_COUNTS = {"ao_rays": 0, "spp": 1, "factor": 1}  # what a method of a kind without the count reads

_CACHE: dict = {}


def contact_field(p: np.ndarray) -> np.ndarray:
    """Signed distance (world units) to a sphere of radius 0.22 at the origin resting on a floor at
    y = -0.22, with a ball of radius 0.12 beside it: AO occluded where they meet.

    Shape:
        p: (..., 3). Returns (...).
    """
    sphere = np.linalg.norm(p, axis=-1) - 0.22
    ball = np.linalg.norm(p - np.array([0.28, -0.1, 0.12]), axis=-1) - 0.12
    floor = p[..., 1] + 0.22
    return np.minimum(np.minimum(sphere, ball), floor)


def scene(anisotropic: bool = False) -> tuple[Renderer, float]:
    """``(renderer, normalized iso)`` of :func:`contact_field` on :data:`conftest.DEVICE` (24^3
    voxels; anisotropic: 24x16x12 voxels spaced 1, 1.5, 2), made once per session."""
    key = ("scene", anisotropic)
    if key not in _CACHE:
        shape, spacing = ((24, 16, 12), (1.0, 1.5, 2.0)) if anisotropic else ((24, 24, 24), (1.0, 1.0, 1.0))
        volume = field_volume(contact_field, shape, spacing)
        _CACHE[key] = Renderer(volume, DEVICE), volume.normalized_iso(0.0)
    return _CACHE[key]


def tiny_model(tmp_path_factory, network_class: type, factor: int) -> Path:
    """A saved tiny network with random weights of ``network_class`` (an ``Upscaler``'s SRNet or a
    ``Reconstructor``'s ReconNet) that upscales ``factor`` times, made once per session."""
    if network_class is Upscaler:
        return tiny_model_dir(tmp_path_factory, upscale=factor)
    if network_class is not Reconstructor:
        raise NotImplementedError(f"no tiny model of {network_class.__name__}: add one to tests/method_contract.py")
    key = ("recon", str(tmp_path_factory.getbasetemp()), factor)
    if key not in _CACHE:
        torch.manual_seed(0)
        folder = tmp_path_factory.mktemp(f"tiny_recon_x{factor}")
        save_pretrained(ReconNet(ReconNetConfig(upscale=factor, **TINY_RECONNET)), folder,
                        {"note": "random weights for tests"})
        _CACHE[key] = folder
    return _CACHE[key]


def networks() -> Networks:
    """A stream's own networks (forked from one root per session: each model loaded once)."""
    if "networks" not in _CACHE:
        _CACHE["networks"] = Networks()
    return _CACHE["networks"].fork()


def copied(buffers: FrameBuffers | None, but: tuple[str, ...] = ()) -> dict[str, torch.Tensor]:
    """Present buffers (none of ``but``), copied (a runner may reuse their memory); empty for None."""
    return {} if buffers is None else {n: getattr(buffers, n).clone() for n in buffers.present() if n not in but}


def buffers_of(result) -> dict[str, torch.Tensor]:
    """A frame's present buffers, copied, once its checks left to read later pass (as its taker reads them)."""
    result.checked()
    return copied(result.buffers)


def layers_of(buffers: FrameBuffers) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """A frame's buffers but its colour (the composite), and its ``behind`` layer's (empty where none), copied."""
    return copied(buffers, ("color",)), copied(buffers.behind, ("color",))


def assert_same_frames(a: list[dict], b: list[dict]) -> None:
    """The same buffers, bit for bit on the CPU (within 1e-5 on CUDA)."""
    assert len(a) == len(b)
    for i, (fa, fb) in enumerate(zip(a, b)):
        assert list(fa) == list(fb), f"frame {i}"
        for name in fa:
            if DEVICE == "cpu":
                assert torch.equal(fa[name], fb[name]), \
                    f"frame {i} {name}: max diff {(fa[name] - fb[name]).abs().max()}"
            else:
                torch.testing.assert_close(fa[name], fb[name], atol=1e-5, rtol=0, msg=f"frame {i} {name}")


def assert_finite_and_bounded(frame: dict[str, torch.Tensor], shaded: bool, where: str) -> None:
    """Every buffer finite; mask, AO and color in [0, 1]; a color where the method shades."""
    for name, t in frame.items():
        assert torch.isfinite(t).all(), f"{where}: {name} is not finite"
    for name in ("mask", "ao", "color"):
        if name in frame:
            assert frame[name].min() >= 0 and frame[name].max() <= 1, \
                f"{where}: {name} in [{frame[name].min()}, {frame[name].max()}]"
    assert ("color" in frame) == shaded, where


class MethodContract:
    """The checks every frame method keeps (module docstring). Subclasses set ``method``.

    Attributes:
        method: the method under test (a learned one's ``model`` is replaced by a tiny model).
        shipped_model: run the method's own model (the shipped one where ``model`` is None).
        known_failures: test name (with its parameter, e.g. ``test_x[case]``) to why the method
            fails it; each runs as a strict xfail.
    """

    method: ClassVar[FrameMethod]
    shipped_model: ClassVar[bool] = False
    known_failures: ClassVar[dict[str, str]] = {}

    @pytest.fixture(autouse=True)
    def _contract_setup(self, request, tmp_path_factory):
        if (reason := self.method.runner.unavailable()) is not None:
            pytest.skip(f"{self.method.kind} cannot run here: {reason}")
        if (reason := self.known_failures.get(request.node.name)) is not None:
            request.applymarker(pytest.mark.xfail(strict=True, reason=reason))
        self.spec = self.method
        self.random_network = self.method.learned and not self.shipped_model  # its mask may cover nothing
        if self.random_network:
            model = tiny_model(tmp_path_factory, self.method.runner.network_class, self.method.factor)
            self.spec = self.method.replace(model=str(model), model_name="tiny")

    def runner(self, width: int = SIZE[0], height: int = SIZE[1], anisotropic: bool = False, iso: float | None = None,
               clip: Clip = Clip(), coloring: Coloring | None = None, surfaces: Surfaces | None = None, draw: int = 0):
        """A new runner of the method on the contact scene (``coloring``: by the scene's own field)."""
        renderer, scene_iso = scene(anisotropic)
        field = None if coloring is None else ColorField.of(coloring, renderer.volume,
                                                            None if coloring.by == GRADIENT else renderer.volume,
                                                            renderer.torch_device)
        return make_runner(self.spec, renderer, scene_iso if iso is None else iso, width, height,
                           ao_radius=AO_RADIUS, networks=networks(), clip=clip, coloring=field, surfaces=surfaces,
                           draw=draw)

    def frame_size(self, runner, width: int = SIZE[0], height: int = SIZE[1]) -> tuple[int, int]:
        """``(H, W)`` of the runner's buffers: the frame's, an unshaded low-res kind's render's."""
        f = self.spec.factor if runner.low_res and not runner.shaded else 1
        return height // f, width // f

    def sequence(self, runner, cameras=CAMERAS) -> list:
        """The runner's frames along ``cameras`` (a new sequence): each ``(result, buffers copied)``."""
        return [(r, buffers_of(r)) for r in (runner.frame(camera, prev) for camera, prev in sequence_cameras(cameras))]

    # -- frames -----------------------------------------------------------------------------------

    def test_frames_have_the_frame_size_dtype_and_bounds(self):
        runner = self.runner()
        h, w = self.frame_size(runner)
        makes = set(runner.makes(self.spec)) | ({"color"} if runner.shaded else set())
        frames = self.sequence(runner)
        assert [r.continued for r, _ in frames] == [False] + [runner.recurrent] * (len(frames) - 1)
        for i, (result, frame) in enumerate(frames):
            where = f"{self.spec.name}, frame {i}"
            assert makes - {"flow"} <= set(frame) <= makes | {"flow"}, (where, sorted(frame))
            assert ("flow" in frame) == (result.continued and "flow" in makes), where
            for name, t in frame.items():
                assert t.dtype == torch.float32, (where, name, t.dtype)
                assert t.shape[:2] == (h, w), (where, name, tuple(t.shape))
                assert t.dim() == (2 if name in ("mask", "depth", "ao") else 3), (where, name, tuple(t.shape))
            for name in ("normal", "position", "color"):
                if name in frame:
                    assert frame[name].shape[2] == 3, (where, name)
            assert_finite_and_bounded(frame, runner.shaded, where)
            if not self.random_network:
                assert (frame["mask"] > 0.5).any(), f"{where}: nothing hit"
            assert {"render"} <= set(result.times) and all(t >= 0 for t in result.times.values()), result.times

    def test_two_runners_make_the_same_frames(self):
        a = [frame for _, frame in self.sequence(self.runner())]
        b = [frame for _, frame in self.sequence(self.runner())]
        assert_same_frames(a, b)

    def test_another_draw_casts_other_ao_rays(self):
        first, other = self.runner(), self.runner(draw=1)
        service_seed = FIRST_TEMPORAL_SEED if first.fresh_rays else 0
        assert (first.render_request(None).seed, other.render_request(None).seed) == (service_seed,
                                                                                      service_seed + DRAW_SEEDS)
        a, b = buffers_of(first.frame(CAMERAS[0])), buffers_of(other.frame(CAMERAS[0]))
        if self.spec.ao_rays:
            assert any(not torch.equal(a[k], b[k]) for k in a), f"{self.spec.name}: another draw, the same frame"
        else:
            assert_same_frames([a], [b])
        with pytest.raises(ValueError, match="draw"):
            self.runner(draw=-1)

    def test_a_frame_without_a_previous_camera_forgets_the_state(self):
        runner = self.runner()
        self.sequence(runner)
        again = runner.frame(CAMERAS[0])
        assert not again.continued
        fresh = self.runner()
        if runner.fresh_rays:  # the AO seed counts the frames made: the same rays as the runner's
            fresh.frames = runner.frames - 1
        assert_same_frames([buffers_of(again)], [buffers_of(fresh.frame(CAMERAS[0]))])

    def test_a_batch_makes_each_stream_s_frames_as_it_would_alone(self):
        """Three streams along their own cameras, made together by the kind's ``make_batch``: each
        frame equals its stream's frame made alone, and the second stream's cut at its third frame
        changes nothing in the others' (recurrent state and AO seeds stay per stream)."""
        paths = [orbit_path(3, yaw0=20.0 + 15.0 * k, yaw_step=4.0, pitch=25.0, distance=1.3) for k in range(3)]
        prevs = [[None, p[0], p[1]] for p in paths]
        prevs[1][2] = None  # the second stream cuts
        alone = [[buffers_of(runner.frame(cam, prev)) for cam, prev in zip(path, prev_cams)]
                 for runner, path, prev_cams in ((self.runner(), p, q) for p, q in zip(paths, prevs))]
        runners = [self.runner() for _ in paths]
        assert len({r.batch_key() for r in runners}) == 1
        together = [[] for _ in paths]
        for t in range(3):
            results = type(runners[0]).make_batch([(r, p[t], q[t]) for r, p, q in zip(runners, paths, prevs)])
            for k, result in enumerate(results):
                assert not isinstance(result, Exception), f"stream {k}, frame {t}: {result!r}"
                together[k].append(buffers_of(result))
        for k in range(3):
            assert_same_frames(together[k], alone[k])

    def test_a_batch_of_streams_that_shade_otherwise_makes_each_as_alone(self):
        """One batch of a plain stream, one with cut faces and one coloured by the scene's field: each frame
        equals its stream's made alone (a kind that shades its batch's frames together keeps each one's own)."""
        makes = (self.runner, lambda: self.runner(clip=CAPPED),
                 lambda: self.runner(coloring=Coloring("field", "magma")))
        alone = [buffers_of(make().frame(CAMERAS[0])) for make in makes]
        runners = [make() for make in makes]
        results = type(runners[0]).make_batch([(runner, CAMERAS[0], None) for runner in runners])
        for k, result in enumerate(results):
            assert not isinstance(result, Exception), f"stream {k}: {result!r}"
        assert_same_frames([buffers_of(result) for result in results], alone)

    def test_hard_cameras_made_together_stay_finite_and_equal_alone(self):
        """The hard cameras (inside the volume, grazing the surface, grazing the box) beside an ordinary one,
        made together (one launch and, for a network, one call over all four), a cut then a continued frame:
        each frame finite and bounded, and equal to its stream's frame made alone."""
        cameras = (CAMERAS[0], INSIDE, GRAZING_SURFACE, GRAZING_BOX)
        nearby = [Camera(tuple(np.add(c.eye, (0.0, 0.004, 0.0))), c.target, c.up, c.fov_y) for c in cameras]
        steps = (list(zip(cameras, [None] * len(cameras))), list(zip(nearby, cameras)))
        alone = [self.runner() for _ in cameras]
        expected = [[buffers_of(runner.frame(*step[k])) for step in steps] for k, runner in enumerate(alone)]
        runners = [self.runner() for _ in cameras]
        together = [[] for _ in cameras]
        for t, step in enumerate(steps):
            results = type(runners[0]).make_batch([(runner, *step[k]) for k, runner in enumerate(runners)])
            for k, result in enumerate(results):
                assert not isinstance(result, Exception), f"camera {k}, frame {t}: {result!r}"
                frame = buffers_of(result)
                assert_finite_and_bounded(frame, runners[k].shaded, f"{self.spec.name}, camera {k}, frame {t}")
                together[k].append(frame)
        for k in range(len(cameras)):
            assert_same_frames(together[k], expected[k])

    def test_a_stream_s_error_in_a_batch_is_its_own(self):
        """A stream whose frame fails (here: its renderer raises) gets the error as its result; its
        batch mates get their frames, equal to those made alone."""
        ok, failing, reference = self.runner(), self.runner(), self.runner()

        class Broken:  # whatever a path reads of it (a plan, a launch, a graph's pool) fails
            device = ok.renderer.device

            def __getattr__(self, name):
                raise RuntimeError("render failed")
        failing.renderer = Broken()
        results = type(ok).make_batch([(failing, CAMERAS[0], None), (ok, CAMERAS[0], None)])
        assert isinstance(results[0], RuntimeError) and "render failed" in str(results[0]), repr(results[0])
        assert_same_frames([buffers_of(results[1])], [buffers_of(reference.frame(CAMERAS[0]))])

    # -- options ----------------------------------------------------------------------------------

    def test_its_options_are_a_frozen_hashable_value_with_valid_defaults(self):
        options, options_type = self.spec.options, self.spec.runner.options_type
        assert type(options) is options_type and options_type.__dataclass_params__.frozen
        first = dataclasses.fields(options)[0].name
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(options, first, getattr(options, first))
        twin = FrameMethod(self.spec.kind, dataclasses.replace(options))
        assert twin == self.spec and hash(twin) == hash(self.spec) and {self.spec: 1}[twin] == 1
        assert type(options_type()) is type(FrameMethod.of(self.spec.kind).options)  # the defaults are valid
        with pytest.raises(TypeError, match=f"its options are a {options_type.__name__}"):
            FrameMethod(self.spec.kind, MethodOptions())

    def test_counts_are_accepted_at_their_bounds_and_refused_past_them(self):
        bounds = self.spec.options.bounds()
        for name, (low, high) in bounds.items():
            assert low <= getattr(self.spec, name) <= high, (name, low, high)
            for value in (low, high):
                assert getattr(self.spec.replace(**{name: value}), name) == value
            for value in (low - 1, high + 1):
                words = rf"{name} must be an integer in \[{low}, {high}\], got {value}"
                with pytest.raises(ValueError, match=f"^{words}"):
                    dataclasses.replace(self.spec.options, **{name: value})
                with pytest.raises(ValueError, match=f"^{self.spec.kind} frame method: {words}"):
                    self.spec.replace(**{name: value})
        for name, neutral in NEUTRAL_COUNTS.items():
            if name not in bounds:
                assert getattr(self.spec, name) == neutral, name

    def test_choices_are_accepted_and_other_values_refused(self):
        for f in dataclasses.fields(self.spec.options):
            choices = f.metadata.get("choices", ())
            for value in choices:
                assert getattr(self.spec.replace(**{f.name: value}).options, f.name) == value
            if choices:
                with pytest.raises(ValueError, match=rf"{f.name} must be one of {', '.join(choices)}, got 'other'"):
                    self.spec.replace(**{f.name: "other"})

    def test_a_knob_the_kind_does_not_take_is_refused(self):
        takes = [f.name for f in dataclasses.fields(self.spec.options)]
        for name in UNREAD_VALUES.keys() - set(takes):
            with pytest.raises(ValueError, match=rf"{self.spec.kind} frame method: takes no {name} "
                                                 rf"\(only {', '.join(takes)}\)"):
                FrameMethod.of(self.spec.kind, **{name: UNREAD_VALUES[name]})

    # -- hard cases -------------------------------------------------------------------------------

    @pytest.mark.parametrize("case", HARD_CASES)
    def test_hard_cases_stay_finite_and_bounded(self, case):
        width, height, camera, iso, anisotropic = *SIZE, CAMERAS[0], None, False
        if case == "inside":
            camera = INSIDE
        elif case == "grazing_surface":
            camera = GRAZING_SURFACE
        elif case == "grazing_box":
            camera = GRAZING_BOX
        elif case in EMPTY_ISOS:
            iso = EMPTY_ISOS[case]
        elif case == "tiny_2x2":
            if 2 % self.spec.factor:
                pytest.skip(f"the factor {self.spec.factor} does not divide a 2x2 frame")
            width, height, camera = 2, 2, TINY
        elif case == "anisotropic":
            anisotropic = True
        runner = self.runner(width, height, anisotropic, iso)
        h, w = self.frame_size(runner, width, height)
        # a cut, then a continued frame (recurrent kinds read the first through the flow)
        nearby = Camera(tuple(np.add(camera.eye, (0.0, 0.004, 0.0))), camera.target, camera.up, camera.fov_y)
        pairs = ((camera, None), (nearby, camera))
        for i, frame in enumerate(buffers_of(runner.frame(cam, prev)) for cam, prev in pairs):
            where = f"{self.spec.name}, {case}, frame {i}"
            assert all(t.shape[:2] == (h, w) for t in frame.values()), (where, {k: t.shape for k, t in frame.items()})
            assert_finite_and_bounded(frame, runner.shaded, where)
            if iso is not None:  # nothing hit
                if not self.spec.learned:  # (a network's mask is its own guess)
                    assert frame["mask"].max() == 0, where
                if "color" in frame:  # the background where the mask is 0, off it by at most the mask
                    background = torch.tensor(BACKGROUND_RGB, device=frame["color"].device)
                    off = (frame["color"] - background).abs().amax(-1)
                    assert (off[frame["mask"] == 0] == 0).all() and (off <= frame["mask"] + 1e-6).all(), \
                        f"{where}: color off the background by {float(off.max()):.3f} where the mask is " \
                        f"{float(frame['mask'].flatten()[off.argmax()]):.3f}"
            elif case in ("inside", "tiny_2x2") and not self.random_network:
                assert (frame["mask"] > 0.5).any(), f"{where}: nothing hit"

    # -- clipping ---------------------------------------------------------------------------------

    @pytest.mark.parametrize("case", ("capped", "nothing_kept"))
    def test_clipping_reaches_the_frame(self, case):
        cut = {"capped": CAPPED,
               "nothing_kept": Clip(planes=[((0.0, 0.0, 0.3), (0.0, 0.0, 1.0)), ((0.0, 0.0, -0.3), (0.0, 0.0, -1.0))],
                                    cap="below")}[case]
        runner = self.runner(clip=cut)
        h, w = self.frame_size(runner)
        for i, (_, frame) in enumerate(self.sequence(runner, CAMERAS[:2])):
            where = f"{self.spec.name}, {case}, frame {i}"
            assert all(t.shape[:2] == (h, w) for t in frame.values()), (where, {k: t.shape for k, t in frame.items()})
            assert_finite_and_bounded({k: t for k, t in frame.items() if k != "cap"}, runner.shaded, where)
            assert "cap" in frame, f"{where}: the cut faces' values travel with the frame"
            if case == "capped":
                assert (frame["cap"][..., 0] > 0).any(), f"{where}: no cut face"
            if case == "nothing_kept":
                if not self.spec.learned:
                    assert frame["mask"].max() == 0, where
                if "color" in frame:
                    background = torch.tensor(BACKGROUND_RGB, device=frame["color"].device)
                    off = (frame["color"] - background).abs().amax(-1)
                    assert (off <= frame["mask"] + 1e-6).all(), where

    # -- colour by a field ------------------------------------------------------------------------

    @pytest.mark.parametrize("coloring", (Coloring("field", "magma"), Coloring("gradient", "viridis", (0.5, 0.5))))
    def test_coloring_reaches_the_frame(self, coloring):
        runner = self.runner(coloring=coloring)
        h, w = self.frame_size(runner)
        for i, (_, frame) in enumerate(self.sequence(runner, CAMERAS[:2])):
            where = f"{self.spec.name}, {coloring.by}, frame {i}"
            assert_finite_and_bounded(frame, runner.shaded, where)
            if runner.shaded:
                assert frame["albedo"].shape == (h, w, 3) and frame["albedo"].min() >= 0 \
                    and frame["albedo"].max() <= 1, where

    # -- several isosurfaces ---------------------------------------------------------------------

    def test_surfaces_reach_the_frame(self):
        """The scene's surface (value 0) inside a shell at value 0.06: the albedo is a surface's colour
        (nearest-upsampled: exact) or 0, mostly the shell's (rays entering the grid between them see the inner)."""
        volume = scene()[0].volume
        inner, outer = (0.1, 0.3, 0.9), (0.9, 0.2, 0.1)
        surfaces = Surfaces.of([(volume.normalized_iso(0.0), inner), (volume.normalized_iso(0.06), outer)])
        runner = self.runner(surfaces=surfaces)
        h, w = self.frame_size(runner)
        for i, (_, frame) in enumerate(self.sequence(runner, CAMERAS[:2])):
            where = f"{self.spec.name}, two surfaces, frame {i}"
            assert_finite_and_bounded(frame, runner.shaded, where)
            if runner.shaded:
                albedo = frame["albedo"]
                assert albedo.shape == (h, w, 3), where
                shell, core = ((albedo - torch.tensor(c, device=albedo.device)).abs().amax(-1) < 1e-6
                               for c in (outer, inner))
                assert (shell | core | (albedo.amax(-1) == 0)).all() and shell.sum() > core.sum(), where

    def translucent(self, outer: float, inner: float = 1.0) -> tuple[Surfaces, Surfaces]:
        """``(translucent, opaque)``: the scene's surface (blue) inside a shell at value 0.06 (red), of opacities
        ``inner`` and ``outer``; the same surfaces opaque."""
        volume = scene()[0].volume
        pairs = [(volume.normalized_iso(0.0), (0.1, 0.3, 0.9)), (volume.normalized_iso(0.06), (0.9, 0.2, 0.1))]
        return Surfaces.of([(*pairs[0], inner), (*pairs[1], outer)]), Surfaces.of(pairs)

    def test_translucent_surfaces_composited_or_refused(self):
        """A translucent shell (30%) over the scene's surface: a shaded kind's colour, finite and bounded, differs
        from the opaque shell's; an unshaded kind refuses it naming the field."""
        translucent, opaque = self.translucent(0.3)
        if not self.spec.runner.shaded:
            with pytest.raises(ValueError, match="surfaces: translucent ones .* need a shaded method"):
                self.runner(surfaces=translucent)
            return
        frames = [frame for _, frame in self.sequence(self.runner(surfaces=translucent), CAMERAS[:2])]
        for i, frame in enumerate(frames):
            assert_finite_and_bounded(frame, True, f"{self.spec.name}, translucent, frame {i}")
        plain = [frame for _, frame in self.sequence(self.runner(surfaces=opaque), CAMERAS[:2])]
        assert (frames[0]["color"] - plain[0]["color"]).abs().amax() > 0.05

    def test_translucent_layers_are_finished_apart_and_composited(self):
        """Along a sequence, the frame's colour is the composite (by the front surface's opacity) of the method's
        ``finish`` run on the front layer alone by one runner and on the behind layer alone by another (each with its
        own recurrent state), and its buffers are the front's: mixed states or swapped layers fail. A layered kind
        composites in its render (the renderer's tests)."""
        if not self.spec.runner.shaded or self.spec.runner.layered:
            pytest.skip("no layers finished apart: unshaded (refused) or composited by the render")
        translucent = self.translucent(0.3)[0]
        runner, front, behind = (self.runner(surfaces=translucent) for _ in range(3))
        assert runner.behind is not None and runner.behind.behind is None
        assert runner.net is None or runner.behind.net is not runner.net  # a copy: its own state
        timer = StageTimer(DEVICE)
        for i, (camera, prev) in enumerate(sequence_cameras(CAMERAS)):
            request = runner.render_request(prev)
            frame = buffers_of(runner.frame(camera, prev))
            rendered = runner.renderer.render(camera, request)
            front.prev_camera = behind.behind.prev_camera = prev
            alone = front.finish(rendered, timer)
            back = behind.behind.finish(rendered.behind, timer)
            expected = composite(alone.color, back.color, front.opacity(rendered))
            where = f"{self.spec.name}, frame {i}"
            assert_same_frames([{"color": frame["color"]}], [{"color": expected}])
            assert_same_frames([{k: v for k, v in frame.items() if k != "color"}],
                               [{k: getattr(alone, k) for k in frame if k != "color"}])
            assert (rendered.behind.mask > 0).any() and (front.opacity(rendered) < 1).any(), where

    def layer_pixels(self, surfaces: Surfaces, camera: Camera) -> FrameBuffers:
        """The render of ``surfaces``' mask and surface (both layers) at the method's render size."""
        f = self.spec.factor
        return scene()[0].render(camera, RenderRequest(SIZE[0] // f, SIZE[1] // f, surfaces.iso, ("mask", "surface"),
                                                       spp=self.spec.spp, surfaces=surfaces))

    def at_frame_size(self, pixels: torch.Tensor) -> torch.Tensor:
        """A boolean image at the render's size, nearest upsampled to the frame's."""
        f = self.spec.factor
        return pixels.repeat_interleave(f, 0).repeat_interleave(f, 1)

    def test_opacity_one_is_the_opaque_frame_and_zero_the_inner_surface(self):
        """Opacities of 1: the opaque frames bit for bit, without a second layer's state. The shell opaque over a
        translucent inner surface: where no ray goes on (the shell or nothing in front; the inner surface shows
        itself where rays enter the grid inside the shell), the opaque surfaces' frames, bit for bit but for the few
        pixels whose AO rays see the translucent surface (it occludes by its opacity), though the layers are made
        apart. The shell at 0: where the inner surface shows behind it (or nothing at all), the inner surface's
        frames alone, within the AO rays' noise (the layers' rays differ) away from the border, where a filter or
        network sees the shell's far side."""
        if not self.spec.runner.shaded:
            pytest.skip("unshaded: translucent surfaces refused")
        translucent, opaque = self.translucent(1.0, inner=1.0)
        runner = self.runner(surfaces=translucent)
        assert runner.behind is None and "surface" not in runner.render_request().outputs
        assert_same_frames([f for _, f in self.sequence(runner, CAMERAS[:2])],
                           [f for _, f in self.sequence(self.runner(surfaces=opaque), CAMERAS[:2])])
        translucent = self.translucent(1.0, inner=0.5)[0]
        runner = self.runner(surfaces=translucent)
        assert self.spec.runner.layered or runner.behind is not None
        for i, (a, b) in enumerate(zip(self.sequence(runner, CAMERAS[:2]),
                                       self.sequence(self.runner(surfaces=opaque), CAMERAS[:2]))):
            layers = self.layer_pixels(translucent, CAMERAS[i])
            alone = self.at_frame_size((layers.behind.mask == 0) & (layers.surface != 0))
            same = (a[1]["color"] == b[1]["color"]).all(-1)[alone]
            assert alone.float().mean() > 0.5 and same.float().mean() > 0.97, (i, float(same.float().mean()))
        invisible = self.translucent(0.0)[0]
        inner = Surfaces((invisible.items[0],))
        for i, (a, b) in enumerate(zip(self.sequence(self.runner(surfaces=invisible), CAMERAS[:2]),
                                       self.sequence(self.runner(surfaces=inner), CAMERAS[:2]))):
            layers = self.layer_pixels(invisible, CAMERAS[i])
            shows = (layers.behind.surface == 0) | ((layers.mask == 0) & (layers.behind.mask == 0))
            shows = self.at_frame_size(-torch.nn.functional.max_pool2d(-shows[None].float(), 3, 1, 1)[0] > 0)
            diff = (a[1]["color"] - b[1]["color"]).abs().amax(-1)[shows]
            assert shows.float().mean() > 0.2 and float(diff.mean()) < 0.05 and float(diff.quantile(0.98)) < 0.2, \
                (self.spec.name, i, float(shows.float().mean()), float(diff.mean()), float(diff.quantile(0.98)))

    def test_a_reset_of_one_layer_s_state_leaves_the_other_s(self):
        """Two runners along a sequence; one's behind twin is made anew before the third frame (its state reset):
        that frame's front buffers equal the other runner's, and its behind buffers those of a twin that starts
        there (for a stateless kind the same as before)."""
        if not self.spec.runner.shaded or self.spec.runner.layered:
            pytest.skip("no layers finished apart")
        translucent = self.translucent(0.3)[0]
        a, b = self.runner(surfaces=translucent), self.runner(surfaces=translucent)
        pairs = list(sequence_cameras(CAMERAS))
        for camera, prev in pairs[:2]:
            a.frame(camera, prev), b.frame(camera, prev)
        b.behind = self.runner(surfaces=translucent).behind
        fresh = self.runner(surfaces=translucent).behind
        request = a.render_request(pairs[2][1])
        (fa, _), (fb, bb) = (layers_of(r.frame(*pairs[2]).buffers) for r in (a, b))
        assert_same_frames([fb], [fa])
        fresh.prev_camera = pairs[2][1]
        again = layers_of(fresh.finish(a.renderer.render(pairs[2][0], request).behind, StageTimer(DEVICE)))[0]
        assert_same_frames([bb], [again])

    # -- bench row --------------------------------------------------------------------------------

    def test_its_bench_row(self, monkeypatch):
        from isosr_bench import bench_pareto

        assert self.spec.name.strip() and self.spec.runner.label.strip()
        assert self.spec.name == self.spec.runner.describe(self.spec)
        # the study measures every shaded kind (its shipped models' too), and scores colors only
        measured = {m.kind for m in bench_pareto.methods(True, DEVICE, bench_pareto.SHIPPED_MODELS)}
        assert (self.spec.kind in measured) == self.spec.runner.shaded, sorted(measured)
        if not self.spec.runner.shaded:
            return  # no color to score: no row (pareto_rows would fail on the missing color)
        references = bench_pareto.reference_frames

        def cached_references(renderer, iso, size, cameras, **options):  # the same for every method
            key = ("references", id(renderer), iso, size, repr(cameras), repr(sorted(options.items())))
            if key not in _CACHE:
                _CACHE[key] = (renderer, references(renderer, iso, size, cameras, **options))
            return _CACHE[key][1]

        monkeypatch.setattr(bench_pareto, "reference_frames", cached_references)
        key = ("smoke volume", "sphere")
        if key not in _CACHE:
            volume, iso = bench_pareto.load("sphere", DEVICE)
            _CACHE[key] = Renderer(volume, DEVICE), iso
        renderer, iso = _CACHE[key]
        size_name, size = next(iter(bench_pareto.SMOKE_SIZES.items()))
        rows = bench_pareto.pareto_rows(renderer, iso, "sphere", size, size_name, [self.spec],
                                        bench_pareto.SMOKE_FRAMES, bench_pareto.SMOKE_WARMUP, DEVICE, networks())
        assert len(rows) == 1
        row = rows[0]
        assert (row["method"], row["kind"], row["learned"]) == (self.spec.name, self.spec.kind, self.spec.learned)
        assert (row["ao_rays"], row["spp"], row["factor"]) == (self.spec.ao_rays, self.spec.spp, self.spec.factor)
        assert row["ms"] > 0 and math.isfinite(row["ms"])
        assert math.isfinite(row["color_psnr"]) and 0 <= row["color_ssim"] <= 1 and 0 < row["coverage"] <= 1
        assert (row["flicker"] is None and self.random_network) or row["flicker"] >= 0  # None: nothing covered
        if row["ao_rmse"] is not None:
            assert 0 <= row["ao_rmse"] <= 1

