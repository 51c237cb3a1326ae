"""What every trained frame network shares at inference: loading, precision, input checks, and
one stream's recurrent state (:class:`RecurrentNetwork`, the base of `Upscaler` and `Reconstructor`).

    net.reset()                           # a cut: forget the previous output
    previous, flow = net.carried(inputs, flow)   # what this frame may warp (None after a cut or resize)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from isosr_render.buffers import FrameBuffers
from isosr_render.conventions import AO, DEPTH, LOWRES_BUFFERS, MASK, NORMAL
from isosr_render.shapes import check_shape
from isosr_net.fastpath import fast_network
from isosr_net.model import load_pretrained

PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}
# fp16 ends at 65504 and the networks' activations grow with the input depth: the shipped upscaler
# gave NaN from depth 4e4 on, finite (if inaccurate) outputs up to 2e4. Deeper frames are refused.
FP16_MAX_DEPTH = 1e4


def default_precision(device: str | torch.device) -> str:
    """The networks' precision where none is asked for: fp16 on CUDA devices (tensor cores), fp32
    elsewhere (CPUs run half precision slower, not faster)."""
    return "fp16" if torch.device(device).type == "cuda" else "fp32"


# The input checks a frame's work computes on the device (one value each, in this order): a flag
# (1) per buffer holding NaN or Inf, a flag for AO outside [0, 1], and the largest finite |depth|.
FRAME_FLAGS = ("mask", "normal", "depth", "flow", "ao", "deepest")


AO_MESSAGE = lambda _: "ao holds values outside [0, 1] (or NaN)"  # noqa: E731


def _not_finite(name: str) -> Callable[[float], str]:
    return lambda _: f"{name} holds NaN or Inf values"


def _flag_clear(flag: float) -> bool:
    return flag == 0


Check = tuple[Callable[[float], bool], Callable[[float], str]]  # ok(value), message(value)
DEEPEST: Check = (lambda d: d <= FP16_MAX_DEPTH,
                  lambda d: f"fp16 takes depths up to {FP16_MAX_DEPTH:g}, this frame reaches {d:.3g}: use bf16 or fp32")
# Per FRAME_FLAGS slot, its check (None: not checked) in fp32/bf16 and in fp16 (depths bounded).
_FLAG_CHECKS = {fp16: tuple((_flag_clear, _not_finite(name)) for name in FRAME_FLAGS[:4])
                + ((_flag_clear, AO_MESSAGE), DEEPEST if fp16 else None) for fp16 in (False, True)}


class InputChecks:
    """Checks of a frame's inputs computed on the device and read with one host sync.

    On a GPU every value read back to the host stalls the CPU until the queue drains, so a frame
    whose checks each read a value stalls once per check. The checks are queued instead and
    :meth:`raise_first` reads them all at once: where the rest of the frame is one compiled call
    (the `Reconstructor`), after it; where eager work follows the network (the `Upscaler`),
    before the network, so that work overlaps it.
    """

    def __init__(self):
        # Queued values (1-d tensors), each element with its check: (ok, message), or None for none.
        self._checks: list[tuple[torch.Tensor, Sequence[Check | None]]] = []

    @classmethod
    def joined(cls, parts: Sequence[InputChecks]) -> InputChecks:
        """One set of the checks queued in ``parts``, in their order."""
        joined = cls()
        joined._checks = [check for part in parts for check in part._checks]
        return joined

    def add(self, value: torch.Tensor, ok: Callable[[float], bool], message: Callable[[float], str]) -> None:
        """Queue a check: ``ok(value)`` on the host, else ``ValueError(message(value))``."""
        self._checks.append((value.detach().reshape(1).float(), [(ok, message)]))

    def add_finite(self, name: str, t: torch.Tensor) -> None:
        """Queue: ``t`` holds no NaN or Inf."""
        self.add(torch.isfinite(t).all(), bool, _not_finite(name))

    def add_flags(self, flags: torch.Tensor, fp16: bool) -> None:
        """Queue the checks of a frame's :data:`FRAME_FLAGS` (the vector read as it is), in their
        order: finite buffers, AO in [0, 1], then (``fp16``) depths within :data:`FP16_MAX_DEPTH`."""
        self._checks.append((flags.detach().float(), _FLAG_CHECKS[fp16]))

    def add_deepest(self, deepest: torch.Tensor) -> None:
        """Queue: the largest |depth| is within what fp16 takes (:data:`FP16_MAX_DEPTH`)."""
        self.add(deepest, *DEEPEST)

    def raise_first(self) -> None:
        """Read every queued check (one host sync) and raise the first that fails."""
        if not self._checks:
            return
        by_device: dict[torch.device, list[int]] = {}
        for i, (values, _) in enumerate(self._checks):
            by_device.setdefault(values.device, []).append(i)
        read: list[list[float]] = [[] for _ in self._checks]
        for indices in by_device.values():  # one read per device (the inputs may sit elsewhere)
            values = [self._checks[i][0] for i in indices]
            flat = (values[0] if len(values) == 1 else torch.cat(values)).tolist()
            for i, v in zip(indices, values):  # each queued vector's share, by its own length
                read[i], flat = flat[:len(v)], flat[len(v):]
        error = self._first_failure([v for values in read for v in values])
        if error is not None:
            raise error

    def read_later(self) -> LateChecks:
        """The queued checks (all on one device) copied to the host behind the device's queued work, with no
        wait: :meth:`LateChecks.error` reads them once the device has got there."""
        values = torch.cat([v for v, _ in self._checks]) if self._checks else torch.zeros(0)
        if values.device.type != "cuda":
            return LateChecks(values, None, self._first_failure)
        host = torch.empty(values.shape, dtype=values.dtype, pin_memory=True)  # pinned: a copy that does not wait
        host.copy_(values, non_blocking=True)
        ready = torch.cuda.Event()
        ready.record()
        return LateChecks(host, ready, self._first_failure)

    @classmethod
    def read_later_each(cls, parts: Sequence[InputChecks]) -> list[LateChecks]:
        """:meth:`read_later` of each of ``parts`` (all on one device), with one copy to the host and one event
        for them all: each part's checks read from its share of the copy."""
        together, start, late = cls.joined(parts).read_later(), 0, []
        for part in parts:
            size = sum(len(values) for values, _ in part._checks)
            late.append(LateChecks(together.values[start:start + size], together.ready, part._first_failure))
            start += size
        return late

    def _first_failure(self, flat: list[float]) -> ValueError | None:
        """The error of the first check that fails, given the queued values read one after the other."""
        for values, checks in self._checks:
            read, flat = flat[:len(values)], flat[len(values):]
            for v, check in zip(read, checks):
                if check is not None and not check[0](v):
                    return ValueError(check[1](v))
        return None


@dataclass(frozen=True, eq=False)
class LateChecks:
    """:class:`InputChecks` read after the fact (:meth:`InputChecks.read_later`): their values on the host
    once ``ready`` has passed (None: at once), read by any thread."""

    values: torch.Tensor
    ready: torch.cuda.Event | None
    first_failure: Callable[[list[float]], ValueError | None]

    def reached(self) -> bool:
        """Whether the device has reached the copy (:meth:`error` would not wait)."""
        return self.ready is None or self.ready.query()

    def error(self) -> ValueError | None:
        """The first failing check's error, or None (waits for the device to reach the copy, not longer)."""
        if self.ready is not None:
            self.ready.synchronize()
        return self.first_failure(self.values.tolist())


SURFACE_SHAPES = {"mask": "(H, W)", "normal": "(H, W, 3)", "depth": "(H, W)", "flow": "(H, W, 2)"}


def check_surface(frame: FrameBuffers) -> dict[str, int]:
    """The host's checks of a frame's first-hit buffers and flow (present where needed, shapes,
    floating point; not their values); returns H and W.

    Raises:
        ValueError: mask, normal or depth missing; a buffer misshapen or not floating point.
    """
    for name in LOWRES_BUFFERS:
        if getattr(frame, name) is None:
            raise ValueError(f"the frame lacks its {name} buffer")
    dims = check_shape(frame.mask, "(H, W)", "mask", "surface_tensors")
    for name, spec in SURFACE_SHAPES.items():
        if getattr(frame, name) is not None:
            check_buffer(getattr(frame, name), spec, name, "surface_tensors", dims)
    return dims


def check_buffer(t: torch.Tensor, spec: str, name: str, where: str, dims: dict[str, int]) -> None:
    """A frame's buffer ``name`` has the shape ``spec`` (with ``dims``) and a floating-point dtype."""
    check_shape(t, spec, name, where, dims)
    if not t.is_floating_point():
        raise ValueError(f"{name} must be floating point, got {t.dtype}")


def surface_tensors(frame: FrameBuffers, checks: InputChecks | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """A frame's first-hit surface as a network reads it: ``(surface, flow or None)``, the surface's
    channels in the order :data:`isosr_render.conventions.LOWRES_CHANNELS` (low-res for the
    `Upscaler`, full-res for the `Reconstructor`).

    Args:
        frame: mask, normal, depth, and flow except on a sequence's first frame.
        checks: where to queue the finiteness checks; None checks at once (a host sync).

    Raises:
        ValueError: a buffer is missing, has the wrong shape or dtype, or (without ``checks``) is not finite.

    Shape:
        Returns surface (1, 5, H, W) and flow (1, 2, H, W), float32.
    """
    check_surface(frame)
    now = checks is None
    checks = InputChecks() if now else checks
    for name in SURFACE_SHAPES:
        if getattr(frame, name) is not None:
            checks.add_finite(name, getattr(frame, name))
    if now:
        checks.raise_first()
    surface = frame.channels_first(LOWRES_BUFFERS)[None]
    flow = None if frame.flow is None else frame.flow.permute(2, 0, 1)[None]
    return surface.float(), None if flow is None else flow.float()


def buffer_stack(output: torch.Tensor) -> torch.Tensor:
    """A network's output stack as the buffers' stack: mask, normals unit where covered and 0
    elsewhere, depth where covered and 0 elsewhere, AO clamped to [0, 1].

    Shape:
        output: (B, 6, H, W). Returns (B, 6, H, W), float32, channels as ``HIGHRES_CHANNELS``.
    """
    out = output.float()
    mask = out[:, MASK]
    covered = mask > 0
    normal = F.normalize(out[:, NORMAL], dim=1, eps=1e-6) * covered
    return torch.cat([mask, normal, out[:, DEPTH] * covered, out[:, AO].clamp(0, 1)], dim=1)


def stack_buffers(stack: torch.Tensor, color: torch.Tensor | None = None) -> FrameBuffers:
    """The first frame of a buffers' stack (:func:`buffer_stack`) as buffers (views), with ``color``."""
    s = stack[0]
    channels = s.unbind(0)  # one call for the single channels
    return FrameBuffers(mask=channels[MASK.start], normal=s[NORMAL].permute(1, 2, 0), depth=channels[DEPTH.start],
                        ao=channels[AO.start], color=color)


def own_streams(batch: torch.Tensor) -> list[torch.Tensor]:
    """Each stream's (1, ...) slice of a batch's tensor (B, ...), of its own memory: a copy, since a view
    would hold the whole batch's for as long as its stream keeps it; one stream's tensor as it is."""
    return [batch] if batch.shape[0] == 1 else [part.clone() for part in batch.split(1)]


def output_buffers(output: torch.Tensor) -> FrameBuffers:
    """A network's output stack (1, 6, H, W) as buffers; normals unit where covered, 0 elsewhere."""
    return stack_buffers(buffer_stack(output))


def ao_in_range(ao: torch.Tensor, batched: bool = False) -> torch.Tensor:
    """Whether every AO value is within [0, 1] (NaN is not), a 0-d bool tensor, or with ``batched``
    one per frame of the first dimension, (B,) (no host sync)."""
    inside = (ao >= 0) & (ao <= 1)
    return inside.reshape(ao.shape[0], -1).all(1) if batched else inside.all()


def frame_flags(mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, ao: torch.Tensor | None,
                flow: torch.Tensor | None) -> torch.Tensor:
    """The :data:`FRAME_FLAGS` of a frame's buffers, (6,) float32 (no host sync)."""
    return frames_flags(*(None if t is None else t[None] for t in (mask, normal, depth, ao, flow)))[0]


def frames_flags(mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, ao: torch.Tensor | None,
                 flow: torch.Tensor | None) -> torch.Tensor:
    """The :data:`FRAME_FLAGS` of each of a batch's frames (no host sync).

    Shape:
        mask, depth, ao: (B, H, W). normal: (B, H, W, 3). flow: (B, H, W, 2). Returns (B, 6) float32.
    """
    b = depth.shape[0]
    zero = depth.new_zeros(b, dtype=torch.bool)
    bad = [zero if t is None else ~torch.isfinite(t.reshape(b, -1)).all(1) for t in (mask, normal, depth, flow)]
    ao_bad = zero if ao is None else ~ao_in_range(ao, batched=True)
    deepest = torch.where(torch.isfinite(depth), depth.abs(), 0.0).reshape(b, -1).amax(1)
    return torch.stack([*(x.float() for x in bad), ao_bad.float(), deepest.float()], dim=1)


class RecurrentNetwork:
    """A loaded frame network and one stream's recurrent state (its previous output).

    Every stream (viewer, sequence) needs its own instance: :meth:`own` makes one that shares
    the loaded weights. Subclasses say how a frame runs (`Upscaler.upscale`,
    `Reconstructor.reconstruct`).

    Args:
        model: a model folder (``config.json`` + ``model.safetensors``).
        device: where to run.
        precision: ``"fp32"``, ``"bf16"`` or ``"fp16"`` (autocast).
        channels_last: keep activations in NHWC (faster convolutions on GPUs).
        fast_layers: the layers rewritten for speed (:mod:`isosr_net.fastpath`); the same function.
        autotune: let cuDNN time its algorithms per input shape (``torch.backends.cudnn.benchmark``,
            a process-wide switch that this turns on).
    """

    # How much larger the output is than the input (1: full resolution in and out).
    upscale_factor: int = 1

    def __init__(self, model: str | Path, device: str = "cpu", precision: str = "fp32", channels_last: bool = False,
                 fast_layers: bool = False, autotune: bool = False):
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
        self.device = torch.device(device)
        self.model = Path(model)
        self.net, self.config = load_pretrained(model, self.device)
        if fast_layers:
            self.net = fast_network(self.net)
        if channels_last:
            self.net = self.net.to(memory_format=torch.channels_last)
        if autotune:
            torch.backends.cudnn.benchmark = True
        self.precision = precision
        self.previous: torch.Tensor | None = None

    def reset(self) -> None:
        """Forget the previous output (a camera cut, a new sequence)."""
        self.previous = None

    def state_bytes(self) -> int:
        """Bytes the stream's recurrent state holds."""
        return 0 if self.previous is None else self.previous.nbytes

    def drop_graphs(self) -> None:
        """Free the CUDA graphs this stream captured and the memory they hold; its weights and compiled code
        stay, and frames after capture anew. A network that captures no graphs of its own has none."""

    def own(self) -> "RecurrentNetwork":
        """A stream's own copy: shares the loaded weights (and compiled code), starts without state."""
        twin = object.__new__(type(self))
        twin.__dict__.update(self.__dict__)
        twin.reset()
        return twin

    def check_precision(self, surface: torch.Tensor, checks: InputChecks) -> None:
        """Queue what the precision needs of the inputs: fp16 takes depths up to :data:`FP16_MAX_DEPTH`."""
        if self.precision == "fp16":
            checks.add_deepest(surface[:, DEPTH].abs().amax())

    def carries(self, height: int, width: int, flow: bool) -> bool:
        """Whether a frame of input size ``height x width`` warps the previous output: not after a cut
        (no flow) or a change of frame size (nothing of this size to warp). The one place the
        recurrent reset is decided."""
        f = self.upscale_factor
        return flow and self.previous is not None and tuple(self.previous.shape[-2:]) == (height * f, width * f)

    def carried(self, surface: torch.Tensor, flow: torch.Tensor | None) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """``(previous, flow)`` to carry into this frame: both None unless it :meth:`carries`."""
        if not self.carries(*surface.shape[-2:], flow is not None):
            return None, None
        return self.previous, flow.to(self.device)
