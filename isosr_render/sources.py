"""Where a volume comes from: a file path, a procedural spec, or a shared volume by name.

An OME-Zarr source may name its multiscale level after a ``#`` (written once, here):
``scan.zarr#level=2`` (the level's dataset path) or ``scan.zarr#max-gb=8`` (the finest level
whose voxels, in their stored type, take at most 8 GB = 8e9 bytes). Without one, the finest.
"""

from __future__ import annotations

import re

from isosr_render.catalog import SHARED_PREFIX, entry
from isosr_render.procedural import parse_procedural
from isosr_render.volume import Volume, VolumeError
from isosr_render.volume_io import load_volume

LEVEL_SPEC = re.compile(r"^(?P<path>.+)#(?:level=(?P<level>[^#=]+)|max-gb=(?P<gb>[^#=]+))$")


def level_spec(source: str) -> tuple[str, dict]:
    """``source`` without its level suffix, and the suffix as :func:`load_volume`'s ``level`` /
    ``max_bytes`` (empty without one); a ``#`` followed by anything else stays part of the path."""
    found = LEVEL_SPEC.match(source)
    if found is None:
        return source, {}
    if found["level"] is not None:
        return found["path"], {"level": found["level"]}
    try:
        gb = float(found["gb"])
    except ValueError:
        gb = float("nan")
    if not 0 < gb < float("inf"):
        raise VolumeError(f"{source}: max-gb must be a positive number of gigabytes, got {found['gb']!r}")
    return found["path"], {"max_bytes": int(gb * 1e9)}


def open_volume(source: str) -> Volume:
    """A volume from a file path (an OME-Zarr's with a level suffix, module docstring), a procedural
    spec such as ``proc:cloud:7``, or a shared volume such as ``shared:bonsai``
    (:mod:`isosr_render.catalog`)."""
    if source.startswith("proc:"):
        return parse_procedural(source)
    if source.startswith(SHARED_PREFIX):
        return load_volume(str(entry(source.removeprefix(SHARED_PREFIX))["path"]))
    path, levels = level_spec(source)
    return load_volume(path, **levels)
