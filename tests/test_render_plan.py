"""Tests for isosr_render.renderer.RenderPlan: frames rendered into reused buffers.

A plan's frames must equal `Renderer.render`'s (a kept plan of its own, buffers copied out) bit for
bit on the CPU, frame after frame with changing cameras, seeds and isos, in the same buffers;
`Renderer.render`'s frames own their memory, per thread; the CUDA tests (skipped without CUDA)
replay the plan's launch from a CUDA graph, whose staged kernel reads the frame's values from
device memory.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch

from conftest import DEVICE, field_volume, sphere_sdf
from isosr_render.camera import Camera, orbit
from isosr_render.clip import Clip
from isosr_render import kernels
from isosr_render import renderer as renderer_module
from isosr_render.renderer import FRAME_DTYPE, MAX_SPP, PLAN_CACHE, Renderer, RenderPlan, RenderRequest, frame_args
from isosr_render.surfaces import Surface, Surfaces
from isosr_render.volume import Volume

W, H = 48, 36
CAMERAS = [orbit(30.0, 20.0, 1.2), orbit(37.0, 24.0, 1.15), orbit(45.0, 15.0, 1.3)]


@pytest.fixture(scope="module")
def sphere_renderer(sphere_volume):
    return Renderer(sphere_volume, DEVICE, threads=2)


def request_of(iso: float, outputs: tuple[str, ...], width: int = W, height: int = H, **kw) -> RenderRequest:
    """A request; one with flow gets a stand-in previous camera (:func:`frames_of` sets each frame's)."""
    prev = CAMERAS[0] if "flow" in outputs else None
    return RenderRequest(width, height, iso, outputs, prev_camera=prev, **kw)


def frames_of(request: RenderRequest, cameras: list[Camera]) -> list[tuple[Camera, RenderRequest]]:
    """Per frame, its camera and request: flow against the camera before, a seed per frame."""
    flow = "flow" in request.outputs
    return [(cam, dataclasses.replace(request, seed=request.seed + i,
                                      prev_camera=(cameras[i - 1] if i else cam) if flow else None))
            for i, cam in enumerate(cameras)]


def assert_same(a, b) -> None:
    assert a.present() == b.present()
    for name in a.present():
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=0, msg=name)


def assert_plan_matches(renderer: Renderer, frames: list[tuple[Camera, RenderRequest]]) -> None:
    """Every frame of one plan equals a fresh render, in the same buffers, each frame its own."""
    plan = renderer.plan(frames[0][1])
    ptrs, previous = None, None
    for camera, request in frames:
        got = plan.render(camera, request)
        assert_same(got, renderer.render(camera, request))
        kernel_made = [n for n in got.present() if n != "color" and not (n == "flow" and request.flow_fill != "none")]
        now = {n: getattr(got, n).data_ptr() for n in kernel_made}
        assert ptrs is None or now == ptrs  # no allocation per frame
        ptrs = now
        if previous is not None:  # the frames differ, so stale buffers would be caught
            assert any(not torch.equal(previous[n], getattr(got, n)) for n in got.present())
        previous = {n: getattr(got, n).clone() for n in got.present()}


REQUESTS = {
    "geometry": dict(outputs=("mask", "normal", "depth", "position")),
    "spp 4": dict(outputs=("mask", "normal", "depth"), spp=4),
    "ao 3 rays": dict(outputs=("mask", "normal", "ao"), ao_samples=3, ao_radius=0.1),
    "ao spp 4": dict(outputs=("mask", "ao"), ao_samples=2, ao_radius=0.1, spp=4),
    "spp past the hit planes": dict(outputs=("mask", "normal", "ao", "samples"), ao_samples=1, ao_radius=0.1, spp=11),
    "flow": dict(outputs=("mask", "normal", "depth", "ao", "flow"), ao_samples=1, ao_radius=0.1),
    "flow filled": dict(outputs=("flow",), flow_fill="pushpull"),
    "color and samples": dict(outputs=("color", "samples"), ao_samples=2, ao_radius=0.1),
    "bisection": dict(outputs=("depth",), refine="bisection", refine_steps=2, step=0.02),
}


@pytest.mark.parametrize("name", REQUESTS)
def test_plan_frames_equal_fresh_renders(sphere_volume, sphere_renderer, name):
    request = request_of(sphere_volume.normalized_iso(0.0), **REQUESTS[name])
    assert_plan_matches(sphere_renderer, frames_of(request, CAMERAS))


# The views of one launch: REQUESTS' and a clipped, capped one and one of several surfaces (each view its own
# camera, previous camera and seed).
VIEW_REQUESTS = {**REQUESTS,
                 "clipped and capped": dict(outputs=("mask", "normal", "color"), ao_samples=1, ao_radius=0.1,
                                            clip=Clip(planes=[((0.0, 0.0, 0.05), (0.0, 0.0, -1.0))], cap="below")),
                 "surfaces": dict(outputs=("mask", "normal", "surface", "color"), several=True)}


@pytest.mark.parametrize("name", VIEW_REQUESTS)
def test_views_rendered_together_equal_each_rendered_alone(sphere_volume, sphere_renderer, name):
    """Renderer.render_views: one launch over three views (a plan of four) and then two (the same plan), each
    view's buffers its own and equal to its render alone, bit for bit on the CPU."""
    iso, kw = sphere_volume.normalized_iso(0.0), dict(VIEW_REQUESTS[name])
    if kw.pop("several", False):  # the sphere's surface and one inside it
        kw["surfaces"] = Surfaces((Surface(iso), Surface(sphere_volume.normalized_iso(-0.05), (0.2, 0.6, 0.9))))
    request = request_of(iso, **kw)
    frames = frames_of(request, CAMERAS)
    alone = [sphere_renderer.render(camera, r) for camera, r in frames]
    for views in (frames, frames[1:]):
        together = sphere_renderer.render_views(views)
        for got, expected in zip(together, alone[len(frames) - len(views):]):
            assert_same(got, expected)
        copied = {f.mask.untyped_storage().data_ptr() for f in together if f.mask is not None}
        assert len(copied) == ("mask" in request.outputs), "a batch's buffers copied out together"


def test_views_past_a_launch_s_pixels_render_in_several_launches(sphere_volume, sphere_renderer, monkeypatch):
    """Views of more pixels than MAX_LAUNCH_PIXELS (a plan's memory) render in launches of at most that many,
    each view still its own render's."""
    monkeypatch.setattr(renderer_module, "MAX_LAUNCH_PIXELS", 2 * W * H)
    request = request_of(sphere_volume.normalized_iso(0.0), ("mask", "normal", "ao"), ao_samples=2, ao_radius=0.1)
    frames = frames_of(request, CAMERAS)
    launches = []
    launch = RenderPlan.launch
    monkeypatch.setattr(RenderPlan, "launch", lambda plan, *a: (launches.append(plan._staged), launch(plan, *a))[1])
    for got, (camera, r) in zip(sphere_renderer.render_views(frames), frames):
        assert_same(got, sphere_renderer.render(camera, r))
    assert launches[:2] == [2, 1]


def test_views_that_a_launch_cannot_share_are_refused(sphere_volume, sphere_renderer):
    """Views of other isos (another empty-space grid), clips or sizes are rendered apart: a clear error."""
    base = RenderRequest(W, H, sphere_volume.normalized_iso(0.0), ("mask", "depth"))
    for other, words in ((dataclasses.replace(base, iso=sphere_volume.normalized_iso(0.05)), "iso"),
                         (dataclasses.replace(base, clip=Clip(planes=[((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))])), "clip"),
                         (dataclasses.replace(base, width=W + 8), "render plan renders")):
        with pytest.raises(ValueError, match=words):
            sphere_renderer.render_views([(CAMERAS[0], base), (CAMERAS[1], other)])
    with pytest.raises(ValueError, match="no views"):
        sphere_renderer.render_views([])
    plan = sphere_renderer.plan(base, views=2)
    with pytest.raises(ValueError, match="1 to 2 views"):
        plan.stage_views([(CAMERAS[0], base)] * 3)
    with pytest.raises(ValueError, match="view_buffers"):
        plan.render(CAMERAS[0], base)


def test_plan_follows_iso_and_ray_parameters(sphere_volume, sphere_renderer):
    """Iso (another grid), AO rays and radius change between frames of one plan."""
    base = RenderRequest(W, H, sphere_volume.normalized_iso(0.0), ("mask", "depth", "ao"), ao_samples=2)
    changes = [dict(), dict(iso=sphere_volume.normalized_iso(0.05)), dict(ao_samples=5, ao_radius=0.05),
               dict(iso=sphere_volume.normalized_iso(-0.05), skip=False)]
    frames = [(CAMERAS[0], dataclasses.replace(base, **c)) for c in changes]
    assert_plan_matches(sphere_renderer, frames)


def test_plan_focus_rows_equal_full_frame_rows(sphere_volume, sphere_renderer):
    request = RenderRequest(W, H, sphere_volume.normalized_iso(0.0), ("mask", "normal", "depth"))
    plan = sphere_renderer.plan(request)
    for camera, rows in zip(CAMERAS, [(0, H), (5, 17), (30, 36)]):
        got = plan.render(camera, request, rows=rows)
        full = sphere_renderer.render(camera, request)
        for name in ("mask", "normal", "depth"):
            torch.testing.assert_close(getattr(got, name)[slice(*rows)], getattr(full, name)[slice(*rows)],
                                       rtol=0, atol=0)


@pytest.mark.parametrize("case", ["anisotropic tiny", "camera inside", "grazing"])
def test_plan_hard_views(case):
    if case == "anisotropic tiny":
        values = np.zeros((3, 4, 2), dtype=np.float32)
        values[1:, 1:3] = 1.0
        volume, iso = Volume.from_array(values, spacing=(1.0, 1.0, 3.0)), 0.5
        cameras = [orbit(60.0, 20.0, 2.0), orbit(70.0, 30.0, 2.2)]
    elif case == "camera inside":
        volume = field_volume(lambda p: np.abs(np.linalg.norm(p, axis=-1) - 0.35) - 0.05, (32, 32, 32))
        iso = volume.normalized_iso(0.0)
        cameras = [Camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0)), Camera((0.05, 0.0, 0.0), (1.0, 0.2, 0.0))]
    else:
        volume = field_volume(lambda p: sphere_sdf(p, 0.3), (33, 33, 33))
        iso = volume.normalized_iso(0.0)
        cameras = [Camera((0.0, 0.5, 2.0), (0.0, 0.5, 0.0)), Camera((0.5, 0.0, 2.0), (0.5, 0.0, 0.0))]
    request = request_of(iso, ("mask", "normal", "depth", "ao", "flow"), height=H + 1, ao_samples=2, ao_radius=0.2)
    assert_plan_matches(Renderer(volume, DEVICE, threads=2), frames_of(request, cameras))


def test_plan_refuses_other_requests(sphere_volume, sphere_renderer):
    request = RenderRequest(W, H, sphere_volume.normalized_iso(0.0), ("mask", "depth"))
    plan = sphere_renderer.plan(request)
    with pytest.raises(ValueError, match="stage a frame"):
        plan.launch()
    for other in (dataclasses.replace(request, width=W + 8), dataclasses.replace(request, outputs=("mask",)),
                  dataclasses.replace(request, outputs=("mask", "flow"), prev_camera=CAMERAS[0], flow_fill="ns"),
                  dataclasses.replace(request, spp=2)):
        with pytest.raises(ValueError, match="render plan renders 48x36"):
            plan.render(CAMERAS[0], other)
    plan.stage(CAMERAS[0], request)
    with pytest.raises(ValueError, match="rows must satisfy"):
        plan.launch(rows=(10, H + 1))


def test_the_most_rays_per_pixel_keep_a_plan_bounded_and_the_frame_sane(sphere_volume, sphere_renderer):
    """A request at the renderer's top rays per pixel: the plan keeps the hits of HIT_PLANES rays only (the
    rest are marched by the surface kernel), and the frame stays finite and in range."""
    request = RenderRequest(16, 12, sphere_volume.normalized_iso(0.0), ("mask", "normal", "ao", "samples"),
                            spp=MAX_SPP, ao_samples=1, ao_radius=0.1)
    plan = sphere_renderer.plan(request)
    frame = plan.render(CAMERAS[0], request)
    assert plan._hits.shape[0] == kernels.HIT_PLANES
    assert 0 < frame.mask.sum() < frame.mask.numel()  # the sphere's edge is in the view
    assert ((frame.mask >= 0) & (frame.mask <= 1)).all() and ((frame.ao >= 0) & (frame.ao <= 1)).all()
    lengths = frame.normal.norm(dim=-1)
    assert torch.isfinite(frame.normal).all() and (lengths <= 1 + 1e-5).all()
    assert ((lengths - 1).abs() < 1e-5)[frame.mask > 0].all()
    assert (frame.samples[frame.mask > 0] >= MAX_SPP).all()  # every ray marched at least once


def test_render_frames_own_their_memory(sphere_volume, sphere_renderer):
    """Renderer.render reuses a kept plan, yet a frame is not overwritten by the next one; a frame's buffers are
    copied out of the plan together (one storage, one copy)."""
    request = request_of(sphere_volume.normalized_iso(0.0), ("mask", "normal", "depth", "ao", "flow"),
                         ao_samples=2, ao_radius=0.1)
    frames = frames_of(request, CAMERAS)
    first = sphere_renderer.render(*frames[0])
    kept = {n: getattr(first, n).clone() for n in first.present()}
    second = sphere_renderer.render(*frames[1])
    for name in first.present():
        assert getattr(first, name).data_ptr() != getattr(second, name).data_ptr(), name
        torch.testing.assert_close(getattr(first, name), kept[name], rtol=0, atol=0, msg=name)
    assert any(not torch.equal(getattr(first, n), getattr(second, n)) for n in first.present())
    assert len({getattr(first, n).untyped_storage().data_ptr() for n in first.present()}) == 1


def test_render_from_threads_equals_serial_renders(sphere_volume):
    """Threads rendering at once through one renderer each get their own kept plan; plans beyond
    PLAN_CACHE are dropped."""
    renderer = Renderer(sphere_volume, DEVICE, threads=1)
    requests = [request_of(sphere_volume.normalized_iso(0.0), ("mask", "depth", "ao"), width=W + 8 * i,
                           ao_samples=1, ao_radius=0.1, seed=i) for i in range(PLAN_CACHE + 2)]
    jobs = [(CAMERAS[i % len(CAMERAS)], requests[i % len(requests)]) for i in range(24)]
    want = [renderer.render(camera, request) for camera, request in jobs]
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda job: renderer.render(*job), jobs))
    for a, b in zip(got, want):
        assert_same(a, b)
    assert len(renderer._plans) <= PLAN_CACHE


def test_a_reused_frame_record_is_written_whole():
    """The plan's host record, staged into frame after frame, holds every field of the new frame:
    written over a record of another frame's bytes, it equals a new one."""
    request = request_of(0.5, ("mask", "normal", "depth", "ao", "flow"), ao_samples=3, spp=2, seed=7)
    stale = np.frombuffer(np.random.default_rng(0).bytes(FRAME_DTYPE.itemsize), dtype=FRAME_DTYPE).copy()
    written = frame_args(CAMERAS[1], request, 0.01, out=stale)
    assert written is stale
    assert written.tobytes() == frame_args(CAMERAS[1], request, 0.01).tobytes()


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


@cuda
@pytest.mark.parametrize("spp", [1, 3])
def test_plan_launch_replays_from_a_cuda_graph(sphere_volume, spp):
    """The launches captured once (first hit, then the surface kernel of one ray or several per pixel)
    render every frame staged after them, as fresh renders do."""
    renderer = Renderer(sphere_volume, "cuda")
    request = request_of(sphere_volume.normalized_iso(0.0), ("mask", "normal", "depth", "ao", "flow"),
                         ao_samples=2, ao_radius=0.1, spp=spp)
    frames = frames_of(request, CAMERAS + [orbit(50.0, 10.0, 1.25)])
    plan = renderer.plan(frames[1][1])
    plan.render(*frames[1])  # records the launch and loads the module outside the capture
    torch.cuda.synchronize()
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        plan.launch()
    for camera, request in frames[1:]:
        plan.stage(camera, request)
        graph.replay()
        assert_same(plan.buffers(request), renderer.render(camera, request))


@cuda
def test_frames_staged_while_the_device_is_busy_each_render_their_own_camera(sphere_volume):
    """The host record is written again only once its last copy has run: frames staged and replayed
    behind a long kernel, without a sync between them, each render their own camera."""
    renderer = Renderer(sphere_volume, "cuda")
    request = request_of(sphere_volume.normalized_iso(0.0), ("mask", "normal", "depth", "flow"))
    frames = frames_of(request, CAMERAS + [orbit(50.0, 10.0, 1.25)])
    plan = renderer.plan(frames[1][1])
    plan.render(*frames[1])
    torch.cuda.synchronize()
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        plan.launch()
    torch.cuda._sleep(200_000_000)  # the copies queue behind it while the host stages the next frames
    outs = []
    for camera, request in frames[1:]:
        plan.stage(camera, request)
        graph.replay()
        outs.append(plan.buffers(request).clone())
    for (camera, request), out in zip(frames[1:], outs):
        assert_same(out, renderer.render(camera, request))
