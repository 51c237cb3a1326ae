"""The ray history (`isosr_net.ray_history`): each frame's AO rays accumulated along the flow,
against a float64 reference of its rule, and on hard cases (disocclusion, silhouettes, hostile values)."""

from __future__ import annotations

import math

import pytest
import torch

from isosr_net.ray_history import MIN_HISTORY_WEIGHT, RayHistory, RayHistoryConfig, accumulate_rays

H, W = 9, 11


def frame(seed: int = 0, covered: float = 0.8, step: float = 0.01):
    """A random frame: a surface plane z = 0 seen head-on (points spaced ``step`` apart), a random
    mask, AO, a subpixel flow, and a pixel or two that are holes."""
    gen = torch.Generator().manual_seed(seed)
    mask = (torch.rand(1, 1, H, W, generator=gen) < covered).float()
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    position = torch.stack([xs * step, ys * step, torch.zeros_like(xs)])[None]
    normal = torch.zeros(1, 3, H, W)
    normal[:, 2] = 1.0
    depth = torch.full((1, 1, H, W), 2.0)
    ao = torch.rand(1, 1, H, W, generator=gen)
    flow = torch.rand(1, 2, H, W, generator=gen) * 1.6 - 0.8
    return dict(ao=ao, mask=mask, normal=normal, depth=depth, position=position, flow=flow)


def reference(f: dict, history: RayHistory | None, rays: int, cap: int, config=RayHistoryConfig()) -> RayHistory:
    """The module docstring's rule, pixel by pixel in float64."""
    d = {k: v.double()[0] for k, v in f.items()}
    out = RayHistory(*(torch.zeros(s, dtype=torch.float64) for s in ((1, H, W), (1, H, W), (1, H, W, 3), (1, H, W, 3))))
    for y in range(H):
        for x in range(W):
            if not d["mask"][0, y, x] > 0:
                continue
            p, n = d["position"][:, y, x], torch.nn.functional.normalize(d["normal"][:, y, x], dim=0)
            total = h_ao = h_count = 0.0
            if history is not None:
                sx, sy = x + float(d["flow"][0, y, x]), y + float(d["flow"][1, y, x])
                steps = [point_step(d, y, x, 0, 1), point_step(d, y, x, 1, 0)]
                for qy in (math.floor(sy), math.floor(sy) + 1):
                    for qx in (math.floor(sx), math.floor(sx) + 1):
                        w = (1 - abs(qx - sx)) * (1 - abs(qy - sy))
                        if w <= 0 or not (0 <= qy < H and 0 <= qx < W) or history.count[0, qy, qx] <= 0:
                            continue
                        tolerance = (config.point_tolerance * float(d["depth"][0, y, x])
                                     + steps[0] * abs(qx - sx) + steps[1] * abs(qy - sy))
                        if float((history.point[0, qy, qx].double() - p).norm()) > tolerance:
                            continue
                        if float(history.normal[0, qy, qx].double() @ n) < config.normal_cosine:
                            continue
                        total += w
                        h_ao += w * float(history.ao[0, qy, qx])
                        h_count += w * float(history.count[0, qy, qx])
            c = min(max(h_count / total, 0.0), cap - rays) if total >= MIN_HISTORY_WEIGHT else 0.0
            h_ao = min(max(h_ao / total, 0.0), 1.0) if total >= MIN_HISTORY_WEIGHT else 0.0
            out.ao[0, y, x] = (c * h_ao + rays * float(d["ao"][0, y, x])) / (c + rays)
            out.count[0, y, x] = c + rays
            out.point[0, y, x], out.normal[0, y, x] = p, n
    return out


def point_step(d: dict, y: int, x: int, dy: int, dx: int) -> float:
    steps = [float((d["position"][:, qy, qx] - d["position"][:, y, x]).norm())
             for qy, qx in ((y + dy, x + dx), (y - dy, x - dx))
             if 0 <= qy < H and 0 <= qx < W and d["mask"][0, qy, qx] > 0]
    return min(steps, default=0.0)


def assert_history_close(a: RayHistory, b: RayHistory, atol: float = 1e-5) -> None:
    for name in ("ao", "count", "point", "normal"):
        torch.testing.assert_close(getattr(a, name).double(), getattr(b, name), rtol=0, atol=atol, msg=name)


@pytest.mark.parametrize("rays, cap", [(1, 16), (4, 64), (16, 16)])
def test_three_frames_match_the_float64_rule(rays, cap):
    history = reference_history = None
    for seed in range(3):
        f = frame(seed)
        history = accumulate_rays(**f, history=history, rays=rays, cap=cap)
        reference_history = reference(f, reference_history, rays, cap)
        assert_history_close(history, reference_history)
    assert history.count.max() <= cap and (history.ao >= 0).all() and (history.ao <= 1).all()
    assert rays == cap or (history.count > rays).any()  # some pixels found their history


def test_a_still_view_averages_its_frames_until_the_cap_then_blends_them_in():
    f = frame(covered=1.0)
    f["flow"].zero_()
    samples, history = [], None
    for t in range(20):
        f["ao"] = torch.rand(1, 1, H, W, generator=torch.Generator().manual_seed(100 + t))
        samples.append(f["ao"][0])
        history = accumulate_rays(**f, history=history, rays=1, cap=16)
        if t < 16:  # a plain mean of every frame so far
            torch.testing.assert_close(history.ao, torch.stack(samples).mean(0), rtol=0, atol=1e-5)
    assert (history.count == 16).all()
    blended = torch.stack(samples[:16]).mean(0)
    for s in samples[16:]:
        blended = blended + (s - blended) / 16
    torch.testing.assert_close(history.ao, blended, rtol=0, atol=1e-5)


def test_without_flow_or_history_or_at_another_size_every_pixel_starts_anew():
    f = frame()
    history = accumulate_rays(**f, history=None, rays=2, cap=32)
    again = accumulate_rays(**{**f, "flow": None}, history=history, rays=2, cap=32)
    covered = f["mask"][:, 0] > 0
    assert (again.count[covered] == 2).all() and (again.count[~covered] == 0).all()
    torch.testing.assert_close(again.ao, f["ao"][:, 0] * covered, rtol=0, atol=0)
    small = {k: v[..., :5, :7] for k, v in f.items()}
    assert (accumulate_rays(**small, history=history, rays=2, cap=32).count <= 2).all()


def test_a_disoccluded_pixel_and_a_turned_surface_restart_and_uncovered_pixels_hold_nothing():
    f = frame(covered=1.0)
    f["flow"].zero_()
    history = accumulate_rays(**f, history=None, rays=1, cap=16)
    moved = {**f, "position": f["position"].clone(), "normal": f["normal"].clone(), "mask": f["mask"].clone()}
    moved["position"][:, 2, 2, 3] = 0.5  # another surface, far in front of the one seen there before
    moved["normal"][0, :, 5, 6] = torch.tensor([1.0, 0.0, 0.0])  # turned by 90 degrees
    moved["mask"][:, :, 7, 8] = 0.0
    out = accumulate_rays(**moved, history=history, rays=1, cap=16)
    assert out.count[0, 2, 3] == 1 and out.count[0, 5, 6] == 1 and out.count[0, 4, 4] == 2
    assert out.count[0, 7, 8] == 0 and out.ao[0, 7, 8] == 0 and (out.point[0, 7, 8] == 0).all()


@pytest.mark.parametrize("name, value", [("flow", float("nan")), ("flow", float("inf")), ("flow", -1e30),
                                         ("position", float("nan")), ("normal", 0.0), ("depth", float("inf"))])
def test_hostile_values_find_no_history_and_stay_finite_and_bounded(name, value):
    f = frame(covered=1.0)
    history = accumulate_rays(**f, history=None, rays=1, cap=16)
    hostile = {k: v.clone() for k, v in f.items()}
    hostile[name][:] = value
    out = accumulate_rays(**hostile, history=history, rays=1, cap=16)
    assert torch.isfinite(out.ao).all() and torch.isfinite(out.count).all()
    assert (out.ao >= 0).all() and (out.ao <= 1).all() and (out.count >= 0).all() and (out.count <= 16).all()
    if name in ("flow", "position") and value != -1e30 or name == "normal":
        assert (out.count <= 1).all()  # nothing from the history
    if name == "depth":  # an infinite tolerance: every texel's point is near enough
        assert (out.count == 2).all()


@pytest.mark.parametrize("change, match", [
    (dict(normal=torch.zeros(1, 2, H, W)), r"normal must be \(1, 3, 9, 11\)"),
    (dict(ao=torch.zeros(1, 2, H, W)), r"accumulate_rays: ao must be \(B, 1, H, W\), got \(1, 2, 9, 11\)"),
    (dict(ao=torch.zeros(1, 1, 0, W)), r"accumulate_rays: the images are empty"),
    (dict(mask=torch.zeros(1, 1, H, W, dtype=torch.int32)), "mask must be floating point"),
    (dict(rays=0), "need integers 1 <= rays <= cap"),
    (dict(rays=4, cap=2), "need integers 1 <= rays <= cap"),
    (dict(rays=True), "need integers 1 <= rays <= cap"),
    (dict(share=torch.zeros(1, H, W - 1)), r"accumulate_rays: share must be \(1, 9, 11\), got \(1, 9, 10\)"),
    (dict(share=torch.zeros(1, H, W, dtype=torch.float64)), "share must be float32 on cpu, got torch.float64"),
])
def test_bad_arguments_are_refused_with_what_is_wrong(change, match):
    args = {**frame(), "history": None, "rays": 1, "cap": 16, **change}
    with pytest.raises(ValueError, match=match):
        accumulate_rays(**args)


def test_a_history_written_into_given_tensors_in_turn_equals_new_ones():
    """Two histories used in turn (as a CUDA graph's frames use them): each frame writes the one it
    does not read, with the values a new history gets, and holds its tensors."""
    pair = (RayHistory.empty(1, H, W, torch.device("cpu")), RayHistory.empty(1, H, W, torch.device("cpu")))
    history = fresh = None
    for seed in range(4):
        f = frame(seed)
        target = pair[seed % 2]
        written = accumulate_rays(**f, history=history, rays=2, cap=32, out=target)
        fresh = accumulate_rays(**f, history=fresh, rays=2, cap=32)
        assert written is target
        for name in ("ao", "count", "point", "normal"):
            assert torch.equal(getattr(written, name), getattr(fresh, name)), name
        history = written


def test_the_share_is_each_covered_pixels_count_over_the_cap_in_a_plane_of_any_strides():
    """The network's sampling plane (a strided view) gets count / cap where covered; other pixels,
    and the plane beside it, keep what they held."""
    f, sampling = frame(seed=3), torch.full((1, 2, H, W), -1.0)
    history = accumulate_rays(**frame(seed=2), history=None, rays=2, cap=32)
    new = accumulate_rays(**f, history=history, rays=2, cap=32, share=sampling[:, 0])
    covered = f["mask"][:, 0] > 0
    assert covered.any() and (~covered).any()
    torch.testing.assert_close(sampling[:, 0][covered], new.count[covered] / 32, rtol=0, atol=0)
    assert (sampling[:, 0][~covered] == -1).all() and (sampling[:, 1] == -1).all()


@pytest.mark.parametrize("out, match", [
    ("history", "out must not be the history it continues"),
    (RayHistory.empty(1, H, W - 1, torch.device("cpu")), r"out must be contiguous float32 tensors of a \(1, 9, 11\)"),
    (RayHistory(*(t.double() for t in RayHistory.empty(1, H, W, torch.device("cpu")).__dict__.values())),
     "out must be contiguous float32"),
])
def test_an_out_history_that_cannot_take_the_frame_is_refused(out, match):
    f = frame()
    history = accumulate_rays(**f, history=None, rays=1, cap=16)
    with pytest.raises(ValueError, match=match):
        accumulate_rays(**f, history=history, rays=1, cap=16, out=history if out == "history" else out)


def test_the_config_refuses_bad_tests():
    with pytest.raises(ValueError, match="point_tolerance"):
        RayHistoryConfig(point_tolerance=float("nan"))
    with pytest.raises(ValueError, match="normal_cosine"):
        RayHistoryConfig(normal_cosine=2.0)
