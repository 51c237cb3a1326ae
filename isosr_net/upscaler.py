"""Inference: the `Upscaler`, a trained network with one stream's recurrent state.

    upscaler = Upscaler()                          # the shipped default model, CPU, fp32
    for frame in low_res_frames:                   # FrameBuffers with mask, normal, depth, flow
        high = upscaler.upscale(frame)             # FrameBuffers: mask (alpha), normal, depth, ao
    upscaler.reset()                               # on a camera cut

Every stream (viewer, sequence) needs its own `Upscaler` (:meth:`~RecurrentNetwork.own`): the
previous output is its state.
"""

from __future__ import annotations

from collections.abc import Generator
from pathlib import Path

import torch

from isosr_render.buffers import FrameBuffers
from isosr_render.steps import finish_steps
from isosr_net.flow_warp import upscale_flow, warp_by_flow
from isosr_net.inference import PRECISIONS, InputChecks, RecurrentNetwork, output_buffers, surface_tensors

DEFAULT_MODEL = Path(__file__).resolve().parent / "default_model"
COMPILE_MODES = (None, "default", "reduce-overhead", "max-autotune")


class Upscaler(RecurrentNetwork):
    """A trained upscaling network (SRNet) and one stream's recurrent state.

    Args:
        model: a model folder; default the shipped one.
        device, precision, channels_last, fast_layers, autotune: as for :class:`RecurrentNetwork`
            (fast layers here also upsample SRNet subpixel-wise).
        tile: low-res tile side for frames too large to run whole (None: whole frames);
            tiles overlap by ``halo`` pixels, more than the network's receptive field, so the
            result matches the untiled one.
        compile: a ``torch.compile`` mode for the network on whole frames (``"default"``,
            ``"max-autotune"``, or ``"reduce-overhead"``, which also replays CUDA graphs);
            None runs eagerly.
    """

    display_name = "network"  # in a method's name: "x4 network bf16"

    def __init__(self, model: str | Path = DEFAULT_MODEL, device: str = "cpu", precision: str = "fp32",
                 tile: int | None = None, halo: int = 24, channels_last: bool = False, compile: str | None = None,
                 fast_layers: bool = False, autotune: bool = False):
        if tile is not None and tile < 1:
            raise ValueError(f"tile must be positive, got {tile}")
        if compile not in COMPILE_MODES:
            raise ValueError(f"compile must be one of {COMPILE_MODES}, got {compile!r}")
        super().__init__(model, device, precision, channels_last=channels_last, fast_layers=fast_layers,
                         autotune=autotune)
        # Static shapes: a viewer sees few frame sizes, and each gets kernels specialized to it.
        # The warp stays eager: its CUDA kernel beat inductor's gather (2.79 vs 2.99 ms a step, H200).
        self._network = torch.compile(self.net, mode=compile, dynamic=False) if compile else self.net
        self.upscale_factor = self.net.config.upscale
        self.tile, self.halo = tile, halo

    @classmethod
    def fastest(cls, model: str | Path = DEFAULT_MODEL, device: str = "cuda", precision: str | None = None) -> "Upscaler":
        """The variant that measured fastest on ``device`` within its tolerance (``isosr bench --only network``);
        ``precision`` overrides its precision (default bf16 on CUDA, fp32 elsewhere)."""
        if torch.device(device).type == "cuda":
            return cls(model, device, precision or "bf16", channels_last=True, compile="reduce-overhead",
                       autotune=True, fast_layers=True)
        return cls(model, device, precision or "fp32", channels_last=True)

    def step(self, lowres: torch.Tensor, flow: torch.Tensor | None, checks: InputChecks | None = None) -> torch.Tensor:
        """Upscale one frame of network inputs (:meth:`steps` run whole)."""
        return finish_steps(self.steps(lowres, flow, checks))

    @torch.no_grad()
    def steps(self, lowres: torch.Tensor, flow: torch.Tensor | None,
              checks: InputChecks | None = None) -> Generator[None, None, torch.Tensor]:
        """Upscale one frame of network inputs; keeps the output as the next frame's previous. A
        generator: a tiled frame yields between tiles (a scheduler may interleave other work; no
        autocast stays entered across a yield), and returns the output.

        Args:
            lowres, flow: the inputs (flow None: the state is reset).
            checks: the inputs' queued checks (see :func:`~isosr_net.inference.surface_tensors`), read with this
                step's own in one sync before the network runs (the eager work after a step
                then overlaps the network on GPUs: reading them at the end cost the x4 path
                about 1 ms at 1080p on an H100); a frame that fails them raises and leaves the
                state as it was.

        Raises:
            ValueError: a failed check, or fp16 and depths beyond :data:`FP16_MAX_DEPTH`.

        Shape:
            lowres: (1, C, h, w). flow: (1, 2, h, w) or None.
            Returns (1, 6, h * s, w * s), float32.
        """
        lowres = lowres.to(self.device)
        checks = InputChecks() if checks is None else checks
        self.check_precision(lowres, checks)
        checks.raise_first()
        previous, flow = self.carried(lowres, flow)
        h, w = lowres.shape[-2:]
        whole = self.tile is None or (h <= self.tile and w <= self.tile)
        with self._autocast():
            warped = self._warp(lowres, previous, flow)
        if whole:
            with self._autocast():
                output = self._network(lowres, warped)
        else:
            output = yield from self._tiled(lowres, warped)
        # A copy: compiled graphs may reuse their output buffers on the next call.
        self.previous = output = output.float().clone()
        return output

    def _autocast(self):
        return torch.autocast(self.device.type, dtype=PRECISIONS[self.precision], enabled=self.precision != "fp32")

    def _warp(self, lowres: torch.Tensor, previous: torch.Tensor | None, flow: torch.Tensor | None) -> torch.Tensor:
        """The previous output warped to this frame, or the first frame's stand-in."""
        if previous is None:
            return self.net.first_previous(lowres)
        return warp_by_flow(previous, upscale_flow(flow, self.upscale_factor))

    def _tiled(self, lowres: torch.Tensor, warped: torch.Tensor) -> Generator[None, None, torch.Tensor]:
        """The network tile by tile with overlapping halos, yielding after each tile but the last."""
        h, w = lowres.shape[-2:]
        s, t, halo = self.upscale_factor, self.tile, self.halo
        output = torch.empty(1, warped.shape[1], h * s, w * s, device=lowres.device)
        corners = [(y0, x0) for y0 in range(0, h, t) for x0 in range(0, w, t)]
        for i, (y0, x0) in enumerate(corners):
            if i:
                yield
            ya, yb = max(0, y0 - halo), min(h, y0 + t + halo)
            xa, xb = max(0, x0 - halo), min(w, x0 + t + halo)
            with self._autocast():
                part = self.net(lowres[..., ya:yb, xa:xb], warped[..., ya * s:yb * s, xa * s:xb * s]).float()
            y1, x1 = min(h, y0 + t), min(w, x0 + t)
            output[..., y0 * s:y1 * s, x0 * s:x1 * s] = part[..., (y0 - ya) * s:(y1 - ya) * s, (x0 - xa) * s:(x1 - xa) * s]
        return output

    def upscale(self, frame: FrameBuffers) -> FrameBuffers:
        """Upscale a low-res frame (mask, normal, depth, and flow except after a cut)."""
        return finish_steps(self.upscale_steps(frame))

    def upscale_steps(self, frame: FrameBuffers) -> Generator[None, None, FrameBuffers]:
        """:meth:`upscale` in slices (:meth:`steps`)."""
        checks = InputChecks()
        lowres, flow = surface_tensors(frame, checks)
        return output_buffers((yield from self.steps(lowres, flow, checks)))
