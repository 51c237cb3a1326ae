"""The SVGF temporal filter (Warp kernels): each step against a float64 numpy reference written from
the module docstring, convergence on a still view, disocclusions, and the hard cases, on
``ISOSR_TEST_DEVICE``."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import DEVICE
from isosr_render import Camera, Renderer, RenderRequest, open_volume, orbit, resolve_iso
from isosr_net.filters.atrous import B3, TINY, VARIANCE_EPS, ATrousConfig, atrous_passes, prepare_guides
from isosr_net.methods import FrameMethod, make_runner
from isosr_net.filters.svgf import MAX_HISTORY, MIN_HISTORY_WEIGHT, SVGFConfig, SVGFHistory, svgf_filter

# The kernels compute in float32; the reference in float64.
TOLERANCE = 1e-4
CAMERA = Camera(eye=(0.0, 0.0, 2.0))  # looks down -z: a point at world z has depth 2 - z


# ---- the float64 reference, one function per kernel (one image, numpy (H, W[, C]) arrays) ----

def ref_depth_step(z, cov, y, x, dy, dx):
    h, w = z.shape
    fy, fx, by, bx = y + dy, x + dx, y - dy, x - dx
    fwd = z[fy, fx] - z[y, x] if fy < h and fx < w and cov[fy, fx] else None
    bwd = z[y, x] - z[by, bx] if by >= 0 and bx >= 0 and cov[by, bx] else None
    if fwd is not None and (bwd is None or abs(fwd) <= abs(bwd)):
        return fwd
    return 0.0 if bwd is None else bwd


def ref_prepare(ao, mask, normal, depth):
    """Clamped AO, unit normals, relative depth and its gradient, coverage."""
    cov = mask > 0.5
    deepest = np.abs(depth[cov]).max() if cov.any() else 0.0
    z = np.where(cov, depth / (deepest or 1.0), 0.0)
    n = np.where(cov[..., None], normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-6), 0.0)
    h, w = ao.shape
    slope = np.zeros((h, w, 2))
    for y in range(h):
        for x in range(w):
            if cov[y, x]:
                slope[y, x] = ref_depth_step(z, cov, y, x, 0, 1), ref_depth_step(z, cov, y, x, 1, 0)
    return np.where(cov, np.clip(ao, 0, 1), 0.0), n, z, slope, cov


def ref_edge(n, z, slope, y, x, qy, qx, a: ATrousConfig):
    cosine = float(n[y, x] @ n[qy, qx])
    log_n = 0.0 if a.sigma_normal == 0 else -math.inf if cosine <= 0 else a.sigma_normal * math.log(min(cosine, 1.0))
    tolerance = a.sigma_depth * abs(slope[y, x, 0] * (qx - x) + slope[y, x, 1] * (qy - y)) \
        + a.depth_tolerance * abs(z[y, x]) + TINY
    return log_n - abs(z[y, x] - z[qy, qx]) / tolerance


def ref_temporal(ao, mask, normal, depth, position, flow, prev, config: SVGFConfig, a: ATrousConfig):
    """Step 2: AO, moments, length, surface, variance; ``prev``: (history arrays, camera) or None."""
    value, n, z, slope, cov = ref_prepare(ao, mask, normal, depth)
    h, w = ao.shape
    out = dict(ao=np.zeros((h, w)), moments=np.zeros((h, w, 2)), length=np.zeros((h, w)),
               surface=np.zeros((h, w, 4)), variance=np.zeros((h, w)))
    for y in range(h):
        for x in range(w):
            if not cov[y, x]:
                continue
            total, acc, mom, length = 0.0, 0.0, np.zeros(2), 0.0
            if prev is not None:
                hist, camera = prev
                back = camera.basis()[2]
                expected = -float((position[y, x] - np.array(camera.eye)) @ back)
                if expected > 0:
                    sx, sy = x + flow[y, x, 0], y + flow[y, x, 1]
                    x0, y0 = math.floor(sx), math.floor(sy)
                    gx, gy = ref_depth_step(depth, cov, y, x, 0, 1), ref_depth_step(depth, cov, y, x, 1, 0)
                    for qy in (y0, y0 + 1):
                        for qx in (x0, x0 + 1):
                            wt = (1 - abs(qx - sx)) * (1 - abs(qy - sy))
                            if wt <= 0 or not (0 <= qy < h and 0 <= qx < w) or hist["length"][qy, qx] <= 0:
                                continue
                            s = hist["surface"][qy, qx]
                            allowance = abs(gx * (qx - sx)) + abs(gy * (qy - sy))
                            if abs(s[3] - expected) > config.depth_tolerance * expected + allowance:
                                continue
                            if n[y, x] @ s[:3] < config.normal_cosine:
                                continue
                            total += wt
                            acc += wt * hist["ao"][qy, qx]
                            mom = mom + wt * hist["moments"][qy, qx]
                            length += wt * hist["length"][qy, qx]
            if total >= MIN_HISTORY_WEIGHT:
                acc, mom, length = acc / total, mom / total, min(length / total + 1, MAX_HISTORY)
            else:
                acc, mom, length = 0.0, np.zeros(2), 1.0
            sample = value[y, x]
            acc += max(config.alpha, 1 / length) * (sample - acc)
            mom = mom + max(config.moments_alpha, 1 / length) * (np.array([sample, sample ** 2]) - mom)
            variance = max(mom[1] - mom[0] ** 2, 0.0)
            if length < config.min_history:
                weights, m1, m2 = 0.0, 0.0, 0.0
                for qy in range(max(0, y - config.radius), min(h, y + config.radius + 1)):
                    for qx in range(max(0, x - config.radius), min(w, x + config.radius + 1)):
                        if cov[qy, qx]:
                            wq = math.exp(ref_edge(n, z, slope, y, x, qy, qx, a))
                            weights, m1, m2 = weights + wq, m1 + wq * value[qy, qx], m2 + wq * value[qy, qx] ** 2
                variance = 0.0 if weights <= 0 else max(m2 / weights - (m1 / weights) ** 2, 0.0)
                variance *= config.min_history / length
            out["ao"][y, x], out["moments"][y, x], out["length"][y, x] = acc, mom, length
            out["surface"][y, x] = [*n[y, x], depth[y, x]]
            out["variance"][y, x] = variance
    return out


def ref_guided_passes(value, variance, n, z, slope, cov, a: ATrousConfig, sigma_variance: float):
    """Step 3: the variance-guided passes; the last output and the first."""
    h, w = value.shape
    outputs = []
    for i in range(a.iterations):
        hole = 2 ** i
        new, new_var = np.zeros((h, w)), np.zeros((h, w))
        for y in range(h):
            for x in range(w):
                if not cov[y, x]:
                    continue
                k = [(B3[dy + 2] * B3[dx + 2], variance[y + dy, x + dx]) for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                     if 0 <= y + dy < h and 0 <= x + dx < w and cov[y + dy, x + dx]]
                blurred = sum(kk * v for kk, v in k) / sum(kk for kk, _ in k)
                inverse = 1 / (sigma_variance * math.sqrt(blurred) + VARIANCE_EPS)
                total = weight = total_var = 0.0
                for ta in range(5):
                    for tc in range(5):
                        qy, qx = y + (ta - 2) * hole, x + (tc - 2) * hole
                        if 0 <= qy < h and 0 <= qx < w and cov[qy, qx]:
                            e = ref_edge(n, z, slope, y, x, qy, qx, a) - abs(value[y, x] - value[qy, qx]) * inverse
                            wq = B3[ta] * B3[tc] * math.exp(e)
                            total, weight = total + wq * value[qy, qx], weight + wq
                            total_var += wq * wq * variance[qy, qx]
                if weight > 0:
                    new[y, x], new_var[y, x] = total / weight, total_var / weight ** 2
        value, variance = new, new_var
        outputs.append(value)
    return outputs[-1], outputs[0]


# ---- inputs ----

def plane_scene(h=6, w=7, seed=0, slope=(0.01, 0.005), shift=(0.0, 0.0)):
    """A slanted plane facing the camera (depth 2 plus ``slope`` per pixel in x and y, moved by ``shift``
    pixels: pixel ``p`` shows what ``p + shift`` showed unmoved), noisy AO, a few uncovered pixels;
    positions consistent with the depths (world z = 2 - depth), so that the depth test passes where
    the flow follows the motion."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    xs, ys = xs + shift[0], ys + shift[1]
    depth = 2.0 + slope[0] * xs + slope[1] * ys
    normal = np.stack([np.full((h, w), 0.05), np.zeros((h, w)), np.ones((h, w))], -1)
    normal = normal + 0.02 * rng.normal(size=(h, w, 3))
    position = np.stack([0.01 * xs, -0.01 * ys, 2.0 - depth], -1)
    mask = (rng.random((h, w)) > 0.1).astype(np.float64)
    return dict(ao=rng.random((h, w)), mask=mask, normal=normal, depth=depth, position=position)


def run(frame, flow=None, camera=None, history=None, config=SVGFConfig(), atrous=ATrousConfig()):
    """svgf_filter on DEVICE from float32 versions of the numpy frame."""
    t = {k: torch.from_numpy(v).float().to(DEVICE) for k, v in frame.items()}
    chw = lambda x: x.permute(2, 0, 1)[None]  # noqa: E731
    flow = None if flow is None else chw(torch.from_numpy(flow).float().to(DEVICE))
    out, hist = svgf_filter(t["ao"][None, None], t["mask"][None, None], chw(t["normal"]), t["depth"][None, None],
                            chw(t["position"]), flow, camera, history, config, atrous)
    assert out.dtype == torch.float32 and torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    return out[0, 0].cpu().double().numpy(), hist


def numpy_history(hist: SVGFHistory) -> dict:
    return {k: getattr(hist, k)[0].cpu().double().numpy() for k in ("ao", "moments", "length", "surface")}


def float32(frame):
    return {k: v.astype(np.float32).astype(np.float64) for k, v in frame.items()}


def reference(frame, flow, prev, config=SVGFConfig(), atrous=ATrousConfig()):
    """The whole filter in float64: temporal step, then the guided passes over the blended AO."""
    t = ref_temporal(frame["ao"], frame["mask"], frame["normal"], frame["depth"], frame["position"], flow, prev,
                     config, atrous)
    _, n, z, slope, cov = ref_prepare(frame["ao"], frame["mask"], frame["normal"], frame["depth"])
    last, first = ref_guided_passes(t["ao"], t["variance"], n, z, slope, cov, atrous, config.sigma_variance)
    return last, {**t, "ao": first}


def assert_close(got, want, what):
    assert np.abs(got - want).max() <= TOLERANCE, (what, float(np.abs(got - want).max()))


# ---- the kernels against the reference ----

@pytest.mark.parametrize("atrous", [ATrousConfig(iterations=2), ATrousConfig(iterations=3, sigma_normal=16.0)])
def test_a_sequence_matches_the_float64_reference_step_by_step(atrous):
    """Three frames of a steep plane moving by a subpixel flow (the texels' depths differ from the
    expected one by more than the tolerance: the gradient's allowance decides), a column whose flow
    leaves the image, uncovered pixels."""
    config = SVGFConfig(radius=2, min_history=3)
    motion = (0.3, -0.2)  # the previous position lies 0.3 px right, 0.2 px up
    frames = [float32(plane_scene(seed=i, slope=(0.1, 0.02), shift=(i * motion[0], i * motion[1])))
              for i in range(3)]
    flow = np.zeros((6, 7, 2))
    flow[..., 0], flow[..., 1] = motion
    flow[:, 0, 0] = 9.0  # the first column came from outside the image
    got_hist, want_hist = None, None
    for i, frame in enumerate(frames):
        prev = None if i == 0 else (want_hist, CAMERA)
        got, got_hist = run(frame, None if i == 0 else flow, None if i == 0 else CAMERA, got_hist, config, atrous)
        want, want_hist = reference(frame, flow, prev, config, atrous)
        assert_close(got, want, f"frame {i} output")
        for name, value in numpy_history(got_hist).items():
            assert_close(value, want_hist[name], f"frame {i} history {name}")
    assert (want_hist["length"][:, 1:][frames[2]["mask"][:, 1:] > 0.5] > 1).any()  # some history carried
    assert want_hist["length"][:, 0][frames[2]["mask"][:, 0] > 0.5].max() == 1  # the outside column restarted


def test_the_guided_passes_match_the_reference_and_filter_the_variance():
    frame = float32(plane_scene(7, 9, seed=4))
    t = {k: torch.from_numpy(v).float().to(DEVICE) for k, v in frame.items()}
    guides = prepare_guides(t["ao"][None, None], t["mask"][None, None], t["normal"].permute(2, 0, 1)[None],
                            t["depth"][None, None])
    rng = np.random.default_rng(1)
    variance = (rng.random((7, 9)) * 0.1).astype(np.float32).astype(np.float64)
    variance[0, 0] = 0.0  # zero variance: the value weight keeps only equal values
    config = ATrousConfig(iterations=3)
    last, first = atrous_passes(guides.value, guides, config, torch.from_numpy(variance).float()[None].to(DEVICE), 4.0)
    _, n, z, slope, cov = ref_prepare(frame["ao"], frame["mask"], frame["normal"], frame["depth"])
    value = guides.value[0].cpu().double().numpy()
    want_last, want_first = ref_guided_passes(value, variance, n, z, slope, cov, config, 4.0)
    assert_close(last[0].cpu().double().numpy(), want_last, "last pass")
    assert_close(first[0].cpu().double().numpy(), want_first, "first pass")
    assert np.abs(want_last - value)[cov].max() > 0.01  # it did filter


# ---- behavior ----

def test_a_still_view_converges_toward_the_many_ray_ao():
    """One AO ray a frame (a new set each frame) on a still view: the error against 256 rays drops."""
    volume = open_volume("proc:cloud:7@32")
    renderer, iso = Renderer(volume, DEVICE), resolve_iso("proc:cloud", volume)
    size, camera, radius = (48, 32), orbit(30.0, 20.0, 1.3), 0.15
    truth = renderer.render(camera, RenderRequest(*size, iso, ("mask", "ao"), ao_samples=256, ao_radius=radius,
                                                  seed=99))
    runner = make_runner(FrameMethod.of("svgf", ao_rays=1), renderer, iso, *size, ao_radius=radius)
    errors = []
    for i in range(10):
        f = runner.frame(camera, None if i == 0 else camera).buffers
        covered = (f.mask > 0.5) & (truth.mask > 0.5)
        errors.append(float((f.ao - truth.ao)[covered].square().mean().sqrt()))
    assert runner.history.length.max() == 10
    assert errors[-1] < 0.4 * errors[0] and errors[4] < errors[0], errors
    raw = [renderer.render(camera, RenderRequest(*size, iso, ("ao",), ao_samples=1, ao_radius=radius, seed=s)).ao
           for s in range(10, 14)]
    raw_error = sum(float((r - truth.ao)[covered].square().mean().sqrt()) for r in raw) / len(raw)
    assert errors[-1] < 0.4 * raw_error, (errors, raw_error)


def test_a_disocclusion_or_a_turned_normal_restarts_the_history():
    frame = plane_scene(8, 8, seed=2)
    frame["mask"][:] = 1.0
    flow = np.zeros((8, 8, 2))
    _, hist = run(frame)
    for _ in range(2):
        _, hist = run(frame, flow, CAMERA, hist)
    assert (hist.length == 3).all()
    moved = {k: v.copy() for k, v in frame.items()}
    moved["depth"][:3] -= 0.5  # an object in front: nearer by 0.5
    moved["position"][:3, :, 2] += 0.5
    moved["normal"][5:, :] = [1.0, 0.0, 0.2]  # a surface turned by 80 degrees at the old depth
    _, hist = run(moved, flow, CAMERA, hist)
    length = hist.length[0].cpu()
    assert (length[:3] == 1).all() and (length[5:] == 1).all() and (length[3:5] == 4).all()


@pytest.mark.parametrize("case", ["background", "empty_with_history", "grazing", "plateau", "outside", "far_flow"])
def test_hard_cases_stay_finite(case):
    frame = plane_scene(8, 9, seed=3)
    flow = np.zeros((8, 9, 2))
    _, hist = run(frame)
    if case == "background":
        frame = {k: np.zeros_like(v) for k, v in frame.items()}
        out, hist = run(frame)
    elif case == "empty_with_history":
        frame["mask"][:] = 0.0
        out, hist = run(frame, flow, CAMERA, hist)
    elif case == "grazing":  # depth rising steeply along x, normals almost perpendicular to the view
        frame["depth"] = frame["depth"] + 50.0 * np.arange(9)[None, :]
        frame["position"][..., 2] = 2.0 - frame["depth"]
        frame["normal"][:] = [1.0, 0.0, 1e-4]
        out, hist = run(frame, flow, CAMERA, hist)
    elif case == "plateau":  # one constant AO and surface: zero variance everywhere
        frame = {**frame, "ao": np.full((8, 9), 0.6), "depth": np.full((8, 9), 2.0), "mask": np.ones((8, 9)),
                 "normal": np.tile([0.0, 0.0, 1.0], (8, 9, 1)), "position": np.zeros((8, 9, 3))}
        _, hist = run(frame)
        out, hist = run(frame, flow, CAMERA, hist)
        assert np.allclose(out, 0.6, atol=1e-6)
    elif case == "outside":  # every point behind the previous camera: no history to reproject
        out, hist = run(frame, flow, Camera(eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 10.0)), hist)
        assert (hist.length[hist.length > 0] == 1).all()
    else:  # flow far outside the image, beyond an int's range
        flow[..., 0] = -1e30
        flow[..., 1] = 3e12
        out, hist = run(frame, flow, CAMERA, hist)
        assert (hist.length[hist.length > 0] == 1).all()
    for t in (hist.ao, hist.moments, hist.length, hist.surface):
        assert torch.isfinite(t).all()
    if frame["mask"].max() == 0:
        assert out.max() == 0 and hist.length.max() == 0


def test_bad_inputs_and_knobs_are_refused():
    frame = {k: torch.from_numpy(v).float() for k, v in plane_scene().items()}
    args = [frame["ao"][None, None], frame["mask"][None, None], frame["normal"].permute(2, 0, 1)[None],
            frame["depth"][None, None], frame["position"].permute(2, 0, 1)[None]]
    with pytest.raises(ValueError, match="svgf_filter: position must be"):
        svgf_filter(*args[:4], args[4][:, :2], None, None, None)
    with pytest.raises(ValueError, match="svgf_filter: flow holds NaN"):
        svgf_filter(*args, torch.full((1, 2, 6, 7), math.nan), CAMERA, None)
    for kwargs, match in ((dict(alpha=0.0), "alpha"), (dict(radius=9), "radius"), (dict(normal_cosine=2.0), "normal"),
                          (dict(min_history=0), "min_history"), (dict(sigma_variance=math.inf), "sigma_variance")):
        with pytest.raises(ValueError, match=match):
            SVGFConfig(**kwargs)
