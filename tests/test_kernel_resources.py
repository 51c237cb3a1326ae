"""The renderer's CUDA kernels compiled for the H100/H200 (sm_90) by NVRTC on this machine, no GPU
needed (isosr_bench.kernel_resources): their registers stay where the measured speed is.

On an H100 the render kernel at 255 registers and a 120-byte stack (a frame struct copied from
device memory, the whole grid struct passed to each sample, the dense and sparse paths in one
kernel) took 1.3-1.4 times as long as at 166-168 (docs/measurements.md): a change that brings
such registers back fails here, before anyone times it.
"""

from __future__ import annotations

import pytest

from isosr_bench.kernel_resources import RENDER_MODULES, module_resources
from isosr_render import kernels

# The render kernel's registers per thread on sm_90 (166-168 measured; 176 leaves 11 warps an SM, 255 left 8).
MAX_RENDER_REGISTERS = 176
# Bytes of stack the render kernel keeps without spilling (its random state and small locals).
MAX_RENDER_STACK = 32
OVERLOADS = [f"({t.__name__}, {layout.key})" for t in kernels.VOXEL_TYPES for layout in kernels.LAYOUTS]


@pytest.fixture(scope="module")
def resources() -> dict[str, dict[str, int]]:
    import warp as wp

    if 90 not in wp.get_cuda_supported_archs():
        pytest.skip("this Warp build's NVRTC cannot compile for sm_90 (a build without CUDA)")
    return {k: v for module in RENDER_MODULES for k, v in module_resources(module, arch=90).items()}


def test_every_overload_is_compiled_and_read(resources):
    for name in ("render_kernel", "render_staged_kernel"):
        assert {f"{name}{o}" for o in OVERLOADS} <= set(resources), sorted(resources)
    assert all(r["registers"] > 0 for r in resources.values())


def test_render_kernel_registers_and_stack(resources):
    for overload in OVERLOADS:
        r = resources[f"render_kernel{overload}"]
        assert r["registers"] <= MAX_RENDER_REGISTERS and r["stack"] <= MAX_RENDER_STACK, (overload, r)


def test_staged_kernel_registers_capped(resources):
    """The kernel CUDA graphs capture keeps the frame's values in the stack, not in registers."""
    for overload in OVERLOADS:
        r = resources[f"render_staged_kernel{overload}"]
        assert r["registers"] <= kernels.STAGED_MAX_REGISTERS, (overload, r)
