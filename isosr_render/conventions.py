"""The conventions every stage of isosr shares, written once.

World frame
    Right-handed. The volume's axes x, y, z are the world's x, y, z. Voxel values are point
    samples on a grid (as in VTK image data): voxel ``(i, j, k)`` sits at
    ``(i, j, k) * spacing``, so the data spans ``(n - 1) * spacing`` per axis. That box is
    centered at the origin and scaled so that its longest side is 1. Lengths given "in
    world units" (step, AO radius, depth) are in this frame.

View space
    OpenGL style: the camera sits at the origin and looks down -z, +x points right and +y
    up. Image rows run top to bottom: pixel ``(row, col)`` has its center at
    ``(col + 0.5, row + 0.5)`` in pixel coordinates, x right and y down.

Buffers (float32, image layout ``(H, W[, C])``)
    mask     1 where the pixel's ray hits the isosurface, else 0. With supersampling it is
             the covered fraction of the pixel, in [0, 1]; the network's mask is an alpha
             in [0, 1] too.
    normal   unit surface normal in view space, the direction of the scalar field's
             gradient turned to face the camera (``dot(normal, to_camera) >= 0``). Where the
             gradient vanishes it is the direction back along the ray. 0 where mask is 0.
    depth    view-space depth of the hit, ``-z_view`` (positive in front of the camera), in
             world units. 0 where mask is 0.
    position world-space hit point. 0 where mask is 0.
    flow     backward screen-space flow in pixels: ``flow[row, col] = p_prev - p_cur``,
             where ``p_cur`` is the pixel's position and ``p_prev`` is where the same
             surface point projects in the previous frame (x right, y down). Sampling the
             previous frame at ``p_cur + flow`` aligns it with the current frame. 0 where
             mask is 0 (unless a dense fill is asked for) or where the point lay behind the
             previous camera.
    ao       ambient occlusion in [0, 1], 1 = unoccluded. 0 where mask is 0.
    color    shaded color in [0, 1], RGB, composited over the background.
    cap      where clip planes or a crop box cut the solid open (:mod:`isosr_render.clip`), two
             channels: the fraction of the pixel's rays that hit a cut face (at most mask), and
             the mean normalized volume value where they hit it. 0 elsewhere.
    albedo   with a coloring (:mod:`isosr_render.coloring`), the colour map's RGB of the coloring's
             values at ``position``, the surface's colour in shading; with several isosurfaces
             (:mod:`isosr_render.surfaces`), the colour of the pixel's surface. 0 where mask is 0.
    surface  with several isosurfaces, the index of the one the pixel shows (of its first ray
             that hits), -1 where mask is 0.
"""

from __future__ import annotations

import numpy as np

# Ambient occlusion rays' length in world units: what the networks were trained with, and every
# stage's default (renderer, frame methods, budget policy, service, command line).
AO_RADIUS = 0.05

# Buffer names in the order the frame file and the API list them.
BUFFER_NAMES = ("mask", "normal", "depth", "position", "flow", "ao", "color", "cap", "albedo", "surface")
# Channels per buffer; 1 means a plain (H, W) image.
BUFFER_CHANNELS = {"mask": 1, "normal": 3, "depth": 1, "position": 3, "flow": 2, "ao": 1, "color": 3, "cap": 2,
                   "albedo": 3, "surface": 1}

# The network's tensors are channels-first, (B, C, H, W), in these channel orders.
# Low-res input: mask, view-space normal, depth; flow travels beside it as (B, 2, H, W).
LOWRES_CHANNELS = ("mask", "normal_x", "normal_y", "normal_z", "depth")
# High-res output and ground truth: the input's channels, then ambient occlusion.
HIGHRES_CHANNELS = LOWRES_CHANNELS + ("ao",)
# The buffers that hold those channels, in the same order.
LOWRES_BUFFERS = ("mask", "normal", "depth")
HIGHRES_BUFFERS = LOWRES_BUFFERS + ("ao",)
MASK, NORMAL, DEPTH, AO = slice(0, 1), slice(1, 4), slice(4, 5), slice(5, 6)
# Full-resolution reconstruction input: the low-res channels rendered at full resolution, the AO
# of a few rays (0 where none were cast), and how it was sampled: AO rays per sample
# (``ao_rays``) and rays per pixel (``spp``), each a constant image scaled as the network's
# module says. Output and ground truth are laid out as HIGHRES_CHANNELS.
RECON_CHANNELS = LOWRES_CHANNELS + ("ao", "ao_rays", "spp")
SAMPLED_AO, SAMPLING = slice(5, 6), slice(6, 8)

# Background color behind the isosurface (RGB in [0, 1]).
BACKGROUND_RGB = (1.0, 1.0, 1.0)
# The surface's colour without a coloring (the shading's albedo; a surface's of several without one).
MATERIAL_RGB = (0.85, 0.78, 0.62)


def world_from_voxel(shape: tuple[int, int, int], spacing: tuple[float, float, float]):
    """Per-axis scale and offset so that ``world = voxel * scale + offset``.

    Args:
        shape: voxel counts ``(nx, ny, nz)``, each at least 2.
        spacing: voxel spacing per axis, positive.

    Returns:
        ``(scale, offset)``, two float64 arrays of shape (3,).
    """
    shape_a = np.asarray(shape, dtype=np.float64)
    spacing_a = np.asarray(spacing, dtype=np.float64)
    extent = (shape_a - 1.0) * spacing_a
    scale = spacing_a / extent.max()
    offset = -0.5 * extent / extent.max()
    return scale, offset

