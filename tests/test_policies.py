"""The policies every stage shares, held once in the library: the iso default
(isosr_render.catalog.resolve_iso), a sequence's previous cameras
(isosr_render.sequence.sequence_requests), float -> uint8 images (isosr_render.images.to_uint8)
and the live upscaler comparison (isosr_net.evaluate.compare_upscalers)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from isosr_net.evaluate import COMPARED, compare_upscalers
from isosr_net.metrics import frame_scores, upscale_baseline
from isosr_net.upscaler import Upscaler
from isosr_net.inference import surface_tensors
from isosr_render import Renderer, RenderRequest, Volume, open_volume, orbit, resolve_iso
from isosr_render.catalog import ENV_VAR
from isosr_render.conventions import HIGHRES_BUFFERS, LOWRES_BUFFERS
from isosr_render.images import to_uint8
from isosr_render.sequence import sequence_requests
from isosr_render.volume import VolumeError
from net_fixtures import tiny_model_dir


def test_iso_of_a_procedural_spec_is_its_own():
    volume = open_volume("proc:metaballs:3@24")
    lo, hi = volume.value_range
    assert resolve_iso("proc:metaballs:3@24", volume) == pytest.approx((0.5 - lo) / (hi - lo))


def test_a_given_iso_wins_in_data_or_normalized_units():
    volume = Volume.from_array(np.linspace(-10, 30, 2 * 3 * 4).reshape(2, 3, 4))
    assert resolve_iso("proc:sphere", volume, 0.0) == pytest.approx(0.25)
    assert resolve_iso("x.nii", volume, 0.7, normalized=True) == 0.7
    for bad in (float("nan"), float("inf"), "3", True):
        with pytest.raises(ValueError, match="iso must be a finite number"):
            resolve_iso("x.nii", volume, bad)


def test_iso_of_a_file_is_otsu_and_of_a_shared_volume_the_manifests(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    values = np.where(rng.random((16, 16, 16)) < 0.5, 10.0, 200.0) + rng.normal(0, 0.2, (16, 16, 16))
    volume = Volume.from_array(values, name="two.npy")
    otsu = resolve_iso("two.npy", volume)
    assert otsu == volume.otsu_iso()
    np.testing.assert_array_equal(volume.data > otsu, values > 100)  # it splits the two modes
    np.save(tmp_path / "two.npy", values)
    (tmp_path / "volumes.json").write_text(json.dumps([{"name": "two", "file": "two.npy", "split": "val",
                                                        "otsu_iso_normalized": 0.375}]))
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    shared = open_volume("shared:two")
    np.testing.assert_array_equal(shared.data, volume.data)
    assert resolve_iso("shared:two", shared) == 0.375
    with pytest.raises(VolumeError, match="no volume named 'three'"):
        open_volume("shared:three")


def test_sequence_requests_give_no_previous_camera_to_the_first_frame():
    cameras = [orbit(30 + 2 * t, 20, 1.5) for t in range(3)]
    pairs = sequence_requests(cameras, 16, 12, 0.4, ("mask", "normal", "flow"), spp=2)
    assert [c for c, _ in pairs] == cameras
    first, second, third = (r for _, r in pairs)
    assert first.prev_camera is None and first.outputs == ("mask", "normal")
    assert second.prev_camera is cameras[0] and third.prev_camera is cameras[1]
    assert second.outputs == ("mask", "normal", "flow") and second.spp == 2
    assert (second.width, second.height) == (16, 12)
    with pytest.raises(ValueError, match="sets prev_camera itself"):
        sequence_requests(cameras, 16, 12, 0.4, ("mask",), prev_camera=cameras[0])


def test_to_uint8_rounds_clamps_and_refuses_nan():
    out = to_uint8(torch.tensor([[-1.0, 0.0, 0.5, 1.0, 2.0, 0.2]]))
    assert out.dtype == np.uint8 and out.tolist() == [[0, 0, 128, 255, 255, 51]]
    assert to_uint8(np.full((2, 2, 3), 0.5)).shape == (2, 2, 3)
    with pytest.raises(ValueError, match="NaN or Inf"):
        to_uint8(np.array([0.5, np.nan]))


def test_compare_upscalers_scores_each_method_and_runs_the_network_recurrently(tmp_path_factory):
    volume = open_volume("proc:cloud:1@32")
    iso = resolve_iso("proc:cloud:1@32", volume)
    renderer = Renderer(volume, "cpu")
    cameras = [orbit(30 + 4 * t, 20, 1.4) for t in range(3)]
    model = tiny_model_dir(tmp_path_factory)
    upscaler = Upscaler(model)
    upscaler.step(torch.zeros(1, 5, 8, 8), None)  # state left over from elsewhere must not leak in
    frames = list(compare_upscalers(renderer, cameras, iso, (16, 12), upscaler, ao_samples=4, spp=1))
    assert len(frames) == 3

    reference = Upscaler(model)
    for t, (frame, camera) in enumerate(zip(frames, cameras)):
        assert list(frame.outputs) == list(COMPARED)
        assert set(frame.ms) == set(COMPARED) | {"low-res render", "ground truth render"}
        assert all(ms >= 0 for ms in frame.ms.values())
        truth = renderer.render(camera, RenderRequest(32, 24, iso, HIGHRES_BUFFERS, spp=1, ao_samples=4))
        torch.testing.assert_close(frame.target, truth.channels_first(HIGHRES_BUFFERS)[None])
        outputs = LOWRES_BUFFERS + (("flow",) if t else ())
        low = renderer.render(camera, RenderRequest(16, 12, iso, outputs, prev_camera=cameras[t - 1] if t else None))
        lowres, flow = surface_tensors(low)
        assert (flow is None) == (t == 0)
        torch.testing.assert_close(frame.outputs["network"], reference.step(lowres, flow))
        torch.testing.assert_close(frame.outputs["bicubic"], upscale_baseline(lowres, 2, "bicubic"))
        for method, out in frame.outputs.items():
            assert out.shape == (1, 6, 24, 32)
            assert frame.color_psnr[method] == pytest.approx(float(frame_scores(out, frame.target)["color_psnr"][0]))
    # The network carried its state: frame 2 differs from a fresh start on the same input.
    assert not torch.allclose(frames[2].outputs["network"], Upscaler(model).step(lowres, None))


def test_render_of_an_unknown_shared_volume_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    from isosr_cli.main import main

    (tmp_path / "volumes.json").write_text("[]")
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    assert main(["render", "shared:nope", "-o", str(tmp_path / "f.npz")]) == 2
    assert "isosr render: error: no volume named 'nope'" in capsys.readouterr().err
    assert not (tmp_path / "f.npz").exists()
