"""Tests for the reconstructed frame as one CUDA graph (`Reconstructor.render_reconstruct`):
render, reconstruction and shading replayed together must equal the render followed by the
eager reconstruction, frame after frame, through new sizes, isos, cuts and interleaved streams.
CPUs (and sparse volumes) take the ungraphed path, which the CPU tests check."""

from __future__ import annotations

import pytest
import torch

from isosr_render import Renderer, open_volume, orbit, orbit_path, resolve_iso
from isosr_render.sequence import sequence_requests
from isosr_render.shading import ShadingParams
from isosr_net.methods import FrameMethod, Networks, make_runner, run_sequence
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
@pytest.mark.parametrize("fused", [False, True], ids=["layers", "fused"])
def test_one_graph_frames_equal_render_then_reconstruct(fused):
    """Over orbits at two sizes and two isos (each a capture of its own), with cuts between; the
    network as PyTorch layers (the graph copies its output into the state) and as the fused
    kernels (their tail writes the state)."""
    renderer, iso = scene("cuda")
    options = dict(device="cuda", precision="fp16", channels_last=True)
    graphed, eager = Reconstructor(graphs=True, fused=fused, **options), Reconstructor(**options)
    shading = ShadingParams()
    for size, level in ((SIZE, iso), ((64, 48), iso), (SIZE, iso + 0.05), (SIZE, iso)):
        for camera, request in sequence_requests(orbit_path(4, yaw_step=3.0), *size, level, OUTPUTS, ao_samples=2):
            assert graphed.graphable(renderer, request)
            rendered, a = graphed.render_reconstruct(renderer, camera, request, 2, 1, shading)
            frame = renderer.render(camera, request)
            for name in OUTPUTS if request.prev_camera else OUTPUTS[:-1]:
                torch.testing.assert_close(getattr(rendered, name), getattr(frame, name), rtol=0, atol=0)
            assert_frames_close(a, eager.reconstruct(frame, 2, 1, shading), atol=2e-2)
    # (a first frame, next frames writing either history of the pair) x (two sizes, a second iso)
    assert len(graphed._frame_graphs) == 9


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
@pytest.mark.parametrize("fused", [False, True], ids=["layers", "fused"])
def test_a_graphed_frame_is_the_streams_state_and_copies_keep_it(fused):
    """No copy after the graph: each frame's output is the stream's state tensor (the same memory
    every frame, which the next frame reads and overwrites; the buffers object its own), its ray
    history the other of a pair than the one it read; the runner's frames kept by run_sequence
    (copies) equal the eager runner's, frame by frame."""
    renderer, iso = scene("cuda")
    options = dict(device="cuda", precision="fp16", channels_last=True)
    graphed = Reconstructor(graphs=True, fused=fused, **options)
    outputs, histories = set(), []
    for camera, request in sequence_requests(orbit_path(4, yaw_step=3.0), *SIZE, iso, OUTPUTS, ao_samples=1):
        _, out = graphed.render_reconstruct(renderer, camera, request, 1, 1)
        assert out.mask.data_ptr() == graphed.previous.data_ptr()
        assert out.samples is None  # what a caller set on the last frame's buffers stays its own
        out.samples = torch.zeros(1)
        outputs.add(out.mask.data_ptr())
        histories.append(graphed.history.count.data_ptr())
    assert len(outputs) == 1
    assert histories[0] == histories[2] != histories[1] == histories[3]
    method, cameras = FrameMethod.of("reconstruct", ao_rays=1, precision="fp16"), orbit_path(4, yaw_step=3.0)
    frames = [run_sequence(make_runner(method, renderer, iso, *SIZE, keep=("flow",),
                                       networks=Networks(lambda *_, g=g: Reconstructor(graphs=g, **options))), cameras)
              for g in (True, False)]
    for a, b in zip(*frames):
        assert_frames_close(a, b, atol=2e-2)
        if b.flow is not None:  # the render's flow, kept
            torch.testing.assert_close(a.flow, b.flow, rtol=0, atol=0)


@cuda
@pytest.mark.parametrize("fused", [False, True], ids=["layers", "fused"])
def test_a_refused_graphed_frame_raises_and_its_stream_starts_anew(fused):
    """A camera 2e4 away with a narrow view: depths past what fp16 takes. The graphed frame raises
    reconstruct's error; having written the state, it leaves none (a cut); the next frames are
    finite again."""
    renderer, iso = scene("cuda")
    graphed = Reconstructor(graphs=True, fused=fused, device="cuda", precision="fp16", channels_last=True)
    near = list(sequence_requests(orbit_path(2, yaw_step=3.0), *SIZE, iso, OUTPUTS, ao_samples=2))
    far = list(sequence_requests([orbit(10.0 + i, 20.0, 2e4, fov_y=0.005) for i in range(2)], *SIZE, iso, OUTPUTS,
                                 ao_samples=2))
    for camera, request in near:
        graphed.render_reconstruct(renderer, camera, request, 2, 1)
    camera, request = far[1]  # with a previous camera: the frame carries the stream
    assert graphed.carries(request.height, request.width, True)
    with pytest.raises(ValueError, match="fp16 takes depths up to 10000, this frame reaches 2e"):
        graphed.render_reconstruct(renderer, camera, request, 2, 1)
    assert graphed.previous is None and graphed.history is None
    for camera, request in near:
        _, out = graphed.render_reconstruct(renderer, camera, request, 2, 1)
        assert all(torch.isfinite(getattr(out, name)).all() for name in out.present())


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
    """A cache bound to the smaller frame's pixels keeps one graph: every frame captures anew; the
    state tensors of a size go with its last graph (a resizing viewer's memory stays bounded)."""
    renderer, iso = scene("cuda")
    options = dict(device="cuda", precision="fp16", channels_last=True)
    graphed, eager = Reconstructor(graphs=True, **options), Reconstructor(**options)
    graphed._frame_graphs.max_pixels = 64 * 48
    for size in (SIZE, (64, 48), SIZE):
        for camera, request in sequence_requests(orbit_path(2, yaw_step=3.0), *size, iso, OUTPUTS, ao_samples=2):
            _, a = graphed.render_reconstruct(renderer, camera, request, 2, 1)
            assert_frames_close(a, eager.reconstruct(renderer.render(camera, request), 2, 1), atol=2e-2)
            assert len(graphed._frame_graphs) == 1
            assert list(graphed._states) == list(graphed._history_states) == [(size[1], size[0])]


@cuda
def test_dropped_graphs_free_their_memory_and_frames_capture_anew():
    """`drop_graphs` (the Pareto study's, between models): the graphs, their state tensors and pool go; the frames
    after capture anew and equal the eager ones."""
    renderer, iso = scene("cuda")
    options = dict(device="cuda", precision="fp16", channels_last=True)
    graphed, eager = Reconstructor(graphs=True, **options), Reconstructor(**options)
    frames = list(sequence_requests(orbit_path(3, yaw_step=3.0), *SIZE, iso, OUTPUTS, ao_samples=2))
    for camera, request in frames:
        graphed.render_reconstruct(renderer, camera, request, 2, 1)
    torch.cuda.synchronize()
    held = torch.cuda.memory_allocated()
    graphed.drop_graphs()
    graphed.reset()
    torch.cuda.synchronize()
    assert not graphed._frame_graphs and not graphed._states and torch.cuda.memory_allocated() < held
    for camera, request in frames:
        _, a = graphed.render_reconstruct(renderer, camera, request, 2, 1)
        assert_frames_close(a, eager.reconstruct(renderer.render(camera, request), 2, 1), atol=2e-2)
    assert graphed._frame_graphs
