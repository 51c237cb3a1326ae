"""ReconNet: full-resolution reconstruction of few-ray ambient occlusion and antialiased edges.

Beyond the paper: instead of fewer pixels, fewer rays. Per frame the network sees the
full-resolution first-hit buffers (mask, normal, depth) rendered with ``spp`` rays per pixel,
the AO of ``ao_rays`` hemisphere rays per hit (0: none cast, AO inferred from the geometry as
in the paper), and its own previous output warped by the flow (the paper's recurrence). It
outputs the converged frame's buffers: AO as from hundreds of rays and mask and normal as
from 4 rays per pixel (an antialiased silhouette); depth passes through from the input. Channel orders:
:data:`isosr_render.conventions.RECON_CHANNELS` in, ``HIGHRES_CHANNELS`` out. AO comes out of a
sigmoid, from scratch or (``ao_prior="rays"``) as a correction of the input rays' mean
(:func:`ao_output`), so that more input rays lift it; with ``ao_prior="blend"`` that correction is
then blended with the rays' mean by how many rays each stands for, so that with many rays the
output converges to the input's AO (never worse than the plain render's).

With ``upscale=2`` (:class:`ReconNetConfig`) it reconstructs and upscales: the inputs are
rendered at half the output's sides, the previous output is read space-to-depth (its 2x2 cells
as channels), the tail writes 2x2 cells (depth-to-space), and the output corrects the inputs
upsampled (:func:`upsampled_inputs`), the paper's upscaling with few AO rays besides.

The network is a small U-Net: AO varies slowly along a surface and needs a wide view (its
rays reach ``ao_radius``, tens of pixels on screen), edges need full resolution. So it
encodes at 1/2, 1/4 and 1/8 resolution, does most of its work at 1/8, and decodes with
additive skips; full resolution carries ``widths[0]`` channels (16), which keeps a 1080p frame
at about 30 GMAC (:func:`macs_per_pixel`). With ``stem_stride=2`` no layer runs at full
resolution: the head is a stride-2 convolution of the full-resolution inputs and the tail writes
each half-resolution feature pixel's 2 x 2 output pixels (depth-to-space), so every level sits one
halving lower (1/2 .. 1/16) while the output still corrects every input pixel. What the coarse tail cannot
tell apart inside its 2 x 2 cells (which of them a silhouette crosses, each pixel's own previous AO), ``pixel_tail``
adds back: a per-pixel MLP at the output's resolution reads the tail's correction with the pixel's own inputs and
previous mask and AO, and corrects it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from isosr_render.conventions import AO, DEPTH, HIGHRES_CHANNELS, MASK, NORMAL, RECON_CHANNELS, SAMPLED_AO, SAMPLING
from isosr_render.shapes import check_int, check_shape
from isosr_net.architectures import ResidualBlock
from isosr_net.flow_warp import upscale_flow, warp_by_flow

INPUTS = len(RECON_CHANNELS)
OUTPUTS = len(HIGHRES_CHANNELS)
# The previous output's channels the network reads back: mask and AO.
RECURRENT = 2
LEVELS = 3  # 1/2, 1/4, 1/8
FIRST_FRAME_MODES = ("zeros", "inputs")
AO_PRIORS = ("none", "rays", "blend")
# The rays a "blend" model's own AO stands for at the start of its training (BLEND_PARAMETER: its log).
BLEND_RAYS_INIT = 16.0
BLEND_PARAMETER = "ao_blend_log"
# A "blend_map" model's per-pixel log-offset of that weight: a 3x3 conv of the tail's features (zero at the start).
BLEND_MAP = "ao_blend_map"
# A gated model's mask and normal corrections, per rays per pixel: the sigmoid of GATE_RATE times its parameter
# (GATE_PARAMETER), at the start of its training nearly 1 (the corrections as the model it starts from made
# them). GATE_RATE: Adam moves a parameter by about the learning rate a step, the logits by GATE_RATE times that
# (at 3e-4, from 6 to -2 in ~500 steps; as plain logits, ~27,000: a 5-minute run would leave them).
GATE_PARAMETER = "geometry_gate_raw"
GATE_LOGIT_INIT = 6.0
GATE_RATE = 50.0
# Output over input resolution: 1 reconstructs at the resolution it is given; 2 and 4 also upscale.
UPSCALES = (1, 2, 4)
# The first level's stride under the input (ReconNetConfig.stem_stride).
STEM_STRIDES = (1, 2)
FLOAT32_MAX = torch.finfo(torch.float32).max
# A config's numbers that no weights depend on (set in a model folder's config.json; each finite, >= 0, 0 is off).
WEIGHTLESS_FIELDS = ("blend_beyond", "ao_interval", "ao_interval_narrows_past")
# A "pixel_tail" model's per-pixel MLP (1x1 convolutions at the output's resolution; its last layer zero at the start).
PIXEL_TAIL = "pixel_tail"


@dataclass(frozen=True)
class RayLimits:
    """The most AO rays per hit and rays per pixel a reconstruction model takes (its training
    range); its sampling channels hold ``ao_rays / max_ao_rays`` and ``spp / max_spp``, at most 1.
    A frame may cast more AO rays per hit than ``max_ao_rays``: the model reads their mean as that
    many (:meth:`read`)."""

    max_ao_rays: int = 8
    max_spp: int = 4

    def __post_init__(self):
        check_int(self.max_ao_rays, "max_ao_rays", 1)
        check_int(self.max_spp, "max_spp", 1)

    def check(self, ao_rays: int, spp: int, where: str) -> None:
        """ValueError unless ``ao_rays`` is in [0, max_ao_rays] and ``spp`` in [1, max_spp]."""
        check_int(ao_rays, "ao_rays", 0, self.max_ao_rays, where=where)
        check_int(spp, "spp", 1, self.max_spp, where=where)

    def channels(self, ao_rays: int, spp: int, like: torch.Tensor) -> torch.Tensor:
        """The two constant sampling images of :data:`RECON_CHANNELS` for a frame like ``like`` (B, C, H, W).

        Shape:
            Returns (B, 2, H, W).
        """
        b, _, h, w = like.shape
        # Filled from Python numbers: a tensor built from host values would be a blocking copy on GPUs.
        sampling = like.new_empty((b, 2, h, w))
        sampling[:, 0].fill_(ao_rays / self.max_ao_rays)
        sampling[:, 1].fill_(spp / self.max_spp)
        return sampling

    def read(self, ao_rays: int) -> int:
        """The AO rays per hit the model reads a frame of ``ao_rays`` as: at most ``max_ao_rays``
        (its sampling channel saturates; the better mean of more rays still lifts its output:
        ``docs/measurements.md``)."""
        return min(ao_rays, self.max_ao_rays)

    def rays(self, spp: int) -> int:
        """The most AO rays behind a pixel's mean at ``spp`` rays per pixel."""
        return self.max_ao_rays * spp


@dataclass(frozen=True)
class ReconNetConfig:
    """ReconNet's hyper-parameters.

    Attributes:
        widths: channels at the input's resolution, 1/2, 1/4 and 1/8 of it.
        blocks: residual blocks at 1/8 of the input's resolution.
        first_frame: the "previous output" of a sequence's first frame: ``"zeros"``, or the
            ``"inputs"`` (their mask and sampled AO, AO 1 where none was cast).
        ao_prior: ``"none"``: AO from scratch; ``"rays"``: a correction of the input rays' mean;
            ``"blend"``: that correction blended with the rays' mean (:func:`ao_output`).
        max_ao_rays, max_spp: the model's :class:`RayLimits`.
        geometry_gate: the mask and normal corrections scaled by a learned gate per rays per pixel
            (:func:`geometry_gate`): where the input's geometry is as good as the target's (as many rays
            per pixel), they can fade.
        blend_map: with ``ao_prior="blend"``, the rays the network's AO stands for per pixel: its learned
            ``k`` times ``exp`` of a map from the tail's features (how far the network trusts itself where it
            sees the surface; ``k`` alone at the start).
        blend_variance: with ``ao_prior="blend"``, ``k`` times ``4 p (1 - p)``, the rays' smoothed mean's
            variance per ray over its largest (:func:`ao_output`): where the rays agree (all lit, all
            occluded) their mean is trusted over the network, where they split the network weighs more.
        blend_beyond: with ``ao_prior="blend"``, ``g`` >= 0: in a frame of ``r`` > 1 times the AO rays the model
            reads (:meth:`RayLimits.read`), its own AO stands for ``k / r ** g`` rays (:func:`blend_rays_at`):
            an input cleaner than any it was trained on is trusted over its correction. Nothing changes
            within its ray limits; no weights depend on it.
        ao_interval: ``z`` >= 0: with ``ao_prior`` "rays" or "blend", the output AO kept within the Wilson score
            interval of the rays' mean at ``z`` standard deviations (:func:`rays_interval`), which narrows to the
            mean as rays grow: the network corrects a mean of many rays only as far as those rays allow. 0: off;
            no weights depend on it.
        ao_interval_narrows_past: ``n0`` > 0: with ``ao_interval``, past ``n0`` rays behind a pixel's mean ``n``
            (all of them: the ray history's and those past the model's ray limits counted) its ``z`` falls as
            ``sqrt(n0 / n)`` (:func:`interval_z`), so the interval narrows as ``1 / n``: the more rays stand behind
            a mean, the less the network may move it. 0: ``z`` at every ``n``.
        upscale: output over input resolution (:data:`UPSCALES`): 2 (4) reconstructs a frame rendered
            at half (a quarter of) the output's sides (:func:`upsampled_inputs` is the base its output corrects).
        stem_stride: the first level's resolution under the input's (:data:`STEM_STRIDES`): 1, or 2: the head a
            stride-2 convolution and the tail writing 2 x 2 output pixels per feature pixel (depth-to-space), so
            that no layer runs at the input's resolution (the levels at 1/2 .. 1/16; with upscale 1 only).
        pixel_tail: the hidden width of a per-pixel MLP at the output's resolution (0: none) that reads the
            tail's correction with the pixel's own inputs (upsampled) and its previous mask and AO, and adds its
            own: the detail inside a stem's 2 x 2 cells (on real sequences, mostly the pixel's previous AO). Its
            last layer starts at zero, so a model without it fine-tunes into one with it from the same output
            (:meth:`ReconNet.correction`).
    """

    type: str = "ReconNet"
    widths: tuple[int, int, int, int] = (16, 32, 64, 64)
    blocks: int = 2
    first_frame: str = "inputs"
    ao_prior: str = "none"
    max_ao_rays: int = 8
    max_spp: int = 4
    upscale: int = 1
    geometry_gate: bool = False
    blend_map: bool = False
    blend_variance: bool = False
    blend_beyond: float = 0.0
    ao_interval: float = 0.0
    ao_interval_narrows_past: float = 0.0
    stem_stride: int = 1
    pixel_tail: int = 0

    def __post_init__(self):
        object.__setattr__(self, "widths", tuple(self.widths))
        if len(self.widths) != LEVELS + 1 or any(isinstance(w, bool) or not isinstance(w, int) or w < 1
                                                 for w in self.widths):
            raise ValueError(f"widths must be {LEVELS + 1} positive integers, got {self.widths}")
        if self.blocks < 0:
            raise ValueError(f"blocks must be >= 0, got {self.blocks}")
        if self.first_frame not in FIRST_FRAME_MODES:
            raise ValueError(f"first_frame must be one of {FIRST_FRAME_MODES}, got {self.first_frame!r}")
        if self.ao_prior not in AO_PRIORS:
            raise ValueError(f"ao_prior must be one of {AO_PRIORS}, got {self.ao_prior!r}")
        RayLimits(self.max_ao_rays, self.max_spp)  # raises for bad limits
        if self.upscale not in UPSCALES:
            raise ValueError(f"upscale must be one of {UPSCALES}, got {self.upscale}")
        if isinstance(self.stem_stride, bool) or not isinstance(self.stem_stride, int) or \
                self.stem_stride not in STEM_STRIDES:
            raise ValueError(f"stem_stride must be one of {STEM_STRIDES}, got {self.stem_stride!r}")
        if self.stem_stride > 1 and self.upscale > 1:
            raise ValueError(f"stem_stride {self.stem_stride} goes with upscale 1, got upscale {self.upscale}")
        check_int(self.pixel_tail, "pixel_tail", 0)
        for flag in ("geometry_gate", "blend_map", "blend_variance"):
            if not isinstance(getattr(self, flag), bool):
                raise ValueError(f"{flag} must be true or false, got {getattr(self, flag)!r}")
        for name in WEIGHTLESS_FIELDS:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= FLOAT32_MAX:
                raise ValueError(f"{name} must be a finite number >= 0 (in float32, as the network takes it), "
                                 f"got {value!r}")
        if self.ao_interval and self.ao_prior == "none":
            raise ValueError("ao_interval keeps a model's AO near its input rays': it needs ao_prior 'rays' or 'blend'")
        if self.ao_interval_narrows_past and not self.ao_interval:
            raise ValueError("ao_interval_narrows_past narrows the rays' interval: it needs ao_interval > 0")
        for flag in ("blend_map", "blend_variance", "blend_beyond"):
            if getattr(self, flag) and self.ao_prior != "blend":
                raise ValueError(f"{flag} weighs a blend model's AO: it needs ao_prior 'blend', got {self.ao_prior!r}")

    @property
    def cell_side(self) -> int:
        """Output pixels per feature pixel of the first level, along a side: the tail's depth-to-space factor."""
        return self.upscale * self.stem_stride

    @property
    def multiple(self) -> int:
        """What the input's sides are padded to a multiple of: the coarsest level's stride."""
        return 2 ** LEVELS * self.stem_stride

    @property
    def limits(self) -> RayLimits:
        """The most AO rays per hit and rays per pixel the model takes."""
        return RayLimits(self.max_ao_rays, self.max_spp)


def interval_z(z: float, rays: torch.Tensor, narrows_past: float) -> torch.Tensor:
    """The interval's ``z`` at ``rays`` behind a pixel's mean: ``z`` up to ``narrows_past`` rays, then
    ``z sqrt(narrows_past / rays)``; ``z`` everywhere where ``narrows_past`` is 0.

    Shape:
        rays: (B, 1, H, W). Returns (B, 1, H, W).
    """
    if not narrows_past:
        return torch.full_like(rays, z)
    return z * torch.sqrt(narrows_past / rays.clamp_min(narrows_past))


def rays_interval(mean: torch.Tensor, rays: torch.Tensor, z: float | torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """The Wilson score interval of an AO that ``rays`` rays of mean ``mean`` estimate, at ``z`` standard
    deviations (one, or one per pixel): the values in ``[0, 1]`` their mean is within ``z`` deviations of (a
    ray's AO lies in ``[0, 1]``, so its variance is at most ``p (1 - p)``; the interval holds where all rays
    agree). ``[0, 1]`` where no ray was cast.

    Shape:
        mean, rays: (B, 1, H, W). z: () or (B, 1, H, W). Returns (low, high), each (B, 1, H, W).
    """
    n = rays.clamp_min(1e-12)
    p = mean.clamp(0.0, 1.0)
    spread = z * z / n
    center = (p + spread / 2) / (1 + spread)
    half = z / (1 + spread) * torch.sqrt(p * (1 - p) / n + spread / (4 * n))
    cast = rays > 0
    return torch.where(cast, center - half, 0.0), torch.where(cast, center + half, 1.0)


def ao_output(raw_ao: torch.Tensor, inputs: torch.Tensor, config: ReconNetConfig,
              blend_rays: torch.Tensor | None = None, ray_factor: float = 1.0) -> torch.Tensor:
    """The output AO from the tail's AO channel ``raw_ao``.

    ``ao_prior="none"``: ``sigmoid(raw_ao)``. ``"rays"``: ``o = sigmoid(logit(p) + raw_ao)`` with
    ``p = (n a + 0.5) / (n + 1)`` the input rays' mean ``a`` (:data:`SAMPLED_AO`) smoothed by the
    ``n = ao_rays * spp`` rays behind it (from the sampling channels and ``config.limits``): never
    0 or 1, 0.5 without rays (today's sigmoid), so with many rays the network only corrects.
    ``"blend"``: ``w a + (1 - w) o`` with ``w = n / (n + k)``, the two estimates weighted by the rays each
    stands for (inverse variance), ``k = blend_rays`` the network's own (learned; per pixel with
    ``blend_map``; times ``4 p (1 - p)`` with ``blend_variance``, the mean's variance per ray, so that rays
    that agree outweigh the network): with many rays the output converges to the rays' mean, the plain
    render's AO; with none it is ``o``. With ``config.ao_interval``, clamped to the rays' interval
    (:func:`rays_interval` of the ``n`` rays times ``ray_factor``, all the rays behind the mean, at their
    :func:`interval_z`).

    Shape:
        raw_ao: (B, 1, H, W). inputs: (B, 8, H, W). blend_rays: () or (B, 1, H, W) (with "blend").
        Returns (B, 1, H, W).
    """
    if config.ao_prior == "none":
        return torch.sigmoid(raw_ao)
    sampling = inputs[:, SAMPLING].float()
    n = sampling[:, :1] * config.max_ao_rays * sampling[:, 1:] * config.max_spp
    mean = inputs[:, SAMPLED_AO].float()
    smoothed = (n * mean + 0.5) / (n + 1)
    ao = torch.sigmoid(torch.logit(smoothed) + raw_ao)
    if config.ao_prior == "blend":
        if blend_rays is None:
            raise ValueError("ao_output: a blend model's AO needs its blend_rays")
        if config.blend_variance:
            blend_rays = blend_rays * 4 * smoothed * (1 - smoothed)
        weight = n / (n + blend_rays).clamp_min(1e-12)  # no rays and a weight worth none: the network's
        ao = weight * mean + (1 - weight) * ao
    if config.ao_interval:
        cast = n * ray_factor
        ao = torch.clamp(ao, *rays_interval(mean, cast, interval_z(config.ao_interval, cast,
                                                                   config.ao_interval_narrows_past)))
    return ao


def blend_rays_at(blend_rays: torch.Tensor | float | None, ray_factor: float, beyond: float = 0.0
                  ) -> torch.Tensor | float | None:
    """What a blend model's own AO stands for beside a mean of ``ray_factor`` times the rays its sampling
    channels count: ``k / ray_factor`` (the weight ``n r / (n r + k)`` of :func:`ao_output` as ``n / (n + k / r)``),
    over ``ray_factor ** beyond`` more (``blend_beyond``: past its ray limits the network's AO stands for
    ``k / r ** beyond`` rays); None for other priors."""
    return None if blend_rays is None else blend_rays / ray_factor ** (1.0 + beyond)


def geometry_gate(logits: torch.Tensor, inputs: torch.Tensor, config: ReconNetConfig) -> torch.Tensor:
    """The factor of each frame's mask and normal corrections: ``sigmoid(logits[spp - 1])``, ``spp`` its rays
    per pixel read from its sampling channel (rounded, within ``[1, max_spp]``; a non-finite one reads as
    ``max_spp``).

    Shape:
        logits: (max_spp,). inputs: (B, 8, H, W). Returns (B, 1, 1, 1).
    """
    share = inputs[:, SAMPLING][:, 1, 0, 0].float()
    spp = torch.nan_to_num(share * config.max_spp, nan=config.max_spp, posinf=config.max_spp, neginf=1.0)
    index = spp.round().clamp(1, config.max_spp).long() - 1
    return torch.sigmoid(logits.float())[index].view(-1, 1, 1, 1)


def macs_per_pixel(config: ReconNetConfig) -> float:
    """Multiply-adds per output pixel (convolutions only; the rest is memory traffic)."""
    w0, w1, w2, w3 = config.widths
    cells = config.upscale ** 2  # output pixels per input pixel
    stem = config.stem_stride ** 2  # input pixels per first-level pixel
    head = (INPUTS + RECURRENT * cells) * w0 * 9
    enc = w0 * w1 * 9 / 4 + w1 * w2 * 9 / 16 + w2 * w3 * 9 / 64
    body = 2 * config.blocks * w3 * w3 * 9 / 64
    dec = w3 * w2 / 64 + w2 * w2 * 9 / 16 + w2 * w1 / 16 + w1 * w1 * 9 / 4 + w1 * w0 / 4 + w0 * w0 * 9
    tail = w0 * OUTPUTS * cells * stem * 9
    pixel_tail = (OUTPUTS + INPUTS + RECURRENT + OUTPUTS) * config.pixel_tail * cells * stem
    return (head + enc + body + dec + tail + pixel_tail) / stem / cells


def upsampled_inputs(inputs: torch.Tensor, factor: int) -> torch.Tensor:
    """The inputs at ``factor`` times their resolution: bilinear, but depth nearest (a blend across
    a silhouette would be a depth where no surface is). The base an upscaling ReconNet corrects.

    Shape:
        inputs: (B, 8, h, w). Returns (B, 8, h * factor, w * factor).
    """
    if factor == 1:
        return inputs
    up = F.interpolate(inputs, scale_factor=factor, mode="bilinear", align_corners=False)
    depth = F.interpolate(inputs[:, DEPTH], scale_factor=factor, mode="nearest")
    return torch.cat([up[:, :DEPTH.start], depth, up[:, DEPTH.stop:]], dim=1)


class ReconNet(nn.Module):
    """Frame-recurrent full-resolution reconstruction of isosurface buffers.

    Frames of any size: sides that are not multiples of 8 are padded (replicating the border)
    and the output cropped.

    Shape:
        inputs: (B, 8, H, W). prev_warped: (B, 6, H, W). Returns (B, 6, H, W).
    """

    def __init__(self, config: ReconNetConfig):
        super().__init__()
        self.config = config
        w = config.widths
        cells = config.upscale ** 2  # the previous output's pixels per input pixel, read space-to-depth
        self.head = nn.Conv2d(INPUTS + RECURRENT * cells, w[0], 3, stride=config.stem_stride, padding=1)
        self.down = nn.ModuleList(nn.Conv2d(w[i], w[i + 1], 3, stride=2, padding=1) for i in range(LEVELS))
        self.body = nn.Sequential(*[ResidualBlock(w[LEVELS]) for _ in range(config.blocks)])
        # Decoding level i (from 1/2^(i+1) to 1/2^i): a 1x1 channel map at the coarse level,
        # bilinear 2x, plus the encoder's features, then a 3x3 conv.
        self.reduce = nn.ModuleList(nn.Conv2d(w[i + 1], w[i], 1) for i in range(LEVELS))
        self.fuse = nn.ModuleList(nn.Conv2d(w[i], w[i], 3, padding=1) for i in range(LEVELS))
        self.tail = nn.Conv2d(w[0], OUTPUTS * config.cell_side ** 2, 3, padding=1)  # depth-to-space after it
        if config.ao_prior == "blend":  # the log of the rays its own AO stands for (ao_output)
            self.register_parameter(BLEND_PARAMETER, nn.Parameter(torch.tensor(math.log(BLEND_RAYS_INIT))))
        if config.blend_map:  # its per-pixel log-offset, from the tail's features; zero: k alone
            offset = nn.Conv2d(w[0], config.cell_side ** 2, 3, padding=1)
            nn.init.zeros_(offset.weight)
            nn.init.zeros_(offset.bias)
            self.add_module(BLEND_MAP, offset)
        if config.geometry_gate:  # per rays per pixel, its geometry corrections' logit over GATE_RATE
            self.register_parameter(GATE_PARAMETER,
                                    nn.Parameter(torch.full((config.max_spp,), GATE_LOGIT_INIT / GATE_RATE)))
        if config.pixel_tail:  # the tail's correction, the pixel's inputs and its previous mask and AO in
            mlp = nn.Sequential(nn.Conv2d(OUTPUTS + INPUTS + RECURRENT, config.pixel_tail, 1), nn.ReLU(),
                                nn.Conv2d(config.pixel_tail, OUTPUTS, 1))
            nn.init.zeros_(mlp[2].weight)
            nn.init.zeros_(mlp[2].bias)
            self.add_module(PIXEL_TAIL, mlp)

    def forward(self, inputs: torch.Tensor, prev_warped: torch.Tensor, ray_factor: float = 1.0) -> torch.Tensor:
        """``ray_factor``: the rays behind the sampled AO's mean per ray the sampling channels count (> 1 for
        a frame of more rays than the model reads, :meth:`RayLimits.read`): a blend model weighs the mean by
        them (:func:`ao_output`)."""
        s = self.config.upscale
        dims = check_shape(inputs, f"(B, {INPUTS}, H, W)", "inputs", "ReconNet")
        h, w = dims["H"], dims["W"]
        check_shape(prev_warped, f"({dims['B']}, {OUTPUTS}, {h * s}, {w * s})", "prev_warped", "ReconNet")
        step = self.config.multiple
        pad = (0, -w % step, 0, -h % step)
        recurrent = torch.cat([prev_warped[:, MASK], prev_warped[:, AO]], dim=1)
        x = torch.cat([inputs, F.pixel_unshuffle(recurrent, s) if s > 1 else recurrent], dim=1)
        if any(pad):
            x = F.pad(x, pad, mode="replicate")
        skips = [F.relu(self.head(x))]
        for conv in self.down:
            skips.append(F.relu(conv(skips[-1])))
        y = self.body(skips[-1])
        for i in reversed(range(LEVELS)):
            y = F.interpolate(self.reduce[i](y), scale_factor=2, mode="bilinear", align_corners=False)
            y = F.relu(self.fuse[i](F.relu(y + skips[i])))
        base = upsampled_inputs(inputs, s)
        raw = self.correction(self.to_output_pixels(self.tail(y), h, w), base, recurrent)
        gate = 1.0 if self.gate_logits is None else geometry_gate(self.gate_logits, inputs, self.config)
        mask = (base[:, MASK] + gate * raw[:, MASK]).clamp(0.0, 1.0)
        normal = base[:, NORMAL] + gate * raw[:, NORMAL]
        blend_rays = self.blend_rays
        if self.config.blend_map:
            blend_rays = blend_rays * torch.exp(self.to_output_pixels(self.ao_blend_map(y), h, w).float())
        ao = ao_output(raw[:, AO], base, self.config, blend_rays_at(blend_rays, ray_factor, self.config.blend_beyond),
                       ray_factor)
        # Depth passes through: the render found it (shading does not read it).
        return torch.cat([mask, normal, base[:, DEPTH], ao], dim=1)

    def correction(self, raw: torch.Tensor, base: torch.Tensor, recurrent: torch.Tensor) -> torch.Tensor:
        """The tail's per-pixel correction ``raw``, plus a ``pixel_tail`` model's MLP of it, the inputs at the
        output's resolution ``base`` and the previous output's mask and AO ``recurrent`` (as it is otherwise).

        Shape:
            raw: (B, 6, sH, sW). base: (B, 8, sH, sW). recurrent: (B, 2, sH, sW). Returns (B, 6, sH, sW).
        """
        if not self.config.pixel_tail:
            return raw
        return raw + self.pixel_tail(torch.cat([raw, base.to(raw.dtype), recurrent.to(raw.dtype)], dim=1))

    def to_output_pixels(self, raw: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """The first level's per-pixel outputs (``config.cell_side`` squared per channel, depth-to-space) at the
        output's pixels, cropped to the frame of ``h`` x ``w`` input pixels.

        Shape:
            raw: (B, C * cell_side ** 2, H', W'), the padded frame's first level. Returns (B, C, sh, sw).
        """
        s, stem = self.config.upscale, self.config.stem_stride
        if stem > 1:  # the stem's cells first: input pixels (upscale 1)
            return F.pixel_shuffle(raw, stem)[..., :h, :w]
        raw = raw[..., :h, :w]
        return F.pixel_shuffle(raw, s) if s > 1 else raw

    @torch.no_grad()
    def open_gates(self) -> None:
        """Set a gated model's geometry gates back at their start (:data:`GATE_LOGIT_INIT`, all but open)
        (ValueError: an ungated model has none)."""
        if not self.config.geometry_gate:
            raise ValueError("open_gates: this ReconNet has no geometry gates (geometry_gate is off)")
        getattr(self, GATE_PARAMETER).fill_(GATE_LOGIT_INIT / GATE_RATE)

    @property
    def gate_logits(self) -> torch.Tensor | None:
        """A gated model's geometry gates' logits, one per rays per pixel (:func:`geometry_gate`); None ungated."""
        return GATE_RATE * getattr(self, GATE_PARAMETER) if self.config.geometry_gate else None

    @property
    def blend_rays(self) -> torch.Tensor | None:
        """The rays a "blend" model's own AO stands for (:func:`ao_output`); None for other priors."""
        return getattr(self, BLEND_PARAMETER).exp() if self.config.ao_prior == "blend" else None

    def first_previous(self, inputs: torch.Tensor) -> torch.Tensor:
        """The stand-in for the previous output on a sequence's first frame, at the output's resolution."""
        inputs = upsampled_inputs(inputs, self.config.upscale)
        b, _, h, w = inputs.shape
        if self.config.first_frame == "zeros":
            return inputs.new_zeros(b, OUTPUTS, h, w)
        sampled = inputs[:, SAMPLING][:, :1] > 0  # AO rays were cast
        ao = torch.where(sampled, inputs[:, SAMPLED_AO], inputs[:, MASK])
        return torch.cat([inputs[:, :AO.start], ao], dim=1)

    def step(self, inputs: torch.Tensor, flow: torch.Tensor | None, previous: torch.Tensor | None,
             ray_factor: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
        """One recurrent step: warp ``previous`` by ``flow``, then reconstruct.

        ``previous`` (and ``flow``) are ``None`` on a sequence's first frame.

        Returns:
            ``(output, previous_warped)``, both (B, 6, sH, sW), ``s`` the config's upscale.

        Shape:
            inputs: (B, 8, H, W). flow: (B, 2, H, W), input pixels. previous: (B, 6, sH, sW).
        """
        if previous is None:
            warped = self.first_previous(inputs)
        else:
            if flow is None:
                raise ValueError("a step with a previous output needs the flow to warp it")
            s = self.config.upscale
            warped = warp_by_flow(previous, upscale_flow(flow, s) if s > 1 else flow)
        return self(inputs, warped, ray_factor), warped
