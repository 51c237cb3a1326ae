"""isosr_render: volumes, cameras and Warp ray casting of isosurfaces into typed buffers.

The public API::

    from isosr_render import open_volume, Renderer, RenderRequest, orbit
    volume = open_volume("proc:sphere")          # a file path or a procedural spec
    frame = Renderer(volume, "cpu").render(orbit(30, 20, 1.8), RenderRequest(256, 256, iso=0.5))

Conventions (frames, units, buffer meanings): :mod:`isosr_render.conventions`.

The names below load on first use (PEP 562), so that importing a light submodule such as
:mod:`isosr_render.conventions` or :mod:`isosr_render.image_codec` loads neither Warp nor torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

# Public name -> the submodule that defines it.
_EXPORTS = {
    "Camera": "isosr_render.camera", "orbit": "isosr_render.camera", "orbit_path": "isosr_render.camera",
    "FrameBuffers": "isosr_render.buffers", "resolve_iso": "isosr_render.catalog",
    "parse_procedural": "isosr_render.procedural", "Renderer": "isosr_render.renderer",
    "RenderRequest": "isosr_render.renderer", "ShadingParams": "isosr_render.shading", "shade": "isosr_render.shading",
    "Volume": "isosr_render.volume", "VolumeError": "isosr_render.volume", "load_volume": "isosr_render.volume_io",
}

if TYPE_CHECKING:
    from isosr_render.buffers import FrameBuffers
    from isosr_render.camera import Camera, orbit, orbit_path
    from isosr_render.catalog import resolve_iso
    from isosr_render.procedural import parse_procedural
    from isosr_render.renderer import Renderer, RenderRequest
    from isosr_render.shading import ShadingParams, shade
    from isosr_render.volume import Volume, VolumeError
    from isosr_render.volume_io import load_volume


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'isosr_render' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this hook
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


def open_volume(source: str) -> Volume:
    """A volume from a file path, a procedural spec such as ``proc:cloud:7``, or a shared volume
    such as ``shared:bonsai`` (:mod:`isosr_render.catalog`)."""
    from isosr_render.catalog import SHARED_PREFIX, entry
    from isosr_render.procedural import parse_procedural
    from isosr_render.volume_io import load_volume

    if source.startswith("proc:"):
        return parse_procedural(source)
    if source.startswith(SHARED_PREFIX):
        return load_volume(str(entry(source.removeprefix(SHARED_PREFIX))["path"]))
    return load_volume(source)


__all__ = ["Camera", "FrameBuffers", "Renderer", "RenderRequest", "ShadingParams", "Volume", "VolumeError",
           "load_volume", "open_volume", "orbit", "orbit_path", "parse_procedural", "resolve_iso", "shade"]
