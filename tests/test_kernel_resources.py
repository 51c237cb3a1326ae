"""The renderer's CUDA kernels compiled for the H100/H200 (sm_90) by NVRTC on this machine, no GPU
needed (isosr_bench.kernel_resources): their registers stay where the measured speed is.

The ray caster is latency-bound: on an H100 one kernel that marched and then made the buffers
(166-168 registers, 12 warps an SM) took 1.3-1.5 times as long as the march alone at 80
registers plus the surface kernel at 128; at 255 registers and a 120-byte stack it had taken
1.3-1.4 times as long again (docs/measurements.md). A change that brings such registers back
fails here, before anyone times it. The reconstruction's fused tail (Triton) compiles here too, by
Triton's own compiler.
"""

from __future__ import annotations

import importlib.util
import os

import pytest

from isosr_bench.kernel_resources import RECORD, fused_tail_resources, recorded_resources, tail_variants
from isosr_render import kernels
from isosr_render.kernels import RENDER_MODULES

# The first-hit march's registers per thread on sm_90 (80 measured: 25 warps an SM; 96 leave 21).
MAX_FIRST_HIT_REGISTERS = 88
# Bytes of stack a kernel keeps without spilling (its random state and small locals).
MAX_STACK = 40
# The surface kernel for several rays per pixel spills some of the frame's values under its cap (and
# marches the rays past a plan's hit planes itself): 232-240 bytes.
MAX_SAMPLES_STACK = 256
# The plain kernels (NoClip), which must cost what they did before clipping, and the clipped ones (ClipArgs,
# their own Warp module, run only for frames that clip).
OVERLOADS = [f"({t.__name__}, {layout.key}, {kernels.NoClip.key}, {kernels.OneIso.key})" for t in kernels.VOXEL_TYPES
             for layout in kernels.LAYOUTS]
CLIPPED_OVERLOADS = [o.replace(kernels.NoClip.key, kernels.ClipArgs.key) for o in OVERLOADS]
# The kernels for several isosurfaces (IsoSet), with and without clipping: their own Warp modules.
SURFACES_OVERLOADS = [o.replace(kernels.OneIso.key, kernels.IsoSet.key) for o in OVERLOADS + CLIPPED_OVERLOADS]
# The clipped kernels, measured on sm_90 when clipping became their own variant (the plane table in device
# memory): first hit 96-118 registers, no stack; surface kernel 128 registers and 168-184 bytes of stack
# (cut faces and AO rays' kept spans under the cap); several rays 448-480 bytes. Bounds a little above.
MAX_CLIPPED_FIRST_HIT_REGISTERS = 128
MAX_CLIPPED_STACK = 200
MAX_CLIPPED_SAMPLES_STACK = 512


# The kernels of several isosurfaces (IsoSet: both layers' march in one first-hit kernel), measured on sm_90 when
# they came: first hit 120-128 registers (clipped 158-168), no stack; surface kernel 128 registers and 32 bytes of
# stack (clipped 184-200); several rays 360-392 bytes (clipped 688-704). Bounds a little above.
MAX_SURFACES_FIRST_HIT_REGISTERS = 176
MAX_SURFACES_STACK = 216
MAX_SURFACES_SAMPLES_STACK = 736


@pytest.fixture(scope="module")
def recorded() -> tuple[dict[str, dict], list[str]]:
    """The modules' figures from the record where it holds their source's, the others compiled; and those."""
    import warp as wp

    if 90 not in wp.get_cuda_supported_archs():
        pytest.skip("this Warp build's NVRTC cannot compile for sm_90 (a build without CUDA)")
    return recorded_resources(list(RENDER_MODULES))


@pytest.fixture(scope="module")
def resources(recorded) -> dict[str, dict[str, int]]:
    return {k: v for found in recorded[0].values() for k, v in found.items()}


def test_the_record_holds_this_source(recorded):
    """A kernel change compiles here (minutes) until its figures are recorded."""
    assert not recorded[1], (f"{RECORD.name} holds other sources of {recorded[1]} (their bounds were checked "
                             f"compiled): python -m isosr_bench.kernel_resources --write")


def test_every_overload_is_compiled_and_read(resources):
    assert set(kernels.VARIANT_MODULES.values()) == set(RENDER_MODULES)
    for name in kernels.FRAME_KERNELS:
        assert {f"{name}{o}" for o in OVERLOADS + CLIPPED_OVERLOADS + SURFACES_OVERLOADS} <= set(resources), \
            sorted(resources)
    assert all(r["registers"] > 0 for r in resources.values())


def test_first_hit_kernel_registers_and_stack(resources):
    for overload in OVERLOADS:
        r = resources[f"first_hit_kernel{overload}"]
        assert r["registers"] <= MAX_FIRST_HIT_REGISTERS and r["stack"] <= MAX_STACK, (overload, r)


def test_surface_kernels_registers_capped(resources):
    """Both surface kernels keep their cap; the one-ray kernel spills nothing under it."""
    for overload in OVERLOADS:
        one, several = resources[f"surface_kernel{overload}"], resources[f"surface_samples_kernel{overload}"]
        assert one["registers"] <= kernels.SURFACE_MAX_REGISTERS and one["stack"] <= MAX_STACK, (overload, one)
        assert several["registers"] <= kernels.SURFACE_MAX_REGISTERS, (overload, several)
        assert several["stack"] <= MAX_SAMPLES_STACK, (overload, several)


def assert_variant_within(resources, overloads: list[str], first_hit_registers: int, stack: int,
                          samples_stack: int) -> None:
    """A kernel variant's first hit, surface and several-rays kernels within their measured bounds."""
    for overload in overloads:
        first = resources[f"first_hit_kernel{overload}"]
        one, several = resources[f"surface_kernel{overload}"], resources[f"surface_samples_kernel{overload}"]
        assert first["registers"] <= first_hit_registers and first["stack"] <= MAX_STACK, (overload, first)
        assert one["registers"] <= kernels.SURFACE_MAX_REGISTERS and one["stack"] <= stack, (overload, one)
        assert several["registers"] <= kernels.SURFACE_MAX_REGISTERS, (overload, several)
        assert several["stack"] <= samples_stack, (overload, several)


def test_clipped_kernels_stay_where_measured(resources):
    assert_variant_within(resources, CLIPPED_OVERLOADS, MAX_CLIPPED_FIRST_HIT_REGISTERS, MAX_CLIPPED_STACK,
                          MAX_CLIPPED_SAMPLES_STACK)


def test_surface_set_kernels_stay_where_measured(resources):
    assert_variant_within(resources, SURFACES_OVERLOADS, MAX_SURFACES_FIRST_HIT_REGISTERS, MAX_SURFACES_STACK,
                          MAX_SURFACES_SAMPLES_STACK)


@pytest.mark.skipif(os.environ.get("TRITON_INTERPRET") == "1" or importlib.util.find_spec("triton") is None,
                    reason="compiling the fused tail needs Triton, not its interpreter")
def test_the_fused_tail_with_a_pixel_tail_compiles_for_sm90_unspilled():
    """The reconstruction's fused tail with a pixel tail's MLP (a stem of stride 2: four output pixels a program's
    pixel) compiled by Triton for sm_90: the kernel tests run it under the interpreter, which compiles nothing, so
    a kernel the GPU's compiler refuses fails here first. At 128 pixels and 8 warps a program, measured at 255
    registers and no stack (``python -m isosr_bench.kernel_resources --fused-tail``): a change that spills there
    fails too."""
    from isosr_net.fused_kernels import CONFIGS

    name = "stem, pixel tail 16"
    (found,) = fused_tail_resources({name: tail_variants()[name]}, [CONFIGS[3]])[name].values()
    assert 0 < found["registers"] <= 255 and found["stack"] == 0
