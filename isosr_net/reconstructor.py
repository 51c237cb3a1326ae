"""Inference: the `Reconstructor`, a trained ReconNet with one stream's recurrent state.

    reconstructor = Reconstructor()                    # the shipped reconstruction model, CPU, fp32
    for frame in frames:                               # full-res FrameBuffers: mask, normal, depth,
        out = reconstructor.reconstruct(frame, 2, 1)   #   ao (2 rays), flow; rendered with spp 1
    reconstructor.reset()                              # on a camera cut

``out`` holds mask (an antialiased alpha), normal, depth and converged-looking AO. Every stream
needs its own `Reconstructor`: the previous output is its state.
"""

from __future__ import annotations

from pathlib import Path

import torch

from isosr_render.buffers import FrameBuffers
from isosr_render.shapes import check_shape
from isosr_net.reconnet import MAX_RECON_AO_RAYS, MAX_RECON_SPP, ReconNet, sampling_channels
from isosr_net.upscaler import InputChecks, Upscaler, highres_frame, lowres_tensors

DEFAULT_RECON_MODEL = Path(__file__).resolve().parent / "recon_model"


def recon_inputs(frame: FrameBuffers, ao_rays: int, spp: int,
                 checks: InputChecks | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """A full-resolution frame as ReconNet's inputs: ``(inputs, flow or None)``, the inputs in
    the channel order :data:`isosr_render.conventions.RECON_CHANNELS`.

    Args:
        frame: mask, normal, depth, and ``ao`` when ``ao_rays > 0``, rendered with ``spp`` rays
            per pixel and ``ao_rays`` AO rays per hit.
        ao_rays: AO rays per hit, 0 to :data:`isosr_net.reconnet.MAX_RECON_AO_RAYS` (0: no AO input).
        spp: rays per pixel, 1 to :data:`isosr_net.reconnet.MAX_RECON_SPP`.
        checks: where to queue the checks of the buffers' values; None checks at once (a host sync).

    Raises:
        ValueError: counts out of range, a buffer missing or misshapen, and (without ``checks``)
            a buffer not finite or AO outside [0, 1].

    Shape:
        Returns inputs (1, 8, H, W) and flow (1, 2, H, W), float32.
    """
    for name, value, low, high in (("ao_rays", ao_rays, 0, MAX_RECON_AO_RAYS), ("spp", spp, 1, MAX_RECON_SPP)):
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise ValueError(f"reconstruction: {name} must be an integer in [{low}, {high}], got {value!r}")
    now = checks is None
    checks = InputChecks() if now else checks
    lowres, flow = lowres_tensors(frame, checks)
    if ao_rays:
        if frame.ao is None:
            raise ValueError(f"reconstruction from {ao_rays} AO rays needs the frame's ao buffer")
        check_shape(frame.ao, "(H, W)", "ao", "recon_inputs", {"H": lowres.shape[2], "W": lowres.shape[3]})
        ao = frame.ao.float()
        checks.add(((ao >= 0) & (ao <= 1)).all(), bool, lambda _: "ao holds values outside [0, 1] (or NaN)")
        ao = ao[None, None]
    else:
        ao = torch.zeros_like(lowres[:, :1])
    if now:
        checks.raise_first()
    return torch.cat([lowres, ao, sampling_channels(ao_rays, spp, lowres)], dim=1), flow


class Reconstructor(Upscaler):
    """A trained reconstruction network and one stream's recurrent state.

    Args:
        model: a ReconNet model folder; default the shipped one.
        device, precision, channels_last, compile, autotune: as for :class:`Upscaler`.
    """

    def __init__(self, model: str | Path = DEFAULT_RECON_MODEL, device: str = "cpu", precision: str = "fp32",
                 channels_last: bool = False, compile: str | None = None, autotune: bool = False):
        super().__init__(model, device, precision, channels_last=channels_last, compile=compile, autotune=autotune)
        if not isinstance(self.net, ReconNet):
            raise ValueError(f"{model}: a {type(self.net).__name__}, not a reconstruction network (ReconNet)")

    @classmethod
    def fastest(cls, model: str | Path = DEFAULT_RECON_MODEL, device: str = "cuda",
                precision: str | None = None) -> "Reconstructor":
        """The variant for interactive use on ``device``: NHWC, compiled with CUDA graphs, fp16
        on CUDA (``precision`` overrides); eager fp32 NHWC elsewhere."""
        if torch.device(device).type == "cuda":
            return cls(model, device, precision or "fp16", channels_last=True, compile="reduce-overhead",
                       autotune=True)
        return cls(model, device, precision or "fp32", channels_last=True)

    def reconstruct(self, frame: FrameBuffers, ao_rays: int, spp: int = 1) -> FrameBuffers:
        """Reconstruct one frame (see :func:`recon_inputs`; ``flow`` except after a cut)."""
        checks = InputChecks()
        inputs, flow = recon_inputs(frame, ao_rays, spp, checks)
        return highres_frame(self.step(inputs, flow, checks))

    def upscale(self, frame: FrameBuffers) -> FrameBuffers:
        raise TypeError("a Reconstructor reconstructs at full resolution: call reconstruct(frame, ao_rays, spp)")
