"""Zarr v2/v3 arrays and OME-Zarr (NGFF) multiscale images as voxel sources, through zarr.

- An OME-Zarr group (NGFF 0.4 ``multiscales`` in the attributes, 0.5 under ``ome``; in a
  bioformats2raw layout, the image ``0``): the axes
  named in the metadata (``z``, ``y``, ``x`` map to the volume's z, y, x; without names, the
  last three space axes are z, y, x); other axes (time, channel) must have one entry, but for a
  ``t`` axis opened by step (``open_zarr(path, step=i)``, :func:`zarr_steps`: a time series).
  Spacing: the level's ``scale`` transformations times the multiscale's own, per axis.
  ``levels`` lists every level finest first (but those with an axis of one voxel); one is
  picked by its dataset path (``level``) or as the finest whose voxels fit ``max_bytes``.
- A plain array (or a group holding exactly one): with ``dimension_names`` (v3) or xarray's
  ``_ARRAY_DIMENSIONS`` (v2) naming x, y, z, those; otherwise the array is indexed ``[x, y, z]``
  like a ``.npy`` file. Spacing 1.

Reads index the store's chunks lazily (``read`` reads only the chunks a box touches).
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from isosr_render.formats.base import TimeSteps, one_line, require, stored_dtype
from isosr_render.voxels import VolumeError, check_source

ZARR_SUFFIXES = (".zarr", ".ome.zarr")
# A folder holding one of these is a store, whatever its name.
ZARR_MARKERS = ("zarr.json", ".zgroup", ".zarray")
SPACE_NAMES = ("x", "y", "z")
# NGFF before 0.3 has no axes: the image is 5D (t, c, z, y, x).
NGFF_DEFAULT_AXES = ("t", "c", "z", "y", "x")


@dataclasses.dataclass(frozen=True, eq=False)
class ZarrSource:
    """A voxel source over a zarr array, whatever its axis order.

    Attributes:
        name: the store's (or file's) name, with ``/level`` for a multiscale level.
        array: the zarr array (any number of axes).
        axes: the array axis that holds x, y and z.
        spacing: voxel size along x, y, z.
        where: the path named in error messages.
        level: the level's dataset path ("" for a plain array).
        levels: every level of the multiscale image, finest first (empty for a plain array).
        rescale: always ``(1, 0)``: Zarr and TIFF store original values.
        time: ``(axis, index)``: the time step read of an array with a ``t`` axis; None: none.
        steps: the entries of the ``t`` axis (1 without one).
    """

    name: str
    array: Any
    axes: tuple[int, int, int]
    spacing: tuple[float, float, float]
    where: str
    level: str = ""
    levels: tuple[ZarrSource, ...] = ()
    rescale: tuple[float, float] = (1.0, 0.0)
    time: tuple[int, int] | None = None
    steps: int = 1

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(self.array.shape[a]) for a in self.axes)

    @property
    def chunks(self) -> tuple[int, int, int]:
        return tuple(int(self.array.chunks[a]) for a in self.axes)

    @property
    def dtype(self) -> np.dtype:
        return stored_dtype(self.array.dtype, self.where)

    @property
    def nbytes(self) -> int:
        """Bytes of the whole level in its stored type."""
        return math.prod(self.shape) * self.dtype.itemsize

    def read(self, x: slice, y: slice, z: slice) -> np.ndarray:
        """Stored values of the box ``[x, y, z]`` (one-entry axes at 0), from the chunks it touches."""
        key: list[slice | int] = [0] * self.array.ndim
        for axis, box in zip(self.axes, (x, y, z)):
            key[axis] = box
        if self.time is not None:
            key[self.time[0]] = self.time[1]
        try:
            block = np.asarray(self.array[tuple(key)])
        except Exception as e:  # whatever the store or its codecs raise (truncated chunk, missing codec)
            raise VolumeError(f"{self.where}: cannot read voxels [{x.start}:{x.stop}, {y.start}:{y.stop}, "
                              f"{z.start}:{z.stop}] ({one_line(e)})") from e
        order = sorted(self.axes)  # the block keeps the spatial axes in the array's order
        return block.transpose([order.index(a) for a in self.axes]).astype(self.dtype, copy=False)



def detect_zarr(path: Path) -> bool:
    """A folder holding Zarr metadata (a store named otherwise than ``.zarr``)."""
    return path.is_dir() and any((path / m).is_file() for m in ZARR_MARKERS)

def spatial_axes(names: list[str], shape: tuple[int, ...], label: str, time: bool = False) -> tuple[int, int, int]:
    """The array axes of x, y and z given the axes' names; every other axis must have one entry
    (with ``time``, but ``t``)."""
    lower = [n.lower() for n in names]
    missing = [n for n in SPACE_NAMES if n not in lower]
    if missing:
        raise VolumeError(f"{label}: no axis named {', '.join(missing)} among the axes {names}")
    axes = tuple(lower.index(n) for n in SPACE_NAMES)
    extra = [f"{names[a]}={shape[a]}" for a in range(len(shape))
             if a not in axes and shape[a] != 1 and not (time and lower[a] == "t")]
    if extra:
        raise VolumeError(f"{label}: a volume is one scalar field, but the axes {', '.join(extra)} "
                          "hold more than one entry" + ("; a t axis is a time series (isosr_render.series)"
                                                        if any(e.lower().startswith("t=") for e in extra) else ""))
    return axes


def zarr_steps(path: str | os.PathLike) -> TimeSteps | None:
    """The time steps of an OME-Zarr image's ``t`` axis (its finest level, a step read at a time),
    or None where it has none or one entry."""
    steps = open_zarr(path, step=0).steps
    return TimeSteps(steps, lambda i: open_zarr(path, step=i)) if steps > 1 else None


def open_zarr(path: str | os.PathLike, *, level: str | None = None, max_bytes: int | None = None,
              step: int | None = None) -> ZarrSource:
    """Open a Zarr store: an OME-Zarr multiscale image or a plain array.

    Args:
        path: the store's directory (``.zarr``, or any folder with Zarr metadata).
        level: an OME-Zarr level by its dataset path (e.g. ``"1"``).
        max_bytes: pick the finest OME-Zarr level whose voxels, in their stored type, fit.
        step: an OME-Zarr image's time step (index on its ``t`` axis, which may then hold more
            than one entry); None: the ``t`` axis must have one.

    Returns:
        The chosen level (the finest by default), its ``levels`` listing all of them.

    Raises:
        VolumeError: no array in the store, a level that is not there or none that fits,
            more than one entry along a non-spatial axis, zarr missing; one line naming the path.
    """
    zarr = require("zarr", str(path), "Zarr")
    path = Path(path)
    if level is not None and max_bytes is not None:
        raise VolumeError(f"{path}: choose a level by name or by max_bytes, not both")
    try:
        node = zarr.open(str(path), mode="r")
    except (OSError, ValueError, KeyError, zarr.errors.BaseZarrError) as e:
        raise VolumeError(f"{path}: no Zarr array or group here ({one_line(e)})") from e
    if isinstance(node, zarr.Array):
        source = _plain_source(node, path.name, str(path))
    else:
        prefix = ""
        if _ngff(node, "bioformats2raw.layout") and "0" in node:  # the image is the group "0"
            node, prefix = node["0"], "0/"
        multiscales = _ngff(node, "multiscales")
        if multiscales:
            levels = _levels(node, multiscales[0], path, prefix, step)
            return dataclasses.replace(_pick_level(levels, level, max_bytes, path), levels=levels)
        arrays = sorted(node.arrays(), key=lambda item: item[0])
        if len(arrays) != 1:
            found = f"arrays {', '.join(n for n, _ in arrays)}" if arrays else "no array"
            raise VolumeError(f"{path}: a Zarr group with {found} and no OME-Zarr multiscales metadata; "
                              "open the array itself")
        name, array = arrays[0]
        source = _plain_source(array, path.name, str(path / name))
    if level is not None or max_bytes is not None:
        raise VolumeError(f"{path}: a plain Zarr array has no levels to choose from")
    return source


def _ngff(group, key: str):
    """An NGFF attribute of the group: at the top (0.4) or under ``ome`` (0.5); None if absent."""
    attrs = group.attrs.asdict()
    return attrs.get(key, attrs.get("ome", {}).get(key))


def _plain_source(array, name: str, where: str) -> ZarrSource:
    """A plain array: axes by ``dimension_names`` / ``_ARRAY_DIMENSIONS``, else ``[x, y, z]``."""
    names = getattr(array.metadata, "dimension_names", None) or array.attrs.get("_ARRAY_DIMENSIONS")
    if names and all(names):
        axes = spatial_axes(list(names), array.shape, where)
    elif array.ndim == 3:
        axes = (0, 1, 2)
    else:
        raise VolumeError(f"{where}: expected a 3D array (or named x, y, z axes), got shape {array.shape}")
    return checked_source(ZarrSource(name, array, axes, (1.0, 1.0, 1.0), where))


def checked_source(source: ZarrSource) -> ZarrSource:
    """The source after its attributes are checked and its first chunk decoded (codecs present, data there)."""
    check_source(source, source.where)
    source.read(*(slice(0, 1) for _ in range(3)))
    return source


def _scale(transforms: list[dict] | None, ndim: int, label: str) -> np.ndarray:
    """The product of the ``scale`` coordinate transformations (translations do not change spacing)."""
    scale = np.ones(ndim)
    for t in transforms or []:
        if t.get("type") == "scale":
            values = np.asarray(t.get("scale", []), dtype=np.float64)
            if values.shape != (ndim,):
                raise VolumeError(f"{label}: a scale transformation with {values.size} values for {ndim} axes")
            scale = scale * values
    return scale


def _levels(group, multiscale: dict, path: Path, prefix: str, step: int | None = None) -> tuple[ZarrSource, ...]:
    """Every dataset of an NGFF multiscale image (the group at ``prefix`` in the store at ``path``) as
    a source, in the metadata's order (finest first); at time ``step`` (None: the ``t`` axis holds one entry)."""
    datasets = multiscale.get("datasets") or []
    if not datasets:
        raise VolumeError(f"{path}: OME-Zarr multiscales metadata lists no datasets")
    levels = []
    for dataset in datasets:
        where = path / (prefix + dataset["path"])
        try:
            array = group[dataset["path"]]
        except KeyError:
            raise VolumeError(f"{path}: the multiscales metadata names the array '{dataset['path']}', "
                              "which the store does not hold") from None
        axes_meta = multiscale.get("axes") or NGFF_DEFAULT_AXES[-array.ndim:]
        names = [a["name"] if isinstance(a, dict) else a for a in axes_meta]
        if len(names) != array.ndim:
            raise VolumeError(f"{where}: {array.ndim}D array, but the metadata names {len(names)} axes")
        if not set(SPACE_NAMES) <= {n.lower() for n in names}:  # other names: the last 3 space axes are z, y, x
            space = [i for i, a in enumerate(axes_meta) if isinstance(a, dict) and a.get("type") == "space"][-3:]
            names = [dict(zip(space, "zyx")).get(i, n) for i, n in enumerate(names)]
        axes = spatial_axes(names, array.shape, str(where), time=step is not None)
        lower = [n.lower() for n in names]
        time, steps = None, 1
        if step is not None and "t" in lower:
            time, steps = (lower.index("t"), step), int(array.shape[lower.index("t")])
            if not 0 <= step < steps:
                raise VolumeError(f"{where}: no time step {step} (t holds {steps})")
        scale = (_scale(dataset.get("coordinateTransformations"), array.ndim, str(where))
                 * _scale(multiscale.get("coordinateTransformations"), array.ndim, str(path)))
        spacing = tuple(float(scale[a]) for a in axes)
        if min(array.shape[a] for a in axes) < 2:
            continue  # a level too coarse to hold a volume
        levels.append(checked_source(ZarrSource(f"{path.name}/{prefix}{dataset['path']}", array, axes, spacing, str(where),
                                                level=dataset["path"], time=time, steps=steps)))
    return tuple(levels)


def _pick_level(levels: tuple[ZarrSource, ...], level: str | None, max_bytes: int | None,
                path: Path) -> ZarrSource:
    """The level named ``level``, else the finest within ``max_bytes``, else the finest."""
    if level is not None:
        chosen = next((s for s in levels if s.level == str(level)), None)
        if chosen is None:
            raise VolumeError(f"{path}: no level '{level}' (levels: {', '.join(s.level for s in levels)})")
        return chosen
    if max_bytes is not None:
        chosen = finest_within(levels, max_bytes)
        if chosen is None:
            smallest = min(levels, key=lambda s: s.nbytes)
            raise VolumeError(f"{path}: no level fits in {max_bytes} bytes; the smallest, "
                              f"'{smallest.level}' {smallest.shape}, needs {smallest.nbytes}")
        return chosen
    return levels[0]


def finest_within(levels: tuple[ZarrSource, ...], max_bytes: int) -> ZarrSource | None:
    """The finest level whose voxels, in their stored type, take at most ``max_bytes`` (None: none)."""
    return next((s for s in levels if s.nbytes <= max_bytes), None)
