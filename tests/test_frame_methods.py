"""Frame methods: names, checks, and the runner computing only what each method needs.

On a GPU machine ``ISOSR_TEST_DEVICE=cuda pytest tests/test_frame_methods.py`` runs the runner
tests there (compiled network and a-trous filter included).
"""

from __future__ import annotations

import pytest
import torch

from isosr_render import Renderer, open_volume, orbit_path, resolve_iso
from isosr_net.frame_methods import FrameMethod, FrameRunner, run_sequence
from conftest import DEVICE
from net_fixtures import tiny_model_dir

SIZE = (48, 32)


@pytest.fixture(scope="module")
def scene():
    volume = open_volume("proc:cloud:7@32")
    return Renderer(volume, DEVICE), resolve_iso("proc:cloud", volume)


def test_names_follow_the_issue():
    assert FrameMethod("full", ao_rays=8).name == "full, AO 8, spp 1"
    assert FrameMethod("full", spp=4).name == "full, AO 0, spp 4"
    assert FrameMethod("atrous", ao_rays=2).name == "full, AO 2, a-trous"
    assert FrameMethod("upscale", factor=4).name == "x4 bilinear"
    recon = FrameMethod("reconstruct", ao_rays=2, precision="fp16", model_name="recon")
    assert recon.name == "full, AO 2, spp 1, recon fp16" and recon.learned
    network = FrameMethod("network", factor=4, precision="bf16")
    assert network.name == "x4 network bf16" and network.learned
    assert not FrameMethod("atrous", ao_rays=1).learned


@pytest.mark.parametrize("kwargs, message", [
    (dict(kind="magic"), "kind"), (dict(kind="full", ao_rays=-1), "ao_rays"), (dict(kind="atrous"), "ao_rays"),
    (dict(kind="upscale", factor=1), "factor"), (dict(kind="upscale", factor=4, ao_rays=4), "ao_rays"),
    (dict(kind="full", factor=2), "factor"), (dict(kind="upscale", factor=2, interpolation="lanczos"), "interpolation"),
    (dict(kind="network", factor=4, precision="fp8"), "precision"), (dict(kind="full", spp=True), "spp"),
    (dict(kind="reconstruct", ao_rays=9), r"ao_rays must be an integer in \[0, 8\]"),
    (dict(kind="reconstruct", spp=8), r"spp must be an integer in \[1, 4\]"),
    (dict(kind="reconstruct", factor=2), "factor")])
def test_bad_methods_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FrameMethod(**kwargs)


@pytest.mark.parametrize("method, buffers", [
    (FrameMethod("full"), ["mask", "normal", "color"]),
    (FrameMethod("full", ao_rays=4, spp=2), ["mask", "normal", "ao", "color"]),
    (FrameMethod("atrous", ao_rays=2), ["mask", "normal", "ao", "color"]),
    (FrameMethod("upscale", factor=4, interpolation="bicubic"), ["mask", "normal", "color"]),
    (FrameMethod("reconstruct", ao_rays=2), ["mask", "normal", "depth", "ao", "color"]),
    (FrameMethod("reconstruct"), ["mask", "normal", "depth", "ao", "color"]),
    (FrameMethod("network", factor=4), ["mask", "normal", "depth", "ao", "color"])])
def test_every_kind_makes_a_bounded_color_frame_and_only_its_buffers(scene, method, buffers):
    renderer, iso = scene
    frames = run_sequence(FrameRunner(method, renderer, iso, *SIZE), orbit_path(2, yaw0=20.0, yaw_step=3.0))
    for f in frames:
        assert f.present() == buffers
        assert f.color.shape == (SIZE[1], SIZE[0], 3)
        assert torch.isfinite(f.color).all() and f.color.min() >= 0 and f.color.max() <= 1
        assert (f.mask > 0.5).any()


def test_the_network_carries_its_state_and_resets_on_a_cut(scene, tmp_path_factory):
    renderer, iso = scene
    method = FrameMethod("network", factor=2, model=str(tiny_model_dir(tmp_path_factory)), model_name="tiny")
    runner = FrameRunner(method, renderer, iso, *SIZE)
    cams = orbit_path(2, yaw0=20.0, yaw_step=3.0)
    first = runner.frame(cams[1])  # a cut: no previous frame
    runner.frame(cams[0])
    carried = runner.frame(cams[1], cams[0])  # the same view, with the previous output warped in
    again = runner.frame(cams[1])
    assert torch.allclose(first.color, again.color, atol=1e-6)
    assert (first.color - carried.color).abs().max() > 1e-3


def test_sizes_the_factor_does_not_divide_and_wrong_models_are_refused(scene, tmp_path_factory):
    renderer, iso = scene
    with pytest.raises(ValueError, match="must divide"):
        FrameRunner(FrameMethod("upscale", factor=4), renderer, iso, 50, 32)
    with pytest.raises(ValueError, match="positive integer"):
        FrameRunner(FrameMethod("full"), renderer, iso, 0, 32)
    tiny = str(tiny_model_dir(tmp_path_factory))  # an x2 model
    with pytest.raises(ValueError, match="upscales x2, not x4"):
        FrameRunner(FrameMethod("network", factor=4, model=tiny), renderer, iso, *SIZE)


def test_an_empty_image_shades_to_the_background(scene):
    renderer, _ = scene
    frame = FrameRunner(FrameMethod("atrous", ao_rays=2), renderer, 2.0, *SIZE).frame(orbit_path(1)[0])
    assert frame.mask.max() == 0 and torch.equal(frame.color, torch.ones_like(frame.color))


def test_runners_share_one_network_per_model_precision_and_device(scene):
    renderer, iso = scene
    upscalers: dict = {}
    bf16 = FrameMethod("network", factor=4, precision="bf16")
    a = FrameRunner(bf16, renderer, iso, *SIZE, upscalers=upscalers)
    b = FrameRunner(bf16, renderer, iso, 96, 64, upscalers=upscalers)
    c = FrameRunner(FrameMethod("network", factor=4), renderer, iso, *SIZE, upscalers=upscalers)
    assert a.upscaler is b.upscaler and a.upscaler.precision == "bf16"
    assert c.upscaler is not a.upscaler and c.upscaler.precision == "fp32" and len(upscalers) == 2
