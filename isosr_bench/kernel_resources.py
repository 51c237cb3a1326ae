"""Registers and stack per CUDA kernel of a Warp module, compiled by NVRTC for a GPU architecture on
any machine (no GPU or driver needed: Warp's wheel carries NVRTC).

    python -m isosr_bench.kernel_resources                      # the renderer's kernels for sm_90 (H100/H200)
    python -m isosr_bench.kernel_resources --arch 80 --modules isosr_render.kernels
    python -m isosr_bench.kernel_resources --write              # and keep them in RECORD (per module hash)

Registers bound how many threads an SM keeps in flight (65536 per SM: 80 registers a thread
leave 25 warps, 168 leave 12, 255 leave 8), and the ray caster is latency-bound: on an H100 the
render kernel at 255 registers and a 120-byte stack took 1.3-1.4 times as long as at 166-168,
and that one kernel 1.3-1.5 times as long as the march alone at 80 plus the surface kernel at
128 (``docs/measurements.md``). Read from the
cubin's ``.nv.info`` attributes (ELF64): ``registers`` (EIATTR_REGCOUNT) and ``stack`` bytes
(EIATTR_MIN_STACK_SIZE, the stack of a kernel without recursion: spills and local arrays).

Compiling the renderer's modules takes minutes on a small machine; ``RECORD`` keeps each module's
figures under its Warp identifier (its source's hash) and Warp's version, and :func:`recorded_resources`
compiles only the modules whose identifier the record does not hold.

The reconstruction's fused tail (a Triton kernel, ``isosr_net.fused_kernels``) compiles the same way, by
Triton's own LLVM and ptxas, per model kind and autotuning config (``--fused-tail``): what a change to it
costs in registers and spills shows before a GPU runs it, and a kernel that would not compile for the GPU
fails here (the interpreter, which the kernel tests use on a CPU, compiles nothing).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import struct
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from isosr_bench.common import commit
from isosr_net.warp_modules import warp_module
from isosr_render.kernels import RENDER_MODULES

RECORD = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "kernel_resources_sm90.json"
EIATTR = {0x2F: "registers", 0x12: "stack"}
EIFMT_SVAL = 0x04  # a record with a 16-bit size and that many bytes; the other formats take 4 bytes in all


def cubin_resources(cubin: bytes) -> dict[str, dict[str, int]]:
    """Per kernel (its symbol) of an ELF64 cubin: ``registers`` and ``stack`` bytes."""
    shoff = struct.unpack_from("<Q", cubin, 0x28)[0]
    entsize, count, names_index = struct.unpack_from("<HHH", cubin, 0x3A)
    # (name, type, flags, addr, offset, size, link, info, align, entsize) per section
    sections = [struct.unpack_from("<IIQQQQIIQQ", cubin, shoff + i * entsize) for i in range(count)]

    def body(section) -> bytes:
        return cubin[section[4]:section[4] + section[5]]

    def name(offset: int, table: bytes) -> str:
        return table[offset:table.index(b"\0", offset)].decode()

    section_names = body(sections[names_index])
    symtab = next(s for s in sections if s[1] == 2)  # SHT_SYMTAB
    symbols, symbol_names = body(symtab), body(sections[symtab[6]])
    out: dict[str, dict[str, int]] = {}
    for section in sections:
        if name(section[0], section_names) != ".nv.info":
            continue
        data, i = body(section), 0
        while i < len(data):
            fmt, attr = data[i], data[i + 1]
            size = struct.unpack_from("<H", data, i + 2)[0] if fmt == EIFMT_SVAL else 0
            if fmt == EIFMT_SVAL and attr in EIATTR:
                symbol, value = struct.unpack_from("<II", data, i + 4)
                kernel = name(struct.unpack_from("<I", symbols, symbol * 24)[0], symbol_names)
                out.setdefault(kernel, {})[EIATTR[attr]] = value
            i += 4 + size
    return out


def overload_names(module: str) -> dict[str, str]:
    """Each compiled kernel's name (``first_hit_kernel_<hash>``) to a readable one: the key and the types
    its generic arguments take (``first_hit_kernel(uint8, Dense)``). Read after the module is compiled."""
    import warp as wp

    names = {}
    for kernel in wp.get_module(module).kernels.values():
        generic = [i for i, arg in enumerate(kernel.adj.args) if "Any" in repr(arg.type)]
        for overload in kernel.overloads.values() if kernel.overloads else [kernel]:
            args = overload.adj.args
            types = [getattr(args[i].type, "dtype", args[i].type) for i in generic]
            label = ", ".join(getattr(t, "key", getattr(t, "__name__", str(t))) for t in types)
            names[overload.get_mangled_name()] = f"{kernel.key}({label})" if label else kernel.key
    return names


def module_resources(module: str, arch: int = 90) -> dict[str, dict[str, int]]:
    """Per kernel (:func:`overload_names`) of Warp module ``module`` (a Python module's name, or a Warp
    module named with ``@wp.kernel(module=...)`` below one), compiled for ``sm_<arch>``:
    ``registers`` and ``stack``."""
    import warp as wp

    wp.init()
    with tempfile.TemporaryDirectory() as out:
        wp.compile_aot_module(warp_module(module), arch=arch, module_dir=out, use_ptx=False)
        found = {}
        for cubin in Path(out).glob("*.cubin"):
            found.update(cubin_resources(cubin.read_bytes()))
    names = overload_names(module)
    return {names.get(k.removesuffix("_cuda_kernel_forward"), k): v for k, v in found.items()}


def modules_resources(modules: list[str], arch: int = 90) -> dict[str, dict[str, dict[str, int]]]:
    """:func:`module_resources` of each of ``modules``, compiled side by side in processes of their own
    (NVRTC compiles a module on one core), one per core at most."""
    processes = max(1, min(len(modules), os.cpu_count() or 1))
    if processes == 1:
        return {m: module_resources(m, arch) for m in modules}
    with ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn")) as pool:
        return dict(zip(modules, pool.map(module_resources, modules, [arch] * len(modules))))


def identifier(module: str) -> str:
    """Warp's identifier of ``module``: its name and its source's hash, with Warp's version."""
    import warp as wp

    wp.init()
    return f"{warp_module(module).get_module_identifier()} (warp {wp.config.version})"


def recorded_resources(modules: list[str], record: Path = RECORD) -> tuple[dict, list[str]]:
    """:func:`modules_resources` for sm_90, from ``record`` for the modules whose identifier it holds; the
    others compiled. Returns them and the modules compiled (the record is stale for those)."""
    held = json.loads(record.read_text())["modules"] if record.is_file() else {}
    stale = [m for m in modules if held.get(m, {}).get("identifier") != identifier(m)]
    found = {m: held[m]["kernels"] for m in modules if m not in stale}
    return found | modules_resources(stale, 90) if stale else found, stale


def write_record(resources: dict[str, dict], record: Path = RECORD) -> None:
    """Keep sm_90 ``resources`` of modules in ``record`` under their identifiers (beside its other modules')."""
    modules = json.loads(record.read_text())["modules"] if record.is_file() else {}
    modules |= {m: {"identifier": identifier(m), "kernels": found} for m, found in resources.items()}
    record.write_text(json.dumps({"device": "sm_90 by NVRTC, no GPU", "commit": commit(),
                                  "command": "python -m isosr_bench.kernel_resources --write",
                                  "modules": dict(sorted(modules.items()))}, indent=1) + "\n")


def triton_type(value) -> str:
    """A Triton kernel argument's type in a compile signature: a tensor's pointer, an int, a float."""
    import torch

    if isinstance(value, torch.Tensor):
        return "*" + {torch.float16: "fp16", torch.float32: "fp32", torch.int32: "i32"}[value.dtype]
    if isinstance(value, bool):
        return "i1"
    if isinstance(value, int):
        return "i32" if -2 ** 31 <= value < 2 ** 31 else "i64"
    return "fp32"


def triton_resources(kernel, args: list, constexprs: dict, configs: list, arch: int = 90) -> dict[str, dict]:
    """Per autotuning config (``triton.Config``) of Triton ``kernel``, compiled for ``sm_<arch>`` by Triton's LLVM
    and ptxas (no GPU): ``registers`` and ``stack``. ``args`` (the call's, in order) give the argument types."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    signature = {name: triton_type(value) for name, value in zip(kernel.arg_names, args)}
    found = {}
    for config in configs:
        constants = constexprs | config.kwargs
        source = ASTSource(kernel, signature | dict.fromkeys(constants, "constexpr"), constants)
        compiled = triton.compile(source, target=GPUTarget("cuda", arch, 32), options={"num_warps": config.num_warps})
        (kernel_found,) = cubin_resources(compiled.asm["cubin"]).values()
        found[f"BLOCK_M {config.kwargs['BLOCK_M']}, {config.num_warps} warps"] = kernel_found
    return found


def tail_variants() -> dict:
    """The fused tail's model kinds (name -> ReconNetConfig): the shipped x1 and x2 models' configs, the stem of
    stride 2 (the x1 model's recipe at widths 32, 32, 64, 64) and it with a pixel tail of 16."""
    from dataclasses import replace

    from isosr_net.reconstructor import DEFAULT_RECON_MODEL, RECON_X2_MODEL, recon_config

    x1 = recon_config(DEFAULT_RECON_MODEL)
    stem = replace(x1, widths=(32, 32, 64, 64), stem_stride=2)
    return {"x1": x1, "x2": recon_config(RECON_X2_MODEL), "stem": stem,
            "stem, pixel tail 16": replace(stem, pixel_tail=16)}


def fused_tail_resources(variants: dict, configs: list | None = None, arch: int = 90) -> dict[str, dict]:
    """:func:`triton_resources` of the fused tail (a frame's, shaded, as the service runs it) for each of
    ``variants`` (name -> ReconNetConfig), over ``configs`` (default: the kernels' autotuning configs)."""
    import torch

    from isosr_net import fused_kernels as k
    from isosr_net.fused_recon import PACKED, FusedReconNet
    from isosr_net.reconnet import ReconNet
    from isosr_render.shading import ShadingParams

    found = {}
    for name, config in variants.items():
        fused, h, w = FusedReconNet(ReconNet(config).eval()), 1080, 1920
        stride = config.stem_stride
        y = torch.zeros(1, h // stride, w // stride, config.widths[0], dtype=torch.float16)
        mask = torch.zeros(1, h, w)
        sources = k.ReconSources.of_buffers(mask, torch.zeros(1, h, w, 3), mask, mask, torch.zeros(1, 2, 1, 1))
        mlp = fused.pixel_tail_mlp()
        packed = torch.zeros(1, h, w, PACKED, dtype=torch.float16) if mlp else None
        launch = k.tail_launch(y, fused.tail_w, fused.tail_b, sources, config, True, ShadingParams(), None,
                               fused.blend_rays, fused.gates, 1.0, packed, mlp)
        found[name] = triton_resources(k._tail_kernel, launch.args, launch.constexprs, configs or k.CONFIGS, arch)
    return found


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arch", type=int, default=90, help="compute capability x10 (90: H100/H200)")
    parser.add_argument("--modules", default=",".join(RENDER_MODULES), help="comma-separated Warp modules")
    parser.add_argument("--write", action="store_true", help=f"keep the figures (sm_90) in {RECORD.name} (default: off)")
    parser.add_argument("--fused-tail", action="store_true",
                        help="the reconstruction's fused tail (Triton) per model kind and config instead")
    args = parser.parse_args(argv)
    if args.fused_tail:
        print(f"| model | config | registers | stack (bytes) |  sm_{args.arch}\n|---|---|---|---|")
        for variant, configs in fused_tail_resources(tail_variants(), arch=args.arch).items():
            for config, r in configs.items():
                print(f"| {variant} | {config} | {r.get('registers')} | {r.get('stack')} |")
        return
    if args.write and args.arch != 90:
        raise SystemExit("--write keeps sm_90's figures only")
    found = modules_resources(args.modules.split(","), args.arch)
    print(f"| module | kernel | registers | stack (bytes) |  sm_{args.arch}\n|---|---|---|---|")
    for module, kernels in found.items():
        for kernel, r in sorted(kernels.items()):
            print(f"| {module} | {kernel} | {r.get('registers')} | {r.get('stack')} |")
    if args.write:
        write_record(found)
        print(f"wrote {RECORD}")


if __name__ == "__main__":
    main()
