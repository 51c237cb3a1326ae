"""`isosr bench`: every timing and accuracy study, then the plots and the Markdown report."""

from __future__ import annotations

import argparse
from pathlib import Path

STUDIES = ("network", "pipeline", "knobs", "render")
# Studies run only when named in --only (server: starts `isosr serve` and drives view sessions;
# memory: loads volumes of up to tens of GB, see isosr_bench.bench_volume_memory).
ON_REQUEST = ("server", "memory")


def add_parser(subparsers) -> None:
    """Register ``bench``."""
    from isosr_bench.common import OUT_HELP, SCRATCH_DIR

    p = subparsers.add_parser("bench", help="timing and accuracy benchmarks (JSON, Markdown, plots)",
                              formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--device", help="cuda or cpu (default: cuda if torch sees a GPU)")
    p.add_argument("--smoke", action="store_true", help="small sizes on the CPU, under two minutes (CI)")
    p.add_argument("--only", default=",".join(STUDIES),
                   help=f"comma-separated subset of {','.join(STUDIES + ON_REQUEST)} (ignored with --pareto)")
    p.add_argument("--out", type=Path, default=SCRATCH_DIR, help=OUT_HELP)
    p.add_argument("--models", default="", help="more networks for the knob sweep: NAME=MODEL_FOLDER,...")
    p.add_argument("--pareto", action="store_true",
                   help="instead: every way to make a frame, timed and scored (pareto_<kind>.json), and the budget "
                        "policy against the best fixed setting")
    p.add_argument("--volumes", default="", help="with --pareto: comma-separated volumes (rows merge into the file)")
    p.add_argument("--sizes", default="", help="with --pareto: comma-separated sizes of 1080p,4k or WxH")
    p.add_argument("--kinds", default="", help="with --pareto: comma-separated method kinds (a quick A/B of models: "
                   "reconstruct,svgf; no budget part; pareto_select_<kind>.json)")
    p.add_argument("--spp", default="", help="with --pareto: only methods of these comma-separated rays per pixel "
                   "(a selection, as --kinds)")
    p.add_argument("--ao-rays", default="", help="with --pareto: only methods of these comma-separated AO rays per "
                   "hit (a selection, as --kinds)")
    p.add_argument("--translucent", type=float, default=None, metavar="A",
                   help="with --pareto: also every method on the iso at opacity A over a surface inside it (rows "
                   "of part layers beside the single surface's; default: none)")
    p.add_argument("--budget-only", action="store_true", help="with --pareto: only the policy's part, scored by "
                   "the methods' rows the result file holds (measured on this kind of device)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from isosr_bench import (bench_knobs, bench_network, bench_pareto, bench_pipeline, bench_render, bench_server,
                             bench_volume_memory, report)

    if (args.volumes or args.sizes or args.kinds or args.spp or args.ao_rays or args.budget_only
            or args.translucent is not None) and not args.pareto:
        raise ValueError("--volumes, --sizes, --kinds, --spp, --ao-rays, --translucent and --budget-only select what "
                         "--pareto measures; give --pareto too")

    studies = [] if args.pareto else [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = sorted(set(studies) - set(STUDIES + ON_REQUEST))
    if unknown:
        raise ValueError(f"unknown studies {unknown}; choose from {', '.join(STUDIES + ON_REQUEST)}")
    bench_knobs.parse_models(args.models)  # a bad --models fails before hours of benchmarks
    device = args.device or ("cuda" if torch.cuda.is_available() and not args.smoke else "cpu")
    out = args.out
    argv = ["--device", device, "--out", str(out)] + (["--smoke"] if args.smoke else [])
    if args.pareto:
        print("== pareto")
        bench_pareto.main(argv + ["--volumes", args.volumes, "--sizes", args.sizes, "--models", args.models,
                                  "--kinds", args.kinds, "--spp", args.spp, "--ao-rays", args.ao_rays]
                          + ["--budget-only"] * args.budget_only
                          + ([] if args.translucent is None else ["--translucent", str(args.translucent)]))
    modules = {"network": bench_network, "pipeline": bench_pipeline, "knobs": bench_knobs, "render": bench_render,
               "server": bench_server, "memory": bench_volume_memory}
    for study in studies:
        print(f"== {study}")
        modules[study].main(argv + (["--models", args.models] if study == "knobs" and args.models else []))
    written = report.write(out, "cuda" if device.startswith("cuda") else "cpu")
    print("wrote " + ", ".join(str(p) for p in written))
    return 0
