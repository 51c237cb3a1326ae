"""`isosr kernels`: compile the project's Warp kernels ahead of time for GPU architectures, on any machine
(no GPU or driver needed: Warp's wheel carries NVRTC), into Warp's kernel cache or a folder for
``WARP_CACHE_PATH``, so that a GPU node loads them instead of compiling them on first use.

Per architecture it writes a cubin and a PTX: Warp loads PTX when the node's driver is at least as new as
Warp's CUDA toolkit, else the cubin. Use the same isosr and warp versions as the node (the cache is keyed
by a hash of the kernels' code and Warp's version).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import warp as wp


def add_parser(subparsers) -> None:
    """Register ``kernels``."""
    p = subparsers.add_parser("kernels", help="compile the Warp kernels ahead of time for GPU nodes (no GPU needed)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--arch", type=int, action="append", default=[], metavar="SM",
                   help="GPU architecture, compute capability x10 (90: H100/H200, 80: A100); repeat for several")
    p.add_argument("--cache", type=Path, help="the folder to set WARP_CACHE_PATH to on the node (default: this "
                                              "machine's Warp kernel cache)")
    p.add_argument("--module", action="append", default=[], help="only this Warp module (see --list); repeatable")
    p.add_argument("--list", action="store_true", help="print the project's Warp modules and exit")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from isosr_net.warp_modules import WARP_MODULES, warp_module

    if args.list:
        print("\n".join(WARP_MODULES))
        return 0
    unknown = sorted(set(args.module) - set(WARP_MODULES))
    if unknown:
        raise ValueError(f"unknown modules {unknown}; the project's Warp modules: {', '.join(WARP_MODULES)}")
    if not args.arch:
        raise ValueError("name at least one GPU architecture: --arch 90 (H100/H200), --arch 80 (A100), ...")
    wp.init()
    check_archs(args.arch)
    cache = cache_dir(args.cache)
    for name in args.module or WARP_MODULES:
        module = warp_module(name)
        start = time.perf_counter()
        files = [path for arch in args.arch for use_ptx in (False, True)
                 for path in wp.compile_aot_module(module, arch=arch, use_ptx=use_ptx,
                                                   module_dir=cache / module.get_module_identifier())]
        print(f"{name}: {time.perf_counter() - start:.1f} s, {' '.join(p.name for p in files)} in {files[0].parent}")
    print(f"on the GPU node: WARP_CACHE_PATH={args.cache.resolve()}" if args.cache else f"Warp's kernel cache: {cache}")
    return 0


def check_archs(archs: list[int]) -> None:
    """Refuse architectures this Warp's NVRTC cannot compile for, naming those it can."""
    supported = wp.get_cuda_supported_archs()
    if not supported:
        raise RuntimeError("this Warp build has no NVRTC: it cannot compile CUDA kernels (install warp-lang's "
                           "CUDA wheel)")
    bad = sorted(set(archs) - set(supported))
    if bad:
        raise ValueError(f"NVRTC cannot compile for --arch {', '.join(map(str, bad))}; it compiles for "
                         f"{', '.join(map(str, supported))}")


def cache_dir(root: Path | None) -> Path:
    """Where Warp looks for the modules: ``<root>/<warp version>`` when WARP_CACHE_PATH is ``root``, else
    this machine's kernel cache."""
    if root is None:
        return Path(wp.config.kernel_cache_dir)
    if root.exists() and not root.is_dir():
        raise ValueError(f"--cache {root} is a file, not a folder")
    return root / wp.config.version
