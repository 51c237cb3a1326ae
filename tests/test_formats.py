"""Tests for isosr_render.formats: DICOM, Zarr / OME-Zarr and TIFF written here, read lazily, each
rendered equal to the same voxels from numpy; bad input gets a one-line error naming the file."""

from __future__ import annotations

import importlib.util
import random
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pydicom
import pytest
import tifffile
import torch
import zarr
from conftest import DEVICE
from dicom_fixtures import ct_slice
from pydicom.dataset import Dataset
from pydicom.encaps import encapsulate
from pydicom.pixels import get_decoder
from pydicom.sequence import Sequence
from pydicom.uid import (
    EnhancedCTImageStorage,
    JPEGLosslessSV1,
    RLELossless,
)

from isosr_render import Renderer, RenderRequest, Volume, open_volume, orbit
from isosr_render.formats.dicom import open_dicom
from isosr_render.formats.tiff import open_tiff
from isosr_render.formats.zarr import open_zarr
from isosr_render.volume_io import open_source, volume_name
from isosr_render.voxels import ArraySource, VolumeError, VoxelSource
from isosr_server.volumes import VolumeCatalog

# Stored values [x, y, z] of an off-center ellipsoid in a non-cubic box: any swap or flip of an
# axis changes both the array and the rendered image.
SHAPE = (20, 16, 12)
SPACING = (0.7, 0.9, 2.5)
SLOPE, INTERCEPT = 2.0, -1024.0


def _field(shape=SHAPE) -> np.ndarray:
    x, y, z = np.meshgrid(*(np.linspace(-1, 1, n) for n in shape), indexing="ij")
    r = np.sqrt(((x - 0.25) / 0.6) ** 2 + ((y + 0.1) / 0.5) ** 2 + (z / 0.8) ** 2)
    return np.round(1000 * (1.2 - r) + 30 * x).astype(np.int16)


VALUES = _field()


def _render(volume: Volume, iso: float) -> dict[str, torch.Tensor]:
    request = RenderRequest(40, 32, iso, outputs=("mask", "normal", "depth"))
    frame = Renderer(volume, DEVICE, threads=2).render(orbit(35, 25, 1.8), request)
    return {name: getattr(frame, name).cpu() for name in request.outputs}


def _assert_same_volume(source: VoxelSource, values: np.ndarray, spacing, rescale=(1.0, 0.0)) -> None:
    """``source`` reads ``values`` (stored) and renders as the same stored values and rescale from numpy."""
    assert isinstance(source, VoxelSource)
    assert source.shape == values.shape and source.dtype == values.dtype
    assert source.spacing == pytest.approx(spacing) and source.rescale == pytest.approx(rescale)
    np.testing.assert_array_equal(source.read(*(slice(0, n) for n in values.shape)), values)
    np.testing.assert_array_equal(source.read(slice(3, 9), slice(1, 2), slice(1, 3)), values[3:9, 1:2, 1:3])
    volume = Volume.from_source(source)
    expected = Volume.from_source(ArraySource(values, spacing, rescale=rescale))
    np.testing.assert_array_equal(volume.data, expected.data)
    original = values.astype(np.float64) * rescale[0] + rescale[1]
    assert volume.value_range == pytest.approx((original.min(), original.max()))
    iso = expected.normalized_iso(float(np.percentile(original, 60)))
    got, want = _render(volume, iso), _render(expected, iso)
    assert want["mask"].sum() > 50  # the surface is in view
    for name in want:
        torch.testing.assert_close(got[name], want[name], atol=0, rtol=0)


def _raises(call, path, *words) -> str:
    """Assert ``call()`` raises a one-line VolumeError naming ``path`` and every word."""
    with pytest.raises(VolumeError) as info:
        call()
    message = str(info.value)
    assert "\n" not in message and str(path) in message, message
    for word in words:
        assert word.lower() in message.lower(), message
    return message


# --- DICOM ----------------------------------------------------------------------------------------

def _dicom(plane: np.ndarray, position, orientation=(1, 0, 0, 0, 1, 0), series: str = "1.2.3.4",
           number: int = 1) -> Dataset:
    """A CT slice of this module's spacing and rescale."""
    return ct_slice(plane, position, orientation, series, SPACING, (SLOPE, INTERCEPT), number)


def _write_series(folder: Path, values=VALUES, orientation=(1, 0, 0, 0, 1, 0), shear=(0.0, 0.0), skip=(),
                  gaps=None, series="1.2.3.4", syntax=None, names=None) -> list[Path]:
    """One file per z slice under shuffled names; returns the paths in z order (skipped ones left out)."""
    folder.mkdir(parents=True, exist_ok=True)
    row, column = np.asarray(orientation[:3], float), np.asarray(orientation[3:], float)
    normal = np.cross(row, column)
    depth = np.cumsum([0.0] + list(gaps or [SPACING[2]] * (values.shape[2] - 1)))
    order = list(range(values.shape[2]))
    random.Random(7).shuffle(order)
    paths = {}
    for n, k in enumerate(order):
        if k in skip:
            continue
        position = np.array([-40.0, 12.0, 100.0]) + depth[k] * normal + k * (shear[0] * row + shear[1] * column)
        ds = _dicom(values[:, :, k].T, position, orientation, series, number=order[-1 - n] + 1)
        if syntax is not None:
            ds.compress(syntax, encoding_plugin="pydicom")
        paths[k] = folder / (names[k] if names else f"IM{n:04d}")  # names unrelated to the order
        ds.save_as(paths[k], enforce_file_format=True)
    return [paths[k] for k in sorted(paths)]


def test_dicom_series_ordered_by_position_with_rescale(tmp_path):
    _write_series(tmp_path / "ct")
    source = open_source(tmp_path / "ct")
    assert source.name == "ct" and source.chunks == (SHAPE[0], SHAPE[1], 1)
    _assert_same_volume(source, VALUES, SPACING, (SLOPE, INTERCEPT))


def test_dicom_list_of_files_and_reversed_normal(tmp_path):
    # Orientation with the column direction flipped: the normal points the other way, so the
    # slices are ordered by position along it, whatever the z coordinates say.
    files = _write_series(tmp_path, orientation=(1, 0, 0, 0, -1, 0))
    _assert_same_volume(open_dicom(random.Random(1).sample(files, len(files))), VALUES, SPACING, (SLOPE, INTERCEPT))


def test_dicom_oblique_series_is_read_in_its_own_axes(tmp_path):
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    _write_series(tmp_path, orientation=(c, s, 0, -0.6 * s, 0.6 * c, 0.8))  # rows turned 30 degrees, columns tilted
    _assert_same_volume(open_source(tmp_path), VALUES, SPACING, (SLOPE, INTERCEPT))


def test_dicom_gantry_tilt_is_refused(tmp_path):
    files = _write_series(tmp_path, shear=(0.0, 0.3))  # 0.3 mm a slice along the columns: 3.7 pixels over 12
    _raises(lambda: open_source(tmp_path), files[-1], "sheared", "gantry tilt", "resample")


def test_dicom_missing_slice_is_reported(tmp_path):
    files = _write_series(tmp_path, skip=(5,))
    _raises(lambda: open_source(tmp_path), files[5], "1 slice(s) missing", files[4].name, "5 mm", "2.5 mm")


def test_dicom_inconsistent_spacing_is_refused(tmp_path):
    files = _write_series(tmp_path, gaps=[2.5] * 6 + [3.4] + [2.5] * 4)
    _raises(lambda: open_source(tmp_path), files[7], "inconsistent slice spacing", "3.4 mm")


def test_dicom_mixed_series_refused_naming_them(tmp_path):
    _write_series(tmp_path, series="1.2.3.4")
    _write_series(tmp_path, values=VALUES[:, :, :4], series="1.2.3.99", names=[f"B{k}" for k in range(4)])
    _raises(lambda: open_source(tmp_path), tmp_path, "2 DICOM series", "1.2.3.4 (CT test, number 3, 12 files)",
            "1.2.3.99 (CT test, number 3, 4 files)")
    _assert_same_volume(open_dicom(tmp_path, series="1.2.3.99"), VALUES[:, :, :4], SPACING, (SLOPE, INTERCEPT))


def test_dicom_rle_compressed_series(tmp_path):
    _write_series(tmp_path, syntax=RLELossless)
    assert pydicom.dcmread(next(tmp_path.iterdir())).file_meta.TransferSyntaxUID == RLELossless
    _assert_same_volume(open_source(tmp_path), VALUES, SPACING, (SLOPE, INTERCEPT))


@pytest.mark.skipif(get_decoder(JPEGLosslessSV1).is_available, reason="a JPEG lossless decoder is installed")
def test_dicom_without_a_decoder_names_what_to_install(tmp_path):
    files = _write_series(tmp_path)
    ds = pydicom.dcmread(files[0])
    ds.file_meta.TransferSyntaxUID = JPEGLosslessSV1
    ds.PixelData = encapsulate([b"\xff\xd8\xff\xc3" + bytes(64)])
    ds["PixelData"].VR, ds["PixelData"].is_undefined_length = "OB", True
    ds.save_as(files[0], enforce_file_format=True)
    _raises(lambda: open_source(tmp_path), files[0], "JPEG Lossless", "no decoder", "isosr[codecs]", "pylibjpeg")


def test_dicom_slices_with_different_rescales_become_float(tmp_path):
    files = _write_series(tmp_path)
    ds = pydicom.dcmread(files[3])
    ds.RescaleIntercept = -1000
    ds.save_as(files[3], enforce_file_format=True)
    original = VALUES.astype(np.float32) * SLOPE + INTERCEPT
    original[:, :, 3] += 24
    source = open_source(tmp_path)
    assert source.dtype == np.float32 and source.rescale == (1.0, 0.0)
    np.testing.assert_array_equal(source.read(slice(0, 20), slice(0, 16), slice(2, 5)), original[:, :, 2:5])


def test_enhanced_multiframe_dicom(tmp_path):
    # Frames stored in reverse z order: their per-frame positions put them right.
    ds = _dicom(VALUES[:, :, 0].T, (0, 0, 0))
    ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID = EnhancedCTImageStorage
    for keyword in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "RescaleSlope",
                    "RescaleIntercept"):
        delattr(ds, keyword)
    shared = Dataset()
    shared.PlaneOrientationSequence = Sequence([Dataset()])
    shared.PlaneOrientationSequence[0].ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
    shared.PixelMeasuresSequence = Sequence([Dataset()])
    shared.PixelMeasuresSequence[0].PixelSpacing = [SPACING[1], SPACING[0]]
    shared.PixelValueTransformationSequence = Sequence([Dataset()])
    shared.PixelValueTransformationSequence[0].RescaleSlope = SLOPE
    shared.PixelValueTransformationSequence[0].RescaleIntercept = INTERCEPT
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    frames = []
    for k in reversed(range(SHAPE[2])):
        item = Dataset()
        item.PlanePositionSequence = Sequence([Dataset()])
        item.PlanePositionSequence[0].ImagePositionPatient = [0.0, 0.0, k * SPACING[2]]
        frames.append(item)
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames)
    ds.NumberOfFrames = SHAPE[2]
    ds.PixelData = np.ascontiguousarray(VALUES[:, :, ::-1].transpose(2, 1, 0), dtype="<i2").tobytes()
    path = tmp_path / "enhanced.dcm"
    ds.save_as(path, enforce_file_format=True)
    _assert_same_volume(open_source(path), VALUES, SPACING, (SLOPE, INTERCEPT))


def test_corrupt_dicom_file(tmp_path):
    files = _write_series(tmp_path)
    files[2].write_bytes(files[2].read_bytes()[:300])  # cut inside the header
    _raises(lambda: open_source(tmp_path), files[2], "corrupt DICOM file")
    files[2].write_bytes(b"\0" * 128 + b"DICM" + bytes(range(256)))
    _raises(lambda: open_source(tmp_path), files[2], "corrupt DICOM file")


def test_truncated_dicom_pixel_data(tmp_path):
    files = _write_series(tmp_path)
    files[6].write_bytes(files[6].read_bytes()[:-100])
    source = open_source(tmp_path)  # headers are fine; the slice's pixels fail when read
    _raises(lambda: source.read(slice(0, 20), slice(0, 16), slice(5, 8)), files[6], "cannot decode")


# --- Zarr and OME-Zarr ----------------------------------------------------------------------------

def _write_ome_zarr(path: Path, values=VALUES, levels=3, zarr_format=3) -> None:
    """An OME-Zarr image (c, z, y, x) with ``levels`` levels, each half the last; NGFF 0.5 (v3) or 0.4 (v2)."""
    group = zarr.open_group(str(path), mode="w", zarr_format=zarr_format)
    datasets = []
    for i in range(levels):
        level = values[:: 2 ** i, :: 2 ** i, :: 2 ** i].transpose(2, 1, 0)[None]
        array = group.create_array(f"s{i}", shape=level.shape, chunks=(1, 4, 8, 8), dtype=level.dtype)
        array[:] = level
        scale = [1.0] + [s * 2 ** i for s in SPACING[::-1]]
        datasets.append({"path": f"s{i}", "coordinateTransformations": [
            {"type": "scale", "scale": scale}, {"type": "translation", "translation": [0, 5.0, 0, 0]}]})
    axes = [{"name": "c", "type": "channel"}] + [{"name": n, "type": "space", "unit": "millimeter"} for n in "zyx"]
    multiscales = [{"version": "0.4", "axes": axes, "datasets": datasets}]
    group.attrs.update({"ome": {"version": "0.5", "multiscales": multiscales}} if zarr_format == 3
                       else {"multiscales": multiscales})


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_ome_zarr_three_levels(tmp_path, zarr_format):
    path = tmp_path / "cells.ome.zarr"
    _write_ome_zarr(path, zarr_format=zarr_format)
    source = open_source(path)
    assert source.name == "cells.ome.zarr/s0" and source.chunks == (8, 8, 4)
    assert [s.level for s in source.levels] == ["s0", "s1", "s2"]
    assert [s.shape for s in source.levels] == [(20, 16, 12), (10, 8, 6), (5, 4, 3)]
    _assert_same_volume(source, VALUES, SPACING)
    coarse = open_zarr(path, level="s1")
    assert coarse.spacing == pytest.approx([2 * s for s in SPACING])
    np.testing.assert_array_equal(coarse.read(slice(0, 10), slice(0, 8), slice(0, 6)), VALUES[::2, ::2, ::2])


def test_ome_zarr_in_a_bioformats2raw_layout(tmp_path):
    path = tmp_path / "converted.zarr"
    _write_ome_zarr(path / "0")
    zarr.open_group(str(path), mode="a").attrs["ome"] = {"version": "0.5", "bioformats2raw.layout": 3}
    source = open_source(path)
    assert source.name == "converted.zarr/0/s0" and len(source.levels) == 3
    _assert_same_volume(source, VALUES, SPACING)


def test_ome_zarr_level_by_memory(tmp_path):
    _write_ome_zarr(tmp_path / "a.zarr")
    assert open_zarr(tmp_path / "a.zarr", max_bytes=VALUES.nbytes).level == "s0"
    assert open_zarr(tmp_path / "a.zarr", max_bytes=VALUES.nbytes - 1).level == "s1"
    assert open_zarr(tmp_path / "a.zarr", max_bytes=10 * 8 * 6 * 2 - 1).level == "s2"
    _raises(lambda: open_zarr(tmp_path / "a.zarr", max_bytes=100), tmp_path / "a.zarr", "no level fits",
            "'s2' (5, 4, 3), needs 120")
    _raises(lambda: open_zarr(tmp_path / "a.zarr", level="s7"), tmp_path / "a.zarr", "no level 's7'", "s0, s1, s2")


def test_ome_zarr_level_from_the_source_spec(tmp_path):
    path = tmp_path / "a.zarr"
    _write_ome_zarr(path)
    assert open_volume(f"{path}#level=s1").shape == (10, 8, 6)
    assert open_volume(f"{path}#max-gb={(VALUES.nbytes - 1) / 1e9}").shape == (10, 8, 6)
    coarse = Volume.from_source(ArraySource(VALUES[::4, ::4, ::4], SPACING))
    np.testing.assert_array_equal(open_volume(f"{path}#level=s2").data, coarse.data)
    _raises(lambda: open_volume(f"{path}#level=s9"), path, "no level 's9'")
    _raises(lambda: open_volume(f"{path}#max-gb=-1"), f"{path}#max-gb=-1", "max-gb must be a positive number")
    np.save(tmp_path / "v.npy", VALUES)
    _raises(lambda: open_volume(f"{tmp_path / 'v.npy'}#level=0"), tmp_path / "v.npy", "only an OME-Zarr store has levels")
    _raises(lambda: open_volume(f"{path}#lod=1"), f"{path}#lod=1", "no such file")  # not a level suffix: a path


def test_a_server_serves_the_finest_level_that_fits_its_memory_setting(tmp_path):
    _write_ome_zarr(tmp_path / "cells.ome.zarr")
    levels = [{"level": f"s{i}", "shape": s, "bytes": 2 * s[0] * s[1] * s[2]}
              for i, s in enumerate([(20, 16, 12), (10, 8, 6), (5, 4, 3)])]
    for max_bytes, level in ((None, "s0"), (VALUES.nbytes, "s0"), (VALUES.nbytes - 1, "s1"), (100, "s2")):
        catalog = VolumeCatalog(tmp_path, max_bytes)
        listed = catalog.info("cells")
        assert (listed.level, listed.levels) == (level, levels)
        volume, info = catalog.load("cells")
        assert info.level == level and info.levels == levels and volume.shape == next(
            tuple(s["shape"]) for s in levels if s["level"] == level)
        np.testing.assert_array_equal(volume.data, open_volume(f"{tmp_path / 'cells.ome.zarr'}#level={level}").data)
    assert VolumeCatalog(tmp_path).info("proc:sphere").levels is None


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_plain_zarr_indexed_like_npy(tmp_path, zarr_format):
    path = tmp_path / "plain.zarr"
    array = zarr.create_array(str(path), shape=SHAPE, chunks=(8, 8, 5), dtype=">i2" if zarr_format == 2 else "<i2",
                              zarr_format=zarr_format)
    array[:] = VALUES
    source = open_source(path)
    assert source.name == "plain.zarr" and source.chunks == (8, 8, 5)
    _assert_same_volume(source, VALUES, (1.0, 1.0, 1.0))


def test_plain_zarr_with_dimension_names(tmp_path):
    array = zarr.create_array(str(tmp_path / "v.zarr"), shape=SHAPE[::-1], chunks=(4, 8, 8), dtype="uint16",
                              dimension_names=("z", "y", "x"))
    array[:] = VALUES.transpose(2, 1, 0) + 2000
    _assert_same_volume(open_source(tmp_path / "v.zarr"), (VALUES + 2000).astype(np.uint16), (1.0, 1.0, 1.0))


def test_zarr_without_the_array(tmp_path):
    zarr.open_group(str(tmp_path / "empty.zarr"), mode="w")
    _raises(lambda: open_source(tmp_path / "empty.zarr"), tmp_path / "empty.zarr", "no array")
    path = tmp_path / "lost.zarr"
    _write_ome_zarr(path)
    group = zarr.open_group(str(path), mode="a")
    del group["s1"]
    _raises(lambda: open_source(path), path, "names the array 's1'", "does not hold")


def test_zarr_with_channels_refused(tmp_path):
    zarr.create_array(str(tmp_path / "c.zarr"), shape=(3, 4, 5, 6), dtype="uint8", dimension_names=("c", "z", "y", "x"))
    _raises(lambda: open_source(tmp_path / "c.zarr"), tmp_path / "c.zarr", "c=3", "one scalar field")


# --- TIFF -----------------------------------------------------------------------------------------

def test_tiff_stack_in_natural_order(tmp_path):
    folder = tmp_path / "stack"
    folder.mkdir()
    for k in random.Random(3).sample(range(SHAPE[2]), SHAPE[2]):  # written out of order
        tifffile.imwrite(folder / f"slice{k}.tif", VALUES[:, :, k].T)  # slice2 before slice10
    (folder / "notes.txt").write_text("not a slice")
    source = open_source(folder)
    assert source.name == "stack"
    _assert_same_volume(source, VALUES, (1.0, 1.0, 1.0))
    assert open_tiff(folder, spacing=SPACING).spacing == SPACING


@pytest.mark.parametrize("kind", ["imagej", "ome", "pages"])
def test_multipage_tiff(tmp_path, kind):
    path = tmp_path / f"vol.{'ome.' if kind == 'ome' else ''}tif"
    zyx = VALUES.transpose(2, 1, 0)
    if kind == "imagej":
        tifffile.imwrite(path, zyx, imagej=True, resolution=(1 / SPACING[0], 1 / SPACING[1]),
                         metadata={"spacing": SPACING[2], "unit": "mm", "axes": "ZYX"})
    elif kind == "ome":
        tifffile.imwrite(path, zyx, ome=True, metadata={"axes": "ZYX", "PhysicalSizeX": SPACING[0],
                                                        "PhysicalSizeY": SPACING[1], "PhysicalSizeZ": SPACING[2]})
    else:
        tifffile.imwrite(path, zyx, photometric="minisblack")
    source = open_source(path)
    assert source.chunks == (SHAPE[0], SHAPE[1], 1)
    _assert_same_volume(source, VALUES, (1.0, 1.0, 1.0) if kind == "pages" else SPACING)


def test_truncated_tiff(tmp_path):
    path = tmp_path / "vol.tif"
    tifffile.imwrite(path, VALUES.transpose(2, 1, 0), photometric="minisblack", compression="zlib")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    _raises(lambda: open_source(path), path, "truncated")


@pytest.mark.skipif(importlib.util.find_spec("imagecodecs") is not None, reason="imagecodecs is installed")
def test_tiff_without_a_codec_names_what_to_install(tmp_path):
    path = tmp_path / "vol.tif"
    tifffile.imwrite(path, VALUES.transpose(2, 1, 0), photometric="minisblack")
    with tifffile.TiffFile(path, mode="r+b") as tif:
        tif.pages.first.tags["Compression"].overwrite(5)  # says LZW, which only imagecodecs decodes
    _raises(lambda: open_source(path), path, "compressed as LZW", "no decoder", "isosr[codecs]")


def test_tiff_stack_files_that_differ(tmp_path):
    for k in range(3):
        tifffile.imwrite(tmp_path / f"s{k}.tif", VALUES[:, :, k].T if k != 1 else VALUES[:10, :, k].T)
    _raises(lambda: open_source(tmp_path), tmp_path / "s1.tif", "(16, 10)", "s0.tif is (16, 20)")


def test_single_2d_tiff_and_rgb_refused(tmp_path):
    tifffile.imwrite(tmp_path / "flat.tif", VALUES[:, :, 0].T)
    _raises(lambda: open_source(tmp_path / "flat.tif"), tmp_path / "flat.tif", "a single 2D image")
    tifffile.imwrite(tmp_path / "zc.tif", np.zeros((4, 2, 8, 8), np.uint8), imagej=True, metadata={"axes": "ZCYX"})
    _raises(lambda: open_source(tmp_path / "zc.tif"), tmp_path / "zc.tif", "ZCYX", "one axis of slices")
    tifffile.imwrite(tmp_path / "rgb.tif", np.zeros((4, 8, 8, 3), np.uint8), photometric="rgb")
    _raises(lambda: open_source(tmp_path / "rgb.tif"), tmp_path / "rgb.tif", "RGB", "one scalar per voxel")


@pytest.mark.parametrize("kind", ["dicom", "ome-zarr", "tiff"])
def test_boxes_read_from_several_threads_at_once(tmp_path, kind):
    """Volumes are scanned and uploaded box by box on several threads: a source's reads must not race."""
    if kind == "dicom":
        _write_series(tmp_path / "v", syntax=RLELossless)
    elif kind == "ome-zarr":
        _write_ome_zarr(tmp_path / "v")
    else:
        tifffile.imwrite(tmp_path / "v", VALUES.transpose(2, 1, 0), photometric="minisblack", compression="zlib")
    source = open_tiff(tmp_path / "v") if kind == "tiff" else open_source(tmp_path / "v")
    rng = np.random.default_rng(0)
    starts = [tuple(int(rng.integers(0, n - 1)) for n in SHAPE) for _ in range(96)]
    boxes = [tuple(slice(s, int(rng.integers(s + 1, n + 1))) for s, n in zip(start, SHAPE)) for start in starts]
    with ThreadPoolExecutor(8) as pool:
        for box, got in zip(boxes, pool.map(lambda b: source.read(*b), boxes)):
            np.testing.assert_array_equal(got, VALUES[box])


# --- where the formats plug in --------------------------------------------------------------------

def test_a_volumes_folder_lists_a_series_a_store_and_a_stack_as_one_volume_each(tmp_path):
    _write_series(tmp_path / "head_ct")
    _write_ome_zarr(tmp_path / "cells.ome.zarr")
    tifffile.imwrite(tmp_path / "stack.tif", VALUES.transpose(2, 1, 0), photometric="minisblack")
    (tmp_path / "empty_folder").mkdir()
    (tmp_path / "loose.dcm").write_bytes(b"")
    names = {p.name: volume_name(p) for p in tmp_path.iterdir()}
    assert names == {"head_ct": "head_ct", "cells.ome.zarr": "cells", "stack.tif": "stack",
                     "empty_folder": None, "loose.dcm": None}
    catalog = VolumeCatalog(tmp_path)
    assert [n for n in catalog.names() if not n.startswith("proc:")] == ["cells", "head_ct", "stack"]
    volume, info = catalog.load("head_ct")
    assert info.shape == SHAPE
    assert info.value_range == (VALUES.min() * SLOPE + INTERCEPT, VALUES.max() * SLOPE + INTERCEPT)
    np.testing.assert_array_equal(volume.data, open_volume(str(tmp_path / "head_ct")).data)
    assert catalog.load("cells")[1].shape == SHAPE
    _raises(lambda: open_volume(str(tmp_path / "empty_folder")), tmp_path / "empty_folder",
            "holds no", "DICOM series", "Zarr store", "TIFF stack")


@pytest.mark.parametrize("package", ["pydicom", "zarr", "tifffile"])
def test_without_the_data_extra_the_error_names_the_package(tmp_path, monkeypatch, package):
    path = {"pydicom": tmp_path / "ct", "zarr": tmp_path / "v.zarr", "tifffile": tmp_path / "v.tif"}[package]
    _write_series(tmp_path / "ct")
    zarr.create_array(str(tmp_path / "v.zarr"), shape=SHAPE, dtype="int16")
    tifffile.imwrite(tmp_path / "v.tif", VALUES.transpose(2, 1, 0), photometric="minisblack")
    monkeypatch.setitem(sys.modules, package, None)  # `import package` now fails
    _raises(lambda: open_source(path), path, f"needs the '{package}' package", "pip install 'isosr[data]'")
