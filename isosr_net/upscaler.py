"""Inference: the `Upscaler`, a trained network with one stream's recurrent state.

    upscaler = Upscaler()                          # the shipped default model, CPU, fp32
    for frame in low_res_frames:                   # FrameBuffers with mask, normal, depth, flow
        high = upscaler.upscale(frame)             # FrameBuffers: mask (alpha), normal, depth, ao
    upscaler.reset()                               # on a camera cut

Every stream (viewer, sequence) needs its own `Upscaler`: the previous output is its state.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F

from isosr_render.buffers import FrameBuffers
from isosr_render.conventions import AO, DEPTH, LOWRES_BUFFERS, MASK, NORMAL
from isosr_render.shapes import check_shape
from isosr_net.flow_warp import upscale_flow, warp_by_flow
from isosr_net.fastpath import fast_network
from isosr_net.model import load_pretrained

DEFAULT_MODEL = Path(__file__).resolve().parent / "default_model"
PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}
COMPILE_MODES = (None, "default", "reduce-overhead", "max-autotune")
# fp16 ends at 65504 and the network's activations grow with the input depth: the shipped model
# gave NaN from depth 4e4 on, finite (if inaccurate) outputs up to 2e4. Deeper frames are refused.
FP16_MAX_DEPTH = 1e4


class InputChecks:
    """Checks of a frame's inputs computed on the device and read with one host sync.

    On a GPU every value read back to the host stalls the CPU until the queue drains, so a frame
    whose checks each read a value stalls once per check. The checks are queued instead and
    :meth:`raise_first` reads them all at once: where the rest of the frame is one compiled call
    (the `Reconstructor`), after it; where eager work follows the network (the `Upscaler`),
    before the network, so that work overlaps it.
    """

    def __init__(self):
        self._checks: list[tuple[torch.Tensor, Callable[[float], bool], Callable[[float], str]]] = []

    def add(self, value: torch.Tensor, ok: Callable[[float], bool], message: Callable[[float], str]) -> None:
        """Queue a check: ``ok(value)`` on the host, else ``ValueError(message(value))``."""
        self._checks.append((value.detach().reshape(()).float(), ok, message))

    def add_finite(self, name: str, t: torch.Tensor) -> None:
        """Queue: ``t`` holds no NaN or Inf."""
        self.add(torch.isfinite(t).all(), bool, lambda _: f"{name} holds NaN or Inf values")

    def raise_first(self) -> None:
        """Read every queued check (one host sync) and raise the first that fails."""
        if not self._checks:
            return
        by_device: dict[torch.device, list[int]] = {}
        for i, (value, _, _) in enumerate(self._checks):
            by_device.setdefault(value.device, []).append(i)
        values = [0.0] * len(self._checks)
        for indices in by_device.values():  # one read per device (the inputs may sit elsewhere)
            for i, v in zip(indices, torch.stack([self._checks[i][0] for i in indices]).tolist()):
                values[i] = v
        for v, (_, ok, message) in zip(values, self._checks):
            if not ok(v):
                raise ValueError(message(v))


def lowres_tensors(frame: FrameBuffers, checks: InputChecks | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """A low-res frame as the network's inputs: ``(lowres (1, 5, h, w), flow (1, 2, h, w) or None)``.

    Args:
        frame: mask, normal, depth, and flow except on a sequence's first frame.
        checks: where to queue the finiteness checks; None checks at once (a host sync).

    Raises:
        ValueError: a buffer is missing, has the wrong shape or dtype, or (without ``checks``) is not finite.
    """
    for name in LOWRES_BUFFERS:
        if getattr(frame, name) is None:
            raise ValueError(f"the low-res frame lacks its {name} buffer")
    dims = check_shape(frame.mask, "(H, W)", "mask", "lowres_tensors")
    now = checks is None
    checks = InputChecks() if now else checks
    for name, spec in (("mask", "(H, W)"), ("normal", "(H, W, 3)"), ("depth", "(H, W)"), ("flow", "(H, W, 2)")):
        t = getattr(frame, name)
        if t is None:
            continue
        check_shape(t, spec, name, "lowres_tensors", dims)
        if not t.is_floating_point():
            raise ValueError(f"{name} must be floating point, got {t.dtype}")
        checks.add_finite(name, t)
    if now:
        checks.raise_first()
    lowres = frame.channels_first(LOWRES_BUFFERS)[None]
    flow = None if frame.flow is None else frame.flow.permute(2, 0, 1)[None]
    return lowres.float(), None if flow is None else flow.float()


def highres_frame(output: torch.Tensor) -> FrameBuffers:
    """The network's output (1, 6, H, W) as high-res buffers; normals unit where covered, 0 elsewhere."""
    out = output[0].float()
    mask = out[MASK][0]
    normal = F.normalize(out[NORMAL], dim=0, eps=1e-6).permute(1, 2, 0) * (mask > 0)[..., None]
    return FrameBuffers(mask=mask, normal=normal, depth=out[DEPTH][0] * (mask > 0), ao=out[AO][0].clamp(0, 1))


class Upscaler:
    """A trained network and one stream's recurrent state.

    Args:
        model: a model folder (``config.json`` + ``model.safetensors``); default the shipped one.
        device: where to run.
        precision: ``"fp32"``, ``"bf16"`` or ``"fp16"`` (autocast).
        tile: low-res tile side for frames too large to run whole (None: whole frames);
            tiles overlap by ``halo`` pixels, more than the network's receptive field, so the
            result matches the untiled one.
        channels_last: keep activations in NHWC (faster convolutions on GPUs).
        compile: a ``torch.compile`` mode for the network on whole frames (``"default"``,
            ``"max-autotune"``, or ``"reduce-overhead"``, which also replays CUDA graphs);
            None runs eagerly.
        fast_layers: run the network's layers rewritten for speed (:mod:`isosr_net.fastpath`:
            channel counts padded to multiples of 8, SRNet's subpixel upsampling); the same function.
        autotune: let cuDNN time its algorithms per input shape (``torch.backends.cudnn.benchmark``,
            a process-wide switch that this turns on).
    """

    def __init__(self, model: str | Path = DEFAULT_MODEL, device: str = "cpu", precision: str = "fp32",
                 tile: int | None = None, halo: int = 24, channels_last: bool = False, compile: str | None = None,
                 fast_layers: bool = False, autotune: bool = False):
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
        if tile is not None and tile < 1:
            raise ValueError(f"tile must be positive, got {tile}")
        if compile not in COMPILE_MODES:
            raise ValueError(f"compile must be one of {COMPILE_MODES}, got {compile!r}")
        self.device = torch.device(device)
        self.net, self.config = load_pretrained(model, self.device)
        if fast_layers:
            self.net = fast_network(self.net)
        if channels_last:
            self.net = self.net.to(memory_format=torch.channels_last)
        if autotune:
            torch.backends.cudnn.benchmark = True
        # Static shapes: a viewer sees few frame sizes, and each gets kernels specialized to it.
        # The warp stays eager: its CUDA kernel beat inductor's gather (2.79 vs 2.99 ms a step, H200).
        self._network = torch.compile(self.net, mode=compile, dynamic=False) if compile else self.net
        self.upscale_factor = self.net.config.upscale
        self.precision = precision
        self.tile, self.halo = tile, halo
        self.previous: torch.Tensor | None = None

    @classmethod
    def fastest(cls, model: str | Path = DEFAULT_MODEL, device: str = "cuda", precision: str | None = None) -> "Upscaler":
        """The variant that measured fastest on ``device`` within its tolerance (``isosr bench --only network``);
        ``precision`` overrides its precision (default bf16 on CUDA, fp32 elsewhere)."""
        if torch.device(device).type == "cuda":
            return cls(model, device, precision or "bf16", channels_last=True, compile="reduce-overhead",
                       autotune=True, fast_layers=True)
        return cls(model, device, precision or "fp32", channels_last=True)

    def reset(self) -> None:
        """Forget the previous output (a camera cut, a new sequence)."""
        self.previous = None

    @torch.no_grad()
    def step(self, lowres: torch.Tensor, flow: torch.Tensor | None, checks: InputChecks | None = None) -> torch.Tensor:
        """Upscale one frame of network inputs; keeps the output as the next frame's previous.

        Args:
            lowres, flow: the inputs (flow None: the state is reset).
            checks: the inputs' queued checks (see :func:`lowres_tensors`), read with this
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
        self._check_precision(lowres, checks)
        checks.raise_first()
        previous, flow = self._carried(lowres, flow)
        h, w = lowres.shape[-2:]
        whole = self.tile is None or (h <= self.tile and w <= self.tile)
        with torch.autocast(self.device.type, dtype=PRECISIONS[self.precision], enabled=self.precision != "fp32"):
            warped = self._warp(lowres, previous, flow)
            output = self._network(lowres, warped) if whole else self._tiled(lowres, warped)
            # A copy: compiled graphs may reuse their output buffers on the next call.
            output = output.float().clone()
        self.previous = output
        return output

    def _check_precision(self, lowres: torch.Tensor, checks: InputChecks) -> None:
        """Queue what the precision needs of the inputs: fp16 takes depths up to :data:`FP16_MAX_DEPTH`."""
        if self.precision == "fp16":
            checks.add(lowres[:, DEPTH].abs().amax(), lambda deepest: deepest <= FP16_MAX_DEPTH,
                       lambda deepest: f"fp16 takes depths up to {FP16_MAX_DEPTH:g}, this frame reaches "
                                       f"{deepest:.3g}: use bf16 or fp32")

    def _carried(self, lowres: torch.Tensor, flow: torch.Tensor | None) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """``(previous, flow)`` to carry into this frame: both None after a cut (no flow) or a
        change of frame size (nothing of this size to warp)."""
        previous = None if flow is None else self.previous
        if previous is not None and previous.shape[-2:] != tuple(s * self.upscale_factor for s in lowres.shape[-2:]):
            previous = None
        return previous, None if previous is None else flow.to(self.device)

    def _warp(self, lowres: torch.Tensor, previous: torch.Tensor | None, flow: torch.Tensor | None) -> torch.Tensor:
        """The previous output warped to this frame, or the first frame's stand-in."""
        if previous is None:
            return self.net.first_previous(lowres)
        return warp_by_flow(previous, upscale_flow(flow, self.upscale_factor))

    def _tiled(self, lowres: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
        """The network tile by tile with overlapping halos."""
        h, w = lowres.shape[-2:]
        s, t, halo = self.upscale_factor, self.tile, self.halo
        output = torch.empty(1, warped.shape[1], h * s, w * s, device=lowres.device)
        for y0 in range(0, h, t):
            for x0 in range(0, w, t):
                ya, yb = max(0, y0 - halo), min(h, y0 + t + halo)
                xa, xb = max(0, x0 - halo), min(w, x0 + t + halo)
                part = self.net(lowres[..., ya:yb, xa:xb], warped[..., ya * s:yb * s, xa * s:xb * s]).float()
                y1, x1 = min(h, y0 + t), min(w, x0 + t)
                output[..., y0 * s:y1 * s, x0 * s:x1 * s] = part[..., (y0 - ya) * s:(y1 - ya) * s,
                                                                 (x0 - xa) * s:(x1 - xa) * s]
        return output

    def upscale(self, frame: FrameBuffers) -> FrameBuffers:
        """Upscale a low-res frame (mask, normal, depth, and flow except after a cut)."""
        checks = InputChecks()
        lowres, flow = lowres_tensors(frame, checks)
        return highres_frame(self.step(lowres, flow, checks))
