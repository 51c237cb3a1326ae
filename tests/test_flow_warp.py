"""Flow warping (isosr_net.flow_warp) against the convention of isosr_render.conventions.

Backward flow: ``flow[p] = p_prev - p_cur`` (x right, y down, pixels), and the warped previous
frame is ``previous(p + flow[p])``. If the content moved by (dx, dy) pixels from the previous
frame to the current one (``cur = roll(prev, (dy, dx))``), then ``p_prev = p_cur - (dx, dy)``,
so the flow is the constant ``(-dx, -dy)``.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from isosr_net.flow_warp import upscale_flow, warp_by_flow


def constant_flow(b: int, h: int, w: int, fx: float, fy: float, dtype=torch.float32) -> torch.Tensor:
    flow = torch.empty(b, 2, h, w, dtype=dtype)
    flow[:, 0], flow[:, 1] = fx, fy
    return flow


@pytest.mark.parametrize("dy, dx", [(0, 0), (1, 0), (0, 1), (2, -3), (-1, 2)])
def test_integer_shift_reproduces_the_previous_frame_in_the_interior(dy, dx):
    g = torch.Generator().manual_seed(0)
    prev = torch.rand(2, 3, 12, 15, generator=g)
    cur_positions = torch.roll(prev, shifts=(dy, dx), dims=(-2, -1))  # content moved by (dx, dy)
    # Backward flow of that motion: where each current pixel was in the previous frame.
    warped = warp_by_flow(prev, constant_flow(2, 12, 15, -dx, -dy))
    m = 3  # rows / cols touched by the wrap-around of roll (or by zeros from outside)
    torch.testing.assert_close(warped[..., m:-m, m:-m], cur_positions[..., m:-m, m:-m], atol=1e-5, rtol=0)


def test_flow_sign_follows_the_documented_convention():
    # One bright pixel at (row 4, col 5) in the previous frame; the flow of every current pixel
    # points +2 in x and +1 in y: out[p] = prev[p + (2, 1)], so the bright pixel appears at (3, 3).
    prev = torch.zeros(1, 1, 9, 9)
    prev[0, 0, 4, 5] = 1.0
    out = warp_by_flow(prev, constant_flow(1, 9, 9, 2.0, 1.0))
    assert out[0, 0, 3, 3] == pytest.approx(1.0, abs=1e-6)
    assert float(out.sum()) == pytest.approx(1.0, abs=1e-5)


def test_half_pixel_shift_is_the_average_of_neighbours():
    g = torch.Generator().manual_seed(1)
    img = torch.rand(1, 2, 7, 9, generator=g, dtype=torch.float64)
    out_x = warp_by_flow(img, constant_flow(1, 7, 9, 0.5, 0.0, torch.float64))
    torch.testing.assert_close(out_x[..., :-1], 0.5 * (img[..., :-1] + img[..., 1:]))
    out_y = warp_by_flow(img, constant_flow(1, 7, 9, 0.0, -0.5, torch.float64))
    torch.testing.assert_close(out_y[..., 1:, :], 0.5 * (img[..., 1:, :] + img[..., :-1, :]))
    out_xy = warp_by_flow(img, constant_flow(1, 7, 9, 0.5, 0.5, torch.float64))
    expected = 0.25 * (img[..., :-1, :-1] + img[..., :-1, 1:] + img[..., 1:, :-1] + img[..., 1:, 1:])
    torch.testing.assert_close(out_xy[..., :-1, :-1], expected)


def test_zeros_come_in_from_outside():
    img = torch.ones(1, 1, 6, 8)
    out = warp_by_flow(img, constant_flow(1, 6, 8, 3.0, 0.0))  # reads 3 columns to the right
    expected = torch.ones(1, 1, 6, 8)
    expected[..., 5:] = 0
    torch.testing.assert_close(out, expected, atol=1e-5, rtol=0)
    out = warp_by_flow(img, constant_flow(1, 6, 8, 0.0, -2.0))  # reads 2 rows up
    expected = torch.ones(1, 1, 6, 8)
    expected[..., :2, :] = 0
    torch.testing.assert_close(out, expected, atol=1e-5, rtol=0)
    # Half a pixel past the border: half of the sample reads the zero padding.
    out = warp_by_flow(img, constant_flow(1, 6, 8, -0.5, 0.0))
    torch.testing.assert_close(out[..., 0], torch.full((1, 1, 6), 0.5), atol=1e-5, rtol=0)
    assert (warp_by_flow(img, constant_flow(1, 6, 8, 100.0, -50.0)) == 0).all()


def test_zero_flow_is_the_identity():
    img = torch.rand(3, 4, 5, 7, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(warp_by_flow(img, torch.zeros(3, 2, 5, 7)), img, atol=1e-6, rtol=0)


def test_per_pixel_flow_is_applied_per_pixel():
    img = torch.arange(20.0).view(1, 1, 4, 5)
    flow = torch.zeros(1, 2, 4, 5)
    flow[0, 0, 1, 2] = 2.0  # only this pixel looks two to the right
    flow[0, 1, 3, 0] = -3.0  # and this one three rows up
    out = warp_by_flow(img, flow)
    expected = img.clone()
    expected[0, 0, 1, 2] = img[0, 0, 1, 4]
    expected[0, 0, 3, 0] = img[0, 0, 0, 0]
    torch.testing.assert_close(out, expected)


@pytest.mark.parametrize("factor", [2, 4])
def test_upscale_flow_scales_lengths_by_the_factor(factor):
    flow = constant_flow(2, 5, 6, 1.5, -0.75)
    up = upscale_flow(flow, factor)
    assert up.shape == (2, 2, 5 * factor, 6 * factor)
    torch.testing.assert_close(up[:, 0], torch.full((2, 5 * factor, 6 * factor), 1.5 * factor))
    torch.testing.assert_close(up[:, 1], torch.full((2, 5 * factor, 6 * factor), -0.75 * factor))


def test_upscaled_flow_warps_the_highres_image_like_the_lowres_one():
    # A 1-pixel low-res shift is a `factor`-pixel high-res shift.
    factor = 4
    g = torch.Generator().manual_seed(3)
    hi = torch.rand(1, 1, 32, 32, generator=g)
    flow_hi = upscale_flow(constant_flow(1, 8, 8, 1.0, -1.0), factor)
    warped = warp_by_flow(hi, flow_hi)
    torch.testing.assert_close(warped[..., 4:, :-4], hi[..., :-4, 4:], atol=1e-5, rtol=0)


def test_shape_errors_name_the_shapes():
    img = torch.zeros(2, 3, 4, 5)
    with pytest.raises(ValueError, match=r"warp_by_flow: image must be \(B, C, H, W\), got \(3, 4, 5\)"):
        warp_by_flow(img[0], torch.zeros(2, 2, 4, 5))
    with pytest.raises(ValueError, match=r"flow must be \(B, 2, H, W\) with B=2, H=4, W=5, got \(2, 3, 4, 5\)"):
        warp_by_flow(img, torch.zeros(2, 3, 4, 5))
    with pytest.raises(ValueError, match=r"got \(1, 2, 4, 5\)"):
        warp_by_flow(img, torch.zeros(1, 2, 4, 5))
    with pytest.raises(ValueError, match=r"got \(2, 2, 4, 6\)"):
        warp_by_flow(img, torch.zeros(2, 2, 4, 6))
    with pytest.raises(ValueError, match=r"upscale_flow: flow must be \(B, 2, H, W\), got \(2, 3, 4, 5\)"):
        upscale_flow(torch.zeros(2, 3, 4, 5), 2)
    with pytest.raises(ValueError, match=r"got \(2, 4, 5\)"):
        upscale_flow(torch.zeros(2, 4, 5), 2)


def test_gradient_reaches_the_image_and_the_flow():
    g = torch.Generator().manual_seed(4)
    img = torch.rand(1, 2, 5, 6, generator=g, dtype=torch.float64, requires_grad=True)
    # Fractional flow away from integer positions: bilinear sampling is smooth there.
    flow = (0.3 + 0.4 * torch.rand(1, 2, 5, 6, generator=g, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda i: warp_by_flow(i, flow.detach()), (img,))
    assert torch.autograd.gradcheck(lambda f: warp_by_flow(img.detach(), f), (flow,))


def test_warp_keeps_the_image_dtype_with_a_float32_flow():
    img = torch.rand(1, 1, 4, 4, dtype=torch.float64)
    assert warp_by_flow(img, torch.zeros(1, 2, 4, 4)).dtype == torch.float64


def test_matches_grid_sample_reference_for_random_flow():
    # Independent reference: bilinear sampling written out with explicit neighbour weights.
    g = torch.Generator().manual_seed(5)
    img = torch.rand(1, 1, 6, 7, generator=g, dtype=torch.float64)
    flow = 3 * torch.randn(1, 2, 6, 7, generator=g, dtype=torch.float64)
    out = warp_by_flow(img, flow)
    padded = F.pad(img, (1, 1, 1, 1))  # zeros outside
    h, w = 6, 7
    for r in range(h):
        for c in range(w):
            x, y = c + float(flow[0, 0, r, c]), r + float(flow[0, 1, r, c])  # pixel index space
            x0, y0 = math.floor(x), math.floor(y)
            ax, ay = x - x0, y - y0

            def at(yy, xx):
                if -1 <= yy <= h and -1 <= xx <= w:
                    return float(padded[0, 0, yy + 1, xx + 1])
                return 0.0

            ref = ((1 - ay) * ((1 - ax) * at(y0, x0) + ax * at(y0, x0 + 1))
                   + ay * ((1 - ax) * at(y0 + 1, x0) + ax * at(y0 + 1, x0 + 1)))
            assert float(out[0, 0, r, c]) == pytest.approx(ref, abs=1e-9)
