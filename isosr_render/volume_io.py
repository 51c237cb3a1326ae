"""Open scalar volumes from the file formats of scientific visualization, by the format registry.

:func:`open_source` picks the reader of a file or folder from :mod:`isosr_render.formats` (by its
suffix, else by what it holds) and returns its :class:`~isosr_render.voxels.VoxelSource`: the
stored values indexed ``[x, y, z]`` (x is the first axis), the voxel spacing and the rescale to
original units; :func:`load_volume` turns that into a :class:`Volume`. :func:`probe` checks a
path cheaply and :func:`volume_name` names it in a folder of volumes.
"""

from __future__ import annotations

import os
from pathlib import Path

from isosr_render.formats import FORMATS, format_of
from isosr_render.volume import Volume, VolumeError
from isosr_render.voxels import VoxelSource


def load_volume(path: str | os.PathLike, *, level: str | None = None, max_bytes: int | None = None) -> Volume:
    """Load a volume file (see :func:`open_source`, also for ``level`` and ``max_bytes``) as a :class:`Volume`.

    Returns:
        The volume named after the file, its data normalized to [0, 1] and indexed
        ``[x, y, z]``; non-finite voxels are replaced with a warning (see
        :meth:`Volume.from_array`).

    Raises:
        VolumeError: as :func:`open_source`.
    """
    return Volume.from_source(open_source(path, level=level, max_bytes=max_bytes))


def open_source(path: str | os.PathLike, *, level: str | None = None, max_bytes: int | None = None) -> VoxelSource:
    """Open a volume file or folder as a voxel source, with the reader :func:`isosr_render.formats.format_of` picks.

    Args:
        path: a file or folder of a registered format (:data:`isosr_render.formats.FORMATS`): a
            ``.nii[.gz]``, ``.nrrd``, ``.nhdr``, ``.dat``, ``_XxYxZ_dtype.raw[.gz]``, ``.npy`` or
            ``.npz`` file (read whole); a DICOM series folder or multi-frame file, a Zarr /
            OME-Zarr store (its finest level), a TIFF file or a folder of 2D TIFFs (read lazily).
        level, max_bytes: a level by name, or the finest whose voxels fit ``max_bytes``, of a
            format with levels (OME-Zarr: :func:`isosr_render.formats.zarr.open_zarr`).

    Returns:
        The stored values named after the file or folder, with spacing and rescale.

    Raises:
        VolumeError: the path is missing, is no registered format's (the message lists them) or
            cannot be read (bad header, unknown data type, size that does not match the header,
            missing data files, not 3D; the formats' own errors). The message names the file
            and the problem.
    """
    path = Path(path)
    if not path.exists():
        raise VolumeError(f"{path}: no such file")
    fmt = format_of(path)
    options = {k: v for k, v in (("level", level), ("max_bytes", max_bytes)) if v is not None}
    if options and (fmt is None or not fmt.levels):
        raise VolumeError(f"{path}: only an OME-Zarr store has levels to choose from")
    if fmt is not None:
        return fmt.open(path, **options)
    folders = [f.folder for f in FORMATS.values() if f.folder]
    folders = f"{', '.join(folders[:-1])} or {folders[-1]}" if len(folders) > 1 else "".join(folders)
    if path.is_dir():
        raise VolumeError(f"{path}: a folder that holds no {folders}")
    known = ", ".join(s for f in FORMATS.values() if f.files for s in f.suffixes)
    raise VolumeError(f"{path}: unknown extension (expected one of {known}; or a {folders} folder)")


# A volume file is read whole to check it (:func:`probe`) up to this size; a larger one when opened.
PROBE_BYTES = 16 << 20


def probe(path: str | os.PathLike) -> None:
    """Raise the `VolumeError` :func:`open_source` would for ``path``, cheaply: a DICOM series, Zarr
    store or TIFF is opened (headers and at most one slice); a file read whole only up to
    ``PROBE_BYTES`` and if it holds its voxels itself (a detached header's are checked when opened)."""
    path = Path(path)
    fmt = format_of(path)
    if fmt is not None and path.is_file() and (path.name.lower().endswith(fmt.detached)
                                               or (fmt.whole and path.stat().st_size > PROBE_BYTES)):
        return
    open_source(path)


def volume_name(path: Path) -> str | None:
    """The name a folder of volumes lists ``path`` under, or None for what :func:`open_source` does not
    take: a volume file's name without its format's suffix (the longest it ends with); a folder's
    name without the suffix that makes it a store (``.zarr``), else whole (a DICOM series, a TIFF
    stack). Files of formats that do not ``list_files`` (loose DICOM files: a series is one folder)
    and files told only by what they hold are not listed."""
    if path.name.startswith("."):
        return None
    fmt = format_of(path)
    if fmt is None or (path.is_file() and not fmt.list_files):
        return None
    if fmt.claims(path):
        return path.name[: -len(fmt.suffix_of(path.name))]
    return path.name if path.is_dir() else None
