"""Native voxel types on the device, streaming loads, and the sparse brick pool (isosr_render.volume,
isosr_render.scan, isosr_render.brick_pool).

Tolerances of native-type rendering against float32 (same original values): the kernels
interpolate ``voxel - d0`` and scale once, float32 normalizes each voxel first; both round
in float32, so depth may differ by 1e-5 world units and normals by 1e-4, and hit masks may
differ at a few silhouette pixels (none measured here; the test allows 3). Sparse and dense
images are identical on CPUs; on CUDA they are separate kernel overloads, which the compiler
may contract into fused multiply-adds differently (:func:`assert_same_render`).
``ISOSR_TEST_DEVICE=cuda`` runs the renders on the GPU.
"""

from __future__ import annotations

import contextlib
from dataclasses import fields

import numpy as np
import pytest
from conftest import DEVICE

from isosr_render import Renderer, RenderRequest, Volume, orbit, voxels
from isosr_render.brick_pool import DeviceMemoryError, coarsen
from isosr_render.procedural import SpheresSource
from isosr_render.scan import BRICK, Scan, scan
from isosr_render.voxels import ArraySource

OUTPUTS = ("mask", "normal", "depth", "ao")
CAMERA = orbit(30, 20, 1.8)


def _render(volume: Volume, iso: float, **kwargs) -> dict[str, np.ndarray]:
    request = RenderRequest(64, 48, iso=iso, outputs=OUTPUTS, ao_samples=8, ao_radius=0.05)
    return Renderer(volume, DEVICE, threads=2, **kwargs).render(CAMERA, request).to_numpy()


def assert_same_render(got: dict[str, np.ndarray], want: dict[str, np.ndarray], names: tuple[str, ...]) -> None:
    """Identical on CPUs. On CUDA the dense and sparse kernels round in the last bits apart (FMA
    contraction differs between two compiled overloads): a hit may flip at a grazing silhouette
    pixel (at most 3), and values agree to 1e-4 where both images hit (AO: an AO ray may flip,
    1 / rays, on at most 1% of the pixels)."""
    if DEVICE == "cpu":
        for name in names:
            np.testing.assert_array_equal(got[name], want[name], err_msg=name)
        return
    both = (got["mask"] == 1) & (want["mask"] == 1)
    assert (got["mask"] != want["mask"]).sum() <= 3
    for name in names:
        diff = np.abs(got[name] - want[name])[both]
        if name == "ao":
            assert (diff > 1e-4).mean() <= 0.01, name
        else:
            assert diff.max() <= 1e-4, name


def _original(source) -> np.ndarray:
    """A source's original values (rescale applied), float64."""
    slope, intercept = source.rescale
    return source.read(*(slice(0, n) for n in source.shape)).astype(np.float64) * slope + intercept


class _CountingSource(SpheresSource):
    """Records the largest box read and the bytes read."""

    largest = total = 0

    def read(self, x, y, z):
        values = super().read(x, y, z)
        self.largest = max(self.largest, values.nbytes)
        self.total += values.nbytes
        return values


@pytest.mark.parametrize("dtype, storage", [("uint8", "uint8"), ("uint16", "uint16"), ("int16", "uint16")])
def test_native_types_stay_narrow_and_render_like_float32(dtype, storage):
    source = SpheresSource((40, 36, 33), dtype, seed=1)
    native = Volume.from_source(source)
    reference = Volume.from_array(_original(source))
    assert native.storage == np.dtype(storage) and native.device_bytes == 40 * 36 * 33 * native.storage.itemsize
    assert native.value_range == pytest.approx(reference.value_range, abs=1e-12)
    np.testing.assert_allclose(native.data, reference.data, atol=1e-6)
    iso = native.normalized_iso(0.0)
    got, want = _render(native, iso), _render(reference, iso)
    assert (got["mask"] != want["mask"]).sum() <= 3 and want["mask"].sum() > 100
    hit = (got["mask"] > 0) & (want["mask"] > 0)
    np.testing.assert_allclose(got["depth"][hit], want["depth"][hit], atol=1e-5)
    np.testing.assert_allclose(got["normal"][hit], want["normal"][hit], atol=1e-4)
    assert (np.abs(got["ao"] - want["ao"]) > 1e-6).sum() <= 3


def test_int16_rescale_and_histogram_are_exact():
    values = np.random.default_rng(0).integers(-1024, 3000, (12, 10, 9)).astype(np.int16)
    volume = Volume.from_source(ArraySource(values, rescale=(0.5, -100.0)))
    original = values * 0.5 - 100.0
    assert volume.value_range == (original.min(), original.max())
    np.testing.assert_allclose(volume.data, (original - original.min()) / np.ptp(original), atol=1e-6)
    expect, _ = np.histogram(Volume.from_array(original).data, bins=64, range=(0.0, 1.0))
    counts = volume.histogram(64)
    assert counts.sum() == values.size and np.abs(counts - expect).sum() <= 4  # bin edges round differently


def test_bricks_bound_their_voxels_with_overlap_and_coarsen():
    values = np.random.default_rng(1).random((27, 18, 9)).astype(np.float32)
    values[3, 4, 5] = np.nan  # counts as the minimum
    with pytest.warns(UserWarning, match="1 NaN"):
        volume = Volume.from_array(values)
    data = volume.data
    for factor in (1, 2):
        b = BRICK * factor
        bricks = coarsen(volume.bricks, factor)
        assert bricks.shape[:3] == tuple(-(-(n - 1) // b) for n in values.shape)
        for i, j, k in np.ndindex(bricks.shape[:3]):
            block = data[i * b: i * b + b + 1, j * b: j * b + b + 1, k * b: k * b + b + 1]
            assert tuple(bricks[i, j, k]) == (block.min(), block.max())


@pytest.mark.parametrize("dtype", ["float32", "int16"])
def test_bricks_range_and_counts_match_a_naive_reference_across_boxes(monkeypatch, dtype):
    monkeypatch.setattr(voxels, "BOX_BYTES", 4096)  # many boxes, cut at odd chunks
    rng = np.random.default_rng(2)
    stored = rng.integers(-32768, 32768, (29, 21, 19)).astype(dtype)
    stored[0, 0, 0], stored[28, 20, 18] = -32768, 32767  # the type's ends, for the counts
    if dtype == "float32":
        stored[3, 4, 5] = stored[9, 9, 9] = np.nan  # the minimum
        stored[20, 1, 2], stored[1, 20, 2] = np.inf, -np.inf
    slope, intercept = -0.25, 10.0
    with pytest.warns(UserWarning) if dtype == "float32" else contextlib.nullcontext():
        volume = Volume.from_source(ArraySource(stored, rescale=(slope, intercept), chunks=(5, 7, 9)))
    original = stored.astype(np.float64) * slope + intercept
    finite = original[np.isfinite(original)]
    lo, hi = finite.min(), finite.max()
    original = np.nan_to_num(original, nan=lo, posinf=hi, neginf=lo)
    assert volume.value_range == (lo, hi)
    normalized = (original - lo) / (hi - lo)
    for i, j, k in np.ndindex(volume.bricks.shape[:3]):
        block = normalized[i * BRICK: i * BRICK + BRICK + 1, j * BRICK: j * BRICK + BRICK + 1,
                           k * BRICK: k * BRICK + BRICK + 1]
        np.testing.assert_allclose(volume.bricks[i, j, k], (block.min(), block.max()), rtol=0, atol=1e-6)
    if dtype == "int16":
        np.testing.assert_array_equal(volume.counts, np.bincount(stored.ravel().astype(np.int64) + 32768, minlength=1 << 16))


@pytest.mark.parametrize("dtype", ["uint8", "int16", "float32"])
@pytest.mark.parametrize("shape", [(32, 24, 16), (29, 21, 19)])
def test_a_fortran_ordered_box_scans_as_its_c_ordered_copy(dtype, shape):
    """NIfTI's arrays are Fortran-ordered: summarized through their transpose, every field of the scan
    equals the C-ordered copy's (padded odd sizes and non-finite values included)."""
    stored = np.random.default_rng(4).integers(-100, 100, shape).astype(dtype)
    if dtype == "float32":
        stored[3, 4, 5], stored[20, 1, 2] = np.nan, np.inf
    fortran = scan(ArraySource(np.asfortranarray(stored)))
    c_order = scan(ArraySource(np.ascontiguousarray(stored)))
    for field in fields(Scan):
        got, want = getattr(fortran, field.name), getattr(c_order, field.name)
        if isinstance(want, list):
            for g, w in zip(got, want, strict=True):
                np.testing.assert_array_equal(g, w, err_msg=field.name)
        else:
            np.testing.assert_array_equal(got, want, err_msg=field.name)


@pytest.mark.parametrize("values", ["spread", "constant", "huge"])
def test_float32_normalized_on_the_device_equals_the_host_and_a_float64_reference(values):
    """float32 travels as stored and is normalized where it lands (where its span fits float32): the device's
    voxels equal the host's normalization of the same box bit for bit and a float64 reference within float32's
    rounding; non-finite voxels at the range's ends. Past float32's span, the host normalizes (in float64)."""
    rng = np.random.default_rng(5)
    stored = {"spread": rng.normal(1e3, 50.0, (21, 17, 13)), "constant": np.full((9, 9, 9), 3.0),
              "huge": rng.uniform(-3e38, 3e38, (9, 9, 9))}[values].astype(np.float32)
    if values == "spread":
        stored[1, 2, 3], stored[4, 4, 4], stored[5, 5, 5] = np.nan, np.inf, -np.inf
    with pytest.warns(UserWarning) if values == "spread" else contextlib.nullcontext():
        volume = Volume.from_source(ArraySource(stored))
    assert volume.raw_float32 == (values != "huge")
    renderer = Renderer(volume, DEVICE)
    on_device = renderer.voxels.numpy()
    np.testing.assert_array_equal(on_device, volume.device_box(stored))
    lo, hi = volume.value_range
    reference = np.nan_to_num(stored.astype(np.float64), nan=lo, posinf=hi, neginf=lo)
    reference = np.clip((reference - lo) / (hi - lo) if hi > lo else 0.0 * reference, 0.0, 1.0)
    np.testing.assert_allclose(on_device, reference, rtol=0, atol=2e-6)


def test_loading_reads_box_by_box(monkeypatch):
    monkeypatch.setattr(voxels, "BOX_BYTES", 100_000)
    source = _CountingSource((96, 80, 72), "uint16", chunks=(32, 32, 32))
    volume = Volume.from_source(source)
    assert source.largest == 32 * 32 * 32 * 2  # one chunk: the smallest box of whole chunks
    source.largest = 0
    renderer = Renderer(volume, DEVICE, threads=1)
    assert source.largest == 32 * 32 * 32 * 2 and renderer.memory().mode == "dense"
    assert source.total == 2 * volume.device_bytes  # the scan, then the upload


def test_load_scans_and_uploads_integers_in_one_read():
    source = _CountingSource((70, 64, 50), "int16", seed=4)
    renderer = Renderer.load(source, DEVICE, threads=2)
    assert source.total == renderer.volume.device_bytes and renderer.memory().mode == "dense"
    request = RenderRequest(48, 40, iso=renderer.volume.normalized_iso(0.0), outputs=("mask", "depth"))
    got = renderer.render(CAMERA, request).to_numpy()
    want = Renderer(Volume.from_source(source), DEVICE, threads=2).render(CAMERA, request).to_numpy()
    for name in ("mask", "depth"):
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)


def test_sparse_volume_renders_like_dense_and_pages_only_the_difference():
    volume = Volume.from_source(SpheresSource((96, 88, 80), "uint16", seed=2))
    limit = volume.device_bytes * 3 // 4
    renderer = Renderer(volume, DEVICE, threads=2, max_device_bytes=limit)
    isos = [volume.normalized_iso(v) for v in (0.0, 0.02)]
    for iso in isos:
        request = RenderRequest(64, 48, iso=iso, outputs=OUTPUTS, ao_samples=8, ao_radius=0.05)
        got = renderer.render(CAMERA, request).to_numpy()
        want = _render(volume, iso)
        assert want["mask"].sum() > 100
        assert_same_render(got, want, OUTPUTS)
    stats = renderer.memory()
    assert stats.mode == "sparse" and stats.resident_bytes <= limit < stats.dense_bytes
    assert stats.page_ins == 2 and 0 < stats.bricks_needed < stats.bricks_total
    first = stats.bricks_paged
    renderer.render(CAMERA, RenderRequest(16, 16, iso=isos[0]))  # back to the first iso: all resident
    assert renderer.memory().bricks_paged == first


def test_sparse_pool_evicts_old_bricks_and_refuses_an_iso_that_cannot_fit():
    volume = Volume.from_source(SpheresSource((96, 88, 80), "uint8", seed=3))
    isos = [volume.normalized_iso(v) for v in (-0.02, 0.05)]
    probe = Renderer(volume, DEVICE, threads=1, max_device_bytes=volume.device_bytes - 1)
    needed = [(probe.grid(iso), probe.memory().bricks_needed)[1] for iso in isos]
    limit = max(needed) * probe.pool.brick_bytes  # room for one iso's bricks, not both
    renderer = Renderer(volume, DEVICE, threads=2, max_device_bytes=limit)
    for iso in isos + isos[:1]:
        request = RenderRequest(48, 40, iso=iso, outputs=("mask", "depth"))
        got = renderer.render(CAMERA, request).to_numpy()
        want = Renderer(volume, DEVICE, threads=2).render(CAMERA, request).to_numpy()
        assert_same_render(got, want, ("mask", "depth"))
    assert renderer.memory().resident_bytes <= limit
    tiny = Renderer(volume, DEVICE, threads=1, max_device_bytes=10 * probe.pool.brick_bytes)
    with pytest.raises(DeviceMemoryError, match=r"needs \d+ bricks .* raise max_device_bytes"):
        tiny.grid(isos[0])
