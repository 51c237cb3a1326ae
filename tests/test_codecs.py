"""The wire codecs: arrays (validation, bounded zlib inflation) and the buffers coding (the device
encoder against a float64 definition of the codes, and the round trip's stated tolerances).
``ISOSR_TEST_DEVICE=cuda`` runs the encoder on the GPU."""

from __future__ import annotations

import math
import tracemalloc
import zlib

import numpy as np
import pytest
import torch

from conftest import DEVICE
from isosr_render import FrameBuffers
from isosr_server import protocol as P
from isosr_server.codecs.arrays import ArrayTooBig, WireArray, decode_array, encode_array
from isosr_server.codecs.buffers import decode_view_buffers
from isosr_server.codecs.buffers_device import encode_view_buffers
from isosr_render.image_codec import decode_image
from isosr_server.encoding import device_jpeg, encode_jpegs

LIMITS = P.Limits()
BOUNDS = LIMITS.array_bounds()


# ---- arrays ---------------------------------------------------------------------------------


def _wire(dtype="float32", shape=(4, 5), data=None, compressed=False) -> WireArray:
    data = bytes(4 * math.prod(shape)) if data is None else data
    return WireArray(dtype, list(shape), data, compressed)


@pytest.mark.parametrize("dtype", ["float16", "float32", "uint8", "uint16"])
@pytest.mark.parametrize("compress", [False, True])
def test_arrays_round_trip_exactly(dtype, compress):
    a = (np.arange(60).reshape(3, 4, 5) % 7).astype(dtype)
    wire = encode_array(a, compress)
    assert wire.zlib == compress and wire.shape == [3, 4, 5]
    back = decode_array(wire, *BOUNDS)
    assert back.dtype == a.dtype and np.array_equal(back, a)


def test_arrays_of_other_dtypes_cannot_travel():
    for dtype in ("float64", "int32", ">f4"):
        with pytest.raises(ValueError, match="cannot travel"):
            encode_array(np.zeros(3, dtype))


@pytest.mark.parametrize("wire, words", [
    (_wire("uint8", data=bytes(20)), "dtype must be one of float16, float32"),
    (_wire(data=bytes(79)), "79 data bytes, but float32 \\(4, 5\\) needs 80"),
    (_wire(shape=(5, 4)), r"shape must be \(4, 5\), got \(5, 4\)"),
    (_wire(shape=(4, 5, 1)), r"shape must be \(4, 5\)"),
    (_wire(data=np.full(20, np.nan, np.float32).tobytes()), "NaN or Inf"),
    (_wire(data=np.full(20, -np.inf, np.float32).tobytes()), "NaN or Inf"),
    (_wire(data=b"garbage", compressed=True), "corrupt zlib"),
    (_wire(data=zlib.compress(bytes(81)), compressed=True), "inflates past the 80 bytes"),
    (_wire(data=zlib.compress(bytes(79)), compressed=True), "79 data bytes"),
])
def test_invalid_arrays_name_the_problem(wire, words):
    with pytest.raises(ValueError, match=words):
        decode_array(wire, *BOUNDS, ("float16", "float32"), (4, 5))


def test_declared_size_is_refused_before_inflating():
    """Garbage data would fail to inflate; the declared shape is refused first."""
    for shape, words in (((1000, 1000), "1000000 elements exceeds"), ((50, 101), "sides <= 100")):
        with pytest.raises(ArrayTooBig, match=words):
            decode_array(_wire(shape=shape, data=b"garbage", compressed=True), 100, 100)
    assert not issubclass(ArrayTooBig, ValueError)  # passes msgspec's decoding unwrapped


@pytest.fixture(scope="module")
def bomb() -> bytes:
    """300 MiB of zeros as one zlib stream of about 0.3 MB."""
    c, chunk = zlib.compressobj(9), bytes(2**20)
    data = b"".join([c.compress(chunk) for _ in range(300)] + [c.flush()])
    assert len(data) < 400_000
    return data


def test_zlib_bomb_inflates_no_further_than_the_declared_shape(bomb):
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match="inflates past the 80 bytes"):
            decode_array(_wire(data=bomb, compressed=True), *BOUNDS)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2**20, f"{peak} bytes allocated while refusing an 80-byte array"


def test_zlib_trailing_and_truncated_streams_are_refused():
    stream = zlib.compress(bytes(80))
    with pytest.raises(ValueError, match="3 bytes after the zlib stream"):
        decode_array(_wire(data=stream + b"xyz", compressed=True), *BOUNDS)
    with pytest.raises(ValueError, match="after the zlib stream"):
        decode_array(_wire(data=stream + stream, compressed=True), *BOUNDS)
    for cut in (1, 4, len(stream) // 2):
        with pytest.raises(ValueError, match="truncated zlib|corrupt zlib"):
            decode_array(_wire(data=stream[:-cut], compressed=True), *BOUNDS)
    assert np.array_equal(decode_array(_wire(data=stream, compressed=True), *BOUNDS), np.zeros((4, 5)))


# ---- buffers coding: the device encoder against the float64 definition ------------------------


def reference_codes(mask, normal, depth, flow) -> dict:
    """The buffers coding's codes in float64 numpy: the definition the device encoder must meet
    (within one code unit).

    Shape:
        mask, depth: (h, w). normal: (h, w, 3). flow: (h, w, 2). float32 numpy.
    """
    covered = mask > 0
    out = {"mask": np.where(covered, np.maximum(np.round(np.clip(mask, 0, 1) * 255), 1), 0).astype(np.uint8)}
    n = normal.astype(np.float64)
    n = n / np.maximum(np.abs(n).sum(-1, keepdims=True), 1e-30)
    xy = n[..., :2]
    folded = (1.0 - np.abs(xy[..., ::-1])) * np.where(xy >= 0, 1.0, -1.0)
    xy = np.where(n[..., 2:3] < 0, folded, xy)
    code = np.round((np.clip(xy, -1, 1) * 0.5 + 0.5) * 65535)
    out["normal"] = np.where(covered[..., None], code, 0).astype(np.uint16)
    hits = depth[covered].astype(np.float64)
    near, far = (hits.min(), hits.max()) if hits.size else (0.0, 0.0)
    scale = 65535.0 / (far - near) if far > near else 0.0
    out["depth"] = np.where(covered, np.round((depth.astype(np.float64) - near) * scale), 0).astype(np.uint16)
    out["depth_range"] = (near, far)
    out["flow"] = np.clip(flow, -P.FLOW_CLIP, P.FLOW_CLIP).astype(np.float16)
    return out


def random_frame(h=37, w=53, seed=0):
    """float32 numpy mask, normal, depth, flow with partial coverage, both hemispheres and a flow beyond the clip."""
    rng = np.random.default_rng(seed)
    mask = (rng.random((h, w)) > 0.3).astype(np.float32)
    mask.flat[:5] = [0.001, 0.3, 0.5, 0.999, 1.0][: mask.size]  # coverage values, one tiny
    n = rng.standard_normal((h, w, 3))
    n[..., 2] = np.where(rng.random((h, w)) > 0.2, np.abs(n[..., 2]), -np.abs(n[..., 2]))  # some z < 0
    normal = (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32) * (mask > 0)[..., None]
    depth = (rng.uniform(1.2, 2.4, (h, w)) * (mask > 0)).astype(np.float32)
    flow = rng.uniform(-40, 40, (h, w, 2)).astype(np.float32)
    flow.flat[:2] = (1e6, -1e6)  # clipped to FLOW_CLIP
    return mask, normal, depth, flow


def axis_frame():
    """Every axis direction and the diagonals of both hemispheres, one pixel each, equal depths."""
    dirs = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1), (1, 1, 1), (-1, -1, -1),
            (1, -1, -1), (-1, 1, -1), (0, 1e-7, -1), (-0.0, 0, -1), (3, 4, 0)]
    normal = np.array(dirs, np.float64)
    normal = (normal / np.linalg.norm(normal, axis=-1, keepdims=True)).astype(np.float32)[None]
    ones = np.ones(normal.shape[:2], np.float32)
    return ones, normal, ones * 1.7, np.zeros(normal.shape[:2] + (2,), np.float32)


def _cases():
    empty = np.zeros((4, 6), np.float32)
    return {
        "random": random_frame(),
        "random_large": random_frame(270, 480, seed=3),
        "axes": axis_frame(),
        "zero_mask": (empty, np.zeros((4, 6, 3), np.float32), empty, np.zeros((4, 6, 2), np.float32)),
        "single_pixel": tuple(a[:1, :1] for a in random_frame(seed=5)),
        "single_pixel_empty": tuple(a[:1, :1] * 0 for a in random_frame(seed=5)),
        "depth_all_equal": (np.ones((5, 7), np.float32), random_frame(5, 7)[1] + np.float32([0, 0, 1]),
                            np.full((5, 7), 2.5, np.float32), np.full((5, 7, 2), 7e4, np.float32)),
        "flow_beyond_clip": (*random_frame(6, 8, seed=2)[:3], np.float32([-1e30, 6e4, 6.0001e4, -7e4])[
            np.arange(96) % 4].reshape(6, 8, 2)),
    }


def device_codes(mask, normal, depth, flow) -> dict:
    """The device encoder's codes (decoded from its wire arrays, which carry them exactly)."""
    frame = FrameBuffers(**{n: torch.from_numpy(a).to(DEVICE) for n, a in
                            dict(mask=mask, normal=normal, depth=depth, flow=flow).items()})
    wire = encode_view_buffers(frame)
    codes = {n: decode_array(getattr(wire, n), *BOUNDS) for n in ("mask", "normal", "depth", "flow")}
    return codes | {"depth_range": wire.depth_range}


@pytest.mark.parametrize("case", list(_cases()))
def test_device_codes_equal_the_float64_definition(case):
    arrays = _cases()[case]
    got, want = device_codes(*arrays), reference_codes(*arrays)
    for name in ("mask", "normal", "depth"):
        assert got[name].dtype == want[name].dtype and got[name].shape == want[name].shape, name
        diff = np.abs(got[name].astype(np.int64) - want[name].astype(np.int64))
        assert diff.max(initial=0) <= 1, f"{name}: {diff.max()} code units off"
    assert np.array_equal(got["mask"] > 0, arrays[0] > 0), "coverage survives exactly"
    assert np.array_equal(got["flow"], want["flow"])
    assert got["depth_range"] == pytest.approx(want["depth_range"], abs=0)


def test_device_codes_mostly_equal_exactly():
    """Float32 changes a code only where the float64 value lies within rounding of a code boundary."""
    arrays = random_frame(270, 480, seed=4)
    got, want = device_codes(*arrays), reference_codes(*arrays)
    for name in ("mask", "normal", "depth"):
        assert (got[name] != want[name]).mean() < 1e-2, name


# ---- buffers coding: round trip ----------------------------------------------------------------


def roundtrip(mask, normal, depth, flow) -> dict:
    """Encode on the device, travel in a frame message, decode with numpy."""
    frame = FrameBuffers(mask=torch.from_numpy(mask), normal=None if normal is None else torch.from_numpy(normal),
                         depth=None if depth is None else torch.from_numpy(depth),
                         flow=None if flow is None else torch.from_numpy(flow))
    buffers = encode_view_buffers(frame)
    msg = P.FrameMsg(seq=0, ack=-1, mode="buffers", method="buffers", width=4 * mask.shape[1],
                     height=4 * mask.shape[0], encoding="buffers", times={}, nbytes=buffers.nbytes, buffers=buffers)
    got = P.parse(P.encode(msg), LIMITS, (P.FrameMsg,))
    return decode_view_buffers(got.buffers, LIMITS)


def test_buffers_coding_within_stated_tolerances():
    mask, normal, depth, flow = random_frame()
    out = roundtrip(mask, normal, depth, flow)
    covered = mask > 0
    assert np.array_equal(out["mask"] > 0, covered)  # "no hit" survives exactly, even at coverage 0.001
    assert np.abs(out["mask"] - mask)[mask >= 1 / 255].max() <= 0.5 / 255 + 1e-7
    cos = (out["normal"][covered] * normal[covered]).sum(-1)
    assert np.arccos(np.clip(cos, -1, 1)).max() < 1e-3
    assert not out["normal"][~covered].any() and not out["depth"][~covered].any()
    near, far = depth[covered].min(), depth[covered].max()
    assert np.abs(out["depth"] - depth).max() <= (far - near) / 131070 + 1e-6
    clipped = np.clip(flow, -P.FLOW_CLIP, P.FLOW_CLIP)
    assert np.all(np.abs(out["flow"] - clipped) <= np.abs(clipped) * 2.0**-11 + 1e-7)
    assert all(out[k].dtype == np.float32 for k in out)


def test_buffers_coding_edge_cases():
    empty = np.zeros((4, 6), np.float32)
    out = roundtrip(empty, np.zeros((4, 6, 3), np.float32), empty, None)
    assert not out["mask"].any() and not out["depth"].any() and "flow" not in out
    flat = np.ones((4, 6), np.float32)  # every hit at one depth: near == far
    n = np.tile(np.float32([0, 0, 1]), (4, 6, 1))
    out = roundtrip(flat, n, flat * 1.5, None)
    np.testing.assert_allclose(out["depth"], 1.5)
    np.testing.assert_allclose(out["normal"], n, atol=1e-4)
    assert sorted(roundtrip(flat, None, None, None)) == ["mask"]


def test_buffers_wire_is_checked():
    flat = np.ones((4, 6), np.float32)
    buffers = encode_view_buffers(FrameBuffers(mask=torch.from_numpy(flat), depth=torch.from_numpy(flat)))
    with pytest.raises(P.ProtocolError, match="near <= far"):
        P.ViewBuffers(buffers.mask, depth=buffers.depth, depth_range=(2.0, 1.0))
    with pytest.raises(P.ProtocolError, match="depth and depth_range travel together"):
        P.ViewBuffers(buffers.mask, depth=buffers.depth)
    for wire, words in ((P.ViewBuffers(buffers.depth), "buffers.mask: dtype must be one of uint8"),
                        (P.ViewBuffers(buffers.mask, normal=buffers.mask), r"buffers.normal: dtype"),
                        (P.ViewBuffers(buffers.mask, flow=encode_array(np.zeros((4, 5, 2), np.float16))),
                         r"buffers.flow: shape must be \(4, 6, 2\)")):
        with pytest.raises(P.ProtocolError, match=words) as e:
            decode_view_buffers(wire, LIMITS)
        assert e.value.close_code == P.CLOSE_BAD_MESSAGE
    with pytest.raises(P.ProtocolError, match="exceeds the limits") as e:
        decode_view_buffers(buffers, P.Limits(max_pixels=5, max_side=100))
    assert e.value.close_code == P.CLOSE_TOO_BIG


def test_buffers_coding_is_smaller_than_float32():
    mask, normal, depth, flow = random_frame(96, 128, seed=1)
    mask[:, :64] = 0  # half the frame empty, as around an object
    normal *= (mask > 0)[..., None]
    frame = FrameBuffers(**{n: torch.from_numpy(a) for n, a in dict(mask=mask, normal=normal, depth=depth,
                                                                    flow=flow).items()})
    coded = len(P.encode(encode_view_buffers(frame)))
    assert coded < 0.5 * sum(a.nbytes for a in (mask, normal, depth, flow))


@pytest.mark.skipif(not device_jpeg(DEVICE), reason="nvJPEG: ISOSR_TEST_DEVICE=cuda with torchvision, on the GPU machine")
def test_jpegs_coded_together_equal_those_coded_alone():
    """nvJPEG over a list of frames of mixed sizes: each frame's bytes as its own call gives them, and the
    image within JPEG's error of the frame."""
    g = torch.Generator().manual_seed(3)
    smooth = [torch.nn.functional.interpolate(torch.rand(1, 3, h // 8, w // 8, generator=g), size=(h, w),
                                              mode="bilinear")[0].permute(1, 2, 0) for h, w in ((64, 96), (48, 48))]
    frames = [(255 * f).round().to(torch.uint8).to(DEVICE) for f in smooth + smooth[:1]]
    together = encode_jpegs(frames, 90)
    assert together == [encode_jpegs([f], 90)[0] for f in frames]
    for data, frame in zip(together, frames):
        image = decode_image(data)
        assert image.shape == tuple(frame.shape)
        assert np.abs(image.astype(float) - frame.cpu().numpy()).mean() < 3.0
