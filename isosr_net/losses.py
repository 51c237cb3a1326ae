"""Training losses of the super-resolution network, built from config dicts.

Every loss is a :class:`WeightedLoss`, an ``nn.Module`` that carries its own weight (as in BasicSR) and maps a
:class:`LossContext` to a weighted scalar (its ``term`` times the weight). The plain functions (:func:`masked_l1`,
:func:`masked_l2`; shading from :mod:`isosr_render.shading`) hold the math; the modules are thin.
Tensors are channels-first ``(B, C, H, W)`` in the orders of
:mod:`isosr_render.conventions` (``HIGHRES_CHANNELS``: mask, normal xyz, depth, ao).

Losses
    ``channel``      L1 / L2 on one output: ``mask`` over all pixels (the alpha is learned
                     everywhere), ``normal``, ``depth`` and ``ao`` over the ground truth's
                     surface pixels, ``color`` on the shaded images over all pixels. With
                     ``against="teacher"``, against a frozen teacher's output instead of the truth
                     (distillation: ``TrainConfig.teacher``), over the truth's surface pixels alike.
    ``perceptual``   L1 / L2 between VGG-19 features of the shaded prediction and ground truth
                     (the networks are in :mod:`isosr_net.architectures`).
    ``temporal``     masked L2 between the output and the previous output warped to this frame.
    ``ao_no_worse``  a reconstruction's AO error beyond its input rays' own, per pixel (a hinge, zero
                     where the output is at least as close to the truth as the rays' mean): what
                     "never worse than the input" asks of it (:func:`ao_excess_error`).
    ``ao_psnr_no_worse``  per frame, how many dB the reconstruction's AO falls short of its input rays' mean
                     (a hinge, zero for frames where the output is at least as close to the truth): the same
                     ask counted as the Pareto study counts it, per frame, so a pixel's loss may pay for
                     another's gain (:func:`psnr_shortfall`).
    ``teacher_psnr_no_worse``  per frame, how many dB the shaded output falls short of a frozen teacher's (the
                     model a fine-tune starts from, run on the same inputs: ``TrainConfig.teacher``): a
                     fine-tune may gain where it can and is held to its start everywhere else.
    ``adversarial``  spatio-temporal conditional GAN (TecoGAN style): the discriminator sees the
                     current frame, the previous frame warped to it and the upsampled low-res
                     input. :meth:`AdversarialLoss.forward` is the generator term;
                     :meth:`AdversarialLoss.discriminator_loss` is the discriminator's, to be
                     minimized over ``AdversarialLoss.discriminator.parameters()`` in a
                     separate step.

The paper's three networks (Weiss et al., TVCG 2019) as configs, in :data:`PAPER_LOSSES`
    ``l1-normal``  L1 on the normals plus mask, depth and AO terms, no GAN, no perceptual term:
                   the network that reproduces the ground truth most closely per pixel.
    ``gan-1``      the L1 terms plus perceptual, temporal and adversarial terms, with a small
                   adversarial weight: sharper detail, little hallucination.
    ``gan-2``      the same terms with a larger adversarial and perceptual weight: more
                   detail, further from the ground truth per pixel.
    The weights are our reading of the paper's setup, not numbers copied from it; tune them.
    The perceptual entries name ``weights/vgg19_features.safetensors``; replace ``weights_path``
    where the file lives elsewhere.

Typical use::

    losses = build_losses(PAPER_LOSSES["gan-1"])
    loss, logs = total_loss(losses, LossContext(pred, target, prev_warped, lowres_up, prev_target_warped))
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from isosr_render.conventions import (AO, DEPTH, HIGHRES_CHANNELS, LOWRES_CHANNELS, MASK, NORMAL, RECON_CHANNELS,
                                      SAMPLED_AO, SAMPLING)
from isosr_render.shading import shade_channels_first
from isosr_render.shapes import check_shape
from isosr_net.architectures import (IMAGENET_MEAN, IMAGENET_STD, VGG19_LAYERS, SpatioTemporalDiscriminator,
                                     load_vgg19_features)

_EPS = 1e-8
_HIGHRES = len(HIGHRES_CHANNELS)
_LOWRES = len(LOWRES_CHANNELS)


@dataclass
class LossContext:
    """Everything a loss may look at for one frame; see the module docstring.

    ``recon_inputs``: a reconstruction network's inputs (:data:`RECON_CHANNELS`: the rays' AO and counts), None
    for an upscaler's. ``teacher``: a frozen teacher model's output for the same inputs, None without one.

    Shape:
        pred, target, prev_warped, prev_target_warped, teacher: (B, 6, H, W). lowres_up: (B, 5, H, W).
        recon_inputs: (B, 8, H, W).
    """

    pred: torch.Tensor
    target: torch.Tensor
    prev_warped: torch.Tensor | None = None
    lowres_up: torch.Tensor | None = None
    prev_target_warped: torch.Tensor | None = None
    recon_inputs: torch.Tensor | None = None
    teacher: torch.Tensor | None = None

    def __post_init__(self) -> None:
        dims = check_shape(self.pred, f"(B, {_HIGHRES}, H, W)", "pred", "LossContext")
        for name in ("target", "prev_warped", "prev_target_warped", "teacher"):
            x = getattr(self, name)
            if x is not None:
                check_shape(x, f"(B, {_HIGHRES}, H, W)", name, "LossContext", dims)
        if self.lowres_up is not None:
            check_shape(self.lowres_up, f"(B, {_LOWRES}, H, W)", "lowres_up", "LossContext", dims)
        if self.recon_inputs is not None:
            check_shape(self.recon_inputs, f"(B, {len(RECON_CHANNELS)}, H, W)", "recon_inputs", "LossContext", dims)


def _masked_error(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, channels: slice,
                  error: Callable[[torch.Tensor], torch.Tensor], name: str) -> torch.Tensor:
    dims = check_shape(pred, "(B, C, H, W)", "pred", name)
    check_shape(target, "(B, C, H, W)", "target", name, dims)
    check_shape(mask, "(B, 1, H, W)", "mask", name, dims)
    c = dims["C"]
    if len(range(c)[channels]) == 0:
        raise ValueError(f"{name}: channels {channels} select nothing of {c} channels")
    return _masked_mean(error(pred[:, channels] - target[:, channels]).mean(dim=1, keepdim=True), mask)


def _masked_mean(per_pixel: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of (B, 1, H, W) ``per_pixel`` where ``mask`` > 0; 0 (with a finite gradient) where it is empty."""
    inside = (mask > 0).to(per_pixel.dtype)
    return (per_pixel * inside).sum() / (inside.sum() + _EPS)


def masked_l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
              channels: slice = slice(None)) -> torch.Tensor:
    """Mean absolute error over ``channels``, averaged over the pixels where ``mask > 0``.

    The average runs over all such pixels of the batch; an empty mask gives 0.

    Args:
        pred: prediction.
        target: reference.
        mask: pixels to count where positive (pass the ground-truth mask).
        channels: the channel slice to compare, e.g. ``conventions.NORMAL``.

    Returns:
        Scalar loss.

    Shape:
        pred, target: (B, C, H, W). mask: (B, 1, H, W). Returns ().
    """
    return _masked_error(pred, target, mask, channels, torch.abs, "masked_l1")


def masked_l2(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
              channels: slice = slice(None)) -> torch.Tensor:
    """Mean squared error over ``channels``, averaged over the pixels where ``mask > 0``.

    Same arguments and shapes as :func:`masked_l1`.
    """
    return _masked_error(pred, target, mask, channels, torch.square, "masked_l2")


def _check_weight(weight: float) -> float:
    if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not math.isfinite(weight) \
            or weight < 0:
        raise ValueError(f"weight must be a finite number >= 0, got {weight!r}")
    return float(weight)


def _check_kind(kind: str) -> str:
    if kind not in ("l1", "l2"):
        raise ValueError(f"kind must be 'l1' or 'l2', got {kind!r}")
    return kind


def _mean_error(a: torch.Tensor, b: torch.Tensor, kind: str) -> torch.Tensor:
    return F.l1_loss(a, b) if kind == "l1" else F.mse_loss(a, b)


class WeightedLoss(nn.Module):
    """A loss term that carries its weight: ``forward(ctx)`` is ``weight * term(ctx)``.

    Args:
        weight: factor on the term, a finite number >= 0.
    """

    name: str
    reads_teacher = False  # whether it needs LossContext.teacher

    def __init__(self, weight: float = 1.0) -> None:
        super().__init__()
        self.weight = _check_weight(weight)

    def term(self, ctx: LossContext) -> torch.Tensor:
        """The unweighted loss (a scalar)."""
        raise NotImplementedError

    def forward(self, ctx: LossContext) -> torch.Tensor:
        return self.weight * self.term(ctx)


class ChannelLoss(WeightedLoss):
    """Weighted L1 / L2 on one output; see the module docstring for what each channel means.

    Args:
        channel: ``"mask"``, ``"normal"``, ``"depth"``, ``"ao"`` or ``"color"``.
        kind: ``"l1"`` or ``"l2"``.
        weight: factor on the loss.
        against: ``"truth"`` (the ground truth) or ``"teacher"`` (a frozen teacher's output: distillation).
    """

    CHANNELS = {"mask": MASK, "normal": NORMAL, "depth": DEPTH, "ao": AO, "color": None}
    AGAINST = ("truth", "teacher")

    def __init__(self, channel: str, kind: str = "l1", weight: float = 1.0, against: str = "truth") -> None:
        super().__init__(weight)
        if channel not in self.CHANNELS:
            raise ValueError(f"channel must be one of {sorted(self.CHANNELS)}, got {channel!r}")
        if against not in self.AGAINST:
            raise ValueError(f"against must be one of {self.AGAINST}, got {against!r}")
        self.channel, self.kind, self.reads_teacher = channel, _check_kind(kind), against == "teacher"
        self.name = f"{channel}_{kind}" + ("_teacher" if self.reads_teacher else "")

    def term(self, ctx: LossContext) -> torch.Tensor:
        pred, target = ctx.pred, (_teacher_output(ctx, self.name) if self.reads_teacher else ctx.target)
        if self.channel == "color":
            return _mean_error(shade_channels_first(pred), shade_channels_first(target), self.kind)
        if self.channel == "mask":
            return _mean_error(pred[:, MASK], target[:, MASK], self.kind)
        masked = masked_l1 if self.kind == "l1" else masked_l2
        return masked(pred, target, ctx.target[:, MASK], self.CHANNELS[self.channel])


class PerceptualLoss(WeightedLoss):
    """Weighted L1 / L2 between VGG-19 features of the shaded prediction and ground truth.

    Both frames are shaded (:func:`shade_channels_first`), normalized by the ImageNet mean and
    std and run through the frozen network; the loss is the mean over ``layers`` of the mean
    error between the two feature maps. The network runs in its own dtype.

    Args:
        weights_path: VGG-19 weights, see :func:`load_vgg19_features`.
        layers: ReLU outputs to compare, named ``"relu{block}_{conv}"``.
        weight: factor on the loss.
        kind: ``"l1"`` or ``"l2"``.
    """

    name = "perceptual"

    def __init__(self, weights_path: str | Path,
                 layers: Sequence[str] = ("relu1_2", "relu2_2", "relu3_4", "relu4_4", "relu5_4"),
                 weight: float = 1.0, kind: str = "l1") -> None:
        super().__init__(weight)
        unknown = [layer for layer in layers if layer not in VGG19_LAYERS]
        if unknown or not layers:
            raise ValueError(f"layers must be a non-empty subset of {list(VGG19_LAYERS)}, got {list(layers)}")
        self.kind = _check_kind(kind)
        self.taps = sorted({VGG19_LAYERS[layer] for layer in layers})
        # Only the layers up to the deepest tap are kept.
        self.vgg = load_vgg19_features(weights_path)[: self.taps[-1] + 1]
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def train(self, mode: bool = True) -> PerceptualLoss:
        super().train(mode)
        self.vgg.eval()
        return self

    def features(self, color: torch.Tensor) -> list[torch.Tensor]:
        """The tapped feature maps of an RGB image (B, 3, H, W) in [0, 1]."""
        dtype = self.mean.dtype
        x = (color.to(dtype) - self.mean) / self.std
        out = []
        for i, layer in enumerate(self.vgg):
            x = layer(x)
            if i in self.taps:
                out.append(x)
        return out

    def term(self, ctx: LossContext) -> torch.Tensor:
        n = ctx.pred.shape[0]
        color = shade_channels_first(torch.cat([ctx.pred, ctx.target]))
        return torch.stack([_mean_error(f[:n], f[n:], self.kind) for f in self.features(color)]).mean()


class TemporalLoss(WeightedLoss):
    """Weighted masked L2 between the output and the previous output warped to this frame.

    Zero (without a graph) on a sequence's first frame, where ``ctx.prev_warped`` is None.

    Args:
        weight: factor on the loss.
    """

    name = "temporal"

    def term(self, ctx: LossContext) -> torch.Tensor:
        if ctx.prev_warped is None:
            return ctx.pred.new_zeros(())
        return masked_l2(ctx.pred, ctx.prev_warped, ctx.target[:, MASK])


def ao_excess_error(pred_ao: torch.Tensor, rays_ao: torch.Tensor, target_ao: torch.Tensor,
                    mask: torch.Tensor) -> torch.Tensor:
    """Mean over ``mask`` of ``relu(|pred_ao - target_ao| - |rays_ao - target_ao|)``: how much further from the truth
    the output's AO is than the rays' mean it was given; 0 where it is nowhere further.

    Shape:
        pred_ao, rays_ao, target_ao, mask: (B, 1, H, W). Returns a scalar.
    """
    dims = check_shape(pred_ao, "(B, 1, H, W)", "pred_ao", "ao_excess_error")
    for name, x in (("rays_ao", rays_ao), ("target_ao", target_ao), ("mask", mask)):
        check_shape(x, "(B, 1, H, W)", name, "ao_excess_error", dims)
    return _masked_mean(F.relu((pred_ao - target_ao).abs() - (rays_ao - target_ao).abs()), mask)


class AONoWorseLoss(WeightedLoss):
    """Weighted :func:`ao_excess_error` of a reconstruction's AO over the ground truth's surface pixels that had AO
    rays (ValueError in a context without a reconstruction's inputs).

    Args:
        weight: factor on the loss.
    """

    name = "ao_no_worse"

    def term(self, ctx: LossContext) -> torch.Tensor:
        return ao_excess_error(ctx.pred[:, AO], *_rays_and_truth(ctx, self.name))


def _teacher_output(ctx: LossContext, loss: str) -> torch.Tensor:
    """The frozen teacher's output, as the losses that read it take it; ValueError in a context without it."""
    if ctx.teacher is None:
        raise ValueError(f"the {loss} loss compares the output with a teacher's: give the run a teacher "
                         "(TrainConfig.teacher, a model folder)")
    return ctx.teacher


def _rays_and_truth(ctx: LossContext, loss: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A reconstruction's input rays' AO mean, the truth's AO and the truth's surface pixels that had AO rays, as
    the losses that compare the output with its input take them; ValueError without a reconstruction's inputs.

    Shape:
        Returns three (B, 1, H, W) tensors.
    """
    if ctx.recon_inputs is None:
        raise ValueError(f"the {loss} loss compares a reconstruction's AO with its input rays': this run's model has "
                         "none at its output's resolution (an upscaler's, or the x2 reconstruction's)")
    rays = ctx.recon_inputs
    with_rays = (ctx.target[:, MASK] > 0.5) & (rays[:, SAMPLING][:, :1] > 0)
    return rays[:, SAMPLED_AO], ctx.target[:, AO], with_rays


# The mean squared error below which two frames count as equal (an RMS error of 1e-5: far under an 8-bit step).
MSE_FLOOR = 1e-10


def psnr_shortfall(pred: torch.Tensor, given: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over the frames of ``relu(10 log10((e_pred + f) / (e_given + f)))``, ``e`` a frame's mean squared error
    against ``target`` over ``mask`` and ``f`` :data:`MSE_FLOOR`: the dB of PSNR each frame of ``pred`` falls short
    of ``given`` (an input's, a teacher's); 0 for a frame where it is at least as close, or where nothing is covered.

    Shape:
        pred, given, target: (B, C, H, W); mask: (B, 1, H, W). Returns a scalar.
    """
    dims = check_shape(pred, "(B, C, H, W)", "pred", "psnr_shortfall")
    for name, x in (("given", given), ("target", target)):
        check_shape(x, "(B, C, H, W)", name, "psnr_shortfall", dims)
    check_shape(mask, "(B, 1, H, W)", "mask", "psnr_shortfall", {k: v for k, v in dims.items() if k != "C"})
    dtype = torch.promote_types(pred.dtype, torch.float32)  # AMP's fp16 squares underflow
    inside = (mask > 0).to(dtype)
    count = inside.sum((1, 2, 3)) * pred.shape[1]

    def frame_mse(x: torch.Tensor) -> torch.Tensor:
        return ((x.to(dtype) - target.to(dtype)) ** 2 * inside).sum((1, 2, 3)) / count.clamp_min(1.0)

    shortfall = F.relu(10 * torch.log10((frame_mse(pred) + MSE_FLOOR) / (frame_mse(given) + MSE_FLOOR)))
    return torch.where(count > 0, shortfall, 0.0).mean()


class AOPSNRNoWorseLoss(WeightedLoss):
    """Weighted :func:`psnr_shortfall` of a reconstruction's AO against its input rays' mean, over the ground truth's
    surface pixels that had AO rays (ValueError in a context without a reconstruction's inputs).

    Args:
        weight: factor on the loss (per dB).
    """

    name = "ao_psnr_no_worse"

    def term(self, ctx: LossContext) -> torch.Tensor:
        return psnr_shortfall(ctx.pred[:, AO], *_rays_and_truth(ctx, self.name))


class TeacherPSNRNoWorseLoss(WeightedLoss):
    """Weighted :func:`psnr_shortfall` of the shaded output against a teacher's, over all pixels (ValueError in a
    context without the teacher's output).

    Args:
        weight: factor on the loss (per dB).
    """

    name = "teacher_psnr_no_worse"
    reads_teacher = True

    def term(self, ctx: LossContext) -> torch.Tensor:
        teacher = _teacher_output(ctx, self.name)
        color, teacher, target = shade_channels_first(torch.cat([ctx.pred, teacher, ctx.target])).chunk(3)
        return psnr_shortfall(color, teacher, target, torch.ones_like(color[:, :1]))


@contextmanager
def _frozen(module: nn.Module) -> Iterator[None]:
    """Run ops on ``module`` without recording its parameters in the graph."""
    flags = [p.requires_grad for p in module.parameters()]
    module.requires_grad_(False)
    try:
        yield
    finally:
        for p, flag in zip(module.parameters(), flags):
            p.requires_grad_(flag)


class AdversarialLoss(WeightedLoss):
    """Spatio-temporal conditional GAN loss with its own discriminator.

    Real pairs are ``(target, prev_target_warped, lowres_up)``, fake ones
    ``(pred, prev_warped, lowres_up)``. Where either previous frame is None both are zeros,
    so real and fake inputs never differ in that alone.

    Args:
        weight: factor on the generator loss.
        discriminator_config: keyword arguments of :class:`SpatioTemporalDiscriminator`.
    """

    name = "adversarial"

    def __init__(self, weight: float = 1.0, discriminator_config: dict[str, Any] | None = None) -> None:
        super().__init__(weight)
        self.discriminator = SpatioTemporalDiscriminator(**(discriminator_config or {}))

    @staticmethod
    def _inputs(ctx: LossContext) -> tuple[torch.Tensor, torch.Tensor]:
        if ctx.lowres_up is None:
            raise ValueError("AdversarialLoss: ctx.lowres_up (the discriminator's condition) is None")
        if ctx.prev_warped is None or ctx.prev_target_warped is None:
            prev_fake = prev_real = torch.zeros_like(ctx.pred)
        else:
            prev_fake, prev_real = ctx.prev_warped, ctx.prev_target_warped
        fake = torch.cat([ctx.pred, prev_fake, ctx.lowres_up], dim=1)
        real = torch.cat([ctx.target, prev_real, ctx.lowres_up], dim=1)
        return fake, real

    def term(self, ctx: LossContext) -> torch.Tensor:
        """Generator loss; gradients reach the prediction, not the discriminator."""
        fake, _ = self._inputs(ctx)
        with _frozen(self.discriminator):
            logits = self.discriminator(fake)
        return F.binary_cross_entropy_with_logits(logits, torch.ones_like(logits))

    def discriminator_loss(self, ctx: LossContext) -> torch.Tensor:
        """Discriminator loss (unweighted), mean of the real and fake terms; fakes are detached."""
        fake, real = self._inputs(ctx)
        logits_real = self.discriminator(real.detach())
        logits_fake = self.discriminator(fake.detach())
        return 0.5 * (F.binary_cross_entropy_with_logits(logits_real, torch.ones_like(logits_real))
                      + F.binary_cross_entropy_with_logits(logits_fake, torch.zeros_like(logits_fake)))


LOSS_TYPES: dict[str, type[WeightedLoss]] = {
    "channel": ChannelLoss,
    "perceptual": PerceptualLoss,
    "temporal": TemporalLoss,
    "adversarial": AdversarialLoss,
    "ao_no_worse": AONoWorseLoss,
    "ao_psnr_no_worse": AOPSNRNoWorseLoss,
    "teacher_psnr_no_worse": TeacherPSNRNoWorseLoss,
}


def build_losses(configs: Sequence[dict[str, Any]]) -> nn.ModuleList:
    """Loss modules from config dicts ``{"type": <LOSS_TYPES key>, **constructor arguments}``.

    Raises:
        ValueError: an entry is not a dict, has an unknown type or bad arguments, or repeats
            another entry's loss name; the message names the entry.
        FileNotFoundError: a perceptual entry's weights file is missing.
    """
    losses = nn.ModuleList()
    names: set[str] = set()
    for i, config in enumerate(configs):
        where = f"loss config #{i} {config!r}"
        if not isinstance(config, dict) or config.get("type") not in LOSS_TYPES:
            raise ValueError(f"{where}: needs a 'type' key, one of {sorted(LOSS_TYPES)}")
        args = {k: v for k, v in config.items() if k != "type"}
        try:
            loss = LOSS_TYPES[config["type"]](**args)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{where}: {e}") from e
        if loss.name in names:
            raise ValueError(f"{where}: a loss named '{loss.name}' is already configured")
        names.add(loss.name)
        losses.append(loss)
    return losses


def total_loss(losses: nn.ModuleList, ctx: LossContext) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Sum of the (weighted) losses and each one's value by name, for logging.

    The values stay detached 0-d tensors on the loss's device: reading each one (``float``)
    would wait for the device once per term and frame; read them together once a step.
    The discriminator's own loss is not part of it: call
    :meth:`AdversarialLoss.discriminator_loss` in the discriminator step.
    """
    total = ctx.pred.new_zeros(())
    logs: dict[str, torch.Tensor] = {}
    for loss in losses:
        value = loss(ctx)
        total = total + value
        logs[loss.name] = logs.get(loss.name, 0.0) + value.detach()
    return total, logs


_VGG_PATH = "weights/vgg19_features.safetensors"
_L1_TERMS: tuple[dict[str, Any], ...] = (
    {"type": "channel", "channel": "mask", "kind": "l2", "weight": 1.0},
    {"type": "channel", "channel": "normal", "kind": "l1", "weight": 1.0},
    {"type": "channel", "channel": "depth", "kind": "l1", "weight": 1.0},
    {"type": "channel", "channel": "ao", "kind": "l1", "weight": 1.0},
)
# Our reading of the paper's three networks; the weights are plausible choices, not copied.
PAPER_LOSSES: dict[str, list[dict[str, Any]]] = {
    "l1-normal": [dict(c) for c in _L1_TERMS],
    "gan-1": [dict(c) for c in _L1_TERMS] + [
        {"type": "perceptual", "weights_path": _VGG_PATH, "weight": 0.1},
        {"type": "temporal", "weight": 0.1},
        {"type": "adversarial", "weight": 1e-3},
    ],
    "gan-2": [dict(c) for c in _L1_TERMS] + [
        {"type": "perceptual", "weights_path": _VGG_PATH, "weight": 1.0},
        {"type": "temporal", "weight": 0.1},
        {"type": "adversarial", "weight": 1e-2},
    ],
}
