"""The shared real volumes (``../shared/volumes``): where they are and their manifest; and
the iso-value policy for every volume source, with its one rule: an iso lies strictly inside
the volume's value range (:func:`check_iso`; the CLI and the server both call it).

A volume source is a file path, a procedural spec (``proc:cloud:7``) or a shared volume
(``shared:bonsai``); :func:`isosr_render.open_volume` opens each.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from isosr_render.procedural import default_iso
from isosr_render.volume import Volume, VolumeError

ENV_VAR = "ISOSR_SHARED_VOLUMES"
SHARED_PREFIX = "shared:"


def shared_volumes_dir() -> Path:
    """``$ISOSR_SHARED_VOLUMES``, else ``shared/volumes`` beside the project checkout."""
    if os.environ.get(ENV_VAR):
        return Path(os.environ[ENV_VAR])
    return Path(__file__).resolve().parents[2] / "shared" / "volumes"


def manifest(root: Path | None = None) -> list[dict]:
    """The entries of ``volumes.json`` (name, file, shape_xyz, spacing_xyz, value_range, split, ...).

    Raises:
        FileNotFoundError: the folder or its manifest is absent, with where it was looked for.
    """
    root = root or shared_volumes_dir()
    path = root / "volumes.json"
    if not path.is_file():
        raise FileNotFoundError(f"no shared volume manifest at {path} (set {ENV_VAR} to the volumes folder)")
    return json.loads(path.read_text())


def entry(name: str, root: Path | None = None) -> dict:
    """One manifest entry by name, with ``path`` added.

    Raises:
        VolumeError: the manifest lists no volume of that name.
    """
    root = root or shared_volumes_dir()
    for e in manifest(root):
        if e["name"] == name:
            return {**e, "path": root / e["file"]}
    raise VolumeError(f"no volume named {name!r} in {root / 'volumes.json'}")


def resolve_iso(source: str, volume: Volume, iso: float | None = None, normalized: bool = False) -> float:
    """The iso-value, on the normalized [0, 1] scale, at which to render ``volume`` opened from ``source``.

    A given ``iso`` wins: in the data's units, or already normalized with ``normalized``.
    Without one: a procedural spec's own iso (:func:`isosr_render.procedural.default_iso`), a
    shared volume's Otsu threshold from the manifest, else Otsu's threshold of the voxels
    (:func:`otsu_inside`).

    The result is not checked against the value range: :func:`check_iso` does that.

    Raises:
        ValueError: ``iso`` is not a finite number.
        VolumeError / FileNotFoundError: a ``shared:NAME`` the manifest does not list, or no manifest.
    """
    if iso is not None:
        if isinstance(iso, bool) or not isinstance(iso, (int, float)) or not math.isfinite(iso):
            raise ValueError(f"iso must be a finite number, got {iso!r}")
        return float(iso) if normalized else volume.normalized_iso(iso)
    if source.startswith("proc:"):
        return volume.normalized_iso(default_iso(source))
    if source.startswith(SHARED_PREFIX):
        return float(entry(source.removeprefix(SHARED_PREFIX))["otsu_iso_normalized"])
    return otsu_inside(volume)


def otsu_inside(volume: Volume) -> float:
    """Otsu's threshold (normalized), or mid-range where it falls on an end (two-valued data:
    OpenCV puts it at the lower value, where no surface is)."""
    otsu = volume.otsu_iso()
    return otsu if 0.0 < otsu < 1.0 else 0.5


class IsoOutOfRange(VolumeError):
    """An iso-value at or outside the volume's value range: no isosurface there."""


def degenerate(volume: Volume, label: str | None = None) -> str | None:
    """Why ``volume`` has no isosurface at any iso (one line), or None: all voxels equal."""
    lo, hi = volume.value_range
    if lo != hi:
        return None
    what = "all zeros" if lo == 0 else f"constant (every voxel {lo:g})"
    return f"{label or volume.name} is {what}: it has no isosurface at any iso"


def check_iso(volume: Volume, iso: float, label: str | None = None) -> float:
    """``iso`` (normalized) if it lies strictly inside (0, 1), the volume's value range: a surface
    needs voxels on both sides of it.

    Raises:
        IsoOutOfRange: naming the volume (``label``, else its name), the iso and the range in data units.
    """
    label = label or volume.name
    reason = degenerate(volume, label)
    if reason is None and 0.0 < iso < 1.0:
        return iso
    if reason is None:
        lo, hi = volume.value_range
        where = "at an end of" if iso in (0.0, 1.0) else "outside"
        reason = f"iso {lo + iso * (hi - lo):g} is {where} {label}'s value range [{lo:g}, {hi:g}]"
    raise IsoOutOfRange(reason)
