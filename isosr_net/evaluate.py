"""Evaluation: `isosr eval` scores the network against nearest, bilinear and bicubic upscaling.

Per volume of a datagen folder's split: masked PSNR and SSIM of the shaded color with AO, PSNR
of normals and of AO, mask IoU (`isosr_net.metrics`), and temporal instability: the mean
change between consecutive shaded outputs after warping the earlier one by the flow (lower
is steadier). Sequences run through the network recurrently, as a viewer would.

With ``oracles``, two references that show where the error lives: ``oracle: bilinear + true
AO`` (classic upscaling that somehow knew the ground-truth occlusion) and ``oracle: true
geometry, no AO`` (exact high-res mask, normals and depth, shaded without occlusion).

:func:`compare_upscalers` does the same comparison live, on a rendered camera path (`isosr demo`).
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import torch

from isosr_render import Camera, Renderer, RenderRequest
from isosr_render.conventions import AO, HIGHRES_BUFFERS, LOWRES_BUFFERS, MASK
from isosr_render.sequence import sequence_requests
from isosr_net.datagen import SequenceDataset
from isosr_net.flow_warp import upscale_flow, warp_by_flow
from isosr_net.metrics import frame_scores, temporal_instability, upscale_baseline
from isosr_net.model import Unrolled
from isosr_net.upscaler import Upscaler
from isosr_net.inference import surface_tensors

BASELINES = ("nearest", "bilinear", "bicubic")
ORACLES = ("oracle: bilinear + true AO", "oracle: true geometry, no AO")
SCORES = ("color_psnr", "color_ssim", "normal_psnr", "ao_psnr", "mask_iou", "temporal")
# The methods of compare_upscalers, in the order it reports them.
COMPARED = BASELINES + ("network",)


@torch.no_grad()
def evaluate(net: torch.nn.Module, data: str, split: str = "val", device: str = "cpu",
             precision: torch.dtype = torch.float32, batch_size: int = 4, oracles: bool = False) -> list[dict]:
    """Rows ``{volume, method, <SCORES>}``, the mean over each volume's sequences and frames
    (methods: the network, :data:`BASELINES`, and with ``oracles`` the :data:`ORACLES`)."""
    dataset = SequenceDataset(data, split)
    factor = net.config.upscale
    unrolled = Unrolled(net).to(device).eval()
    sums: dict[tuple[str, str], dict[str, float]] = defaultdict(lambda: defaultdict(float))
    counts: dict[tuple[str, str], dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for start in range(0, len(dataset), batch_size):
        batch = dataset.batch(slice(start, start + batch_size)).to(device)
        volumes = dataset.volumes[start:start + len(batch)]
        lowres, flow, target = batch.lowres, batch.flow, batch.highres
        b, t = lowres.shape[:2]
        with torch.autocast(torch.device(device).type, dtype=precision, enabled=precision != torch.float32):
            network = unrolled(lowres, flow)[0].float()
        outputs = {"network": network}
        for mode in BASELINES:
            up = upscale_baseline(lowres.flatten(0, 1), factor, mode)
            outputs[mode] = up.unflatten(0, (b, t))
        if oracles:  # the true AO where the ground truth covers, none elsewhere
            true_ao = torch.where(target[:, :, MASK] > 0, target[:, :, AO], torch.ones_like(target[:, :, AO]))
            outputs[ORACLES[0]] = torch.cat([outputs["bilinear"][:, :, :AO.start], true_ao], dim=2)
            outputs[ORACLES[1]] = torch.cat([target[:, :, :AO.start], torch.ones_like(target[:, :, AO])], dim=2)
        flows_hr = upscale_flow(flow.flatten(0, 1), factor).unflatten(0, (b, t)).transpose(0, 1)
        for method, out in outputs.items():
            scores = frame_scores(out.flatten(0, 1), target.flatten(0, 1))
            scores = {k: v.unflatten(0, (b, t)) for k, v in scores.items()}
            scores["temporal"] = temporal_instability(out.transpose(0, 1), flows_hr, warp_by_flow)[:, None]
            for i, volume in enumerate(volumes):
                for name, values in scores.items():
                    finite = values[i][torch.isfinite(values[i])]
                    sums[volume, method][name] += float(finite.sum())
                    counts[volume, method][name] += finite.numel()
    rows = []
    for (volume, method), total in sorted(sums.items()):
        row = {"volume": volume, "method": method}
        row.update({k: total[k] / counts[volume, method][k] if counts[volume, method][k] else math.nan
                    for k in SCORES})
        rows.append(row)
    return rows


def gains(rows: list[dict]) -> dict[str, dict[str, float]]:
    """Per volume, the network's color PSNR gain (dB) over bilinear and over the best baseline."""
    by_volume = defaultdict(dict)
    for r in rows:
        by_volume[r["volume"]][r["method"]] = r["color_psnr"]
    return {v: {"vs_bilinear": m["network"] - m["bilinear"], "vs_best_baseline": m["network"] - max(m[b] for b in BASELINES)}
            for v, m in by_volume.items()}


@dataclass
class FrameComparison:
    """One frame of :func:`compare_upscalers`.

    Attributes:
        outputs: each method's high-res buffers (:data:`COMPARED` order), on the CPU.
        target: the ground-truth render (mask, normal, depth, AO), on the CPU.
        color_psnr: each method's color PSNR against ``target``, dB.
        ms: wall time of each method and of the ``"low-res render"`` and ``"ground truth render"``.

    Shape:
        outputs' values, target: (1, 6, H, W).
    """

    outputs: dict[str, torch.Tensor]
    target: torch.Tensor
    color_psnr: dict[str, float]
    ms: dict[str, float]


def _timed(fn: Callable[[], object], device: torch.device) -> tuple[object, float]:
    """``fn()`` and its wall time in ms, the device synchronized after it."""
    start = time.perf_counter()
    result = fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return result, (time.perf_counter() - start) * 1e3


@torch.no_grad()
def compare_upscalers(renderer: Renderer, cameras: Sequence[Camera], iso: float, size: tuple[int, int],
                      upscaler: Upscaler, ao_samples: int = 64, spp: int = 2) -> Iterator[FrameComparison]:
    """Per frame of a camera path: the network against nearest, bilinear and bicubic upscaling.

    Renders the low-res sequence (mask, normal, depth, and flow from the frame before; none on
    the first frame), upscales it with each baseline and with ``upscaler`` (recurrently: its
    state carries over, and is reset on the first frame), renders the ground truth at the
    upscaler's factor with AO, and scores each method's shaded color.

    Args:
        renderer: the volume's renderer.
        cameras: the path.
        iso: normalized iso-value.
        size: low-res ``(width, height)``.
        upscaler: the network; its factor sets the ground truth's size.
        ao_samples, spp: the ground truth's AO rays per hit and rays per pixel.
    """
    s = upscaler.upscale_factor
    width, height = size
    device = upscaler.device
    upscaler.reset()
    truth = RenderRequest(width * s, height * s, iso, HIGHRES_BUFFERS, spp=spp, ao_samples=ao_samples)
    for camera, request in sequence_requests(cameras, width, height, iso, LOWRES_BUFFERS + ("flow",)):
        ms = {}
        low, ms["low-res render"] = _timed(lambda: renderer.render(camera, request), device)
        high, ms["ground truth render"] = _timed(lambda: renderer.render(camera, truth), device)
        target = high.channels_first(HIGHRES_BUFFERS)[None].cpu()
        lowres, flow = surface_tensors(low)
        outputs = {}
        for mode in BASELINES:
            outputs[mode], ms[mode] = _timed(lambda: upscale_baseline(lowres, s, mode), device)
        outputs["network"], ms["network"] = _timed(lambda: upscaler.step(lowres, flow), device)
        outputs = {method: out.float().cpu() for method, out in outputs.items()}
        psnr = {method: float(frame_scores(out, target)["color_psnr"][0]) for method, out in outputs.items()}
        yield FrameComparison(outputs, target, psnr, ms)
