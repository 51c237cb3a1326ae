"""Lazy readers of the formats scientists' volumes arrive in: DICOM, Zarr / OME-Zarr and TIFF.

Each reader returns a :class:`~isosr_render.voxels.VoxelSource` that reads boxes from the store
(slice files, chunks, pages) when asked, never the whole volume at once:

- :func:`isosr_render.formats.dicom.open_dicom`: a DICOM series (a folder or a list of files)
  or a multi-frame file, through pydicom.
- :func:`isosr_render.formats.zarr.open_zarr`: a plain Zarr v2/v3 array or an OME-Zarr
  multiscale image (a level chosen by name or by the memory it needs), through zarr.
- :func:`isosr_render.formats.tiff.open_tiff`: a multi-page or 3D TIFF (ImageJ and OME-TIFF
  spacing), or a folder of 2D TIFFs, through tifffile.

Orientation, as for NIfTI (:mod:`isosr_render.volume_io`): the volume's axes are the stored
axes, never flipped, rotated or resampled; a 2D image's columns are x, its rows y (top to
bottom), and the slices z. :func:`open_format` picks the reader from a path;
:func:`isosr_render.volume_io.open_source` calls it for the paths these readers take. The
libraries come with the ``data`` extra (``pip install 'isosr[data]'``); compressed DICOM and
TIFF codecs with the ``codecs`` extra.
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from types import ModuleType

import numpy as np

from isosr_render.voxels import VolumeError, VoxelSource

DICOM_MAGIC_OFFSET = 128
DICOM_SUFFIXES = (".dcm", ".dicom")
TIFF_SUFFIXES = (".tif", ".tiff", ".btf")
ZARR_MARKERS = ("zarr.json", ".zgroup", ".zarray")


def require(module: str, label: str, what: str) -> ModuleType:
    """Import ``module``, or raise `VolumeError` naming ``label`` and the package to install."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise VolumeError(f"{label}: reading {what} needs the '{module}' package: "
                          "pip install 'isosr[data]'") from None


def stored_dtype(dtype: np.dtype, label: str) -> np.dtype:
    """The type a source hands out for a store's ``dtype``: native byte order; bool as uint8,
    float16 as float32, 64-bit integers as float64 (as :func:`isosr_render.volume_io.open_source`)."""
    dtype = np.dtype(dtype)
    if dtype == np.bool_:
        return np.dtype(np.uint8)
    if dtype.kind == "f" and dtype.itemsize == 2:
        return np.dtype(np.float32)
    if dtype.kind in "iu" and dtype.itemsize == 8:
        return np.dtype(np.float64)
    if dtype.kind not in "iuf":
        raise VolumeError(f"{label}: unsupported voxel dtype {dtype}")
    return dtype.newbyteorder("=")


def one_line(error: BaseException) -> str:
    """A library's error as one line: its type and its message with whitespace runs collapsed."""
    return f"{type(error).__name__}: {' '.join(str(error).split())}"


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


def format_of(path: str | os.PathLike) -> str | None:
    """``"zarr"``, ``"dicom"`` or ``"tiff"``: the reader that takes ``path``, or None.

    A ``.zarr`` directory or one holding Zarr metadata is a Zarr store; another folder is a
    DICOM series if it holds a DICOM file, else a TIFF stack if it holds a TIFF; a file is told
    by its extension (or the DICOM marker).
    """
    path = Path(path)
    if path.is_dir():
        if path.name.lower().endswith(".zarr") or any((path / m).is_file() for m in ZARR_MARKERS):
            return "zarr"
        files = sorted(p for p in path.iterdir() if not p.name.startswith("."))
        if any(is_dicom_file(p) for p in files):
            return "dicom"
        if any(p.is_file() and p.name.lower().endswith(TIFF_SUFFIXES) for p in files):
            return "tiff"
        return None
    if not path.is_file():
        return None
    if path.name.lower().endswith(TIFF_SUFFIXES):
        return "tiff"
    return "dicom" if is_dicom_file(path) else None


def open_format(path: str | os.PathLike) -> VoxelSource:
    """The voxel source of a DICOM series or file, a Zarr store or a TIFF (stack), by :func:`format_of`.

    Raises:
        VolumeError: no reader here takes ``path``, or the reader's own errors.
    """
    kind = format_of(path)
    if kind == "zarr":
        from isosr_render.formats.zarr import open_zarr
        return open_zarr(path)
    if kind == "dicom":
        from isosr_render.formats.dicom import open_dicom
        return open_dicom(path)
    if kind == "tiff":
        from isosr_render.formats.tiff import open_tiff
        return open_tiff(path)
    raise VolumeError(f"{path}: neither a DICOM series or file, a Zarr store nor a TIFF (stack)")
