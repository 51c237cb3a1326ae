"""A low-res ray cast upscaled by the trained network, which infers AO."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from isosr_net.methods.base import FrameMethod, FrameRunner, LowResOptions, ModelOptions, register_runner
from isosr_net.model import read_config
from isosr_net.reconnet import RayLimits
from isosr_net.timing import StageTimer
from isosr_net.upscaler import DEFAULT_MODEL, Upscaler
from isosr_render import FrameBuffers
from isosr_render.conventions import LOWRES_BUFFERS


@dataclass(frozen=True)
class NetworkOptions(ModelOptions, LowResOptions):
    """An upscaling network's factor (its model's upscale) and model."""

    model_name: str = Upscaler.display_name

    @classmethod
    def of(cls, **knobs) -> NetworkOptions:
        """As :meth:`MethodOptions.of`, the factor the model's own unless given."""
        knobs.setdefault("factor", read_config(knobs.get("model") or DEFAULT_MODEL)["model"]["upscale"])
        return super().of(**knobs)


@register_runner("network")
class NetworkRunner(FrameRunner):
    """A low-res ray cast upscaled by the trained network (which infers AO), shaded."""

    label = "network upscaling"
    warm_up = True
    serve_bench_ao = (0,)
    plot_color = "C3"

    low_res = True
    recurrent = True
    network_class = Upscaler
    default_model = DEFAULT_MODEL
    options_type = NetworkOptions

    @classmethod
    def bench_methods(cls, smoke: bool, device: str, model: tuple[str, Path] | None = None) -> list[FrameMethod]:
        """An upscaling model (an SRNet's folder) at its factor, in fp32, bf16, fp16 on CUDA (elsewhere fp32)."""
        if model is None:
            return []
        name, folder = model
        config = read_config(folder)["model"]
        if config.get("type", "SRNet") != "SRNet":
            return []
        precisions = ("fp32", "bf16", "fp16") if device.startswith("cuda") else ("fp32",)
        return [FrameMethod.of(cls.kind, factor=config["upscale"], precision=p,
                               model=None if folder == cls.default_model else str(folder), model_name=name)
                for p in precisions]

    @classmethod
    def candidates(cls, device: str, precision: str | None = None, limits: RayLimits | None = None,
                   x2_model: str | os.PathLike | None = None) -> tuple[tuple[float, FrameMethod], ...]:
        """The shipped x4 network, in ``precision`` (None: bf16 on CUDA, fp32 elsewhere)."""
        return (3, FrameMethod.of(cls.kind, factor=4, precision=precision or (
            "bf16" if device.startswith("cuda") else "fp32"))),

    @classmethod
    def describe(cls, m: FrameMethod) -> str:
        return f"x{m.factor} {m.options.model_name} {m.options.precision}"

    def outputs(self) -> tuple[str, ...]:
        return LOWRES_BUFFERS

    @classmethod
    def makes(cls, m: FrameMethod) -> tuple[str, ...]:
        return LOWRES_BUFFERS + ("ao",)

    def finish(self, rendered: FrameBuffers, timer: StageTimer) -> FrameBuffers:
        with timer("network"):
            high = self.net.upscale(rendered)
        return self.colored(high, timer, rendered)
