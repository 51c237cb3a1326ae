"""Screen-space Phong shading of buffers, differentiable (torch).

The one shading function of the project: the renderer's ``color`` buffer, the network's
losses and evaluation, the server and the clients all call :func:`shade`. Light and view
directions are fixed in view space (a headlight slightly above and left of the camera,
the viewer along +z), so a frame shades from its buffers alone.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from isosr_render.conventions import (
    AO,
    BACKGROUND_RGB,
    HIGHRES_CHANNELS,
    LOWRES_CHANNELS,
    MASK,
    MATERIAL_RGB,
    NORMAL,
)


@dataclass(frozen=True)
class ShadingParams:
    """Phong material and light, view space."""

    albedo: tuple[float, float, float] = MATERIAL_RGB
    ambient: float = 0.25
    diffuse: float = 0.65
    specular: float = 0.25
    shininess: float = 24.0
    light_dir: tuple[float, float, float] = (-0.3, 0.4, 1.0)
    background: tuple[float, float, float] = BACKGROUND_RGB


def shade(mask: torch.Tensor, normal: torch.Tensor, ao: torch.Tensor | None = None,
          params: ShadingParams = ShadingParams(), cap: torch.Tensor | None = None,
          albedo: torch.Tensor | None = None) -> torch.Tensor:
    """Phong (ambient + diffuse + specular) times AO, composited by ``mask`` over the background.

    Args:
        mask: coverage / alpha in [0, 1].
        normal: view-space normals; normalized here, so network outputs need not be unit.
        ao: ambient occlusion in [0, 1]; ``None`` shades without occlusion.
        params: material and light.
        cap: the cut faces (conventions): where the pixel's hits are on them, the albedo is the
            volume's value in grey (:func:`cap_albedo`); ``None``: no cut faces.
        albedo: per pixel surface colour in [0, 1] (a coloring's, :mod:`isosr_render.coloring`) instead of
            the material's; ``None``: the material's.

    Returns:
        RGB color in [0, 1].

    Shape:
        mask, ao: (*, H, W). normal, albedo: (*, H, W, 3). cap: (*, H, W, 2). Returns (*, H, W, 3).
    """
    if normal.shape[-1] != 3 or normal.shape[:-1] != mask.shape:
        raise ValueError(f"shade: normal must be mask's shape + (3,), got normal {tuple(normal.shape)} "
                         f"and mask {tuple(mask.shape)}")
    if ao is not None and ao.shape != mask.shape:
        raise ValueError(f"shade: ao must have mask's shape {tuple(mask.shape)}, got {tuple(ao.shape)}")
    if cap is not None and cap.shape != (*mask.shape, 2):
        raise ValueError(f"shade: cap must be mask's shape + (2,), got cap {tuple(cap.shape)}")
    if albedo is not None and albedo.shape != normal.shape:
        raise ValueError(f"shade: albedo must be mask's shape + (3,), got albedo {tuple(albedo.shape)}")
    # Light, half vector, albedo and background enter as Python numbers, not as device tensors:
    # building a tensor on a GPU from host values is a blocking copy, a stall per frame.
    light, half = light_and_half(params)
    n = F.normalize(normal, dim=-1, eps=1e-6)
    nx, ny, nz = n.unbind(-1)
    n_dot_l = (nx * light[0] + ny * light[1] + nz * light[2]).clamp(min=0.0)
    n_dot_h = (nx * half[0] + ny * half[1] + nz * half[2]).clamp(min=0.0)
    diffuse = params.ambient + params.diffuse * n_dot_l
    specular = params.specular * n_dot_h.pow(params.shininess)
    occlusion = 1.0 if ao is None else ao
    alpha = mask.clamp(0.0, 1.0)
    surface = params.albedo if albedo is None else albedo.unbind(-1)
    surface = surface if cap is None else cap_albedo(cap, mask, surface)
    return torch.stack([(alpha * ((a * diffuse + specular) * occlusion) + (1.0 - alpha) * b).clamp(0.0, 1.0)
                        for a, b in zip(surface, params.background)], dim=-1)


def cap_albedo(cap: torch.Tensor, mask: torch.Tensor,
               albedo: tuple) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per pixel albedo ``(r, g, b)``: the surface's (numbers or (*, H, W) tensors), blended towards the cut
    faces' grey map of the volume's value (normalized, clamped to [0, 1]) by the share of the pixel's hits on them.

    Shape:
        cap: (*, H, W, 2). mask: (*, H, W). Returns three (*, H, W).
    """
    share = (cap[..., 0] / mask.clamp(min=1e-6)).clamp(0.0, 1.0)
    grey = cap[..., 1].clamp(0.0, 1.0)
    return tuple(a + share * (grey - a) for a in albedo)


@functools.lru_cache(maxsize=None)
def shade_on(device_type: str) -> Callable[..., torch.Tensor]:
    """:func:`shade` as it runs fastest on a device type: on CUDA compiled (its twenty-odd
    elementwise operations fused, with shapes dynamic: no recompiling for a new frame size; a few
    seconds to compile on first use), elsewhere as it is (compiling costs CPUs more than it saves).
    The same function: equal to :func:`shade` within float32 rounding."""
    return torch.compile(shade, dynamic=True) if device_type == "cuda" else shade


def light_and_half(params: ShadingParams) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """The unit light direction and the unit half vector between it and the viewer (+z)."""
    light = _unit(params.light_dir)
    return light, _unit(tuple(a + b for a, b in zip(light, (0.0, 0.0, 1.0))))


def _unit(v: tuple[float, float, float]) -> tuple[float, float, float]:
    """``v`` scaled to unit length (the zero vector stays zero, as F.normalize leaves it)."""
    length = max(math.sqrt(sum(c * c for c in v)), 1e-12)
    return tuple(c / length for c in v)


def shade_channels_first(stack: torch.Tensor, params: ShadingParams = ShadingParams()) -> torch.Tensor:
    """:func:`shade` for the network's channels-first buffer stacks.

    Args:
        stack: buffers in ``HIGHRES_CHANNELS`` order, or ``LOWRES_CHANNELS`` (no AO: shaded
            without occlusion).
        params: material and light.

    Returns:
        RGB color in [0, 1].

    Shape:
        stack: (B, 6, H, W) or (B, 5, H, W). Returns (B, 3, H, W).
    """
    if stack.ndim != 4 or stack.shape[1] not in (len(HIGHRES_CHANNELS), len(LOWRES_CHANNELS)):
        raise ValueError(f"shade_channels_first: stack must be (B, 6, H, W) or (B, 5, H, W), got {tuple(stack.shape)}")
    ao = stack[:, AO.start] if stack.shape[1] == len(HIGHRES_CHANNELS) else None
    color = shade(stack[:, MASK.start], stack[:, NORMAL].permute(0, 2, 3, 1), ao, params)
    return color.permute(0, 3, 1, 2)


def composite(front: torch.Tensor, behind: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Two layers' colours front to back: ``alpha * front + (1 - alpha) * behind``, ``alpha`` the front surface's
    opacity per pixel (1 where the front hits nothing: its colour is the background there); ``behind`` shaded
    over the background by its coverage times its own surface's opacity (what lies behind it is not seen).

    Shape:
        front, behind: (*, H, W, 3). alpha: (*, H, W). Returns (*, H, W, 3).
    """
    a = alpha[..., None]
    return a * front + (1.0 - a) * behind
