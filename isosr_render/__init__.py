"""isosr_render: volumes, cameras and Warp ray casting of isosurfaces into typed buffers.

The public API::

    from isosr_render import open_volume, Renderer, RenderRequest, orbit
    volume = open_volume("proc:sphere")          # a file path or a procedural spec
    frame = Renderer(volume, "cpu").render(orbit(30, 20, 1.8), RenderRequest(256, 256, iso=0.5))

Conventions (frames, units, buffer meanings): :mod:`isosr_render.conventions`.
"""

from isosr_render.buffers import FrameBuffers
from isosr_render.camera import Camera, orbit, orbit_path
from isosr_render.catalog import SHARED_PREFIX, entry, resolve_iso
from isosr_render.procedural import parse_procedural
from isosr_render.renderer import Renderer, RenderRequest
from isosr_render.shading import ShadingParams, shade
from isosr_render.volume import Volume, VolumeError
from isosr_render.volume_io import load_volume


def open_volume(source: str) -> Volume:
    """A volume from a file path, a procedural spec such as ``proc:cloud:7``, or a shared volume
    such as ``shared:bonsai`` (:mod:`isosr_render.catalog`)."""
    if source.startswith("proc:"):
        return parse_procedural(source)
    if source.startswith(SHARED_PREFIX):
        return load_volume(str(entry(source.removeprefix(SHARED_PREFIX))["path"]))
    return load_volume(source)


__all__ = ["Camera", "FrameBuffers", "Renderer", "RenderRequest", "ShadingParams", "Volume", "VolumeError",
           "load_volume", "open_volume", "orbit", "orbit_path", "parse_procedural", "resolve_iso", "shade"]
