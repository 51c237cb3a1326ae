"""isosr_render: volumes, cameras and Warp ray casting of isosurfaces into typed buffers.

The public API::

    from isosr_render import open_volume, Renderer, RenderRequest, orbit
    volume = open_volume("proc:sphere")          # a file path or a procedural spec
    frame = Renderer(volume, "cpu").render(orbit(30, 20, 1.8), RenderRequest(256, 256, iso=0.5))

Conventions (frames, units, buffer meanings): :mod:`isosr_render.conventions`. The names below
load on first use (PEP 562), so that ``import isosr_render.conventions`` (numpy only) stays light
for the protocol and the clients, which need neither torch nor Warp.
"""

import importlib

# Public name -> the module that defines it.
_EXPORTS = {"FrameBuffers": "buffers", "Camera": "camera", "orbit": "camera", "orbit_path": "camera",
            "SHARED_PREFIX": "catalog", "entry": "catalog", "resolve_iso": "catalog",
            "parse_procedural": "procedural", "Renderer": "renderer", "RenderRequest": "renderer",
            "ShadingParams": "shading", "shade": "shading", "Volume": "volume", "VolumeError": "volume",
            "load_volume": "volume_io", "open_volume": "sources"}


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'isosr_render' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"isosr_render.{_EXPORTS[name]}"), name)
    globals()[name] = value
    return value


__all__ = ["Camera", "FrameBuffers", "Renderer", "RenderRequest", "ShadingParams", "Volume", "VolumeError",
           "load_volume", "open_volume", "orbit", "orbit_path", "parse_procedural", "resolve_iso", "shade"]
