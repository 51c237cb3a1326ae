"""Evaluation metrics of the super-resolution network and the classic upscalers it is compared with.

Every score is per image, shape (B,), computed on a region: color and normals where either the
prediction's or the ground truth's mask covers (:func:`eval_region`), AO where the ground truth
covers. Masks count as covering where they are > 0.5.

Empty regions: an image whose region is empty has nothing to compare, so its score is NaN
(never 0 or inf). Average scores over images with ``torch.nanmean``, which skips them.
"""

from __future__ import annotations

from typing import Callable, Literal

import torch
import torch.nn.functional as F
from torch import Tensor
from torchmetrics.functional.image import structural_similarity_index_measure

from isosr_render.conventions import AO, DEPTH, MASK, NORMAL
from isosr_render.shading import shade_channels_first
from isosr_render.shapes import check_int, check_shape

# Floor of the mean squared error in PSNR: identical images score 100 dB at data range 1.
MSE_FLOOR = 1e-10
# Side of torchmetrics' Gaussian SSIM window for sigma 1.5; images must be at least this large.
SSIM_WINDOW = 11


def _check_pair(fn: str, pred: Tensor, target: Tensor, mask: Tensor | None = None) -> None:
    """Raise ValueError unless ``pred`` is (B, C, H, W), ``target`` its shape and ``mask`` (B, 1, H, W)."""
    dims = check_shape(pred, "(B, C, H, W)", "pred", fn)
    check_shape(target, "(B, C, H, W)", "target", fn, dims)
    if mask is not None:
        check_shape(mask, "(B, 1, H, W)", "mask", fn, dims)


def _masked_mean(values: Tensor, region: Tensor) -> Tensor:
    """Mean of ``values`` (B, C, H, W) over channels and the pixels of ``region`` (B, 1, H, W),
    per image; NaN where the region is empty."""
    count = region.flatten(1).sum(1) * values.shape[1]
    total = (values * region).flatten(1).sum(1)
    return torch.where(count > 0, total / count.clamp_min(1), torch.full_like(total, float("nan")))


def eval_region(pred_mask: Tensor, target_mask: Tensor) -> Tensor:
    """Pixels where the prediction's alpha or the ground truth's mask covers (> 0.5): the union.

    Args:
        pred_mask: predicted mask / alpha.
        target_mask: ground-truth mask.

    Returns:
        Boolean region.

    Shape:
        pred_mask, target_mask: (B, 1, H, W). Returns (B, 1, H, W).
    """
    dims = check_shape(pred_mask, "(B, 1, H, W)", "pred_mask", "eval_region")
    check_shape(target_mask, "(B, 1, H, W)", "target_mask", "eval_region", dims)
    return (pred_mask > 0.5) | (target_mask > 0.5)


def scene_region(target_mask: Tensor) -> Tensor:
    """Pixels the ground truth covers (> 0.5) and their eight neighbours: one region for every method scored
    against it, its edges' band included (where :func:`eval_region` differs between methods: a mask a hair
    above 0.5 at a half-covered pixel adds that pixel to one method's region and not to another's).

    Shape:
        target_mask: (B, 1, H, W). Returns (B, 1, H, W) bool.
    """
    check_shape(target_mask, "(B, 1, H, W)", "target_mask", "scene_region")
    return torch.nn.functional.max_pool2d((target_mask > 0.5).float(), 3, stride=1, padding=1) > 0


def masked_psnr(pred: Tensor, target: Tensor, mask: Tensor, data_range: float = 1.0) -> Tensor:
    """PSNR per image over the pixels where ``mask`` > 0.5.

    The MSE is averaged over the masked pixels and all channels and floored at ``MSE_FLOOR``,
    so identical images score ``10 * log10(data_range**2 / MSE_FLOOR)`` (100 dB at range 1).

    Args:
        pred: predicted image.
        target: reference image.
        mask: region to score, float or bool.
        data_range: range of the pixel values (max - min).

    Returns:
        PSNR in dB; NaN for an image with an empty mask.

    Shape:
        pred, target: (B, C, H, W). mask: (B, 1, H, W). Returns (B,).
    """
    _check_pair("masked_psnr", pred, target, mask)
    mse = _masked_mean((pred - target).square(), mask > 0.5)
    return 10.0 * torch.log10(data_range ** 2 / mse.clamp_min(MSE_FLOOR))


def masked_ssim(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """SSIM per image, torchmetrics' SSIM map averaged over channels and the pixels where ``mask`` > 0.5.

    The map is torchmetrics' (Gaussian window 11, sigma 1.5, data range 1, reflected borders), so with
    a full mask this equals ``structural_similarity_index_measure(pred, target, data_range=1.0)``.

    Args:
        pred: predicted image, values in [0, 1].
        target: reference image, values in [0, 1], same dtype as ``pred``.
        mask: region to score, float or bool.

    Returns:
        Mean SSIM; NaN for an image with an empty mask.

    Shape:
        pred, target: (B, C, H, W) with H, W >= 11. mask: (B, 1, H, W). Returns (B,).
    """
    _check_pair("masked_ssim", pred, target, mask)
    if pred.shape[-2] < SSIM_WINDOW or pred.shape[-1] < SSIM_WINDOW:
        raise ValueError(f"masked_ssim: pred must be at least {SSIM_WINDOW}x{SSIM_WINDOW} (the SSIM window), "
                         f"got {tuple(pred.shape)}")
    _, ssim_map = structural_similarity_index_measure(pred, target, gaussian_kernel=True, sigma=1.5,
                                                      kernel_size=SSIM_WINDOW, data_range=1.0,
                                                      reduction="none", return_full_image=True)
    return _masked_mean(ssim_map, mask > 0.5)


# The classic interpolations (``F.interpolate`` modes) a baseline upscales with.
INTERPOLATIONS = ("nearest", "bilinear", "bicubic")


def upscale_baseline(lowres: Tensor, factor: int,
                     mode: Literal["nearest", "bilinear", "bicubic"] = "bilinear") -> Tensor:
    """Classic upscaling of the low-res buffers, the network's baseline.

    Mask, normals and depth are interpolated with ``F.interpolate`` (``align_corners=False`` for
    bilinear and bicubic); the mask is clamped to [0, 1] and nonzero normals are renormalized.
    A classic upscaler knows no ambient occlusion: the AO channel is 1 everywhere, so a baseline
    shades without occlusion, as the paper compares.

    Args:
        lowres: low-res buffers in the order of ``LOWRES_CHANNELS``.
        factor: integer upscaling factor, at least 1.
        mode: interpolation, ``"nearest"``, ``"bilinear"`` or ``"bicubic"``.

    Returns:
        High-res buffers in the order of ``HIGHRES_CHANNELS``.

    Shape:
        lowres: (B, 5, H, W). Returns (B, 6, H * factor, W * factor).
    """
    check_shape(lowres, "(B, 5, H, W)", "lowres", "upscale_baseline")
    check_int(factor, "factor", 1, where="upscale_baseline")
    if mode not in INTERPOLATIONS:
        raise ValueError(f"upscale_baseline: mode must be one of {INTERPOLATIONS}, got {mode!r}")
    size = (lowres.shape[-2] * factor, lowres.shape[-1] * factor)
    up = F.interpolate(lowres, size=size, mode=mode, align_corners=None if mode == "nearest" else False)
    normal = up[:, NORMAL]
    length = normal.norm(dim=1, keepdim=True)
    normal = torch.where(length > 0, normal / length.clamp_min(torch.finfo(up.dtype).tiny), normal)
    return torch.cat([up[:, MASK].clamp(0.0, 1.0), normal, up[:, DEPTH], torch.ones_like(up[:, MASK])], dim=1)


def frame_scores(pred: Tensor, target: Tensor) -> dict[str, Tensor]:
    """Per-image scores of predicted high-res buffers against the ground truth.

    - ``color_psnr``, ``color_ssim``: shaded color with AO, on :func:`eval_region`.
    - ``normal_psnr``: normals mapped to [0, 1] by ``(n + 1) / 2`` as given (not renormalized),
      on :func:`eval_region`.
    - ``ao_psnr``: AO where the ground truth's mask covers.
    - ``mask_iou``: intersection over union of the masks thresholded at 0.5.

    Each is NaN for an image whose region is empty (for ``mask_iou``: both masks empty).

    Args:
        pred: predicted buffers in the order of ``HIGHRES_CHANNELS``.
        target: ground-truth buffers, same order.

    Returns:
        Scores by name.

    Shape:
        pred, target: (B, 6, H, W) with H, W >= 11. Each score: (B,).
    """
    dims = check_shape(pred, "(B, 6, H, W)", "pred", "frame_scores")
    check_shape(target, "(B, 6, H, W)", "target", "frame_scores", dims)
    region = eval_region(pred[:, MASK], target[:, MASK])
    color_pred, color_target = shade_channels_first(pred), shade_channels_first(target)
    target_region = target[:, MASK] > 0.5
    intersection = ((pred[:, MASK] > 0.5) & target_region).to(pred.dtype)
    return {
        "color_psnr": masked_psnr(color_pred, color_target, region),
        "color_ssim": masked_ssim(color_pred, color_target, region),
        "normal_psnr": masked_psnr((pred[:, NORMAL] + 1) / 2, (target[:, NORMAL] + 1) / 2, region),
        "ao_psnr": masked_psnr(pred[:, AO], target[:, AO], target_region),
        "mask_iou": _masked_mean(intersection, region),
    }


def temporal_instability(outputs: Tensor, flows_hr: Tensor, warp_fn: Callable[[Tensor, Tensor], Tensor]) -> Tensor:
    """Flicker of a predicted sequence of buffers: :func:`color_instability` of their shaded colors.

    Args:
        outputs: predicted buffers per frame, in the order of ``HIGHRES_CHANNELS``.
        flows_hr: backward flow per frame in high-res pixels (see ``conventions``); ``flows_hr[0]``
            is not used.
        warp_fn: as :func:`color_instability`'s.

    Returns:
        Mean absolute difference per sequence; NaN where every step's region is empty.

    Shape:
        outputs: (T, B, 6, H, W) with T >= 2. flows_hr: (T, B, 2, H, W). Returns (B,).
    """
    dims = check_shape(outputs, "(T, B, 6, H, W)", "outputs", "temporal_instability")
    check_shape(flows_hr, "(T, B, 2, H, W)", "flows_hr", "temporal_instability", dims)
    if dims["T"] < 2:
        raise ValueError(f"temporal_instability: outputs needs T >= 2 frames, got {tuple(outputs.shape)}")
    color = shade_channels_first(outputs.flatten(0, 1)).unflatten(0, (dims["T"], dims["B"]))
    return color_instability(color, outputs[:, :, MASK], flows_hr, warp_fn)


def color_instability(colors: Tensor, masks: Tensor, flows: Tensor,
                      warp_fn: Callable[[Tensor, Tensor], Tensor]) -> Tensor:
    """Flicker of a sequence of frames: how much each frame's color differs from the previous one warped to it.

    For every ``t >= 1`` color ``t - 1`` and its mask are warped to frame ``t`` by
    ``warp_fn(image, flows[t])``; the step's score is the mean absolute color difference over the
    channels and the pixels where frame ``t``'s or the warped mask covers (> 0.5). The result is the
    mean over the steps (NaN steps, with an empty region, skipped). Lower is steadier; 0 is perfectly
    steady. A converged reference scores above 0 too (resampling, view-dependent shading): compare
    a method's flicker with the reference's own.

    Args:
        colors: colors per frame in [0, 1].
        masks: coverage per frame.
        flows: backward flow per frame in pixels (see ``conventions``); ``flows[0]`` is not used.
        warp_fn: ``warp_fn(image (B, C, H, W), flow (B, 2, H, W)) -> (B, C, H, W)``, sampling
            ``image`` at each pixel's position plus ``flow``.

    Returns:
        Mean absolute difference per sequence; NaN where every step's region is empty.

    Shape:
        colors: (T, B, 3, H, W) with T >= 2. masks: (T, B, 1, H, W). flows: (T, B, 2, H, W). Returns (B,).
    """
    dims = check_shape(colors, "(T, B, 3, H, W)", "colors", "color_instability")
    check_shape(masks, "(T, B, 1, H, W)", "masks", "color_instability", dims)
    check_shape(flows, "(T, B, 2, H, W)", "flows", "color_instability", dims)
    if dims["T"] < 2:
        raise ValueError(f"color_instability: colors needs T >= 2 frames, got {tuple(colors.shape)}")
    steps = []
    for t in range(1, dims["T"]):
        warped = warp_fn(torch.cat([colors[t - 1], masks[t - 1]], dim=1), flows[t])
        region = (masks[t] > 0.5) | (warped[:, 3:] > 0.5)
        steps.append(_masked_mean((colors[t] - warped[:, :3]).abs(), region))
    return torch.stack(steps).nanmean(0)
