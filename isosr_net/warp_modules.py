"""The project's Warp modules, by the names Warp keys their kernels under: what `isosr kernels` compiles
ahead of time, and (the renderer's) what isosr_bench.kernel_resources reads registers from."""

from __future__ import annotations

import importlib

import warp as wp

from isosr_render.kernels import RENDER_MODULES
from isosr_render.mesh import MESH_MODULE

NET_MODULES = ("isosr_net.ray_history", "isosr_net.filters.svgf", "isosr_net.filters.atrous")
WARP_MODULES = RENDER_MODULES + (MESH_MODULE,) + NET_MODULES


def warp_module(name: str) -> wp.Module:
    """Warp module ``name`` (a Python module's name, or a Warp module named with ``@wp.kernel(module=...)``
    below one), its kernels defined: the Python module that defines it imported first."""
    parent = name
    while True:
        try:
            importlib.import_module(parent)
            return wp.get_module(name)
        except ModuleNotFoundError as e:
            if e.name != parent or "." not in parent:
                raise
            parent = parent.rsplit(".", 1)[0]
