"""TIFF volumes as voxel sources, through tifffile (pages and files read lazily through its Zarr view).

- A multi-page or 3D TIFF (ImageJ hyperstack, OME-TIFF, plain pages): the first image series;
  its last two axes are y (rows, top to bottom) and x (columns), and the one other axis with
  more than one entry is z. Spacing: OME-TIFF's ``PhysicalSize{X,Y,Z}``; else ImageJ's (x and y
  from the resolution tags, z from ``spacing``); else 1.
- A folder of 2D TIFFs (one slice a file): the files in natural order of their names
  (``slice2`` before ``slice10``: TIFF records no slice position), each of the same size and
  type. Spacing 1 unless given.

A page whose data run past the end of the file (a truncated TIFF), or whose compression no
installed codec decodes (LZW, JPEG and others need imagecodecs: ``pip install 'isosr[codecs]'``),
is refused when opened.
"""

from __future__ import annotations

import os
import struct
import threading
from pathlib import Path

from isosr_render.formats.base import natural_key, one_line, require
from isosr_render.formats.zarr import ZarrSource, checked_source
from isosr_render.voxels import VolumeError

TIFF_SUFFIXES = (".tif", ".tiff", ".btf")
# Photometric interpretations whose samples are colors, not one scalar.
_COLOR = ("RGB", "PALETTE", "YCBCR", "CMYK", "SEPARATED", "CIELAB")


def open_tiff(path: str | os.PathLike, *, spacing: tuple[float, float, float] | None = None) -> ZarrSource:
    """Open a multi-page/3D TIFF file or a folder of 2D TIFFs as a voxel source.

    Args:
        path: a ``.tif``/``.tiff`` file or a folder of them.
        spacing: voxel size (x, y, z); default from the file's metadata (see the module), else 1.

    Raises:
        VolumeError: not a TIFF, truncated, a single 2D image, color samples, more than one
            non-spatial axis, files of a stack that differ; one line naming the file.
    """
    tifffile = require("tifffile", str(path), "TIFF")
    require("zarr", str(path), "TIFF")
    path = Path(path)
    if path.is_dir():
        return _open_stack(tifffile, path, spacing or (1.0, 1.0, 1.0))
    tif = _open(tifffile, path)
    series = tif.series[0]
    _check_pages(tifffile, series, path)
    axes = series.axes.upper()
    if axes[-2:] != "YX":
        raise VolumeError(f"{path}: expected pages of 2D images (axes ending in YX), got axes {axes}")
    stacked = [a for a in range(series.ndim - 2) if series.shape[a] > 1]
    if not stacked:
        raise VolumeError(f"{path}: a single 2D image of shape {series.shape}, not a volume")
    if len(stacked) > 1:
        raise VolumeError(f"{path}: axes {axes} with shape {series.shape}: a volume has one axis of slices "
                          "besides YX (one channel, one time point)")
    array = _as_zarr(series.aszarr(lock=threading.RLock()), path)  # sources are read from several threads
    spacing = spacing or _spacing(tifffile, tif, path)
    axes = (series.ndim - 1, series.ndim - 2, stacked[0])
    return checked_source(ZarrSource(path.name, array, axes, tuple(float(s) for s in spacing), str(path)))



def detect_tiff_stack(path: Path) -> bool:
    """A folder holding a TIFF file (a stack of 2D images)."""
    return path.is_dir() and any(p.is_file() and p.name.lower().endswith(TIFF_SUFFIXES)
                                 for p in path.iterdir() if not p.name.startswith("."))

def _open(tifffile, path: Path):
    """The opened TiffFile (kept open: the source reads its pages later)."""
    try:
        return tifffile.TiffFile(path)
    except (OSError, ValueError, EOFError, struct.error, tifffile.TiffFileError) as e:
        raise VolumeError(f"{path}: not a readable TIFF ({one_line(e)})") from e


def _check_pages(tifffile, series, path: Path) -> None:
    """Refuse color samples, a compression no installed codec decodes and data past the end of the file."""
    page = series.keyframe
    if page.photometric.name in _COLOR or page.samplesperpixel > 1:
        raise VolumeError(f"{path}: {page.photometric.name} images with {page.samplesperpixel} samples per "
                          "pixel; a volume needs one scalar per voxel")
    try:
        tifffile.TIFF.DECOMPRESSORS[page.compression]
    except KeyError:
        raise VolumeError(f"{path}: pages compressed as {page.compression.name} and no decoder is installed "
                          "(pip install 'isosr[codecs]' for imagecodecs)") from None
    size = os.path.getsize(path)
    end = (series.dataoffset + series.nbytes if series.dataoffset is not None
           else max((o + n for p in series.pages if p is not None for o, n in zip(p.dataoffsets, p.databytecounts)),
                    default=0))
    if end > size:
        raise VolumeError(f"{path}: truncated, the image data run to byte {end} but the file has {size} bytes")


def _as_zarr(store, path: Path):
    """The zarr view of tifffile's store."""
    import zarr
    try:
        return zarr.open(store, mode="r")
    except Exception as e:  # tifffile's store: whatever a malformed file makes it raise
        raise VolumeError(f"{path}: cannot map the TIFF's pages ({one_line(e)})") from e


def _spacing(tifffile, tif, path: Path) -> tuple[float, float, float]:
    """Voxel size (x, y, z) from OME-XML, else ImageJ metadata, else 1."""
    if tif.is_ome:
        pixels = tifffile.xml2dict(tif.ome_metadata)["OME"]["Image"]
        pixels = (pixels[0] if isinstance(pixels, list) else pixels)["Pixels"]
        return tuple(float(pixels.get(f"PhysicalSize{a}", 1.0)) for a in "XYZ")
    if tif.is_imagej:
        tags = tif.pages.first.tags
        x, y = (_pixel_size(tags[t].value) if t in tags else 1.0 for t in ("XResolution", "YResolution"))
        return x, y, float(tif.imagej_metadata.get("spacing", 1.0))
    return 1.0, 1.0, 1.0


def _pixel_size(resolution: tuple[int, int]) -> float:
    """A resolution tag's pixels per unit (a rational: numerator, denominator) as the size of a pixel."""
    pixels, units = resolution
    return units / pixels if pixels > 0 and units > 0 else 1.0


def _open_stack(tifffile, folder: Path, spacing) -> ZarrSource:
    """A folder of 2D TIFFs, one slice a file, in natural order of the names."""
    files = sorted((str(p) for p in folder.iterdir()
                    if p.is_file() and p.name.lower().endswith(TIFF_SUFFIXES) and not p.name.startswith(".")),
                   key=lambda p: natural_key(Path(p).name))
    if len(files) < 2:
        raise VolumeError(f"{folder}: a TIFF stack needs at least 2 files, found {len(files)}")
    first = None
    for file in map(Path, files):
        with _open(tifffile, file) as tif:
            series = tif.series[0]
            _check_pages(tifffile, series, file)
            found = (tuple(s for s in series.shape if s != 1), series.dtype)
        if len(found[0]) != 2:
            raise VolumeError(f"{file}: a TIFF stack takes one 2D image a file, this one has shape {series.shape}")
        first = first or (file, found)
        if found != first[1]:
            raise VolumeError(f"{file}: {found[0]} {found[1]} image, but {first[0].name} is {first[1][0]} "
                              f"{first[1][1]}; a stack's images share size and type")
    try:
        store = tifffile.TiffSequence(files, sort=False).aszarr()
    except (OSError, ValueError, tifffile.TiffFileError) as e:
        raise VolumeError(f"{folder}: cannot map the TIFF stack ({one_line(e)})") from e
    array = _as_zarr(store, folder)
    axes = (array.ndim - 1, array.ndim - 2, 0)  # files along the first axis, one-entry axes between
    return checked_source(ZarrSource(folder.name, array, axes, tuple(float(s) for s in spacing), str(folder)))
