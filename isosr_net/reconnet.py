"""ReconNet: full-resolution reconstruction of few-ray ambient occlusion and antialiased edges.

Beyond the paper: instead of fewer pixels, fewer rays. Per frame the network sees the
full-resolution first-hit buffers (mask, normal, depth) rendered with ``spp`` rays per pixel,
the AO of ``ao_rays`` hemisphere rays per hit (0: none cast, AO inferred from the geometry as
in the paper), and its own previous output warped by the flow (the paper's recurrence). It
outputs the converged frame's buffers: AO as from hundreds of rays and mask and normal as
from 4 rays per pixel (an antialiased silhouette); depth passes through from the input. Channel orders:
:data:`isosr_render.conventions.RECON_CHANNELS` in, ``HIGHRES_CHANNELS`` out.

The network is a small U-Net: AO varies slowly along a surface and needs a wide view (its
rays reach ``ao_radius``, tens of pixels on screen), edges need full resolution. So it
encodes at 1/2, 1/4 and 1/8 resolution, does most of its work at 1/8, and decodes with
additive skips; full resolution carries ``widths[0]`` channels (16), which keeps a 1080p frame
at about 30 GMAC (:func:`macs_per_pixel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from isosr_render.conventions import AO, DEPTH, HIGHRES_CHANNELS, MASK, NORMAL, RECON_CHANNELS, SAMPLED_AO, SAMPLING
from isosr_render.shapes import check_shape
from isosr_net.architectures import ResidualBlock
from isosr_net.flow_warp import warp_by_flow

INPUTS = len(RECON_CHANNELS)
OUTPUTS = len(HIGHRES_CHANNELS)
# The previous output's channels the network reads back: mask and AO.
RECURRENT = 2
# The most AO rays per hit and rays per pixel the network takes: its training range. The
# sampling channels hold ao_rays / MAX_RECON_AO_RAYS and spp / MAX_RECON_SPP, at most 1.
MAX_RECON_AO_RAYS, MAX_RECON_SPP = 8, 4
LEVELS = 3  # 1/2, 1/4, 1/8
FIRST_FRAME_MODES = ("zeros", "inputs")


@dataclass(frozen=True)
class ReconNetConfig:
    """ReconNet's hyper-parameters.

    Attributes:
        widths: channels at full resolution, 1/2, 1/4 and 1/8.
        blocks: residual blocks at 1/8 resolution.
        first_frame: the "previous output" of a sequence's first frame: ``"zeros"``, or the
            ``"inputs"`` (their mask and sampled AO, AO 1 where none was cast).
    """

    type: str = "ReconNet"
    widths: tuple[int, int, int, int] = (16, 32, 64, 64)
    blocks: int = 2
    first_frame: str = "inputs"

    def __post_init__(self):
        object.__setattr__(self, "widths", tuple(self.widths))
        if len(self.widths) != LEVELS + 1 or any(isinstance(w, bool) or not isinstance(w, int) or w < 1
                                                 for w in self.widths):
            raise ValueError(f"widths must be {LEVELS + 1} positive integers, got {self.widths}")
        if self.blocks < 0:
            raise ValueError(f"blocks must be >= 0, got {self.blocks}")
        if self.first_frame not in FIRST_FRAME_MODES:
            raise ValueError(f"first_frame must be one of {FIRST_FRAME_MODES}, got {self.first_frame!r}")

    @property
    def upscale(self) -> int:
        """Output over input resolution: 1, the network reconstructs at the resolution it is given."""
        return 1


def sampling_channels(ao_rays: int, spp: int, like: torch.Tensor) -> torch.Tensor:
    """The two constant sampling images of :data:`RECON_CHANNELS` for a frame like ``like`` (B, C, H, W).

    Shape:
        Returns (B, 2, H, W).
    """
    b, _, h, w = like.shape
    # Filled from Python numbers: a tensor built from host values would be a blocking copy on GPUs.
    return torch.cat([like.new_full((b, 1, h, w), ao_rays / MAX_RECON_AO_RAYS),
                      like.new_full((b, 1, h, w), spp / MAX_RECON_SPP)], dim=1)


def macs_per_pixel(config: ReconNetConfig) -> float:
    """Multiply-adds per full-resolution pixel (convolutions only; the rest is memory traffic)."""
    w0, w1, w2, w3 = config.widths
    enc = (INPUTS + RECURRENT) * w0 * 9 + w0 * w1 * 9 / 4 + w1 * w2 * 9 / 16 + w2 * w3 * 9 / 64
    body = 2 * config.blocks * w3 * w3 * 9 / 64
    dec = w3 * w2 / 64 + w2 * w2 * 9 / 16 + w2 * w1 / 16 + w1 * w1 * 9 / 4 + w1 * w0 / 4 + w0 * w0 * 9
    return enc + body + dec + w0 * OUTPUTS * 9


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
        self.head = nn.Conv2d(INPUTS + RECURRENT, w[0], 3, padding=1)
        self.down = nn.ModuleList(nn.Conv2d(w[i], w[i + 1], 3, stride=2, padding=1) for i in range(LEVELS))
        self.body = nn.Sequential(*[ResidualBlock(w[LEVELS]) for _ in range(config.blocks)])
        # Decoding level i (from 1/2^(i+1) to 1/2^i): a 1x1 channel map at the coarse level,
        # bilinear 2x, plus the encoder's features, then a 3x3 conv.
        self.reduce = nn.ModuleList(nn.Conv2d(w[i + 1], w[i], 1) for i in range(LEVELS))
        self.fuse = nn.ModuleList(nn.Conv2d(w[i], w[i], 3, padding=1) for i in range(LEVELS))
        self.tail = nn.Conv2d(w[0], OUTPUTS, 3, padding=1)

    def forward(self, inputs: torch.Tensor, prev_warped: torch.Tensor) -> torch.Tensor:
        dims = check_shape(inputs, f"(B, {INPUTS}, H, W)", "inputs", "ReconNet")
        check_shape(prev_warped, f"(B, {OUTPUTS}, H, W)", "prev_warped", "ReconNet", dims)
        h, w = dims["H"], dims["W"]
        step = 2 ** LEVELS
        pad = (0, -w % step, 0, -h % step)
        x = torch.cat([inputs, prev_warped[:, MASK], prev_warped[:, AO]], dim=1)
        if any(pad):
            x = F.pad(x, pad, mode="replicate")
        skips = [F.relu(self.head(x))]
        for conv in self.down:
            skips.append(F.relu(conv(skips[-1])))
        y = self.body(skips[-1])
        for i in reversed(range(LEVELS)):
            y = F.interpolate(self.reduce[i](y), scale_factor=2, mode="bilinear", align_corners=False)
            y = F.relu(self.fuse[i](F.relu(y + skips[i])))
        raw = self.tail(y)[..., :h, :w]
        mask = (inputs[:, MASK] + raw[:, MASK]).clamp(0.0, 1.0)
        normal = inputs[:, NORMAL] + raw[:, NORMAL]
        ao = torch.sigmoid(raw[:, AO])
        # Depth passes through: at full resolution the render found it (shading does not read it).
        return torch.cat([mask, normal, inputs[:, DEPTH], ao], dim=1)

    def first_previous(self, inputs: torch.Tensor) -> torch.Tensor:
        """The stand-in for the previous output on a sequence's first frame."""
        b, _, h, w = inputs.shape
        if self.config.first_frame == "zeros":
            return inputs.new_zeros(b, OUTPUTS, h, w)
        sampled = inputs[:, SAMPLING][:, :1] > 0  # AO rays were cast
        ao = torch.where(sampled, inputs[:, SAMPLED_AO], inputs[:, MASK])
        return torch.cat([inputs[:, :AO.start], ao], dim=1)

    def step(self, inputs: torch.Tensor, flow: torch.Tensor | None,
             previous: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """One recurrent step: warp ``previous`` by ``flow``, then reconstruct.

        ``previous`` (and ``flow``) are ``None`` on a sequence's first frame.

        Returns:
            ``(output, previous_warped)``, both (B, 6, H, W).

        Shape:
            inputs: (B, 8, H, W). flow: (B, 2, H, W), pixels. previous: (B, 6, H, W).
        """
        if previous is None:
            warped = self.first_previous(inputs)
        else:
            if flow is None:
                raise ValueError("a step with a previous output needs the flow to warp it")
            warped = warp_by_flow(previous, flow)
        return self(inputs, warped), warped
