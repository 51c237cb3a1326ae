"""The one volume format registry: every registered format is described, and a small sample of
each, written here, is detected as that format and opened through it (by suffix, and by what it
holds where the format detects); unknown paths are refused naming the registry's formats."""

from __future__ import annotations

import gzip
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from isosr_cli.main import build_parser
from isosr_render.formats import FORMATS, Format, format_of, help_text, register
from isosr_render.volume_io import open_source, probe, volume_name
from isosr_render.voxels import VolumeError

# Stored values [x, y, z]: a non-cubic box of distinct values, so a swapped or flipped axis shows.
VALUES = np.arange(5 * 4 * 3, dtype=np.int16).reshape(5, 4, 3) * 7 - 100


def _xfastest(values: np.ndarray) -> bytes:
    """Voxels as raw files hold them: x fastest, little-endian."""
    return np.ascontiguousarray(values.transpose(2, 1, 0)).astype(values.dtype.newbyteorder("<")).tobytes()


def _nifti(folder: Path) -> Path:
    nib = pytest.importorskip("nibabel", reason="writing a NIfTI sample needs nibabel")
    path = folder / "sample.nii.gz"
    nib.save(nib.Nifti1Image(VALUES, np.eye(4)), path)
    return path


def _nrrd(folder: Path) -> Path:
    nrrd = pytest.importorskip("nrrd", reason="writing an NRRD sample needs pynrrd")
    path = folder / "sample.nrrd"
    nrrd.write(str(path), VALUES)
    return path


def _dat(folder: Path) -> Path:
    (folder / "sample_data.raw").write_bytes(_xfastest(VALUES.astype(np.uint16)))
    path = folder / "sample.dat"
    path.write_text("ObjectFileName: sample_data.raw\nResolution: 5 4 3\nFormat: USHORT\n")
    return path


def _raw(folder: Path) -> Path:
    path = folder / "sample_5x4x3_int16.raw.gz"
    path.write_bytes(gzip.compress(_xfastest(VALUES)))
    return path


def _numpy(folder: Path) -> Path:
    path = folder / "sample.npy"
    np.save(path, VALUES)
    return path


def _zarr(folder: Path) -> Path:
    zarr = pytest.importorskip("zarr", reason="writing a Zarr sample needs zarr")
    path = folder / "sample.zarr"
    zarr.create_array(str(path), shape=VALUES.shape, chunks=(2, 2, 2), dtype=VALUES.dtype)[:] = VALUES
    return path


def _dicom(folder: Path) -> Path:
    """A series folder of bare-named slice files (no ``.dcm``: found by their ``DICM`` marker)."""
    pytest.importorskip("pydicom", reason="writing a DICOM sample needs pydicom")
    from dicom_fixtures import ct_slice

    path = folder / "sample_series"
    path.mkdir()
    for z in range(VALUES.shape[2]):
        ds = ct_slice(VALUES[:, :, z].T, (0.0, 0.0, float(z)), series="1.2.3")
        ds.save_as(path / f"slice{z}", enforce_file_format=True)
    return path


def _tiff(folder: Path) -> Path:
    tifffile = pytest.importorskip("tifffile", reason="writing a TIFF sample needs tifffile")
    pytest.importorskip("zarr", reason="reading a TIFF needs zarr")
    path = folder / "sample.ome.tif"
    tifffile.imwrite(path, VALUES.transpose(2, 1, 0), photometric="minisblack")
    return path


def _tiff_stack(folder: Path) -> Path:
    """A folder of 2D TIFFs, one a slice."""
    tifffile = pytest.importorskip("tifffile", reason="writing a TIFF sample needs tifffile")
    pytest.importorskip("zarr", reason="reading a TIFF needs zarr")
    path = folder / "stack"
    path.mkdir()
    for z in range(VALUES.shape[2]):
        tifffile.imwrite(path / f"slice{z}.tif", VALUES[:, :, z].T, photometric="minisblack")
    return path


# Name -> a writer of a small sample (returns its path); a registered format needs one here.
SAMPLES: dict[str, Callable[[Path], Path]] = {"nifti": _nifti, "nrrd": _nrrd, "dat": _dat, "raw": _raw,
                                              "numpy": _numpy, "zarr": _zarr, "dicom": _dicom, "tiff": _tiff}
# Name -> a writer of a sample told by what it holds, its name without a suffix (formats that detect).
DETECTED_SAMPLES: dict[str, Callable[[Path], Path]] = {"zarr": lambda folder: _zarr(folder).rename(folder / "store"),
                                                       "dicom": _dicom, "tiff": _tiff_stack}


@pytest.mark.parametrize("name", list(FORMATS))
def test_every_format_is_described(name):
    fmt = FORMATS[name]
    assert fmt.name == name and fmt.description and "\n" not in fmt.description
    assert fmt.suffixes and all(s.startswith(".") and s == s.lower() for s in fmt.suffixes), fmt.suffixes
    assert callable(fmt.open) and (fmt.detect is None or callable(fmt.detect))
    assert fmt.files or fmt.folder, "a format reads files, folders or both"
    assert fmt.help in help_text() and fmt.help in " ".join(build_parser().format_help().split())


@pytest.mark.parametrize("name", list(FORMATS))
def test_a_sample_of_every_format_is_detected_and_opened_through_it(tmp_path, name):
    assert name in SAMPLES, f"format {name!r} is registered without a sample writer in SAMPLES"
    path = SAMPLES[name](tmp_path)
    fmt = FORMATS[name]
    assert format_of(path) is fmt
    source = open_source(path)
    expected = VALUES.astype(np.uint16) if name == "dat" else VALUES
    np.testing.assert_array_equal(source.read(*(slice(0, n) for n in VALUES.shape)), expected)
    np.testing.assert_array_equal(fmt.open(path).read(slice(1, 4), slice(0, 2), slice(2, 3)), expected[1:4, 0:2, 2:3])
    probe(path)
    assert volume_name(path) == (None if path.is_file() and not fmt.list_files else
                                 path.name[: -len(fmt.suffix_of(path.name))] if fmt.claims(path) else path.name)


@pytest.mark.parametrize("name", [n for n, f in FORMATS.items() if f.detect is not None])
def test_a_format_that_detects_takes_its_sample_by_what_it_holds(tmp_path, name):
    """A store, series or stack folder with no suffix in its name."""
    assert name in DETECTED_SAMPLES, f"format {name!r} detects, but DETECTED_SAMPLES writes no sample of it"
    path = DETECTED_SAMPLES[name](tmp_path)
    assert path.suffix == "" and format_of(path) is FORMATS[name] and volume_name(path) == path.name
    np.testing.assert_array_equal(open_source(path).read(*(slice(0, n) for n in VALUES.shape)), VALUES)


def test_a_dicom_file_is_told_by_its_marker_and_not_listed_alone(tmp_path):
    one = next(_dicom(tmp_path).iterdir())
    assert one.suffix == "" and format_of(one) is FORMATS["dicom"] and volume_name(one) is None


def test_a_suffix_names_files_only_except_for_a_folder_only_format(tmp_path):
    (tmp_path / "not_a_volume.nii").mkdir()
    (tmp_path / "not_a_store.zarr").write_bytes(b"\0" * 16)
    assert format_of(tmp_path / "not_a_volume.nii") is None and format_of(tmp_path / "not_a_store.zarr") is None
    assert format_of(tmp_path / "missing.npy") is None


def test_unknown_paths_are_refused_naming_the_registrys_formats(tmp_path):
    path = tmp_path / "vol.vtk"
    path.write_bytes(bytes(16))
    with pytest.raises(VolumeError) as info:
        open_source(path)
    message = str(info.value)
    assert message.startswith(f"{path}: unknown extension")
    assert all(s in message for f in FORMATS.values() if f.files for s in f.suffixes), message
    assert all(f.folder in message for f in FORMATS.values() if f.folder), message
    with pytest.raises(VolumeError, match="a folder that holds no"):
        open_source(tmp_path)


def test_register_refuses_a_taken_name_or_a_clashing_suffix():
    with pytest.raises(ValueError, match="registered already"):
        register(Format("numpy", "again", (".npy2",), FORMATS["numpy"].open))
    with pytest.raises(ValueError, match=r"\.gz / \.nii\.gz"):
        register(Format("gzip", "any gzipped file", (".gz",), FORMATS["numpy"].open))
    assert "gzip" not in FORMATS
