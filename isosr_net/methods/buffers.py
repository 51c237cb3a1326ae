"""The low-res ray cast itself, unshaded, for a client that upscales."""

from __future__ import annotations

from dataclasses import dataclass

from isosr_net.methods.base import FrameMethod, FrameRunner, LowResOptions, register_runner
from isosr_net.timing import StageTimer
from isosr_render import FrameBuffers
from isosr_render.conventions import LOWRES_BUFFERS


@dataclass(frozen=True)
class BuffersOptions(LowResOptions):
    """The low-res render's factor."""


@register_runner("buffers")
class BuffersRunner(FrameRunner):
    """The low-res ray cast itself (mask, normal, depth; flow after a previous camera), unshaded:
    for a client that upscales and shades them."""

    label = "low-res buffers (the client upscales)"
    serve_bench_ao = (0,)

    low_res = True
    recurrent = True
    shaded = False
    options_type = BuffersOptions

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"x{m.factor} buffers"

    def outputs(self) -> tuple[str, ...]:
        return LOWRES_BUFFERS

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return LOWRES_BUFFERS + ("flow",)

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        return rendered
