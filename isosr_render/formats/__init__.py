"""The volume formats: one registry of every reader, by name, with its suffixes, detection and opener.

``FORMATS`` maps a name to its :class:`~isosr_render.formats.base.Format`; :func:`format_of`
picks the one that reads a path and :func:`isosr_render.volume_io.open_source` opens it. The CLI
help (:func:`help_text`) and a server's volume listing
(:func:`isosr_render.volume_io.volume_name`) read the registry. A new format is a reader module
and one :func:`register` call below.

- Read whole (:mod:`~isosr_render.formats.arrays`): NIfTI, NRRD, Volume Library ``.dat``, named
  ``.raw`` and NumPy files.
- Read lazily, box by box (never the whole volume at once): a DICOM series (a folder) or
  multi-frame file (:mod:`~isosr_render.formats.dicom`, pydicom); a Zarr / OME-Zarr store
  (:mod:`~isosr_render.formats.zarr`, zarr); a multi-page TIFF or a folder of 2D TIFFs
  (:mod:`~isosr_render.formats.tiff`, tifffile).

Orientation, as for NIfTI: the volume's axes are the stored axes, never flipped, rotated or
resampled; a 2D image's columns are x, its rows y (top to bottom), and the slices z. The lazy
readers' libraries come with the ``data`` extra (``pip install 'isosr[data]'``); compressed
DICOM and TIFF codecs with the ``codecs`` extra.
"""

from __future__ import annotations

import os
from pathlib import Path

from isosr_render.formats import arrays, dicom, tiff, zarr
from isosr_render.formats.base import Format

__all__ = ["FORMATS", "Format", "format_of", "help_text", "register"]

# Name -> format, in registration order: ``detect`` is asked in this order.
FORMATS: dict[str, Format] = {}


def register(fmt: Format) -> Format:
    """Add ``fmt`` to ``FORMATS``.

    Raises:
        ValueError: its name is taken, or one of its suffixes ends (or is the end of) another
            format's, so that a name would not tell the two apart.
    """
    if fmt.name in FORMATS:
        raise ValueError(f"a volume format named {fmt.name!r} is registered already")
    for other in FORMATS.values():
        clash = [f"{s} / {t}" for s in fmt.suffixes for t in other.suffixes if s.endswith(t) or t.endswith(s)]
        if clash:
            raise ValueError(f"volume format {fmt.name!r}: suffixes {', '.join(clash)} clash with {other.name!r}'s")
    FORMATS[fmt.name] = fmt
    return fmt


def format_of(path: str | os.PathLike) -> Format | None:
    """The format that reads ``path``, or None.

    The format one of whose suffixes ends the name of ``path`` (a file; a folder for a format that
    reads only folders, such as a ``.zarr`` store); else the first, in registration order, whose
    ``detect`` takes it (a folder with Zarr metadata, a DICOM series or a TIFF stack; a file with
    the DICOM marker). A missing path is no format's.
    """
    path = Path(path)
    named = next((f for f in FORMATS.values() if f.claims(path)), None)
    return named or next((f for f in FORMATS.values() if f.detect is not None and f.detect(path)), None)


def help_text() -> str:
    """Every format with its suffixes, one sentence for help texts (``isosr --help``)."""
    return "; ".join(f.help for f in FORMATS.values())


for _format in (
    Format("nifti", "NIfTI image", (".nii", ".nii.gz"), arrays.open_nifti, whole=True, header=arrays.nifti_header,
           steps=arrays.nifti_steps),
    Format("nrrd", "NRRD file or detached header", (".nrrd", ".nhdr"), arrays.open_nrrd, whole=True,
           detached=(".nhdr",)),
    Format("dat", "Volume Library header beside its .raw file", (".dat",), arrays.open_dat, whole=True,
           detached=(".dat",)),
    Format("raw", "raw voxels named NAME_XxYxZ_DTYPE", (".raw", ".raw.gz"), arrays.open_raw, whole=True),
    Format("numpy", "NumPy array", (".npy", ".npz"), arrays.open_numpy, whole=True, header=arrays.numpy_header,
           steps=arrays.numpy_steps),
    Format("zarr", "Zarr or OME-Zarr store folder", zarr.ZARR_SUFFIXES, zarr.open_zarr, zarr.detect_zarr,
           files=False, folder="Zarr store", levels=True, steps=zarr.zarr_steps),
    Format("dicom", "DICOM series folder or multi-frame file", dicom.DICOM_SUFFIXES, dicom.open_dicom,
           dicom.detect_dicom, folder="DICOM series", list_files=False),
    Format("tiff", "multi-page TIFF or a folder of 2D TIFFs",
           tiff.TIFF_SUFFIXES + tuple(".ome" + s for s in tiff.TIFF_SUFFIXES), tiff.open_tiff,
           tiff.detect_tiff_stack, folder="TIFF stack"),
):
    register(_format)
del _format
