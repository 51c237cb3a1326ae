"""What every format module shares: the :class:`Format` a reader registers as, and small helpers.

:mod:`isosr_render.formats` holds the registry; the reader modules import only this module, so
that the registry can import them.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from isosr_render.voxels import VolumeError, VoxelSource


@dataclass(frozen=True)
class Format:
    """One volume format: how a path is recognized as it and how it is opened.

    A path is a format's when its name ends with one of the format's ``suffixes`` (a file; a
    folder for a format that reads folders only), else when the format's ``detect`` says so
    (:func:`isosr_render.formats.format_of`).

    Attributes:
        name: the registry key (``"nifti"``).
        description: what the format is, one short phrase for help texts and errors.
        suffixes: lower-case name endings that make a path this format's; the longest one a
            name ends with is the extension a listed volume's name drops (``.ome.tif``).
        open: the reader: ``open(path)`` returns a :class:`~isosr_render.voxels.VoxelSource`, or
            raises `VolumeError` naming the path and the problem; with ``levels``, it also takes
            ``level=`` and ``max_bytes=`` (:func:`isosr_render.formats.zarr.open_zarr`).
        detect: whether a path whose name has no registered suffix is this format, by what it
            holds (a marker in a file, the files of a folder); None where only the suffix tells.
        files: whether it reads files (else only folders, which its suffixes then name).
        folder: what a folder of this format is (``"DICOM series"``); empty if it reads no folders.
        levels: whether a store holds several resolutions to choose from (OME-Zarr).
        list_files: whether a folder of volumes lists a file of this format as a volume (not a
            DICOM file: most often one slice of a series, whose folder is listed instead).
        whole: whether opening reads the whole file into memory (checks skip a large one).
        detached: suffixes of a header whose voxels lie in other files (checks skip it).
        header: reads only a file's :class:`Layout` (no voxels), where opening reads them all;
            None where opening is as cheap (a series checks its files' layouts with it).
        steps: the :class:`TimeSteps` of a file or store with a time axis of more than one entry,
            else None (:mod:`isosr_render.series`); None for a format without time axes.
    """

    name: str
    description: str
    suffixes: tuple[str, ...]
    open: Callable[..., VoxelSource]
    detect: Callable[[Path], bool] | None = None
    files: bool = True
    folder: str = ""
    levels: bool = False
    list_files: bool = True
    whole: bool = False
    detached: tuple[str, ...] = ()
    header: Callable[[Path], Layout] | None = None
    steps: Callable[[Path], TimeSteps | None] | None = None

    def suffix_of(self, name: str) -> str | None:
        """The longest of the suffixes ``name`` ends with (any case), or None."""
        lower = name.lower()
        return max((s for s in self.suffixes if lower.endswith(s)), key=len, default=None)

    def claims(self, path: Path) -> bool:
        """Whether ``path`` is this format's by its name: an existing file (a folder for a format
        that reads only folders) whose name ends with one of the suffixes."""
        kind_ok = path.is_file() if self.files else path.is_dir()
        return kind_ok and self.suffix_of(path.name) is not None

    @property
    def help(self) -> str:
        """The description and the suffixes, as help texts list the format."""
        return f"{self.description} ({', '.join(self.suffixes)})"


@dataclass(frozen=True)
class Layout:
    """What the time steps of a series share: voxels (x, y, z), spacing and the stored type as
    sources hand it out (:func:`stored_dtype`)."""

    shape: tuple[int, int, int]
    spacing: tuple[float, float, float]
    dtype: np.dtype

    @classmethod
    def of(cls, source: VoxelSource) -> Layout:
        return cls(tuple(int(n) for n in source.shape), tuple(float(s) for s in source.spacing),
                   np.dtype(source.dtype))

    def differs(self, other: Layout) -> str | None:
        """How ``other`` differs from this layout (``"shape (4, 4, 3) instead of (4, 4, 4)"``), or None."""
        if other.shape != self.shape:
            return f"shape {other.shape} instead of {self.shape}"
        if not np.allclose(other.spacing, self.spacing, rtol=1e-6, atol=0.0):
            return f"spacing {other.spacing} instead of {self.spacing}"
        if other.dtype != self.dtype:
            return f"dtype {other.dtype} instead of {self.dtype}"
        return None


@dataclass(frozen=True)
class TimeSteps:
    """The time steps one file or store holds along its time axis (a 4D NIfTI, a (t, z, y, x) array).

    Attributes:
        count: how many (at least 2).
        open: ``open(i)`` reads step ``i`` and returns its source (all of one :class:`Layout`).
    """

    count: int
    open: Callable[[int], VoxelSource]


def natural_key(name: str) -> tuple:
    """Sort key of a file name whose digit runs compare as numbers (``slice2`` before ``slice10``): the
    order of a folder's TIFF slices and of a series' files."""
    return tuple((0, int(part), "") if part.isdigit() else (1, 0, part.lower()) for part in re.split(r"(\d+)", name)
                 if part)


def require(module: str, label: str, what: str) -> ModuleType:
    """Import ``module``, or raise `VolumeError` naming ``label`` and the package to install."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise VolumeError(f"{label}: reading {what} needs the '{module}' package: "
                          "pip install 'isosr[data]'") from None


def stored_dtype(dtype: np.dtype, label: str) -> np.dtype:
    """The type a source hands out for a store's ``dtype``: native byte order; bool as uint8,
    float16 as float32, 64-bit integers as float64 (as the files read whole,
    :mod:`isosr_render.formats.arrays`)."""
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
