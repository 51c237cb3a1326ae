"""Tests for isosr_render.volume_io: real shared volumes, [x, y, z] orientation, broken files."""

from __future__ import annotations

import gzip
import json
import os
from pathlib import Path

import nibabel as nib
import nrrd
import numpy as np
import pytest

from isosr_render.volume import VolumeError
from isosr_render.volume_io import load_volume

SHARED = Path(os.environ.get("ISOSR_SHARED_VOLUMES",
                             Path(__file__).resolve().parents[1].parent / "shared" / "volumes"))
ENTRIES = json.loads((SHARED / "volumes.json").read_text()) if (SHARED / "volumes.json").is_file() else []

# An asymmetric pattern: every voxel differs, so any axis swap or flip changes the array.
SHAPE = (5, 4, 3)
PATTERN = np.arange(np.prod(SHAPE), dtype=np.int16).reshape(SHAPE) * 7 - 20


def _expected(values: np.ndarray) -> np.ndarray:
    """The normalized array ``load_volume`` should return for ``values``."""
    values = values.astype(np.float64)
    return ((values - values.min()) / (values.max() - values.min())).astype(np.float32)


def _assert_pattern(path: Path, spacing=(1.0, 1.0, 1.0)) -> None:
    """Load ``path`` and check it holds PATTERN indexed [x, y, z] with ``spacing``."""
    volume = load_volume(path)
    assert volume.shape == SHAPE
    assert volume.name == path.name
    np.testing.assert_allclose(volume.data, _expected(PATTERN), atol=1e-6)
    assert volume.value_range == (float(PATTERN.min()), float(PATTERN.max()))
    assert volume.spacing == pytest.approx(spacing)


def _write_multifile_nhdr(folder: Path, *, encoding: str = "raw", endian: str = "little",
                          first: int = 1, step: int = 1, subdim: str = "") -> Path:
    """Write PATTERN as one file per z slice (``slice.%03d``) and a detached header over them."""
    dtype = np.dtype(np.int16).newbyteorder("<" if endian == "little" else ">")
    for k in range(SHAPE[2]):
        data = PATTERN[:, :, k].astype(dtype).tobytes(order="F")  # x-fastest
        if encoding == "gzip":
            data = gzip.compress(data)
        (folder / f"slice.{first + k * step:03d}").write_bytes(data)
    last = first + (SHAPE[2] - 1) * step
    header = folder / "vol.nhdr"
    header.write_text("NRRD0004\ndimension: 3\ntype: short\n"
                      f"sizes: {' '.join(map(str, SHAPE))}\nspacings: 0.5 0.75 2\n"
                      f"endian: {endian}\nencoding: {encoding}\n"
                      f"data file: slice.%03d {first} {last} {step} {subdim}\n")
    return header


def _write_dat(folder: Path, data: bytes, fmt: str = "USHORT", resolution=SHAPE) -> Path:
    """Write a ``.raw`` file and a ``.dat`` header that names it."""
    (folder / "vol.raw").write_bytes(data)
    header = folder / "vol.dat"
    header.write_text(f"ObjectFileName: vol.raw\nResolution: {' '.join(map(str, resolution))}\n"
                      f"SliceThickness: 1.5 1 2.5\nFormat: {fmt}\n")
    return header


def _raises(path: Path, *words: str) -> VolumeError:
    """Assert ``load_volume(path)`` raises a VolumeError naming the file and every word."""
    with pytest.raises(VolumeError) as info:
        load_volume(path)
    message = str(info.value)
    assert path.name in message
    for word in words:
        assert word.lower() in message.lower(), message
    return info.value


# --- the real volumes of ../shared/volumes --------------------------------------------------------

@pytest.mark.parametrize("entry", ENTRIES or [None], ids=[e["name"] for e in ENTRIES] or ["absent"])
def test_shared_volume(entry):
    if entry is None:
        pytest.skip(f"../shared/volumes not found: {SHARED} (set ISOSR_SHARED_VOLUMES)")
    volume = load_volume(SHARED / entry["file"])
    assert volume.shape == tuple(entry["shape_xyz"])
    assert volume.spacing == pytest.approx(entry["spacing_xyz"], rel=1e-6)
    assert volume.value_range == pytest.approx(entry["value_range"])
    assert volume.data.dtype == np.float32
    assert volume.data.min() >= 0.0 and volume.data.max() <= 1.0


# --- orientation: every format yields data[x, y, z] ------------------------------------------------

@pytest.mark.parametrize("gzipped", [False, True])
def test_named_raw_orientation(tmp_path, gzipped):
    data = PATTERN.astype("<i2").tobytes(order="F")  # x-fastest on disk
    path = tmp_path / ("vol_5x4x3_int16.raw" + (".gz" if gzipped else ""))
    path.write_bytes(gzip.compress(data) if gzipped else data)
    _assert_pattern(path)


def test_dat_orientation(tmp_path):
    values = (PATTERN + 100).astype(np.uint16)  # USHORT: shift to non-negative
    volume = load_volume(_write_dat(tmp_path, values.astype("<u2").tobytes(order="F")))
    np.testing.assert_allclose(volume.data, _expected(values), atol=1e-6)
    assert volume.spacing == (1.5, 1.0, 2.5)


def test_nrrd_orientation(tmp_path):
    path = tmp_path / "vol.nrrd"
    nrrd.write(str(path), PATTERN, {"spacings": [0.5, 0.75, 2.0]})
    _assert_pattern(path, (0.5, 0.75, 2.0))


def test_nrrd_spacing_from_space_directions(tmp_path):
    # Rows are the axes' vectors: axis x along world y with length 2, axis y along world x with 3.
    path = tmp_path / "vol.nrrd"
    directions = np.array([[0.0, 2.0, 0.0], [3.0, 0.0, 0.0], [0.0, 0.0, 4.0]])
    nrrd.write(str(path), PATTERN, {"space": "left-posterior-superior", "space directions": directions})
    _assert_pattern(path, (2.0, 3.0, 4.0))


@pytest.mark.parametrize("encoding, endian, first, step, subdim", [
    ("raw", "little", 1, 1, ""), ("gzip", "big", 0, 2, "2"), ("raw", "big", 9, -3, "")])
def test_multifile_nhdr_orientation(tmp_path, encoding, endian, first, step, subdim):
    header = _write_multifile_nhdr(tmp_path, encoding=encoding, endian=endian, first=first,
                                   step=step, subdim=subdim)
    _assert_pattern(header, (0.5, 0.75, 2.0))


@pytest.mark.parametrize("kind", ["nhdr", "dat"])
def test_detached_data_found_from_a_relative_header_path(tmp_path, monkeypatch, kind):
    """Data files sit beside the header, also when the header is named by a relative path."""
    folder = tmp_path / "vols"
    folder.mkdir()
    if kind == "nhdr":
        header = _write_multifile_nhdr(folder)
    else:
        header = _write_dat(folder, (PATTERN + 100).astype("<u2").tobytes(order="F"))
    expected = load_volume(header).data
    monkeypatch.chdir(tmp_path)
    np.testing.assert_array_equal(load_volume(header.relative_to(tmp_path)).data, expected)


def test_npy_orientation(tmp_path):
    path = tmp_path / "vol.npy"
    np.save(path, PATTERN)
    _assert_pattern(path)


@pytest.mark.parametrize("key", ["volume", "data", "whatever"])
def test_npz_orientation_and_spacing(tmp_path, key):
    path = tmp_path / "vol.npz"
    np.savez(path, **{key: PATTERN}, spacing=np.array([1.0, 2.0, 3.0]))
    _assert_pattern(path, (1.0, 2.0, 3.0))


@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_nifti_orientation_both_byte_orders(tmp_path, byte_order):
    header = nib.Nifti1Header() if byte_order == "<" else nib.Nifti1Header().as_byteswapped(">")
    image = nib.Nifti1Image(PATTERN.astype(f"{byte_order}i2"), np.diag([0.5, 0.75, 2.0, 1.0]), header=header)
    image.header.set_data_dtype(f"{byte_order}i2")
    path = tmp_path / "vol.nii.gz"
    nib.save(image, path)
    assert nib.load(path).header.endianness == byte_order  # the file really has that byte order
    _assert_pattern(path, (0.5, 0.75, 2.0))


def test_nifti_trailing_singleton_axis_is_squeezed(tmp_path):
    path = tmp_path / "vol.nii"
    nib.save(nib.Nifti1Image(PATTERN[..., None], np.eye(4)), path)
    _assert_pattern(path)


# --- broken files ---------------------------------------------------------------------------------

def test_truncated_raw(tmp_path):
    path = tmp_path / "vol_5x4x3_int16.raw"
    path.write_bytes(PATTERN.astype("<i2").tobytes(order="F")[:-1])
    _raises(path, "expected 120 bytes", "found 119 bytes")


def test_truncated_gzip_raw(tmp_path):
    path = tmp_path / "vol_5x4x3_int16.raw.gz"
    path.write_bytes(gzip.compress(PATTERN.astype("<i2").tobytes(order="F"))[:-10])
    _raises(path, "cannot read")


def test_dat_size_mismatch(tmp_path):
    path = _write_dat(tmp_path, bytes(100))
    error = _raises(path, "vol.raw", "expected 120 bytes", "found 100 bytes")
    assert "size mismatch" in str(error)


def test_dat_unknown_format(tmp_path):
    _raises(_write_dat(tmp_path, bytes(120), fmt="DOUBLE"), "Format", "DOUBLE")


def test_dat_unparseable_header(tmp_path):
    path = _write_dat(tmp_path, bytes(120))
    path.write_text(path.read_text() + "garbage without a colon\n")
    _raises(path, "unparseable", "line 5")
    _raises(_write_dat(tmp_path, bytes(120), resolution=(5, 4, "three")), "unparseable", "Resolution")


def test_dat_missing_raw(tmp_path):
    path = _write_dat(tmp_path, bytes(120))
    (tmp_path / "vol.raw").unlink()
    _raises(path, "missing", "vol.raw")


def test_raw_unknown_dtype(tmp_path):
    path = tmp_path / "vol_5x4x3_uint12.raw"
    path.write_bytes(bytes(60))
    _raises(path, "dtype", "uint12")


def test_raw_name_without_shape(tmp_path):
    path = tmp_path / "vol.raw"
    path.write_bytes(bytes(60))
    _raises(path, "name_XxYxZ_dtype")


@pytest.mark.parametrize("shape", [(4, 5), (2, 3, 4, 5)])
def test_npy_not_3d(tmp_path, shape):
    path = tmp_path / "vol.npy"
    np.save(path, np.zeros(shape, dtype=np.uint8))
    _raises(path, "3D", f"{len(shape)}D")


class _TouchOnUnpickle:
    """Unpickling this object creates a file: proof that a loader executed a pickle."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return Path.touch, (self.marker,)


def test_npy_object_array_is_not_unpickled(tmp_path):
    marker = tmp_path / "unpickled"
    path = tmp_path / "vol.npy"
    np.save(path, np.array([_TouchOnUnpickle(marker)] * 8, dtype=object).reshape(2, 2, 2), allow_pickle=True)
    _raises(path, "pickle")
    assert not marker.exists()


def test_npz_ambiguous_arrays(tmp_path):
    path = tmp_path / "vol.npz"
    np.savez(path, a=PATTERN, b=PATTERN)
    _raises(path, "'volume' or 'data'")


def test_multifile_nhdr_missing_slice(tmp_path):
    header = _write_multifile_nhdr(tmp_path)
    (tmp_path / "slice.002").unlink()
    _raises(header, "missing", "slice.002")


def test_multifile_nhdr_short_slice(tmp_path):
    header = _write_multifile_nhdr(tmp_path)
    (tmp_path / "slice.003").write_bytes(bytes(39))
    _raises(header, "slice.003", "does not match")


def test_nan_and_inf_voxels_are_replaced_with_a_warning(tmp_path):
    # Volume.from_array replaces NaN by the smallest finite value (empty space), +Inf by the
    # largest and -Inf by the smallest, and warns with the counts; the loaded data is finite.
    values = PATTERN.astype(np.float32)
    values[0, 0, 0], values[1, 0, 0], values[2, 0, 0] = np.nan, np.inf, -np.inf
    path = tmp_path / "vol.npy"
    np.save(path, values)
    with pytest.warns(UserWarning, match=r"vol\.npy: replaced 1 NaN .* 1 \+Inf .* 1 -Inf"):
        volume = load_volume(path)
    assert np.isfinite(volume.data).all()
    assert volume.data[0, 0, 0] == 0.0 and volume.data[1, 0, 0] == 1.0 and volume.data[2, 0, 0] == 0.0
    finite = np.isfinite(values)
    assert volume.value_range == (float(values[finite].min()), float(values[finite].max()))


def test_missing_file(tmp_path):
    _raises(tmp_path / "nothing_here_64x64x64_uint8.raw", "no such file")


def test_unknown_extension(tmp_path):
    path = tmp_path / "vol.vtk"
    path.write_bytes(bytes(16))
    _raises(path, "unknown extension", ".nrrd", ".tiff", "DICOM series")


def test_corrupt_nifti_and_nrrd(tmp_path):
    for name in ("vol.nii", "vol.nrrd"):
        path = tmp_path / name
        path.write_bytes(b"not a volume at all" * 40)
        _raises(path, "cannot read")
