"""The volumes a server offers: files of its ``--volumes`` folder by name, and small procedural ones.

Clients name volumes; they never send paths. A name is looked up in the folder's
``volumes.json`` manifest (or, without one, among the folder's volume files by their name
without extension); ``proc:`` specs are built here, at most ``MAX_PROCEDURAL_SIZE`` voxels a side.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from isosr_render import Volume, open_volume
from isosr_render.catalog import manifest
from isosr_render.procedural import default_iso

MAX_PROCEDURAL_SIZE = 128
PROCEDURAL_OFFER = ("proc:sphere", "proc:torus", "proc:cloud:0", "proc:metaballs:0")
VOLUME_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".dat", ".raw", ".raw.gz", ".npy", ".npz")
HISTOGRAM_BINS = 64
CACHE = 4


class UnknownVolume(KeyError):
    """The client named a volume this server does not offer."""

    def __str__(self) -> str:
        return self.args[0]


@dataclass(frozen=True)
class VolumeInfo:
    """What a viewer needs to pick a volume and an iso-value.

    Attributes:
        name: the name clients use.
        shape: voxels (x, y, z).
        value_range: original data range.
        iso: suggested iso-value, data units (the procedural one, else Otsu's threshold).
        histogram: voxel counts in ``HISTOGRAM_BINS`` equal bins over ``value_range``
            (None until the volume was loaded).
    """

    name: str
    shape: tuple[int, int, int] | None
    value_range: tuple[float, float] | None
    iso: float | None
    histogram: list[int] | None = None

    def to_json(self) -> dict:
        return {"name": self.name, "shape": self.shape, "value_range": self.value_range, "iso": self.iso,
                "histogram": self.histogram, "histogram_bins": HISTOGRAM_BINS}


def _file_name(path: Path) -> str | None:
    """A volume file's name without its (possibly double) extension, or None for other files."""
    for suffix in sorted(VOLUME_SUFFIXES, key=len, reverse=True):
        if path.name.endswith(suffix):
            return path.name[: -len(suffix)]
    return None


class VolumeCatalog:
    """Names -> volume files of one folder, plus procedural specs; loaded volumes cached (LRU).

    Args:
        root: the ``--volumes`` folder, or None for procedural volumes only.
    """

    def __init__(self, root: Path | None):
        self.root = None if root is None else Path(root).resolve()
        self._files: dict[str, Path] = {}
        self._manifest: dict[str, dict] = {}
        if self.root is not None:
            if not self.root.is_dir():
                raise FileNotFoundError(f"volumes folder {self.root} does not exist")
            if (self.root / "volumes.json").is_file():
                for e in manifest(self.root):
                    self._manifest[e["name"]] = e
                    self._files[e["name"]] = self.root / e["file"]
            else:
                for path in sorted(self.root.iterdir()):
                    name = _file_name(path)
                    if name and path.is_file() and not name.startswith("."):
                        self._files.setdefault(name, path)
        self._cache: dict[str, tuple[Volume, VolumeInfo]] = {}
        self._lock = threading.Lock()

    def names(self) -> list[str]:
        return list(self._files) + list(PROCEDURAL_OFFER)

    def _source(self, name: str) -> str:
        """The file path or procedural spec behind a name; `UnknownVolume` otherwise."""
        if name.startswith("proc:"):
            size = name.partition("@")[2]
            if size and (not size.isdigit() or int(size) > MAX_PROCEDURAL_SIZE):
                raise UnknownVolume(f"procedural volumes here take a size of at most {MAX_PROCEDURAL_SIZE}: {name!r}")
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
        """Metadata without loading: from the manifest, the cache, or the procedural spec."""
        if name in self._cache:
            return self._cache[name][1]
        self._source(name)
        e = self._manifest.get(name)
        if e is None:
            return VolumeInfo(name, None, None, default_iso(name) if name.startswith("proc:") else None)
        lo, hi = e["value_range"]
        iso = lo + e["otsu_iso_normalized"] * (hi - lo) if "otsu_iso_normalized" in e else None
        return VolumeInfo(name, tuple(e["shape_xyz"]), (lo, hi), iso)

    def load(self, name: str) -> tuple[Volume, VolumeInfo]:
        """The volume and its full info (histogram included); loads and caches it (blocking)."""
        source = self._source(name)
        with self._lock:
            if name in self._cache:
                self._cache[name] = self._cache.pop(name)  # most recent last
                return self._cache[name]
            volume = open_volume(source)
            lo, hi = volume.value_range
            iso = default_iso(name) if name.startswith("proc:") else lo + volume.otsu_iso() * (hi - lo)
            counts, _ = np.histogram(volume.data, bins=HISTOGRAM_BINS, range=(0.0, 1.0))
            info = VolumeInfo(name, volume.shape, (lo, hi), iso, counts.tolist())
            self._cache[name] = (volume, info)
            while len(self._cache) > CACHE:
                self._cache.pop(next(iter(self._cache)))
            return volume, info
