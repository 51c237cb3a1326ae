"""Frame methods: names, checks, the registry, and what is particular to some kinds (the buffers
each kind's settings make, kept buffers, streams and shared networks, SVGF's seeds and history, a
network's state carried, frames in slices). The one contract every registered method keeps (frame
size and bounds, determinism, reset, option bounds, hard cases, its bench row) is
``tests/method_contract.py``, run for each method by ``tests/test_method_contract.py``.

On a GPU machine ``ISOSR_TEST_DEVICE=cuda pytest tests/test_frame_methods.py`` runs the runner
tests there (compiled network and a-trous filter included).
"""

from __future__ import annotations

import pytest
import torch

from isosr_render import Renderer, RenderRequest, open_volume, orbit_path, resolve_iso
from isosr_render.steps import count_steps
from isosr_net.filters import oidn
from isosr_net.methods import FrameMethod, FrameStream, Networks, make_runner, unavailable_kinds
from conftest import DEVICE
from net_fixtures import tiny_model_dir

SIZE = (48, 32)


@pytest.fixture(scope="module")
def scene():
    volume = open_volume("proc:cloud:7@32")
    return Renderer(volume, DEVICE), resolve_iso("proc:cloud", volume)


def test_names_follow_the_issue():
    assert FrameMethod.of("full", ao_rays=8).name == "full, AO 8, spp 1"
    assert FrameMethod.of("full", spp=4).name == "full, AO 0, spp 4"
    assert FrameMethod.of("atrous", ao_rays=2).name == "full, AO 2, a-trous"
    assert FrameMethod.of("upscale", factor=4).name == "x4 bilinear"
    recon = FrameMethod.of("reconstruct", ao_rays=2, precision="fp16", model_name="recon")
    assert recon.name == "full, AO 2, spp 1, recon fp16" and recon.learned
    network = FrameMethod.of("network", factor=4, precision="bf16")
    assert network.name == "x4 network bf16" and network.learned
    assert not FrameMethod.of("atrous", ao_rays=1).learned
    assert FrameMethod.of("svgf", ao_rays=2).name == "full, AO 2, svgf"
    assert FrameMethod.of("oidn", ao_rays=1, quality="fast", spp=2).name == "full, AO 1, oidn fast, spp 2"


@pytest.mark.parametrize("kwargs, message", [
    (dict(kind="magic"), "unknown frame method"), (dict(kind="full", ao_rays=-1), "ao_rays"), (dict(kind="atrous", ao_rays=0), "ao_rays"),
    (dict(kind="upscale", factor=1), "factor"), (dict(kind="upscale", factor=4, ao_rays=4), "ao_rays"),
    (dict(kind="full", factor=2), "factor"), (dict(kind="upscale", factor=2, interpolation="lanczos"), "interpolation"),
    (dict(kind="network", factor=4, precision="fp8"), "precision"), (dict(kind="full", spp=True), "spp"),
    (dict(kind="reconstruct", ao_rays=4097), r"ao_rays must be an integer in \[0, 4096\]"),
    (dict(kind="buffers", factor=1), "factor"),
    (dict(kind="reconstruct", spp=8), r"spp must be an integer in \[1, 4\]"),
    (dict(kind="reconstruct", factor=8), r"factor must be an integer in \[1, 4\]"),
    (dict(kind="svgf", ao_rays=0), "ao_rays"),
    (dict(kind="atrous", ao_rays=1, quality="fast"), "takes no quality"),
    (dict(kind="oidn", ao_rays=1, quality="best"), "quality must be one of")])
def test_bad_methods_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FrameMethod.of(**kwargs)


@pytest.mark.parametrize("method, buffers", [
    (FrameMethod.of("full"), ["mask", "normal", "color"]),
    (FrameMethod.of("full", ao_rays=4, spp=2), ["mask", "normal", "ao", "color"]),
    (FrameMethod.of("atrous", ao_rays=2), ["mask", "normal", "ao", "color"]),
    (FrameMethod.of("svgf", ao_rays=1), ["mask", "normal", "ao", "color"]),
    pytest.param(FrameMethod.of("oidn", ao_rays=1, quality="fast"), ["mask", "normal", "color"],
                 marks=pytest.mark.skipif(oidn.unavailable() is not None, reason=str(oidn.unavailable()))),
    (FrameMethod.of("upscale", factor=4, interpolation="bicubic"), ["mask", "normal", "depth", "color"]),
    (FrameMethod.of("reconstruct", ao_rays=2), ["mask", "normal", "depth", "ao", "color"]),
    (FrameMethod.of("reconstruct", ao_rays=0), ["mask", "normal", "depth", "ao", "color"]),
    (FrameMethod.of("network", factor=4), ["mask", "normal", "depth", "ao", "color"]),
    (FrameMethod.of("buffers", factor=4), ["mask", "normal", "depth"])])
def test_every_kind_makes_a_bounded_color_frame_and_only_its_buffers(scene, method, buffers):
    renderer, iso = scene
    runner = make_runner(method, renderer, iso, *SIZE)
    cams = orbit_path(2, yaw0=20.0, yaw_step=3.0)
    results = [runner.frame(cams[0]), runner.frame(cams[1], cams[0])]
    assert [r.continued for r in results] == [False, runner.recurrent]
    for r in results:
        f = r.buffers
        assert f.present() == buffers + (["flow"] if r.continued and not runner.shaded else [])
        assert {"render"} <= set(r.times) and all(t >= 0 for t in r.times.values())
        assert (f.mask > 0.5).any() and torch.isfinite(f.mask).all()
        if runner.shaded:
            assert f.color.shape == (SIZE[1], SIZE[0], 3)
            assert torch.isfinite(f.color).all() and f.color.min() >= 0 and f.color.max() <= 1


def test_the_registry_names_every_kind_and_refuses_a_second_registration():
    from isosr_net.methods import RUNNERS, register_runner
    from isosr_net.methods.full import FullRunner
    assert set(RUNNERS) == {"full", "atrous", "svgf", "oidn", "reconstruct", "upscale", "network", "buffers"}
    assert all(cls.kind == kind for kind, cls in RUNNERS.items())
    assert set(unavailable_kinds()) <= {"oidn"}
    with pytest.raises(ValueError, match="registered already"):
        register_runner("full")(FullRunner)


def test_a_kind_without_its_package_is_unavailable_with_the_reason(scene, monkeypatch):
    renderer, iso = scene
    monkeypatch.setattr(oidn, "unavailable", lambda: "the pyoidn package is not installed")
    assert unavailable_kinds() == {"oidn": "the pyoidn package is not installed"}
    with pytest.raises(RuntimeError, match="full, AO 1, oidn high cannot run here: the pyoidn package is not"):
        make_runner(FrameMethod.of("oidn", ao_rays=1), renderer, iso, *SIZE)


def test_svgf_casts_new_ao_rays_each_frame_and_restarts_its_history_on_a_cut(scene):
    renderer, iso = scene
    runner = make_runner(FrameMethod.of("svgf", ao_rays=1), renderer, iso, *SIZE)
    cams = orbit_path(3, yaw0=20.0, yaw_step=3.0)
    seeds = [runner.render_request(None).seed]
    runner.frame(cams[0])
    seeds.append(runner.render_request(cams[0]).seed)
    assert seeds[0] != seeds[1] and 1 not in seeds  # never the quality reference's seed
    runner.frame(cams[1], cams[0])
    assert runner.history.length.max() == 2
    runner.frame(cams[2])  # no previous camera: a cut
    assert runner.history.length.max() == 1


@pytest.mark.parametrize("method, keep", [(FrameMethod.of("full"), ("depth", "flow")),
                                          (FrameMethod.of("network", factor=4), ("flow",)),
                                          (FrameMethod.of("atrous", ao_rays=1), ("depth",))])
def test_kept_buffers_come_at_the_frame_size_and_flow_in_its_pixels(scene, method, keep):
    renderer, iso = scene
    runner = make_runner(method, renderer, iso, *SIZE, keep=keep)
    cams = orbit_path(2, yaw0=20.0, yaw_step=6.0)
    runner.frame(cams[0])
    f = runner.frame(cams[1], cams[0]).buffers
    for name in keep:
        assert getattr(f, name).shape[:2] == (SIZE[1], SIZE[0])
    if "flow" in keep:
        full = renderer.render(cams[1], RenderRequest(*SIZE, iso, ("mask", "flow"), prev_camera=cams[0]))
        covered = (full.mask > 0.5) & (f.mask > 0.5)
        # flow of a low-res render, upsampled and scaled, agrees with the full-res flow to about a low-res pixel
        assert (f.flow - full.flow)[covered].abs().median() < method.factor


def test_a_stream_starts_a_new_runner_and_a_new_sequence_when_its_settings_change(scene):
    renderer, iso = scene
    stream = FrameStream(Networks())
    cams = orbit_path(3, yaw0=20.0, yaw_step=3.0)
    recon = FrameMethod.of("reconstruct", ao_rays=1)
    assert not stream.frame(recon, renderer, iso, *SIZE, cams[0], None).continued
    first = stream.runner
    assert stream.frame(recon, renderer, iso, *SIZE, cams[1], cams[0]).continued and stream.runner is first
    # a new AO ray count, size or iso is a cut: a new runner, its previous camera ignored
    assert not stream.frame(FrameMethod.of("reconstruct", ao_rays=2), renderer, iso, *SIZE, cams[2], cams[1]).continued
    assert stream.runner is not first
    assert not stream.frame(FrameMethod.of("reconstruct", ao_rays=2), renderer, iso, 32, 16, cams[2], cams[1]).continued


def test_forked_networks_share_weights_and_own_their_state(scene):
    renderer, iso = scene
    root = Networks()
    a, b = root.fork(), root.fork()
    recon = FrameMethod.of("reconstruct", ao_rays=1)
    ra, rb = (make_runner(recon, renderer, iso, *SIZE, networks=n) for n in (a, b))
    assert ra.net is not rb.net and ra.net.net is rb.net.net
    cams = orbit_path(2, yaw0=20.0, yaw_step=3.0)
    ra.frame(cams[0])
    assert ra.net.previous is not None and rb.net.previous is None


def test_the_network_carries_its_state_and_resets_on_a_cut(scene, tmp_path_factory):
    renderer, iso = scene
    method = FrameMethod.of("network", factor=2, model=str(tiny_model_dir(tmp_path_factory)), model_name="tiny")
    runner = make_runner(method, renderer, iso, *SIZE)
    cams = orbit_path(2, yaw0=20.0, yaw_step=3.0)
    first = runner.frame(cams[1])  # a cut: no previous frame
    runner.frame(cams[0])
    carried = runner.frame(cams[1], cams[0])  # the same view, with the previous output warped in
    again = runner.frame(cams[1])
    assert torch.allclose(first.buffers.color, again.buffers.color, atol=1e-6)
    assert (first.buffers.color - carried.buffers.color).abs().max() > 1e-3


def test_sizes_the_factor_does_not_divide_and_wrong_models_are_refused(scene, tmp_path_factory):
    renderer, iso = scene
    with pytest.raises(ValueError, match="must divide"):
        make_runner(FrameMethod.of("upscale", factor=4), renderer, iso, 50, 32)
    with pytest.raises(ValueError, match="must be an integer >= 1"):
        make_runner(FrameMethod.of("full"), renderer, iso, 0, 32)
    tiny = str(tiny_model_dir(tmp_path_factory))  # an x2 model
    with pytest.raises(ValueError, match="upscales x2, not x4"):
        make_runner(FrameMethod.of("network", factor=4, model=tiny), renderer, iso, *SIZE)


def test_runners_share_one_network_per_model_precision_and_device(scene):
    renderer, iso = scene
    networks = Networks()
    bf16 = FrameMethod.of("network", factor=4, precision="bf16")
    a = make_runner(bf16, renderer, iso, *SIZE, networks=networks)
    b = make_runner(bf16, renderer, iso, 96, 64, networks=networks)
    c = make_runner(FrameMethod.of("network", factor=4), renderer, iso, *SIZE, networks=networks)
    assert a.net is b.net and a.net.precision == "bf16"
    assert c.net is not a.net and c.net.precision == "fp32" and len(networks._loaded) == 2


@pytest.mark.parametrize("method", [FrameMethod.of("full", ao_rays=4), FrameMethod.of("atrous", ao_rays=2),
                                    FrameMethod.of("reconstruct", ao_rays=1)])
def test_a_frame_in_slices_equals_the_frame_whole(scene, method):
    renderer, iso = scene
    cam = orbit_path(1, yaw0=20.0)[0]
    whole = make_runner(method, renderer, iso, *SIZE).frame(cam).buffers
    runner = make_runner(method, renderer, iso, *SIZE)
    slices, result = count_steps(runner.steps(cam, slice_ms=1e-6))
    sliced = result.buffers  # one band a slice
    assert slices >= SIZE[1] // 32  # the first band, then bands of a row (each slice far over its budget)
    for name in whole.present():
        torch.testing.assert_close(getattr(sliced, name), getattr(whole, name), atol=1e-6, rtol=0)
    count_steps(runner.steps(orbit_path(2, yaw0=40.0)[1], cam, slice_ms=1e-6))  # the next frame, sliced too
    for name in whole.present():  # leaves this frame's buffers as they were
        torch.testing.assert_close(getattr(sliced, name), getattr(whole, name), atol=1e-6, rtol=0)


def test_shading_runs_compiled_on_cuda_only_and_equals_shade():
    from isosr_render.shading import shade, shade_on

    assert shade_on("cpu") is shade
    if not torch.cuda.is_available():
        pytest.skip("compiled shading is CUDA's (run with ISOSR_TEST_DEVICE=cuda on the GPU machine)")
    g = torch.Generator().manual_seed(0)
    for h, w in ((24, 32), (37, 53)):  # a second size: dynamic shapes, no recompiling
        mask, normal, ao = torch.rand(h, w, generator=g), torch.randn(h, w, 3, generator=g), torch.rand(h, w, generator=g)
        for occlusion in (None, ao):
            args = [t.cuda() if t is not None else None for t in (mask, normal, occlusion)]
            torch.testing.assert_close(shade_on("cuda")(*args), shade(*args), atol=1e-5, rtol=0)


def test_timed_steps_count_only_their_own_slices():
    """Work a scheduler does between the slices (here 30 ms of sleep) is not the stage's time."""
    import time

    from isosr_net.timing import StageTimer, timed_steps

    def slices():
        for _ in range(3):
            time.sleep(0.01)
            yield
        return "done"

    timer = StageTimer("cpu")
    steps = timed_steps(slices(), timer, "network")
    for _ in range(3):
        next(steps)
        time.sleep(0.03)  # another session's frame
    with pytest.raises(StopIteration) as done:
        next(steps)
    assert done.value.value == "done"
    assert 30 <= timer.ms()["network"] < 90


def test_a_reconstruction_past_its_models_ao_rays_casts_them_and_they_lift_its_ao():
    """At 64 AO rays per hit (4 rays per pixel) the reconstruct runner renders 64 and its network
    reads their mean as its max_ao_rays (16, a saturated channel). On the MRI at 96x64 against the
    Pareto study's reference the AO error falls from 16 to 64 rays (there 0.0266 -> 0.0236; at
    960x540 the color 44.2 -> 46.4 dB, the plain render's 64 rays 46.0: docs/measurements.md)."""
    from isosr_net.budget import reference_frames
    from isosr_render.catalog import shared_volumes_dir
    if not (shared_volumes_dir() / "volumes.json").is_file():
        pytest.skip(f"shared volumes not found at {shared_volumes_dir()} (set ISOSR_SHARED_VOLUMES)")
    volume = open_volume("shared:avg152t1")
    renderer, iso, size = Renderer(volume, DEVICE), resolve_iso("shared:avg152t1", volume), (96, 64)
    camera = orbit_path(1, yaw0=30.0, pitch=20.0, distance=1.6)[0]
    reference = reference_frames(renderer, iso, size, [camera])[0]
    error = {}
    for rays in (16, 64):
        runner = make_runner(FrameMethod.of("reconstruct", ao_rays=rays, spp=4), renderer, iso, *size)
        assert runner.render_request().ao_samples == rays and runner.read_rays == 16
        out = runner.frame(camera).buffers
        both = (out.mask > 0.5) & (reference.mask > 0.5)
        error[rays] = float((out.ao - reference.ao)[both].square().mean().sqrt())
    assert error[64] < 0.95 * error[16], error
