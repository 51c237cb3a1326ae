"""The reconstruction's ray history: each frame's few AO rays accumulated along the flow.

AO depends on the surface point alone, not on the view: the rays cast at a point in earlier
frames count as much as this frame's. So before the network (:class:`~isosr_net.reconstructor.
Reconstructor`), each covered pixel's AO becomes the mean of its own rays and of those its
history holds (SVGF's temporal accumulation, Schied et al. 2017, without its filter), and the
network is told, per pixel, how many rays that mean stands for: it then denoises 16 rays' AO
where a frame cast 1. One kernel per frame (Warp, on every device):

- A covered pixel ``p`` looks up the history at ``p + flow[p]`` (bilinear: the 4 texels around
  it). A texel counts only if it lies in the image, holds rays, its surface point lies within
  ``point_tolerance`` of the pixel's depth (plus the distance the pixel's neighbors predict
  over the texel's offset) from the pixel's point, and its view-space normal is within
  ``normal_cosine`` of the pixel's. The counted texels' bilinear weights, renormalized, average
  the history's AO and ray count; where they sum to less than ``MIN_HISTORY_WEIGHT`` the pixel is
  disoccluded and its history restarts.
- With ``c`` the history's count, capped at ``cap - rays``, and this frame's ``rays`` rays of
  mean ``a``: AO ``(c h + rays a) / (c + rays)``, count ``c + rays``. ``cap`` is the most rays
  the network takes at the frame's rays per pixel, so the blend becomes an exponential one
  (weight ``rays / cap``) once the history is full.

A pixel is covered where any of its rays per pixel hit (mask > 0: a silhouette's partly covered
pixels hold rays too). Surface points are world-space, so the test needs no camera (and a CUDA
graph can replay it). Uncovered pixels get AO 0 and count 0. A frame without flow, or a history of another size,
starts every pixel anew. float32.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import warp as wp

from isosr_render.buffers import FrameBuffers
from isosr_render.shapes import check_shape
from isosr_net.filters.atrous import check_buffers, on_device, reprojected_texel
from isosr_net.inference import own_streams
from isosr_net.reconnet import RayLimits

wp.set_module_options({"enable_backward": False})

# Reprojected texels whose bilinear weights sum to less than this are a disocclusion (as SVGF's).
MIN_HISTORY_WEIGHT = 0.01
MIN_HISTORY_WEIGHT_WP = wp.constant(MIN_HISTORY_WEIGHT)


@dataclass(frozen=True)
class RayHistoryConfig:
    """The reprojection's tests.

    Attributes:
        point_tolerance: a history texel's surface point may lie this fraction of the pixel's
            depth from the pixel's (plus the neighbors' spacing over the texel's offset).
        normal_cosine: its view-space normal must have at least this cosine with the pixel's
            (the threshold must allow one frame's camera turn).
    """

    point_tolerance: float = 0.01
    normal_cosine: float = 0.9

    def __post_init__(self):
        if not (isinstance(self.point_tolerance, (int, float)) and 0 <= self.point_tolerance < float("inf")):
            raise ValueError(f"RayHistoryConfig.point_tolerance must be a finite number >= 0, "
                             f"got {self.point_tolerance!r}")
        if not (isinstance(self.normal_cosine, (int, float)) and -1 <= self.normal_cosine <= 1):
            raise ValueError(f"RayHistoryConfig.normal_cosine must be in [-1, 1], got {self.normal_cosine!r}")


@dataclass
class RayHistory:
    """One stream's accumulated rays after a frame (float32, on the frame's device; 0 where not covered).

    Shape:
        ao, count: (B, H, W). point: (B, H, W, 3), world space. normal: (B, H, W, 3), view space, unit.
    """

    ao: torch.Tensor
    count: torch.Tensor
    point: torch.Tensor
    normal: torch.Tensor

    @staticmethod
    def layout(b: int, h: int, w: int) -> tuple[tuple[int, ...], ...]:
        """The shapes of ``ao``, ``count``, ``point``, ``normal`` for a frame of this size."""
        return (b, h, w), (b, h, w), (b, h, w, 3), (b, h, w, 3)

    @classmethod
    def empty(cls, b: int, h: int, w: int, device: torch.device) -> RayHistory:
        """Uninitialized tensors for a frame of this size (a kernel's outputs)."""
        return cls(*(torch.empty(shape, dtype=torch.float32, device=device) for shape in cls.layout(b, h, w)))

    def tensors(self) -> tuple[torch.Tensor, ...]:
        """``ao``, ``count``, ``point``, ``normal``."""
        return self.ao, self.count, self.point, self.normal

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.count.shape)

    @property
    def nbytes(self) -> int:
        return sum(t.nbytes for t in self.tensors())

    def streams(self) -> list[RayHistory]:
        """Each stream's history, (1, H, W), of its own memory (:func:`~isosr_net.inference.own_streams`)."""
        return [RayHistory(*parts) for parts in zip(*(own_streams(t) for t in self.tensors()))]

    def copy_(self, other: RayHistory) -> RayHistory:
        """Copy ``other``'s values into these tensors (a graph's state); returns self."""
        for mine, theirs in zip(self.tensors(), other.tensors()):
            mine.copy_(theirs)
        return self


@wp.struct
class Previous:
    """The history as the kernel reads it."""

    ao: wp.array3d(dtype=float)
    count: wp.array3d(dtype=float)
    point: wp.array3d(dtype=wp.vec3)
    normal: wp.array3d(dtype=wp.vec3)
    present: int  # 0: none (every pixel starts anew); the arrays are 1-element stand-ins


@wp.func
def point_at(position: wp.array4d(dtype=float), b: int, y: int, x: int) -> wp.vec3:
    return wp.vec3(position[b, 0, y, x], position[b, 1, y, x], position[b, 2, y, x])


@wp.func
def point_step(mask: wp.array4d(dtype=float), position: wp.array4d(dtype=float), b: int, y: int, x: int, dy: int,
               dx: int) -> float:
    """The distance between a covered pixel's point and its neighbor's along (dy, dx): the smaller
    of the covered forward and backward ones, so that silhouettes do not count; 0 without either."""
    h = mask.shape[2]
    w = mask.shape[3]
    p = point_at(position, b, y, x)
    step = float(-1.0)
    for sign in range(2):
        qy = y + wp.where(sign == 0, dy, -dy)
        qx = x + wp.where(sign == 0, dx, -dx)
        if qy >= 0 and qy < h and qx >= 0 and qx < w:  # bounds first: Warp evaluates every operand
            if mask[b, 0, qy, qx] > 0.0:
                d = wp.length(point_at(position, b, qy, qx) - p)
                if step < 0.0 or d < step:
                    step = d
    return wp.max(step, 0.0)


@wp.func
def texel_weight(prev: Previous, b: int, qy: int, qx: int, w: float, p: wp.vec3, n: wp.vec3, tolerance: float,
                 normal_cosine: float) -> float:
    """The bilinear weight ``w`` of history texel (qy, qx), or 0 where it does not count (module docstring)."""
    if w <= 0.0 or qy < 0 or qy >= prev.count.shape[1] or qx < 0 or qx >= prev.count.shape[2]:
        return 0.0
    if not (prev.count[b, qy, qx] > 0.0):
        return 0.0
    d = wp.length(prev.point[b, qy, qx] - p)
    if not (d <= tolerance):  # NaN fails too
        return 0.0
    if not (wp.dot(prev.normal[b, qy, qx], n) >= normal_cosine):
        return 0.0
    return w


@wp.kernel
def accumulate_kernel(mask: wp.array4d(dtype=float), normal: wp.array4d(dtype=float),
                      depth: wp.array4d(dtype=float), position: wp.array4d(dtype=float),
                      ao: wp.array4d(dtype=float), flow: wp.array4d(dtype=float), prev: Previous, rays: float,
                      cap: float, point_tolerance: float, normal_cosine: float, ao_out: wp.array3d(dtype=float),
                      count_out: wp.array3d(dtype=float), point_out: wp.array3d(dtype=wp.vec3),
                      normal_out: wp.array3d(dtype=wp.vec3), share_out: wp.array3d(dtype=float), row0: int):
    """The module docstring's blend for the pixels of rows ``row0`` on; where ``share_out`` is
    given (not None), each covered pixel's count over ``cap`` there too."""
    b, row, x = wp.tid()
    y = row0 + row
    if not (mask[b, 0, y, x] > 0.0):
        ao_out[b, y, x] = 0.0
        count_out[b, y, x] = 0.0
        point_out[b, y, x] = wp.vec3(0.0)
        normal_out[b, y, x] = wp.vec3(0.0)
        return
    p = point_at(position, b, y, x)
    n = wp.vec3(normal[b, 0, y, x], normal[b, 1, y, x], normal[b, 2, y, x])
    n = n / wp.max(wp.length(n), 1.0e-12)
    total = float(0.0)
    history_ao = float(0.0)
    history_count = float(0.0)
    if prev.present != 0:
        u = flow[b, 0, y, x]
        v = flow[b, 1, y, x]
        if wp.isfinite(u) and wp.isfinite(v):  # a NaN or Inf flow finds no history
            x0, y0, fx, fy = reprojected_texel(x, y, u, v, prev.count.shape[1], prev.count.shape[2])
            gx = point_step(mask, position, b, y, x, 0, 1)
            gy = point_step(mask, position, b, y, x, 1, 0)
            base = point_tolerance * wp.abs(depth[b, 0, y, x])
            for j in range(2):
                for i in range(2):
                    qx = x0 + i
                    qy = y0 + j
                    w = wp.where(i == 1, fx, 1.0 - fx) * wp.where(j == 1, fy, 1.0 - fy)
                    allowance = gx * wp.abs(float(i) - fx) + gy * wp.abs(float(j) - fy)  # |q - (p + flow)|
                    w = texel_weight(prev, b, qy, qx, w, p, n, base + allowance, normal_cosine)
                    if w > 0.0:
                        total = total + w
                        history_ao = history_ao + w * prev.ao[b, qy, qx]
                        history_count = history_count + w * prev.count[b, qy, qx]
    c = float(0.0)
    if total >= MIN_HISTORY_WEIGHT_WP:
        c = wp.clamp(history_count / total, 0.0, wp.max(cap - rays, 0.0))
        history_ao = wp.clamp(history_ao / total, 0.0, 1.0)
    a = ao[b, 0, y, x]
    ao_out[b, y, x] = (c * history_ao + rays * a) / (c + rays)
    count_out[b, y, x] = c + rays
    if share_out.shape[0] > 0:
        share_out[b, y, x] = (c + rays) / cap
    point_out[b, y, x] = p
    normal_out[b, y, x] = n


def accumulate_rays(ao: torch.Tensor, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor,
                    position: torch.Tensor, flow: torch.Tensor | None, history: RayHistory | None, rays: int, cap: int,
                    config: RayHistoryConfig = RayHistoryConfig(), out: RayHistory | None = None,
                    share: torch.Tensor | None = None) -> RayHistory:
    """One frame's rays blended into the history (module docstring), with no host sync.

    Runs on the inputs' device (CPU or CUDA, on torch's current stream), in float32. The inputs'
    values are not checked here (the reconstruction's frame checks do that; a NaN point or flow
    finds no history).

    Args:
        ao: this frame's AO, the mean of ``rays`` rays per pixel.
        mask: coverage; a pixel that any ray per pixel hit (> 0) holds rays.
        normal: view-space normals (normalized here).
        depth: view-space depth, world units.
        position: world-space hit points.
        flow: backward flow to the previous frame, pixels (conventions); None: no previous frame.
        history: the previous frame's (None, or another size: none).
        rays: the rays behind each pixel's ``ao`` (AO rays per hit times rays per pixel), >= 1.
        cap: the most rays a pixel's mean stands for, >= ``rays``.
        config: the reprojection's tests.
        out: where to write the new history (None: new tensors); not ``history`` (a pixel reads
            its neighbours' history).
        share: where given, each covered pixel's new count over ``cap`` is written there (float32,
            any strides: a plane of the network's sampling input); uncovered pixels are left.

    Returns:
        The new history (``out`` where given): its ``ao`` is the accumulated AO, its ``count`` the
        rays behind it.

    Raises:
        ValueError: wrong shapes, dtypes or devices, counts out of range, or ``out`` misshapen,
            elsewhere, or ``history`` itself.

    Shape:
        ao, mask, depth: (B, 1, H, W). normal, position: (B, 3, H, W). flow: (B, 2, H, W).
        share: (B, H, W).
    """
    b, h, w = _check(ao, mask, normal, depth, position, flow, rays, cap)
    if share is not None:
        check_shape(share, f"({b}, {h}, {w})", "share", "accumulate_rays")
        if share.dtype != torch.float32 or share.device != ao.device:
            raise ValueError(f"accumulate_rays: share must be float32 on {ao.device}, got {share.dtype} on "
                             f"{share.device}")
    out = RayHistory.empty(b, h, w, ao.device) if out is None else _check_out(out, history, (b, h, w), ao.device)
    continued = flow is not None and history is not None and history.shape == (b, h, w)
    wp.init()  # a no-op after the first call
    sources = [wp.from_torch(t.float()) for t in (mask, normal, depth, position, ao, flow if continued else depth)]
    with on_device(ao.device) as launch:
        launch(accumulate_kernel, (b, h, w),
               [*sources, _previous(history if continued else None, ao.device), float(rays), float(cap),
                float(config.point_tolerance), float(config.normal_cosine), wp.from_torch(out.ao),
                wp.from_torch(out.count), wp.from_torch(out.point, dtype=wp.vec3),
                wp.from_torch(out.normal, dtype=wp.vec3), None if share is None else wp.from_torch(share)])
    return out


def accumulate_frames(frames: Sequence[FrameBuffers], history: RayHistory | None, rays: int, cap: int,
                      config: RayHistoryConfig = RayHistoryConfig(), out: RayHistory | None = None,
                      share: torch.Tensor | None = None) -> RayHistory:
    """:func:`accumulate_rays` on the buffers of one frame of each of several streams (one size, one
    launch; one frame's buffers are viewed, several stacked): mask, normal, depth, position, ao, and
    flow (None on the first: frames without a previous one); ``history`` their histories in their
    order (:func:`joined_histories`); into ``out`` (and ``share``) where given.

    Shape:
        frames' buffers: (H, W), normal, position (H, W, 3), flow (H, W, 2). Returns (B, H, W) tensors.
    """
    def stacked(name: str) -> torch.Tensor:  # (B, C, H, W)
        planes = [getattr(f, name) for f in frames]
        batch = planes[0][None] if len(planes) == 1 else torch.stack(planes)
        return (batch[..., None] if batch.dim() == 3 else batch).permute(0, 3, 1, 2)  # a plane (H, W) as (H, W, 1)
    flow = None if frames[0].flow is None else stacked("flow")
    return accumulate_rays(stacked("ao"), stacked("mask"), stacked("normal"), stacked("depth"), stacked("position"),
                           flow, history, rays, cap, config, out, share)


def histories_join(histories: Sequence[RayHistory | None]) -> bool:
    """Whether streams' histories make one for :func:`accumulate_frames`: none has one, or all have one of
    one size (else each stream accumulates alone)."""
    present = [h is not None for h in histories]
    return not any(present) or (all(present) and len({h.shape[1:] for h in histories}) == 1)


def joined_histories(histories: Sequence[RayHistory | None]) -> RayHistory | None:
    """Several streams' histories as one (B, H, W) history for :func:`accumulate_frames` (one stream's
    as it is): None where none has one. ValueError where they do not join (:func:`histories_join`).
    """
    if not histories_join(histories):
        raise ValueError("joined_histories: the streams' histories are of different sizes, or some have none")
    if histories[0] is None:
        return None
    if len(histories) == 1:
        return histories[0]
    return RayHistory(*(torch.cat(parts) for parts in zip(*(h.tensors() for h in histories))))


def network_inputs(frames: Sequence[FrameBuffers], history: RayHistory | None, ao_rays: int, spp: int,
                   limits: RayLimits, out: RayHistory | None = None) -> tuple[torch.Tensor, torch.Tensor, RayHistory]:
    """What a reconstruction network of ``limits`` reads of frames (one of each stream, one size: see
    :func:`accumulate_frames`) whose ``ao_rays`` AO rays (at ``spp`` rays per pixel) join ``history``:
    ``(ao, sampling, new history)``, with no host sync; the new history written into ``out`` where given.
    The sampling's AO plane counts, per pixel, the rays behind the mean; uncovered pixels hold
    none and read as the frame's own rays, the value training gave them (a 0 there cost 0.3-0.8 dB
    at 16 AO rays, spp 4).

    Shape:
        Returns ao (B, H, W), sampling (B, 2, H, W).
    """
    # A frame's own rays' share where uncovered (the constant sampling), the history's where covered.
    sampling = limits.channels(ao_rays, spp, frames[0].mask[None, None].expand(len(frames), 1, *frames[0].mask.shape))
    history = accumulate_frames(frames, history, ao_rays * spp, limits.rays(spp), out=out, share=sampling[:, 0])
    return history.ao, sampling, history


def history_traffic(h: int, w: int) -> int:
    """The bytes a frame's accumulation moves at least (each buffer read or written once, float32):
    mask, normal, depth, position, AO, flow and the history in; the history out."""
    history = 4 * (1 + 1 + 3 + 3)
    return h * w * (4 * (1 + 3 + 1 + 3 + 1 + 2) + 2 * history)


def _check(ao: torch.Tensor, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, position: torch.Tensor,
           flow: torch.Tensor | None, rays: int, cap: int) -> tuple[int, int, int]:
    """ValueError unless the buffers are (B, C, H, W) floating point on one device (their values
    unchecked: no host sync) and 1 <= rays <= cap; returns B, H, W."""
    guides = {"mask": (mask, 1), "normal": (normal, 3), "depth": (depth, 1), "position": (position, 3)}
    check_buffers("accumulate_rays", ao, guides | ({} if flow is None else {"flow": (flow, 2)}), finite=False)
    if isinstance(rays, bool) or not isinstance(rays, int) or isinstance(cap, bool) or not isinstance(cap, int) \
            or not 1 <= rays <= cap:
        raise ValueError(f"accumulate_rays: need integers 1 <= rays <= cap, got rays={rays!r}, cap={cap!r}")
    b, _, h, w = ao.shape
    return b, h, w


def _check_out(out: RayHistory, history: RayHistory | None, shape: tuple[int, int, int],
               device: torch.device) -> RayHistory:
    """``out`` if it can take a new history of ``shape`` on ``device`` beside ``history``, else ValueError."""
    if any(t.shape != s or t.device != device or t.dtype != torch.float32 or not t.is_contiguous()
           for t, s in zip(out.tensors(), RayHistory.layout(*shape))):
        raise ValueError(f"accumulate_rays: out must be contiguous float32 tensors of a {shape} history on "
                         f"{device}, got shape {out.shape} on {out.ao.device}")
    if history is not None and any(t.data_ptr() == h.data_ptr() for t in out.tensors() for h in history.tensors()):
        raise ValueError("accumulate_rays: out must not be the history it continues (a pixel reads its neighbours')")
    return out


def _previous(history: RayHistory | None, device: torch.device) -> Previous:
    """The kernel's view of the history (1-element stand-ins and ``present`` 0 without one)."""
    prev = Previous()
    prev.present = int(history is not None)
    if history is None:
        history = RayHistory(*(torch.zeros(s, dtype=torch.float32, device=device)
                               for s in ((1, 1, 1), (1, 1, 1), (1, 1, 1, 3), (1, 1, 1, 3))))
    prev.ao = wp.from_torch(history.ao)
    prev.count = wp.from_torch(history.count)
    prev.point = wp.from_torch(history.point, dtype=wp.vec3)
    prev.normal = wp.from_torch(history.normal, dtype=wp.vec3)
    return prev
