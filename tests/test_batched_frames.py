"""Frames of several view sessions made together (issue 50): the engine gathers the frames asked for
while its device thread is busy and makes those of one runner kind, volume and size through the
kind's ``make_batch`` (:meth:`isosr_server.engine.Engine._batch_sync`). Each session's frames equal
those it gets alone, a session's failure or departure is its own, and mixed sizes form their own
batches. The device thread is held busy while the sessions ask (as under load), so that their
frames meet in one batch; a session's first frame runs alone, in slices."""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import Future

import msgspec
import numpy as np
import pytest
import torch
from conftest import record_make_batch
from server_fixtures import DEVICE, VOLUME, H, W, server_settings

from isosr_net.methods import reconstruct as reconstruct_module
from isosr_render import open_volume, orbit
from isosr_render.catalog import resolve_iso
from isosr_render.image_codec import decode_image
from isosr_server import engine as engine_module
from isosr_server import protocol as P
from isosr_server.encoding import CodedImage, device_jpeg, encode_image
from isosr_server.engine import Engine, ImageCodes
from isosr_server.codecs.video import coded_size
from isosr_server.video import device_i420
from isosr_server.views import VIEWS, FrameJob

SESSIONS = 3
FRAMES = 3  # the first runs alone (a new runner's frame runs in slices); the others in batches
MODES = [m for m in VIEWS if m != "auto"]  # auto's choice follows the device's load, not the frames


def image_difference(g: bytes, e: bytes) -> tuple[int, float] | None:
    """How two coded images differ: (the largest difference in levels, the share of values that differ);
    None where their shapes differ."""
    a, b = (decode_image(x).astype(np.int16) for x in (g, e))
    return (int(np.abs(a - b).max()), float((a != b).mean())) if a.shape == b.shape else None


# On CUDA a batch's network call rounds otherwise than one frame's (its kernels at another batch size): the
# float colours agree within about 1e-5 (the bound), and a difference d flips a value's 8-bit rounding
# with chance 255 d, so the images may differ by one level in about that share of their values.
FLOAT_TOLERANCE = 1e-5
FLIPPED_SHARE = 255 * FLOAT_TOLERANCE


def same(got: list, expected: list) -> bool:
    """Whether a session's frames equal the expected ones: bit for bit on the CPU; on CUDA images within one
    level in at most :data:`FLIPPED_SHARE` of their values."""
    if DEVICE == "cpu" or len(got) != len(expected):
        return got == expected
    for g, e in zip(got, expected):
        if isinstance(g, bytes) and isinstance(e, bytes):
            diff = image_difference(g, e)
            if diff is None or diff[0] > 1 or diff[1] > FLIPPED_SHARE:
                return False
        elif g != e:
            return False
    return True


def differences(got: list[list], expected: list[list]) -> list[list]:
    """Per session and frame, how coded images differ (:func:`image_difference`), or whether other results
    are equal; for a failed comparison's message."""
    return [[image_difference(g, e) if isinstance(g, bytes) and isinstance(e, bytes) else g == e
             for g, e in zip(gs, es)] for gs, es in zip(got, expected)]


def png(rgb, i420=None) -> CodedImage:
    return CodedImage(encode_image(rgb, "png", 90), "png")


def jpeg(rgb, i420=None) -> CodedImage:
    return CodedImage(encode_image(rgb, "jpeg", JPEG_QUALITY), "jpeg")


JPEG_QUALITY = 85


@pytest.fixture(scope="module")
def engine():
    # A runner's frames after its first are made in one slice (batched) whatever its last render took:
    # with the default, a render timed across a host stall (a kernel compiling on a cold GPU) sent the
    # next frame to slices, alone, and the batches these tests expect did not form.
    engine = Engine(server_settings(slice_ms=1e9))
    asyncio.run(engine.call(engine.start_sync))
    yield engine
    engine.shutdown()


@pytest.fixture(autouse=True, params=["as the device batches", "network batched"])
def network_batching(request, monkeypatch) -> None:
    """Each test as the device batches (on CPUs, the network frame by frame), and on CPUs again with the
    network's batch path let in: the path GPUs take (one call a batch, its checks read late)."""
    if request.param == "network batched":
        if DEVICE != "cpu":
            pytest.skip("the device batches its network calls already")
        monkeypatch.setattr(reconstruct_module, "BATCHED_NETWORK_DEVICES", ("cuda", "cpu"))


@pytest.fixture
def batches(monkeypatch) -> list[int]:
    """The sizes of the batches the engine gave the runners' ``make_batch``."""
    sizes: list[int] = []
    record_make_batch(monkeypatch, lambda frames: sizes.append(len(frames)))
    return sizes


class Sessions:
    """``SESSIONS`` view sessions' device-side state on one volume, each orbiting from its own yaw."""

    def __init__(self, engine: Engine, settings: list[P.ViewSettings], jpeg: bool = False):
        self.engine, self.settings, self.jpeg = engine, settings, jpeg
        volume = open_volume(VOLUME)
        self.iso = resolve_iso(VOLUME, volume)
        self.renderer = asyncio.run(engine.call(engine.renderer_sync, VOLUME, volume))
        self.frames = [engine.new_session_frames(VOLUME) for _ in settings]

    def job(self, k: int, t: int) -> FrameJob:
        return FrameJob(self.settings[k], orbit(20.0 + 25.0 * k + 3.0 * t, 25.0, 1.8), self.iso, P.FocusMsg(),
                        t, False, len(self.settings))

    async def one(self, k: int, t: int, deadline: float | None = None) -> bytes | P.ViewBuffers:
        code, quality = (jpeg, JPEG_QUALITY) if self.jpeg else (png, None)
        encode = await self.engine.view_frame(self.frames[k], self.renderer, self.job(k, t), code, deadline=deadline,
                                              jpeg=quality)
        made = await encode()
        return made.image.data if made.image is not None else made.buffers

    async def together(self, t: int, ks: list[int], cancel: int | None = None,
                       deadlines: list[float] | None = None) -> list:
        """Frame ``t`` of the sessions ``ks``, asked for while the device thread is busy; ``cancel``:
        a session that leaves while its frame waits; ``deadlines``: each one's. Each result, or the
        exception it raised."""
        release = threading.Event()
        busy = asyncio.ensure_future(self.engine.call(release.wait))
        tasks = [asyncio.ensure_future(self.one(k, t, None if deadlines is None else deadlines[i]))
                 for i, k in enumerate(ks)]
        await asyncio.sleep(0.05)  # every session's frame is asked for
        if cancel is not None:
            tasks[ks.index(cancel)].cancel()
        release.set()
        await busy
        return await asyncio.gather(*tasks, return_exceptions=True)


def alone(engine: Engine, settings: list[P.ViewSettings], jpeg: bool = False) -> list[list]:
    """Each session's frames made with nothing else asked for meanwhile (PNGs, or JPEGs coded alone)."""
    s = Sessions(engine, settings, jpeg)
    return [[asyncio.run(s.one(k, t)) for t in range(FRAMES)] for k in range(len(settings))]


def together(engine: Engine, settings: list[P.ViewSettings], cancel: tuple[int, int] | None = None,
             jpeg: bool = False) -> list[list]:
    s = Sessions(engine, settings, jpeg)
    out = [[] for _ in settings]
    for t in range(FRAMES):
        leaving = cancel[0] if cancel is not None and cancel[1] == t else None
        for k, frame in enumerate(asyncio.run(s.together(t, list(range(len(settings))), leaving))):
            out[k].append(frame)
    return out


def view_settings(engine: Engine, mode: str, width: int = W, height: int = H) -> P.ViewSettings:
    """``mode`` at the size, with 2 AO rays where it takes them (within its bounds)."""
    options = {o.name: o for m in engine.modes if m.name == mode for o in m.options}
    ao = options.get("ao_rays")
    return P.ViewSettings(mode=mode, width=width, height=height, refine=False,
                          ao_rays=0 if ao is None else max(ao.low, min(2, ao.high)))


@pytest.mark.parametrize("mode", MODES)
def test_frames_made_together_equal_those_made_alone(engine, batches, mode):
    settings = [view_settings(engine, mode)] * SESSIONS
    expected = alone(engine, settings)
    batches.clear()
    got = together(engine, settings)
    assert all(map(same, got, expected)), differences(got, expected)
    assert batches == [SESSIONS] * (FRAMES - 1), "after their first frames, the sessions' frames met in one batch"


def clipped(settings: P.ViewSettings) -> P.ViewSettings:
    """``settings`` with the volume's upper half cut away."""
    plane = P.ClipPlane((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    return msgspec.structs.replace(settings, clip=P.ClipSettings(planes=(plane,)))


@pytest.fixture
def held_kernel_loads(engine, monkeypatch) -> tuple[threading.Event, list]:
    """The engine's render kernels loaded anew (none loaded yet, as on a cold cache), each load held until the
    event is set (as a compile takes seconds on a CPU): the event, and the loads asked for."""
    monkeypatch.setattr(engine, "_kernel_loads", {})
    release, loads = threading.Event(), []
    load = engine_module.load_frame_kernels

    def held(*key):
        loads.append(key)
        assert release.wait(60), "the test never released the load"
        load(*key)
    monkeypatch.setattr(engine_module, "load_frame_kernels", held)
    return release, loads


def test_kernels_compiling_for_one_session_hold_no_other_s_frames(engine, held_kernel_loads):
    """Two sessions' clipped frames wait for their kernels' one load (off the device thread), while a plain
    session's frames keep coming; then theirs come, equal to those made alone."""
    release, loads = held_kernel_loads
    settings = [view_settings(engine, "full")] + [clipped(view_settings(engine, "full"))] * 2
    s = Sessions(engine, settings)

    async def run() -> tuple[list, list]:
        waiting = [asyncio.ensure_future(s.one(k, 0)) for k in (1, 2)]
        plain = [await s.one(0, t) for t in range(FRAMES)]
        assert not any(w.done() for w in waiting), "the clipped frames came before their kernels were loaded"
        release.set()
        return plain, await asyncio.gather(*waiting)
    plain, cut = asyncio.run(run())
    assert [key[1:] for key in loads] == [(True, False)], "one load, of the clipped kernels"
    expected = alone(engine, settings)
    assert same(plain, expected[0]) and same(cut, [expected[1][0], expected[2][0]])
    assert not same(cut[:1], [alone(engine, settings[:1] * 2)[1][0]]), "the clip cut nothing"


def test_a_failed_kernel_load_fails_its_frame_only_and_is_tried_again(engine, monkeypatch):
    monkeypatch.setattr(engine, "_kernel_loads", {})
    load, loads = engine_module.load_frame_kernels, []

    def fail_once(*key):
        loads.append(key)
        if len(loads) == 1:
            raise RuntimeError("the compiler ran out of memory")
        load(*key)
    monkeypatch.setattr(engine_module, "load_frame_kernels", fail_once)
    s = Sessions(engine, [clipped(view_settings(engine, "full"))])
    with pytest.raises(RuntimeError, match="out of memory"):
        asyncio.run(s.one(0, 0))
    assert isinstance(asyncio.run(s.one(0, 0)), bytes) and len(loads) == 2


def test_a_cut_in_one_session_changes_nothing_in_the_others(engine):
    """A session whose camera cuts (a new runner: another method) beside two that go on: theirs
    equal their frames made alone."""
    settings = [view_settings(engine, "reconstruct")] * SESSIONS
    expected = alone(engine, settings)
    s = Sessions(engine, settings)
    got = [[] for _ in settings]
    for t in range(FRAMES):
        if t == 2:  # the second session changes its settings: a cut, and a batch of its own
            s.settings = [settings[0], view_settings(engine, "full"), settings[2]]
        for k, frame in enumerate(asyncio.run(s.together(t, list(range(SESSIONS))))):
            got[k].append(frame)
    assert same(got[0], expected[0]) and same(got[2], expected[2]), differences(got, expected)
    assert same(got[1][:2], expected[1][:2]) and not same(got[1][2:], expected[1][2:])


def test_a_session_s_failure_is_its_own(engine, monkeypatch):
    """One session's frame raises (its renderer fails on its camera, in the batch's launch and alone): its
    view_frame raises that error; its batch mates get their frames, equal to those made alone."""
    settings = [view_settings(engine, "full")] * SESSIONS
    expected = alone(engine, settings)
    s = Sessions(engine, settings)
    failing_camera = s.job(1, FRAMES - 1).camera
    render_views = type(s.renderer).render_views

    def render_or_fail(renderer, frames):
        if any(camera == failing_camera for camera, _ in frames):
            raise RuntimeError("the device lost this frame")
        return render_views(renderer, frames)
    got = [[] for _ in settings]
    for t in range(FRAMES):
        if t == FRAMES - 1:
            monkeypatch.setattr(type(s.renderer), "render_views", render_or_fail)
        for k, frame in enumerate(asyncio.run(s.together(t, list(range(SESSIONS))))):
            got[k].append(frame)
    assert isinstance(got[1][-1], RuntimeError) and "lost this frame" in str(got[1][-1])
    assert same(got[0], expected[0]) and same(got[2], expected[2]), differences(got, expected)


def test_a_session_that_leaves_mid_batch_leaves_the_others_theirs(engine):
    settings = [view_settings(engine, "reconstruct")] * SESSIONS
    expected = alone(engine, settings)
    got = together(engine, settings, cancel=(1, 1))
    assert isinstance(got[1][1], asyncio.CancelledError)
    assert same(got[0], expected[0]) and same(got[2], expected[2]), differences(got, expected)


def test_mixed_sizes_form_their_own_batches(engine, batches):
    settings = [view_settings(engine, "full"), view_settings(engine, "full", 2 * W, 2 * H),
                view_settings(engine, "full")]
    expected = alone(engine, settings)
    batches.clear()
    assert together(engine, settings) == expected
    assert sorted(batches) == [1, 1, 2, 2], "per frame: the two sessions of one size together, the other alone"


def test_the_batch_with_the_earliest_deadline_is_made_first(engine, batches):
    """Asked for in one order, made in the order of their deadlines: the lone 2x-size frame, due first,
    before the pair of the other size; with the deadlines the other way round, after it."""
    settings = [view_settings(engine, "full"), view_settings(engine, "full", 2 * W, 2 * H),
                view_settings(engine, "full")]
    s = Sessions(engine, settings)
    for k in range(len(settings)):  # each session's first frame (alone, in slices)
        asyncio.run(s.one(k, 0))
    for t, (deadlines, order) in enumerate((([3.0, 1.0, 2.0], [1, 2]), ([1.0, 3.0, 2.0], [2, 1])), start=1):
        batches.clear()
        asyncio.run(s.together(t, [0, 1, 2], deadlines=deadlines))
        assert batches == order


def test_a_batch_waits_for_the_sessions_yet_to_ask_within_its_deadline(engine, batches, monkeypatch):
    """With a wait, a frame asked for while the device is free waits for the other sessions' (here
    asked 0.2 s later) and is made with them, ending as soon as all have asked (the wait, far longer,
    would fail the test's timeout); without, or with its deadline passed, it is made alone first."""
    settings = [view_settings(engine, "full")] * 2
    s = Sessions(engine, settings)
    for k in range(len(settings)):  # each session's first frame (alone, in slices)
        asyncio.run(s.one(k, 0))

    async def staggered(t: int, deadline: float | None) -> list[int]:
        first = asyncio.ensure_future(s.one(0, t, deadline))
        await asyncio.sleep(0.2)
        await asyncio.wait_for(asyncio.gather(first, s.one(1, t)), 60)
        return list(batches)
    monkeypatch.setattr(engine, "batch_wait_s", 600.0)
    batches.clear()
    assert asyncio.run(staggered(1, time.monotonic() + 600)) == [2]
    batches.clear()
    assert asyncio.run(staggered(2, time.monotonic() - 1)) == [1, 1], "its deadline passed: no wait"
    monkeypatch.setattr(engine, "batch_wait_s", 0.0)
    batches.clear()
    assert asyncio.run(staggered(3, time.monotonic() + 600)) == [1, 1]


def test_a_nan_in_one_session_s_buffers_fails_that_session_only(engine, monkeypatch):
    """The reconstruction leaves a batch's input checks to read when each frame is coded (no wait for the
    device on its thread): one session whose rendered depth holds a NaN gets the check's error and then
    its next frame; its batch mates get their frames, equal to those made alone."""
    settings = [view_settings(engine, "reconstruct")] * SESSIONS
    expected = alone(engine, settings)
    s = Sessions(engine, settings)
    poisoned_camera = s.job(1, 1).camera
    render, render_views = type(s.renderer).render, type(s.renderer).render_views

    def poisoned(camera, out):
        if camera == poisoned_camera:
            out.depth = out.depth.clone()
            out.depth[0, 0] = float("nan")
        return out

    def render_with_nan(renderer, camera, request, *args, **kwargs):
        return poisoned(camera, render(renderer, camera, request, *args, **kwargs))

    def render_views_with_nan(renderer, frames):  # a batch's one launch (on GPUs)
        return [poisoned(camera, out) for (camera, _), out in zip(frames, render_views(renderer, frames))]
    monkeypatch.setattr(type(s.renderer), "render", render_with_nan)
    monkeypatch.setattr(type(s.renderer), "render_views", render_views_with_nan)
    got = [[] for _ in settings]
    for t in range(FRAMES):
        for k, frame in enumerate(asyncio.run(s.together(t, list(range(SESSIONS))))):
            got[k].append(frame)
        if t == 1:
            poisoned_camera = None
    assert isinstance(got[1][1], ValueError) and "NaN" in str(got[1][1]), got[1][1]
    assert same(got[0], expected[0]) and same(got[2], expected[2]), differences(got, expected)
    assert same(got[1][:1], expected[1][:1]) and isinstance(got[1][2], bytes), "the session goes on"


def test_each_frame_says_how_many_frames_were_made_with_it(engine):
    """An encoded frame carries its batch's size: 1 for a session's first frame (alone, in slices), the
    sessions asked together after."""
    settings = [view_settings(engine, "full")] * SESSIONS
    s = Sessions(engine, settings)

    async def batch_sizes(t: int) -> list[int]:
        release = threading.Event()
        busy = asyncio.ensure_future(engine.call(release.wait))

        async def one(k: int) -> int:
            encode = await engine.view_frame(s.frames[k], s.renderer, s.job(k, t), png)
            return (await encode()).batch
        tasks = [asyncio.ensure_future(one(k)) for k in range(SESSIONS)]
        await asyncio.sleep(0.05)
        release.set()
        await busy
        return await asyncio.gather(*tasks)
    assert asyncio.run(batch_sizes(0)) == [1] * SESSIONS
    assert asyncio.run(batch_sizes(1)) == [SESSIONS] * SESSIONS


def test_jpegs_of_a_batch_equal_those_coded_alone(engine, monkeypatch):
    """Frames coded as JPEGs: made together, their bytes equal those of the frames made and coded alone;
    where the device encodes JPEGs (nvJPEG), a batch's are coded in one encoder job, else each by its session."""
    calls: list[int] = []
    code_jpegs_in_turn = engine_module.code_jpegs_in_turn

    def counted(codes, quality, futures):
        calls.append(len(codes))
        return code_jpegs_in_turn(codes, quality, futures)
    monkeypatch.setattr(engine_module, "code_jpegs_in_turn", counted)
    settings = [view_settings(engine, "full")] * SESSIONS
    expected = alone(engine, settings, jpeg=True)
    calls.clear()
    assert together(engine, settings, jpeg=True) == expected
    assert calls == ([SESSIONS] * (FRAMES - 1) if device_jpeg(engine.device) else [])


@pytest.mark.skipif(DEVICE != "cuda", reason="CUDA streams: ISOSR_TEST_DEVICE=cuda, on the GPU machine")
def test_the_device_thread_works_on_a_cuda_stream_of_its_own(engine):
    """Its work never shares the legacy default stream, which nvJPEG synchronizes before each image
    (an encoder would otherwise wait for every batch the device thread issued after its frame's)."""
    current = asyncio.run(engine.call(lambda: torch.cuda.current_stream(engine.device)))
    assert current == engine.stream != torch.cuda.default_stream(engine.device)


@pytest.mark.parametrize("width, height", [(W, H), (W - 1, H - 1)])
def test_a_video_frame_s_planes_are_made_where_its_colors_are(engine, width, height):
    """On a GPU the device thread converts a video frame to its encoder's I420 planes (odd sides padded to the
    coded size) and copies them to pinned host memory before the frame's event, so the video encoder thread makes
    no device call; on a CPU the encoder converts the colors itself (FFmpeg's swscale) and gets no planes."""
    s, given = Sessions(engine, [view_settings(engine, "full", width, height)]), []

    async def one() -> None:
        encode = await engine.view_frame(s.frames[0], s.renderer, s.job(0, 0),
                                         lambda rgb, i420: given.append((rgb, i420)) or png(rgb), video="h264")
        await encode()
    asyncio.run(one())
    rgb, i420 = given[0]
    if not rgb.is_cuda:
        assert i420 is None
        return
    assert i420.device.type == "cpu" and i420.is_pinned()
    assert torch.equal(i420, device_i420(rgb, *coded_size("h264", width, height)).cpu())


def test_a_batch_s_jpegs_are_released_one_by_one(monkeypatch):
    """A batch's JPEGs are coded in turn, each frame's bytes released as soon as they are made (not when
    its batch's last is), and a frame that fails to code fails alone."""
    futures = [Future() for _ in range(3)]
    released: list[list[bool]] = []

    def code(rgbs, quality):
        released.append([f.done() for f in futures])
        if len(released) == 2:
            raise RuntimeError("nvJPEG refused the frame")
        return [bytes([len(released)])]
    monkeypatch.setattr(engine_module, "encode_jpegs", code)
    codes = [ImageCodes(torch.zeros(4, 4, 3, dtype=torch.uint8), None, lambda: None) for _ in futures]
    engine_module.code_jpegs_in_turn(codes, JPEG_QUALITY, futures)
    assert released == [[False, False, False], [True, False, False], [True, True, False]]
    assert futures[0].result() == b"\x01" and futures[2].result() == b"\x03"
    assert "refused" in str(futures[1].exception())
