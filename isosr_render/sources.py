"""Where a volume comes from: a file path, a procedural spec, or a shared volume by name."""

from __future__ import annotations

from isosr_render.catalog import SHARED_PREFIX, entry
from isosr_render.procedural import parse_procedural
from isosr_render.volume import Volume
from isosr_render.volume_io import load_volume


def open_volume(source: str) -> Volume:
    """A volume from a file path, a procedural spec such as ``proc:cloud:7``, or a shared volume
    such as ``shared:bonsai`` (:mod:`isosr_render.catalog`)."""
    if source.startswith("proc:"):
        return parse_procedural(source)
    if source.startswith(SHARED_PREFIX):
        return load_volume(str(entry(source.removeprefix(SHARED_PREFIX))["path"]))
    return load_volume(source)
