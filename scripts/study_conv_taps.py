"""Study: ReconNet's 3x3 convolution as 9 dots of K = CI (the shipped kernel) or 3 dots of K = 4 CI.

NHWC stores a pixel's three horizontal taps (x-1, x, x+1) next to each other, so a row of taps is
one load of 3 CI contiguous values a pixel (4 CI: K a power of 2, the fourth pixel's weights zero):
3 dots a tile instead of 9. Times both (autotuned over the same configs) on the network's shapes
and checks them against torch's conv2d.

    python scripts/study_conv_taps.py --out results.json      # CUDA; torch + Triton only
"""

from __future__ import annotations

import argparse
import json
import os

import torch
import torch.nn.functional as F
import triton
import triton.language as tl
import triton.testing

INTERPRET = os.environ.get("TRITON_INTERPRET") == "1"
CONFIGS = [triton.Config({"BLOCK_M": m}, num_warps=w) for m, w in ((64, 4), (32, 2), (128, 4), (128, 8), (256, 8))]


def tuned(kernel):
    if INTERPRET:
        return kernel
    return triton.autotune(CONFIGS, key=["ho", "wo", "STRIDE", "CI", "CO"])(kernel)


@triton.jit
def taps9(x_ptr, w_ptr, b_ptr, out_ptr, hi, wi, ho, wo, STRIDE: tl.constexpr, CI: tl.constexpr, CO: tl.constexpr,
          BLOCK_M: tl.constexpr):
    b = tl.program_id(1).to(tl.int64)
    offs = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    valid = offs < ho * wo
    y, x = offs // wo, offs % wo
    ci, co = tl.arange(0, CI), tl.arange(0, CO)
    acc = tl.zeros((BLOCK_M, CO), dtype=tl.float32)
    for tap in tl.static_range(9):
        yy = y * STRIDE + (tap // 3 - 1)
        xx = x * STRIDE + (tap % 3 - 1)
        inside = valid & (yy >= 0) & (yy < hi) & (xx >= 0) & (xx < wi)
        a = tl.load(x_ptr + b * hi * wi * CI + ((yy * wi + xx) * CI)[:, None] + ci[None, :], mask=inside[:, None],
                    other=0.0)
        acc = tl.dot(a, tl.load(w_ptr + tap * CI * CO + ci[:, None] * CO + co[None, :]), acc)
    acc = tl.maximum(acc + tl.load(b_ptr + co)[None, :], 0.0)
    tl.store(out_ptr + b * ho * wo * CO + offs[:, None] * CO + co[None, :], acc.to(tl.float16), mask=valid[:, None])


@triton.jit
def taps3(x_ptr, w_ptr, b_ptr, out_ptr, hi, wi, ho, wo, STRIDE: tl.constexpr, CI: tl.constexpr, CO: tl.constexpr,
          ROW_MASK: tl.constexpr, BLOCK_M: tl.constexpr):
    """ROW_MASK: the loads masked by row alone (so they vectorize), the taps across the sides zeroed after (taps3u:
    the tensor needs a few pixels of slack before and after it, SLACK); else masked per element."""
    b = tl.program_id(1).to(tl.int64)
    offs = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    valid = offs < ho * wo
    y, x = offs // wo, offs % wo
    k, co = tl.arange(0, 4 * CI), tl.arange(0, CO)
    dx = k // CI - 1  # the pixel of column k: x-1 .. x+2 (x+2's weights are zero)
    xx = x[:, None] * STRIDE + dx[None, :]
    across = (xx >= 0) & (xx < wi) & (dx < 2)[None, :]
    acc = tl.zeros((BLOCK_M, CO), dtype=tl.float32)
    for dy in tl.static_range(3):
        yy = y * STRIDE + (dy - 1)
        rows = valid & (yy >= 0) & (yy < hi)
        ptrs = x_ptr + b * hi * wi * CI + ((yy * wi + x * STRIDE - 1) * CI)[:, None] + k[None, :]  # from the left tap
        if ROW_MASK:
            a = tl.where(across, tl.load(ptrs, mask=rows[:, None], other=0.0), 0.0)
        else:
            a = tl.load(ptrs, mask=rows[:, None] & across, other=0.0)
        acc = tl.dot(a, tl.load(w_ptr + dy * 4 * CI * CO + k[:, None] * CO + co[None, :]), acc)
    acc = tl.maximum(acc + tl.load(b_ptr + co)[None, :], 0.0)
    tl.store(out_ptr + b * ho * wo * CO + offs[:, None] * CO + co[None, :], acc.to(tl.float16), mask=valid[:, None])


# name: (kernel, its variant's constants); each autotuned on its own
KERNELS = {"taps9": (tuned(taps9), {}), "taps3": (tuned(taps3), {"ROW_MASK": False}),
           "taps3u": (tuned(taps3), {"ROW_MASK": True})}
SLACK = 4  # pixels before and after the input tensor (taps3u reads up to 2 past either end)


def weights_for(name: str, weight: torch.Tensor) -> torch.Tensor:
    """(CO, CI, 3, 3) -> taps9: (9, CI, CO); taps3(u): (3, 4 CI, CO), the fourth pixel zero."""
    co, ci = weight.shape[:2]
    taps = weight.permute(2, 3, 1, 0)  # (ky, kx, ci, co)
    if name == "taps9":
        return taps.reshape(9, ci, co).half().contiguous()
    rows = weight.new_zeros(3, 4, ci, co)
    rows[:, :3] = taps
    return rows.reshape(3, 4 * ci, co).half().contiguous()


def run(name: str, x: torch.Tensor, w: torch.Tensor, bias: torch.Tensor, stride: int) -> torch.Tensor:
    b, hi, wi, ci = x.shape
    co = bias.shape[0]
    ho, wo = hi // stride, wi // stride
    out = x.new_empty(b, ho, wo, co)
    fixed = {"BLOCK_M": 64} if INTERPRET else {}
    kernel, variant = KERNELS[name]
    kernel[lambda m: (triton.cdiv(ho * wo, m["BLOCK_M"]), b)](x, w, bias, out, hi, wi, ho, wo, STRIDE=stride, CI=ci,
                                                              CO=co, **variant, **fixed)
    return out


SHAPES = {  # name: (h, w, ci, co, stride)
    "head/fuse0 1080p": (1080, 1920, 16, 16, 1), "head/fuse0 4K": (2160, 3840, 16, 16, 1),
    "down1 1080p": (1080, 1920, 16, 32, 2), "fuse1 1080p": (540, 960, 32, 32, 1),
    "fuse1 4K": (1080, 1920, 32, 32, 1), "fuse2 4K": (540, 960, 64, 64, 1),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="")
    parser.add_argument("--small", action="store_true", help="tiny shapes (the interpreter's check)")
    args = parser.parse_args()
    device = "cpu" if INTERPRET else "cuda"
    shapes = {"small": (7, 13, 16, 16, 1), "small s2": (8, 14, 16, 32, 2), "small 32": (5, 6, 32, 32, 1)} \
        if args.small else SHAPES
    rows = []
    for label, (h, w, ci, co, stride) in shapes.items():
        gen = torch.Generator().manual_seed(0)
        slack = torch.randn(h * w * ci + 2 * SLACK * ci, generator=gen).half().to(device)
        x = slack[SLACK * ci:SLACK * ci + h * w * ci].view(1, h, w, ci)  # one frame, as taps3u needs it
        weight = (torch.randn(co, ci, 3, 3, generator=gen) * 0.2).to(device)
        bias = torch.randn(co, generator=gen).to(device)
        ref = F.relu(F.conv2d(x.permute(0, 3, 1, 2).float(), weight.half().float(), bias, stride=stride, padding=1))
        row = {"shape": label, "h": h, "w": w, "ci": ci, "co": co, "stride": stride}
        for name in KERNELS:
            wt = weights_for(name, weight)
            got = run(name, x, wt, bias, stride)
            row[f"{name}_max_err"] = (got.permute(0, 3, 1, 2).float() - ref).abs().max().item()
            if device == "cuda":
                row[f"{name}_us"] = 1e3 * triton.testing.do_bench_cudagraph(lambda: run(name, x, wt, bias, stride),
                                                                          rep=200)
                row[f"{name}_config"] = str(KERNELS[name][0].best_config)
        print(row, flush=True)
        rows.append(row)
    if args.out:
        meta = {"device": torch.cuda.get_device_name() if device == "cuda" else "cpu (interpreter)",
                "commit": os.environ.get("ISOSR_COMMIT", "unknown"), "torch": torch.__version__,
                "triton": triton.__version__, "command": "python scripts/study_conv_taps.py", "rows": rows}
        with open(args.out, "w") as f:
            json.dump(meta, f, indent=1)


if __name__ == "__main__":
    main()
