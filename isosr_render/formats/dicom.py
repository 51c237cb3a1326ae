"""DICOM series and multi-frame DICOM files as voxel sources, through pydicom.

Geometry (DICOM's patient frame, millimetres):
- x runs along a row (ImageOrientationPatient's first vector: columns, left to right), y along
  a column (its second vector: rows, top to bottom), z along the slice normal x cross y, so the
  volume is never mirrored. Slices are ordered by their position along the normal
  (ImagePositionPatient . normal), never by file name or instance number.
- Spacing: PixelSpacing (row spacing is y's, column spacing x's); z's from the slice positions.
  A gap that is a multiple of the others (a missing slice), gaps that vary, two slices at one
  position, or an orientation or pixel spacing that changes within the series are refused.
- An oblique series (rows and columns not along the patient axes, slices stacked along their
  normal) is read as is: the volume's axes are the image's, as with NIfTI, so the surface is
  exact; it is not turned into the patient frame. A gantry-tilted (sheared) series, whose slice
  positions drift within the slice plane by more than half a pixel over the series, is refused:
  it would need resampling (e.g. dcm2niix's tilt correction first).
- Values stay in the stored type (BitsAllocated, PixelRepresentation); RescaleSlope and
  RescaleIntercept become the source's ``rescale``. Where slices carry different rescales, the
  source holds float32 original values instead (rescale ``(1, 0)``).

A folder holds one series: several are refused, naming each (pass ``series=`` to pick one). A
Siemens mosaic (many slices tiled in one 2D image: NumberOfImagesInMosaic (0019,100A), or MOSAIC
in ImageType) is refused: it needs unpacking first (e.g. dcm2niix).
Files without the DICOM marker (``.dcm`` files aside) and a DICOMDIR are passed over. A
multi-frame file (enhanced CT/MR: positions from the per-frame functional groups) is a volume
by itself. Compressed transfer syntaxes decode through pydicom's plugins (RLE built in, JPEG
baseline and JPEG 2000 also through Pillow where installed; JPEG lossless, JPEG-LS and the rest
through pylibjpeg: ``pip install 'isosr[codecs]'``); without a decoder the series is refused
naming what to install.
"""

from __future__ import annotations

import dataclasses
import os
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from isosr_render.formats.base import one_line, require, stored_dtype
from isosr_render.voxels import VolumeError, check_source

DICOM_MAGIC_OFFSET = 128
DICOM_SUFFIXES = (".dcm", ".dicom")
# Slices agree on orientation within this (direction cosines), and on pixel spacing to this fraction.
ORIENTATION_TOLERANCE = 1e-4
# Slice gaps agree to this fraction of the median gap.
GAP_TOLERANCE = 0.01
# In-plane drift of the slice positions over the series, in pixels, beyond which it is sheared.
SHEAR_TOLERANCE = 0.5
# The SOP class of a DICOMDIR, passed over in a folder.
DICOMDIR_CLASS = "1.2.840.10008.1.3.10"
# Siemens' private NumberOfImagesInMosaic.
MOSAIC_TAG = (0x0019, 0x100A)
# What every image of a series shares (checked equal across files).
LAYOUT = ("Rows", "Columns", "BitsAllocated", "PixelRepresentation", "SamplesPerPixel")


@dataclasses.dataclass(frozen=True, eq=False)
class Slice:
    """One 2D image of a series: a file (and a frame of it) with its geometry and rescale."""

    path: Path
    frame: int | None  # the frame of a multi-frame file; None for a single-frame file
    position: np.ndarray  # ImagePositionPatient, (3,)
    orientation: np.ndarray  # ImageOrientationPatient: row then column direction, (6,)
    pixel_spacing: tuple[float, float]  # (between rows, between columns)
    rescale: tuple[float, float]


@dataclasses.dataclass(frozen=True, eq=False)
class DicomSource:
    """The slices of a series in order along the normal, read a slice at a time.

    Attributes (besides the VoxelSource ones):
        slices: the images in order of z.
        slice_rescale: whether each slice's own rescale is applied in ``read`` (then ``dtype`` is
            float32 and ``rescale`` is ``(1, 0)``).
    """

    name: str
    slices: tuple[Slice, ...]
    shape: tuple[int, int, int]
    dtype: np.dtype
    spacing: tuple[float, float, float]
    rescale: tuple[float, float]
    slice_rescale: bool = False

    @property
    def chunks(self) -> tuple[int, int, int]:
        return self.shape[0], self.shape[1], 1  # a slice a file (or frame)

    def read(self, x: slice, y: slice, z: slice) -> np.ndarray:
        """Stored values of the box ``[x, y, z]``, decoding the slices it crosses."""
        out = np.empty((x.stop - x.start, y.stop - y.start, z.stop - z.start), self.dtype)
        wanted = self.slices[z]
        for j, (s, plane) in enumerate(zip(wanted, _decode(wanted, self.shape[1], self.shape[0]))):
            block = plane[y, x].T
            if self.slice_rescale:
                block = block.astype(np.float32) * np.float32(s.rescale[0]) + np.float32(s.rescale[1])
            out[:, :, j] = block
        return out



def has_dicom_magic(path: Path) -> bool:
    """Whether the file holds ``DICM`` after the 128-byte preamble (a DICOM Part 10 file)."""
    try:
        with open(path, "rb") as f:
            f.seek(DICOM_MAGIC_OFFSET)
            return f.read(4) == b"DICM"
    except OSError:
        return False


def is_dicom_file(path: Path) -> bool:
    """A DICOM file by its extension or its ``DICM`` marker (many series have bare file names)."""
    return path.is_file() and (path.name.lower().endswith(DICOM_SUFFIXES) or has_dicom_magic(path))


def detect_dicom(path: Path) -> bool:
    """A file with the ``DICM`` marker, or a folder holding a DICOM file (a series)."""
    if path.is_dir():
        return any(is_dicom_file(p) for p in path.iterdir() if not p.name.startswith("."))
    return is_dicom_file(path)

def open_dicom(source: str | os.PathLike | Iterable[str | os.PathLike], *, series: str | None = None) -> DicomSource:
    """Open a DICOM series (a folder or a list of files) or a multi-frame DICOM file.

    Args:
        source: a folder, a list of slice files, or one multi-frame file.
        series: the SeriesInstanceUID to read where the files hold several series.

    Returns:
        The series as a voxel source (see the module for geometry and values).

    Raises:
        VolumeError: an unreadable or non-image file, several series, a missing slice, uneven
            spacing, a sheared series, no decoder for the transfer syntax, pydicom missing;
            one line naming the file and the problem.
    """
    files, label = _files(source)
    pydicom = require("pydicom", str(label), "DICOM")
    headers = [(f, _header(pydicom, f)) for f in files]
    headers = [(f, ds) for f, ds in headers if ds is not None]
    if not headers:
        raise VolumeError(f"{label}: no DICOM image" + (" (only a DICOMDIR)" if files else ""))
    _refuse_mosaic(headers)
    headers = _one_series(headers, series, label)
    multi = [f for f, ds in headers if int(ds.get("NumberOfFrames", 1) or 1) > 1]
    if multi and len(headers) > 1:
        raise VolumeError(f"{multi[0]}: a multi-frame file is a volume by itself; open it alone, "
                          f"not with {len(headers) - 1} other files of its series")
    _check_layout(headers)
    slices = [s for f, ds in headers for s in _slices(f, ds)]
    if len(slices) < 2:
        raise VolumeError(f"{label}: one slice only; a volume needs at least 2")
    slices, spacing = _order(slices)
    first = headers[0][1]
    for f, ds in {str(ds.file_meta.get("TransferSyntaxUID")): (f, ds) for f, ds in headers}.values():
        _check_decoder(ds, f)
    rescales = {s.rescale for s in slices}
    uniform = len(rescales) == 1
    plane = next(_decode(slices[:1], int(first.Rows), int(first.Columns)))
    name = label.name if isinstance(label, Path) else label
    source = DicomSource(name, tuple(slices), (int(first.Columns), int(first.Rows), len(slices)),
                         stored_dtype(plane.dtype, str(label)) if uniform else np.dtype(np.float32), spacing,
                         slices[0].rescale if uniform else (1.0, 0.0), slice_rescale=not uniform)
    check_source(source, str(label))
    return source


def _files(source) -> tuple[list[Path], Path | str]:
    """The candidate files and the label errors name: the folder, the file, or the files' folder."""
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if path.is_dir():
            files = sorted(p for p in path.iterdir() if not p.name.startswith(".") and is_dicom_file(p))
            return files, path
        if not path.is_file():
            raise VolumeError(f"{path}: no such file or folder")
        return [path], path
    files = [Path(f) for f in source]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise VolumeError(f"{missing[0]}: no such file ({len(missing)} of {len(files)} listed files missing)")
    parents = {f.parent for f in files}
    return files, parents.pop() if len(parents) == 1 else f"{len(files)} DICOM files"


def _header(pydicom, path: Path):
    """The file's dataset without pixel data; None for a DICOMDIR (a folder's index)."""
    if not has_dicom_magic(path):
        raise VolumeError(f"{path}: not a DICOM file (no 'DICM' marker after the 128-byte preamble)")
    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except Exception as e:  # pydicom raises many kinds on corrupt files
        raise VolumeError(f"{path}: corrupt DICOM file ({one_line(e)})") from e
    if ds.file_meta.get("MediaStorageSOPClassUID") == DICOMDIR_CLASS:
        return None
    if "Rows" not in ds:  # pydicom reads a truncated file up to its end without a word
        raise VolumeError(f"{path}: corrupt DICOM file or not an image (no Rows)")
    return ds


def _refuse_mosaic(headers: list) -> None:
    """Refuse a Siemens mosaic: its one 2D image tiles many slices (module docstring)."""
    for f, ds in headers:
        kinds = ds.get("ImageType") or []
        kinds = [kinds] if isinstance(kinds, str) else kinds
        if MOSAIC_TAG in ds or any("MOSAIC" in str(k).upper() for k in kinds):
            count = ds[MOSAIC_TAG].value if MOSAIC_TAG in ds else None
            tiles = f"{count} slices" if isinstance(count, int) else "slices"
            raise VolumeError(f"{f}: a Siemens mosaic ({tiles} tiled in one 2D image); "
                              "unpack it into a series first (e.g. dcm2niix)")


def _describe(uid: str, members: list) -> str:
    """A series as the error lists it: UID, modality, description, number, file count."""
    ds = members[0][1]
    what = " ".join(str(v) for v in (ds.get("Modality"), ds.get("SeriesDescription")) if v)
    number = ds.get("SeriesNumber")
    return f"{uid} ({what or 'no description'}{f', number {number}' if number is not None else ''}, " \
           f"{len(members)} files)"


def _one_series(headers: list, series: str | None, label) -> list:
    """The files of the one series (or of ``series``); several without a choice are refused, named."""
    groups = defaultdict(list)
    for f, ds in headers:
        groups[str(ds.get("SeriesInstanceUID", ""))].append((f, ds))
    if series is not None:
        if series not in groups:
            found = "; ".join(_describe(u, m) for u, m in groups.items())
            raise VolumeError(f"{label}: no series {series}; found {found}")
        return groups[series]
    if len(groups) > 1:
        raise VolumeError(f"{label}: {len(groups)} DICOM series mixed; open one (series=UID, or its files): "
                          f"{'; '.join(_describe(u, m) for u, m in groups.items())}")
    return next(iter(groups.values()))


def _check_layout(headers: list) -> None:
    """Every image of the series has the first's size and pixel layout, one sample per pixel."""
    first_file, first = headers[0]
    for f, ds in headers:
        missing = [k for k in LAYOUT if k not in ds and k != "SamplesPerPixel"]
        if missing:
            raise VolumeError(f"{f}: no {', '.join(missing)}")
        if int(ds.get("SamplesPerPixel", 1)) != 1:
            raise VolumeError(f"{f}: {ds.SamplesPerPixel} samples per pixel ({ds.get('PhotometricInterpretation')}); "
                              "a volume needs one scalar per voxel")
        for key in LAYOUT:
            if ds.get(key, 1) != first.get(key, 1):
                raise VolumeError(f"{f}: {key} {ds.get(key)} differs from {first_file.name}'s {first.get(key)}")


def _item(ds, frame: int | None, sequence: str):
    """The functional group item ``sequence`` of a frame (per-frame, else shared), or None."""
    for groups, index in (("PerFrameFunctionalGroupsSequence", frame), ("SharedFunctionalGroupsSequence", 0)):
        if index is not None and groups in ds and len(ds[groups].value) > index:
            group = ds[groups].value[index]
            if sequence in group and len(group[sequence].value):
                return group[sequence].value[0]
    return None


def _value(ds, path: Path, frame: int | None, sequence: str, keyword: str, default=None):
    """An attribute from the frame's functional group ``sequence``, else the dataset's top level."""
    item = _item(ds, frame, sequence)
    value = item.get(keyword) if item is not None else None
    value = ds.get(keyword) if value is None else value
    if value is None and default is None:
        where = f"frame {frame + 1} of " if frame is not None else ""
        raise VolumeError(f"{where}{path}: no {keyword}, so the slice cannot be placed")
    return default if value is None else value


def _slices(path: Path, ds) -> list[Slice]:
    """The 2D images of a file: one for a single-frame file, one a frame for a multi-frame file."""
    frames = int(ds.get("NumberOfFrames", 1) or 1)
    out = []
    for frame in (range(frames) if frames > 1 else (None,)):
        position = _value(ds, path, frame, "PlanePositionSequence", "ImagePositionPatient")
        orientation = _value(ds, path, frame, "PlaneOrientationSequence", "ImageOrientationPatient")
        spacing = _value(ds, path, frame, "PixelMeasuresSequence", "PixelSpacing")
        slope = _value(ds, path, frame, "PixelValueTransformationSequence", "RescaleSlope", 1.0)
        intercept = _value(ds, path, frame, "PixelValueTransformationSequence", "RescaleIntercept", 0.0)
        out.append(Slice(path, frame, np.asarray(position, np.float64), np.asarray(orientation, np.float64),
                         (float(spacing[0]), float(spacing[1])), (float(slope), float(intercept))))
    return out


def _where(s: Slice) -> str:
    """A slice as errors name it."""
    return s.path.name if s.frame is None else f"{s.path.name} frame {s.frame + 1}"


def _order(slices: list[Slice]) -> tuple[list[Slice], tuple[float, float, float]]:
    """The slices sorted along the normal, and the spacing (x, y, z); refuses what is not one regular grid."""
    first = slices[0]
    for s in slices:
        if np.abs(s.orientation - first.orientation).max() > ORIENTATION_TOLERANCE:
            raise VolumeError(f"{s.path}: ImageOrientationPatient {s.orientation.tolist()} differs from "
                              f"{_where(first)}'s {first.orientation.tolist()}")
        if not np.allclose(s.pixel_spacing, first.pixel_spacing, rtol=GAP_TOLERANCE, atol=0):
            raise VolumeError(f"{s.path}: PixelSpacing {s.pixel_spacing} differs from {_where(first)}'s "
                              f"{first.pixel_spacing}")
    row, column = first.orientation[:3], first.orientation[3:]
    if np.abs([row @ row - 1, column @ column - 1, row @ column]).max() > 10 * ORIENTATION_TOLERANCE:
        raise VolumeError(f"{first.path}: ImageOrientationPatient {first.orientation.tolist()} is not two "
                          "orthogonal unit vectors")
    normal = np.cross(row, column)
    positions = np.array([s.position for s in slices])
    depth = positions @ normal
    order = np.argsort(depth, kind="stable")
    slices, depth, positions = [slices[i] for i in order], depth[order], positions[order]
    gaps = np.diff(depth)
    gap = float(np.median(gaps))
    for i, g in enumerate(gaps):
        if g <= GAP_TOLERANCE * gap or gap <= 0:
            raise VolumeError(f"{slices[i + 1].path}: at the same position ({depth[i]:.4g} mm along the normal) "
                              f"as {_where(slices[i])}; one volume needs one slice per position")
        if abs(g - gap) > GAP_TOLERANCE * gap:
            between = f"between {_where(slices[i])} and {_where(slices[i + 1])}"
            ratio = g / gap
            if round(ratio) >= 2 and abs(ratio - round(ratio)) < GAP_TOLERANCE * ratio:
                raise VolumeError(f"{slices[i + 1].path}: {round(ratio) - 1} slice(s) missing {between} "
                                  f"(a gap of {g:.4g} mm, the others are {gap:.4g} mm)")
            raise VolumeError(f"{slices[i + 1].path}: inconsistent slice spacing, {g:.4g} mm {between} "
                              f"where the others are {gap:.4g} mm")
    drift = positions[-1] - positions[0]
    pixels = (abs(drift @ row) / first.pixel_spacing[1], abs(drift @ column) / first.pixel_spacing[0])
    if max(pixels) > SHEAR_TOLERANCE:
        tilt = np.degrees(np.arctan2(np.linalg.norm(drift - (drift @ normal) * normal), drift @ normal))
        raise VolumeError(f"{slices[-1].path}: sheared series (gantry tilt {tilt:.2f} degrees: the slices drift "
                          f"{max(pixels):.1f} pixels within their plane); resample it first")
    return slices, (first.pixel_spacing[1], first.pixel_spacing[0], gap)


def _check_decoder(ds, path: Path) -> None:
    """Refuse a transfer syntax no installed plugin decodes, naming what to install."""
    from pydicom.pixels import get_decoder

    syntax = ds.file_meta.get("TransferSyntaxUID")
    if syntax is None or not syntax.is_compressed:
        return
    try:
        decoder = get_decoder(syntax)
    except NotImplementedError:
        raise VolumeError(f"{path}: pixel data in {syntax.name}, which pydicom cannot decode") from None
    if not decoder.is_available:
        options = "; or ".join(decoder.missing_dependencies)
        raise VolumeError(f"{path}: pixel data compressed as {syntax.name} and no decoder is installed "
                          f"(pip install 'isosr[codecs]'; the plugins: {options})")


def _decode(slices: tuple[Slice, ...] | list[Slice], rows: int, columns: int):
    """The slices' stored values, (rows, columns) each, in order; one pass over a multi-frame file."""
    from pydicom.pixels import iter_pixels, pixel_array

    if slices and slices[0].frame is not None:  # the frames of one multi-frame file
        indices = [s.frame for s in slices]
        unique = sorted(set(indices))
        try:
            planes = dict(zip(unique, iter_pixels(slices[0].path, indices=unique)))
        except Exception as e:  # pydicom's decoders raise many kinds on corrupt data
            raise VolumeError(f"{slices[0].path}: cannot decode the pixel data ({one_line(e)})") from e
        yield from (_checked_plane(planes[i], slices[0].path, rows, columns) for i in indices)
        return
    for s in slices:
        try:
            plane = pixel_array(s.path)
        except Exception as e:  # as above
            raise VolumeError(f"{s.path}: cannot decode the pixel data ({one_line(e)})") from e
        yield _checked_plane(plane, s.path, rows, columns)


def _checked_plane(plane: np.ndarray, path: Path, rows: int, columns: int) -> np.ndarray:
    """The plane, if it has the series' size."""
    if plane.shape != (rows, columns):
        raise VolumeError(f"{path}: decoded pixel data of shape {plane.shape}, expected ({rows}, {columns})")
    return plane
