"""Tests for the reconstructed frame as one CUDA graph (`Reconstructor.render_reconstruct`):
render, reconstruction and shading replayed together must equal the render followed by the
eager reconstruction, frame after frame, through new sizes, isos, cuts and interleaved streams.
CPUs (and sparse volumes) take the ungraphed path, which the CPU tests check."""

from __future__ import annotations

import pytest
import torch

from isosr_render import Renderer, open_volume, orbit_path, resolve_iso
from isosr_render.sequence import sequence_requests
from isosr_render.shading import ShadingParams
from isosr_net.frame_methods import FrameMethod, Networks, make_runner
from isosr_net.reconstructor import GraphCache, Reconstructor

SIZE = (96, 64)  # width, height
OUTPUTS = ("mask", "normal", "depth", "position", "ao", "flow")  # with positions: the ray history too
SOURCE = "proc:cloud:3@48"
NAMES = ("mask", "normal", "depth", "ao", "color")
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (run on the GPU machine)")


def scene(device: str) -> tuple[Renderer, float]:
    volume = open_volume(SOURCE)
    return Renderer(volume, device), resolve_iso(SOURCE, volume)


def assert_frames_close(a, b, atol: float) -> None:
    for name in NAMES:
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=atol, msg=name)


def test_without_cuda_it_is_the_render_then_the_reconstruction():
    renderer, iso = scene("cpu")
    shading, ours, reference = ShadingParams(), Reconstructor(), Reconstructor()
    for camera, request in sequence_requests(orbit_path(3, yaw_step=3.0), *SIZE, iso, OUTPUTS, ao_samples=2):
        assert not ours.graphable(renderer, request)
        rendered, out = ours.render_reconstruct(renderer, camera, request, 2, 1, shading)
        frame = renderer.render(camera, request)
        assert_frames_close(out, reference.reconstruct(frame, 2, 1, shading), atol=0)
        torch.testing.assert_close(rendered.depth, frame.depth, rtol=0, atol=0)


@cuda
def test_one_graph_frames_equal_render_then_reconstruct():
    """Over orbits at two sizes and two isos (each a capture of its own), with cuts between."""
    renderer, iso = scene("cuda")
    options = dict(device="cuda", precision="fp16", channels_last=True)
    graphed, eager, shading = Reconstructor(graphs=True, **options), Reconstructor(**options), ShadingParams()
    for size, level in ((SIZE, iso), ((64, 48), iso), (SIZE, iso + 0.05), (SIZE, iso)):
        for camera, request in sequence_requests(orbit_path(4, yaw_step=3.0), *size, level, OUTPUTS, ao_samples=2):
            assert graphed.graphable(renderer, request)
            rendered, a = graphed.render_reconstruct(renderer, camera, request, 2, 1, shading)
            frame = renderer.render(camera, request)
            for name in OUTPUTS if request.prev_camera else OUTPUTS[:-1]:
                torch.testing.assert_close(getattr(rendered, name), getattr(frame, name), rtol=0, atol=0)
            assert_frames_close(a, eager.reconstruct(frame, 2, 1, shading), atol=2e-2)
    assert len(graphed._frame_graphs) == 6  # (first frame, next frames) x (two sizes, a second iso)


@cuda
def test_interleaved_streams_keep_their_own_state():
    renderer, iso = scene("cuda")
    options = dict(device="cuda", precision="fp16", channels_last=True)
    shared = Reconstructor(graphs=True, **options)
    streams = [(shared.own(), Reconstructor(**options), orbit_path(4, yaw0=y, yaw_step=3.0)) for y in (0.0, 90.0)]
    sequences = [sequence_requests(path, *SIZE, iso, OUTPUTS, ao_samples=1) for _, _, path in streams]
    for frames in zip(*sequences):
        for (graphed, eager, _), (camera, request) in zip(streams, frames):
            _, a = graphed.render_reconstruct(renderer, camera, request, 1, 1)
            b = eager.reconstruct(renderer.render(camera, request), 1, 1)
            for name in ("mask", "normal", "ao"):
                torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=2e-2)


@cuda
def test_the_runner_makes_graphed_frames_like_eager_ones_and_keeps_copies():
    renderer, iso = scene("cuda")
    method = FrameMethod("reconstruct", ao_rays=1, precision="fp16")
    options = dict(device="cuda", precision="fp16", channels_last=True)
    graphed = make_runner(method, renderer, iso, *SIZE, keep=("flow",),
                          networks=Networks(lambda *_: Reconstructor(graphs=True, **options)))
    eager = make_runner(method, renderer, iso, *SIZE, keep=("flow",),
                        networks=Networks(lambda *_: Reconstructor(**options)))
    kept = []
    for camera, prev in zip(orbit_path(4, yaw_step=3.0), [None, *orbit_path(3, yaw_step=3.0)]):
        a, b = graphed.frame(camera, prev), eager.frame(camera, prev)
        assert_frames_close(a.buffers, b.buffers, atol=2e-2)
        if prev is not None:  # the render's flow, kept
            torch.testing.assert_close(a.buffers.flow, b.buffers.flow, rtol=0, atol=0)
            kept.append((a.buffers.flow, a.buffers.flow.clone()))
    for flow, when_made in kept:  # copies: later frames (the render plan's buffers) leave them alone
        torch.testing.assert_close(flow, when_made, rtol=0, atol=0)


def test_the_graph_cache_keeps_the_most_recently_used_within_its_count_and_pixels():
    cache = GraphCache(max_graphs=3, max_pixels=100)
    for key, pixels in (("a", 40), ("b", 40)):
        cache.add(key, key.upper(), pixels)
    assert cache.use("a") == "A" and cache.use("z") is None
    cache.add("c", "C", 40)  # 120 pixels: the least recently used ("b") goes
    assert list(cache) == ["a", "c"]
    for key in "def":
        cache.add(key, key.upper(), 1)
    assert list(cache) == ["d", "e", "f"]  # at most 3
    cache.add("huge", "H", 1000)  # past the pixels alone: kept, every other dropped
    assert list(cache) == ["huge"]


@cuda
def test_frames_stay_right_when_the_graph_cache_drops_and_captures_again():
    """A cache bound to the smaller frame's pixels keeps one graph: every frame captures anew."""
    renderer, iso = scene("cuda")
    options = dict(device="cuda", precision="fp16", channels_last=True)
    graphed, eager = Reconstructor(graphs=True, **options), Reconstructor(**options)
    graphed._frame_graphs.max_pixels = 64 * 48
    for size in (SIZE, (64, 48), SIZE):
        for camera, request in sequence_requests(orbit_path(2, yaw_step=3.0), *size, iso, OUTPUTS, ao_samples=2):
            _, a = graphed.render_reconstruct(renderer, camera, request, 2, 1)
            assert_frames_close(a, eager.reconstruct(renderer.render(camera, request), 2, 1), atol=2e-2)
            assert len(graphed._frame_graphs) == 1
