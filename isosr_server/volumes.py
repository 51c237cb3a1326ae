"""The volumes a server offers: files of its ``--volumes`` folder by name, and small procedural ones.

Clients name volumes; they never send paths. A name is looked up in the folder's
``volumes.json`` manifest (or, without one, among the folder's volumes: files by their name
without extension, a DICOM series or TIFF stack folder or a ``.zarr`` store each as one volume,
see :func:`isosr_render.volume_io.volume_name`); ``proc:`` specs are built here, at most
``MAX_PROCEDURAL_SIZE`` voxels a side.

A multiscale OME-Zarr is served at one level, chosen by the server's memory setting
(``--max-volume-bytes``, the renderers' ``max_device_bytes``): the finest level whose voxels fit
it, which then renders dense (no paging on iso changes); if none fits, the coarsest, which
renders sparse (only the bricks an iso needs resident: the fewest of any level). Without a
setting, the finest (on CUDA the renderer then goes sparse above half the free memory). A level
too big for dense could render sparse too, but each iso change would page its bricks in and an
iso touching many bricks would not fit; the finest level that fits keeps every iso working.
Listings show every level and the one served.

Time series (:mod:`isosr_render.series`): a folder of volume files that is no volume itself, a
manifest entry whose ``file`` is a glob, a 4D NIfTI, a ``(t, z, y, x)`` ``.npy`` or an OME-Zarr
with a ``t`` axis is one volume with ``steps``; its step 0 stands for it where one volume is
meant (value range, suggested iso, histogram, slices, meshes), and view sessions show any step
(:class:`isosr_server.sessions.StepView`). A series whose steps differ in shape, spacing or
dtype is listed with the ``error`` naming the first that differs.

Bad folders and data. A volume that cannot be opened stays listed, with the reason as ``error``
(found by a cheap check when first listed, :func:`isosr_render.volume_io.probe`, or by a failed
load); opening it answers 422 / CLOSE_POLICY with that reason. A loaded constant volume lists why
it has no isosurface. Entries of the folder (symlinks) or manifest that resolve outside it are
skipped with a warning when the catalog is made. Routes load volumes with :func:`load_volume`, which
answers bad names with 400, unknown ones with 404; a view's iso goes through :func:`session_iso`.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path

from isosr_render import Volume, VolumeError, open_volume
from isosr_render.catalog import IsoOutOfRange, check_iso, degenerate, manifest, otsu_inside
from isosr_render.formats import format_of
from isosr_render.formats.zarr import ZarrSource, finest_within, open_zarr
from isosr_render.procedural import default_iso
from isosr_render.series import VolumeSeries, is_series, open_series
from isosr_render.volume_io import probe, volume_name
from isosr_render.coloring import GRADIENT
from isosr_server.protocol import (CLOSE_NOT_FOUND, CLOSE_POLICY, VOLUME_NAME, ProtocolError, SettingRefused,
                                   ViewSettings)

log = logging.getLogger("isosr.server")

MAX_PROCEDURAL_SIZE = 128
PROCEDURAL_OFFER = ("proc:sphere", "proc:torus", "proc:cloud:0", "proc:metaballs:0")
HISTOGRAM_BINS = 64
CACHE = 4


class UnknownVolume(KeyError):
    """The client named a volume this server does not offer."""

    def __str__(self) -> str:
        return self.args[0]


class VolumeTooBig(ValueError):
    """The client asked for a procedural volume larger than this server builds."""


@dataclass(frozen=True)
class VolumeInfo:
    """What a viewer needs to pick a volume and an iso-value.

    Attributes:
        name: the name clients use.
        shape: voxels (x, y, z).
        value_range: original data range.
        iso: suggested iso-value, data units (`VolumeCatalog.suggested_iso`).
        histogram: voxel counts in ``HISTOGRAM_BINS`` equal bins over ``value_range``
            (None until the volume was loaded).
        level: a multiscale volume's level served (module docstring); None for others.
        levels: a multiscale volume's levels, finest first: ``level`` (dataset path), ``shape``
            and ``bytes`` (voxels in their stored type).
        error: why no view can open it (unreadable, or constant); None for a good volume. In
            the JSON only when set.
        steps: a time series' steps (1: a volume).
    """

    name: str
    shape: tuple[int, int, int] | None
    value_range: tuple[float, float] | None
    iso: float | None
    histogram: list[int] | None = None
    level: str | None = None
    levels: list[dict] | None = None
    error: str | None = None
    steps: int = 1

    def to_json(self) -> dict:
        info = {"name": self.name, "shape": self.shape, "value_range": self.value_range, "iso": self.iso,
                "histogram": self.histogram, "histogram_bins": HISTOGRAM_BINS, "level": self.level,
                "levels": self.levels, "steps": self.steps}
        return info if self.error is None else info | {"error": self.error}


class VolumeCatalog:
    """Names -> volumes (files, DICOM/TIFF folders, Zarr stores) of one folder, plus procedural specs;
    loaded volumes cached (LRU).

    Args:
        root: the ``--volumes`` folder, or None for procedural volumes only.
        max_bytes: the server's device memory setting, which picks a multiscale volume's level
            (module docstring); None: the finest.
    """

    def __init__(self, root: Path | None, max_bytes: int | None = None):
        self.root = None if root is None else Path(root).resolve()
        self.max_bytes = max_bytes
        self._levels: dict[str, tuple[ZarrSource, ...]] = {}
        self._series: dict[str, VolumeSeries | None] = {}  # name -> its series (None: one volume)
        self._files: dict[str, Path] = {}
        self._manifest: dict[str, dict] = {}
        self._errors: dict[str, str] = {}  # name -> why it cannot be opened
        self._probed: set[str] = set()
        if self.root is not None:
            if not self.root.is_dir():
                raise FileNotFoundError(f"volumes folder {self.root} does not exist")
            if (self.root / "volumes.json").is_file():
                for e in manifest(self.root):
                    if self._inside(self.root / e["file"], f"volumes.json entry {e['name']!r}"):
                        self._manifest[e["name"]] = e
                        self._files[e["name"]] = self.root / e["file"]
            else:
                for path in sorted(self.root.iterdir()):
                    if path.name.startswith(".") or not self._inside(path):
                        continue
                    name = volume_name(path) or (path.name if path.is_dir() and is_series(path) else None)
                    if name:
                        self._files.setdefault(name, path)
        self._cache: dict[str, tuple[Volume, VolumeInfo]] = {}
        self._lock = threading.Lock()

    def _inside(self, path: Path, what: str | None = None) -> bool:
        """Whether ``path`` resolves inside the folder; a warning (once: at start) where it does not."""
        try:
            inside = self.root in path.resolve().parents
        except (OSError, RuntimeError):  # a symlink loop
            inside = False
        if not inside:
            log.warning("volumes folder: skipped %s: it leads outside %s", what or path.name, self.root)
        return inside

    def names(self) -> list[str]:
        return list(self._files) + list(PROCEDURAL_OFFER)

    def _probe(self, name: str, source: str) -> None:
        """Check a file or folder once, cheaply (`probe`); remember why it cannot be opened."""
        if name in self._probed or source.startswith("proc:"):
            return
        self._probed.add(name)
        try:
            if self.series(name) is None:
                probe(source)
        except (VolumeError, OSError) as e:
            self._remember(name, e)

    def series(self, name: str) -> VolumeSeries | None:
        """The time series behind a name (its files' headers checked once: `VolumeError` naming the
        first step that differs), or None for a single volume."""
        if name not in self._series:
            source = self._source(name)
            found = None if source.startswith("proc:") else open_series(source)
            self._series[name] = found if found is not None and found.count > 1 else None
        return self._series[name]

    def _remember(self, name: str, e: Exception) -> str:
        """Record why ``name`` cannot be opened: one line, paths relative to the folder."""
        reason = " ".join(str(e).split())
        if self.root is not None:
            reason = reason.replace(str(self.root) + os.sep, "")
        self._errors[name] = reason
        return reason

    def _source(self, name: str) -> str:
        """The file path or procedural spec behind a name; `UnknownVolume` or `VolumeTooBig` otherwise."""
        if name.startswith("proc:"):
            size = name.partition("@")[2]
            if size and not size.isdigit():
                raise UnknownVolume(f"no procedural volume {name!r}: its size must be a number")
            if size and int(size) > MAX_PROCEDURAL_SIZE:
                raise VolumeTooBig(f"procedural volumes here take a size of at most {MAX_PROCEDURAL_SIZE}: {name!r}")
            try:
                default_iso(name)  # validates the spec
            except ValueError as e:
                raise UnknownVolume(str(e)) from None
            return name
        path = self._files.get(name)
        if path is None:
            raise UnknownVolume(f"no volume named {name!r}; GET /v1/volumes lists them")
        # Names come from the folder listing or its manifest; a manifest entry may still point outside.
        if self.root not in path.resolve().parents:
            raise UnknownVolume(f"volume {name!r} lies outside the volumes folder")
        return str(path)

    def info(self, name: str) -> VolumeInfo:
        """Metadata without loading: from the manifest, the cache, the procedural spec, or a
        multiscale store's metadata (its levels); ``error`` where the file or folder cannot be
        opened (checked once, headers only: blocking)."""
        if name in self._cache:
            return self._cache[name][1]
        try:
            source = self._source(name)
        except UnknownVolume as e:
            if name not in self._files:
                raise
            return VolumeInfo(name, None, None, None, error=str(e))  # retargeted outside since the start
        self._probe(name, source)
        try:
            level, levels = self._level(name, source)
        except VolumeError as err:
            level, levels = None, None
            self._remember(name, err)
        e = self._manifest.get(name)
        error = self._errors.get(name)
        steps = self._steps(name)
        if e is None:
            shape = None if level is None else level.shape
            return VolumeInfo(name, shape, None, self.suggested_iso(name, None), None, *_level_json(level, levels),
                              error, steps)
        value_range = tuple(e["value_range"])
        return VolumeInfo(name, tuple(e["shape_xyz"]), value_range, self.suggested_iso(name, value_range), None,
                          *_level_json(level, levels), error, steps)

    def _steps(self, name: str) -> int:
        """A series' steps, 1 for a volume (and for a series that cannot be opened)."""
        series = self._series.get(name)
        return 1 if series is None else series.count

    def _level(self, name: str, source: str) -> tuple[ZarrSource | None, tuple[ZarrSource, ...]]:
        """The level served of a multiscale store (module docstring) and all its levels; (None, ())
        for other volumes. The store's metadata is read once."""
        if name not in self._levels:
            fmt = None if source.startswith("proc:") or self.series(name) is not None else format_of(source)
            self._levels[name] = open_zarr(source).levels if fmt is not None and fmt.levels else ()
        levels = self._levels[name]
        if not levels:
            return None, ()
        fits = levels[0] if self.max_bytes is None else finest_within(levels, self.max_bytes)
        return fits or levels[-1], levels

    def suggested_iso(self, name: str, value_range: tuple[float, float] | None,
                      volume: Volume | None = None) -> float | None:
        """The suggested iso-value in data units, the same before and after loading: a procedural
        spec's own; the manifest's Otsu threshold; else, once loaded, Otsu's threshold of the voxels
        (:func:`isosr_render.catalog.otsu_inside`)."""
        if name.startswith("proc:"):
            return default_iso(name)
        normalized = self._manifest.get(name, {}).get("otsu_iso_normalized")
        if normalized is None and volume is not None:
            normalized = otsu_inside(volume)
        if normalized is None:
            return None
        lo, hi = value_range
        return lo + normalized * (hi - lo)

    def load(self, name: str) -> tuple[Volume, VolumeInfo]:
        """The volume and its full info (histogram included); loads and caches it (blocking).

        Raises:
            VolumeError: it cannot be opened; the reason is also listed from now on.
        """
        source = self._source(name)
        with self._lock:
            if name in self._cache:
                self._cache[name] = self._cache.pop(name)  # most recent last
                return self._cache[name]
            try:
                level, levels = self._level(name, source)
                series = self.series(name)
                if series is not None:
                    volume = series.step(0)
                else:
                    volume = open_volume(source) if level is None else Volume.from_source(level)
            except (VolumeError, OSError) as e:
                raise VolumeError(self._remember(name, e)) from None
            self._errors.pop(name, None)
            counts = volume.histogram(HISTOGRAM_BINS)
            iso = self.suggested_iso(name, volume.value_range, volume)
            info = VolumeInfo(name, volume.shape, volume.value_range, iso, counts.tolist(), *_level_json(level, levels),
                              degenerate(volume, name), self._steps(name))
            self._cache[name] = (volume, info)
            while len(self._cache) > CACHE:
                self._cache.pop(next(iter(self._cache)))
            return volume, info


def _level_json(level: ZarrSource | None, levels: tuple[ZarrSource, ...]) -> tuple[str | None, list[dict] | None]:
    """`VolumeInfo`'s ``level`` and ``levels`` of a multiscale volume (None, None for others)."""
    if level is None:
        return None, None
    return level.level, [{"level": s.level, "shape": s.shape, "bytes": s.nbytes} for s in levels]


async def load_volume(catalog: VolumeCatalog, name: str) -> tuple[Volume, VolumeInfo]:
    """The named volume and its info, loaded off the event loop; `ProtocolError` 400 for a name
    that is no name (a path) or a procedural volume over the bound, 404 (CLOSE_NOT_FOUND) for an
    unknown one, 422 (CLOSE_POLICY) with the reason for one that cannot be opened."""
    if not VOLUME_NAME.match(name):
        raise ProtocolError(f"bad volume name {name!r}: a name from GET /v1/volumes, never a path"[:200])
    try:
        return await asyncio.to_thread(catalog.load, name)
    except VolumeTooBig as e:
        raise ProtocolError(str(e)) from None
    except UnknownVolume as e:
        raise ProtocolError(str(e), CLOSE_NOT_FOUND, 404) from None
    except VolumeError as e:
        raise ProtocolError(f"volume {name!r} cannot be opened: {e}", CLOSE_POLICY, 422) from None


async def coloring_field(catalog: VolumeCatalog, settings: ViewSettings, volume: Volume,
                         seq: int | None = None) -> Volume | None:
    """The volume ``settings.coloring`` colours by (None: no coloring, or the gradient), loaded off the event
    loop (the catalog caches it); `SettingRefused` (of the update ``seq``) as :func:`load_volume`'s error
    for its name, 422 (CLOSE_POLICY) for another grid than ``volume``'s, naming both shapes."""
    coloring = settings.coloring
    if coloring is None or coloring.by == GRADIENT:
        return None
    try:
        field, _ = await load_volume(catalog, coloring.by)
    except ProtocolError as e:
        raise SettingRefused(f"settings.coloring.by: {e.reason}", e.close_code, e.http_status, seq) from None
    if field.shape != volume.shape:
        raise SettingRefused(f"settings.coloring.by: {coloring.by!r} has the grid {field.shape}, not the viewed "
                             f"volume's {volume.shape}: a coloring needs the same grid", CLOSE_POLICY, 422, seq)
    return field


def session_iso(volume: Volume, name: str, iso: float, normalized: bool, field: str) -> float:
    """A view session's iso, normalized, if :func:`isosr_render.catalog.check_iso` takes it;
    else `ProtocolError` (CLOSE_POLICY, 422) naming ``field`` and the value range."""
    try:
        return check_iso(volume, iso if normalized else volume.normalized_iso(iso), name)
    except IsoOutOfRange as e:
        raise ProtocolError(f"{field}: {e}", CLOSE_POLICY, 422) from None
