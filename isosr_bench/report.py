"""The benchmarks' report: Markdown tables and PNG plots made from their JSON results.

    python -m isosr_bench.report [RESULTS_DIR] [--kind cuda|cpu]
    python -m isosr_bench.report --docs     # docs/performance.md, the README's figures table, auto's cost tables
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

from isosr_render.atomic import atomic_write
from isosr_net.methods import RUNNERS
from isosr_net.budget import PRIORS_DIR, CostTable, front_psnr

from .common import RESULTS_DIR


def _load(folder: Path, name: str, kind: str) -> dict | None:
    path = folder / f"{name}_{kind}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def _table(rows: list[dict], columns: list[str]) -> list[str]:
    def fmt(v):
        return f"{v:.3g}" if isinstance(v, float) else ("" if v is None else str(v))
    return ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)] + \
        ["| " + " | ".join(fmt(r.get(c)) for c in columns) + " |" for r in rows]


def _run_lines(record: dict) -> list[str]:
    """A result's run (device, commit, date, command) and its note, where it has one, as paragraphs."""
    run = [f"{record['device']}, commit {record['commit']}, {record['date']}: `{record['command']}`", ""]
    return run + ([record["note"], ""] if "note" in record else [])


def markdown(folder: Path, kind: str) -> str:
    """The report's text: one section per study that has results."""
    lines = [f"# Benchmarks ({kind})", ""]
    sections = (("bench_network", "The network's fast path",
                 ["variant", "size", "ms", "wall_ms", "max |diff| vs fp32", "GFLOP/frame", "floor ms"]),
                ("bench_pipeline", "The paper's table, the interactive path and how cost grows",
                 ["part", "role", "volume", "case", "size", "ms", "speedup vs AO"]),
                ("bench_knobs", "What accuracy costs in time",
                 ["knob", "setting", "size", "ms", "error", "error unit", "mask mismatch", "device", "commit"]),
                ("bench_render", "The renderer",
                 ["volume", "case", "size", "ms", "kernel_ms", "samples/pixel", "max samples/pixel", "skip speedup"]),
                ("bench_recon_path", "What the reconstruction adds to a full-resolution frame",
                 ["volume", "size", "method", "variant", "full", "path", "added", "render", "network_gflop",
                  "floor_ms", "device", "commit"]))
    for name, title, columns in sections:
        record = _load(folder, name, kind)
        if record is None:
            continue
        lines += [f"## {title}", ""] + _run_lines(record) + _table(record["rows"], columns) + [""]
    lines += cluster_markdown(folder, kind)
    lines += pareto_markdown(folder, kind)
    return "\n".join(lines)


CLUSTER_COLUMNS = ["lease", "server", "gpus", "mode", "ao", "sessions", "fps", "fps_per_session", "latency_p50_ms",
                   "latency_p99_ms", "errors", "methods", "gpu_busy", "server_cores", "proxy_cores",
                   "replica_cores_max"]


def cluster_markdown(folder: Path, kind: str) -> list[str]:
    """The service over several GPUs and with several replicas on one GPU (`bench_cluster`):
    each case, its scaling against one replica, and failover."""
    lines = []
    for name, title in (("bench_cluster_gpus_1080p", "The service over several GPUs (one replica per GPU)"),
                        ("bench_cluster_one_gpu_1080p", "Several replicas sharing one GPU")):
        record = _load(folder, name, kind)
        if record is None:
            continue
        cases = [r for r in record["rows"] if "study" not in r]
        lines += [f"## {title}", ""] + _run_lines(record) + _table(cases, CLUSTER_COLUMNS) + [""]
        scaled = [r for r in record["rows"] if r.get("study") == "scaling"]
        if scaled:
            lines += _table(scaled, ["lease", "server", "replicas", "mode", "ao", "sessions", "fps", "fps_one", "efficiency",
                                     "p99_ms", "p99_one_at_1_over_n_ms", "p99_ratio"]) + [""]
        failover = [r for r in record["rows"] if r.get("study") == "failover"]
        if failover:
            lines += _table(failover, ["lease", "server", "sessions", "moved_sessions", "failover_max_s", "unmoved",
                                       "other_sessions", "other_max_gap_s", "health_ready"]) + [""]
    return lines


def plots(folder: Path, kind: str) -> list[Path]:
    """PNG plots of the pipeline scaling and the accuracy/time trade-offs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    pipeline = _load(folder, "bench_pipeline", kind)
    if pipeline:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for ax, part, xlabel in ((axes[0], "resolution", "output pixels"), (axes[1], "volume size", "voxels per side")):
            series = defaultdict(list)
            for r in pipeline["rows"]:
                if r["part"] == part:
                    w, h = map(int, r["size"].split("x"))
                    x = w * h if part == "resolution" else int(r["volume"].split("^")[0])
                    series[r["case"]].append((x, r["ms"]))
            for case, points in series.items():
                xs, ys = zip(*sorted(points))
                ax.plot(xs, ys, marker="o", label=case)
            ax.set(xscale="log", yscale="log", xlabel=xlabel, ylabel="ms per frame", title=f"time against {part}")
            ax.legend()
        path = folder / f"scaling_{kind}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    knobs = _load(folder, "bench_knobs", kind)
    if knobs:
        groups = defaultdict(list)
        for r in knobs["rows"]:
            groups[r["knob"].split(" x")[0] if r["knob"].startswith("upscale") else r["knob"]].append(r)
        fig, axes = plt.subplots(1, len(groups), figsize=(4 * len(groups), 3.6), squeeze=False)
        for ax, (knob, rows) in zip(axes[0], groups.items()):
            if knob == "upscale":
                _upscale_panel(ax, rows)
            else:
                for r in rows:
                    ax.scatter(r["ms"], r["error"], color="C0")
                    ax.annotate(r["setting"], (r["ms"], r["error"]), fontsize=7)
            times = [r["ms"] for r in rows]
            spread = max(times) / min(times) > 10  # log axes only where times span a decade
            ax.set(xscale="log" if spread else "linear", xlabel="ms per frame", ylabel=rows[0]["error unit"],
                   title=knob)
            if spread:
                ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        path = folder / f"knobs_{kind}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    cluster = _load(folder, "bench_cluster_gpus_1080p", kind)
    if cluster:
        written.append(cluster_plot(plt, cluster, folder / f"cluster_gpus_{kind}.png"))
    return written + pareto_plots(folder, kind)


def cluster_plot(plt, record: dict, path: Path) -> Path:
    """Frames/s against GPUs (one replica each) per mode and session count, beside N times one
    replica's (dashed) and the plain server on one GPU (crosses): per mode, the latest lease that
    measured one replica in it (a comparison is drawn within one lease)."""
    cases = [r for r in record["rows"] if "fps" in r and "study" not in r]
    modes = sorted({(r["mode"], r["ao"]) for r in cases if r["replicas"] == 1})
    colour = {n: f"C{k}" for k, n in enumerate(sorted({r["sessions"] for r in cases}))}
    fig, axes = plt.subplots(1, len(modes), figsize=(5 * len(modes), 3.8), squeeze=False)
    for ax, (mode, ao) in zip(axes[0], modes):
        rows = [r for r in cases if (r["mode"], r["ao"]) == (mode, ao)]
        lease = max(r.get("lease") or "" for r in rows if r["replicas"] == 1)
        rows = [r for r in rows if r.get("lease") == lease]
        for sessions in sorted({r["sessions"] for r in rows}):
            at = sorted((r["replicas"], r["fps"]) for r in rows if r["sessions"] == sessions and r["replicas"] > 0)
            if at:
                xs, ys = zip(*at)
                ax.plot(xs, ys, marker="o", color=colour[sessions], label=f"{sessions} sessions")
                one = dict(at).get(1)
                if one:
                    ax.plot(xs, [one * x for x in xs], linestyle="--", color=colour[sessions], alpha=0.5)
            plain = [r["fps"] for r in rows if r["sessions"] == sessions and r["replicas"] == 0]
            if plain:
                ax.scatter([1] * len(plain), plain, marker="x", color=colour[sessions],
                           label=f"plain server, {sessions}")
        ax.set(xlabel="GPUs (one replica each)", ylabel="frames/s, all sessions", xticks=[1, 2, 4])
        ax.set_title(f"{mode}, AO {ao}, lease {lease}\ndashed: N x one replica", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _upscale_panel(ax, rows: list[dict]) -> None:
    """Upscalers per factor (one color each): classic ones as dots, networks as stars, one label per model."""
    for i, factor in enumerate(sorted({r["knob"] for r in rows})):
        suffix = " " + factor.split()[-1]  # "upscale x2" -> " x2", dropped from model names
        named = set()
        for j, r in enumerate(r for r in rows if r["knob"] == factor):
            classic = r["setting"] in ("nearest", "bilinear", "bicubic")
            ax.scatter(r["ms"], r["error"], color=f"C{i}", marker="o" if classic else "*", s=20 if classic else 60,
                       label=suffix.strip() if j == 0 else None)
            model = r["setting"].rsplit(" ", 1)[0].replace(suffix, "")  # without precision and factor
            if model not in named:
                ax.annotate(model, (r["ms"], r["error"]), fontsize=7)
                named.add(model)
    ax.legend(fontsize=7)


def _pareto_scenes(record: dict) -> dict[tuple[str, str], list[dict]]:
    """The Pareto rows by (volume, size), each scene's rows sorted by time."""
    scenes = defaultdict(list)
    for r in record["rows"]:
        if r["part"] == "pareto":
            scenes[(r["volume"], r["size"])].append(r)
    return {k: sorted(v, key=lambda r: r["ms"]) for k, v in scenes.items()}


def pareto_markdown(folder: Path, kind: str) -> list[str]:
    """The Pareto study's section: per scene its table, where each method wins (the front, from
    which time on it is the best) and where the learned, filtered and upscaled ones lose (to what)."""
    from .bench_pareto import dominator, pareto_front

    record = _load(folder, "pareto", kind)
    if record is None:
        return []
    lines = ["## Every way to make a frame: time against quality", "", *_run_lines(record),
             "ms: the whole path per frame. Scores against 4 rays per pixel and 512 AO rays; PSNR and SSIM of the "
             "color on the covered region (color_psnr_scene: on the scene's region, the same pixels for every row, "
             "what the fronts rank by; image_psnr: the whole image); empty: nothing covered. flicker: the mean "
             "absolute color change between frames along the flow; flicker_ratio: over the reference's own. "
             "front: no method is both at least as fast and at least as good.", ""]
    scenes = _pareto_scenes(record)
    on_front = defaultdict(int)
    for (volume, size), rows in scenes.items():
        front = pareto_front([(r["ms"], front_psnr(r)) for r in rows])
        for r, f in zip(rows, front):
            r["front"] = "yes" if f else ""
            on_front[r["method"]] += f
        winners = [r for r in rows if r["front"]]
        run = f" ({rows[0]['device']}, {rows[0]['commit']})" if "device" in rows[0] else ""
        lines += [f"### {volume}, {rows[0].get('pixels', size)}{run}", ""]
        lines += _table(rows, ["method", "learned", "ms", "color_psnr", "color_psnr_scene", "color_ssim", "image_psnr",
                               "ao_rmse",
                               "flicker", "flicker_ratio", "front"]) + [""]
        wins = [f"{r['method']} from {r['ms']:.3g} ms ({front_psnr(r):.1f} dB)" for r in winners]
        lines += ["Wins (the best there is from that frame time on, up to the next): " + "; ".join(wins) + ".", ""]
        losses = []
        for r in rows:
            if r["kind"] != "full" and not r["front"]:
                d = dominator(r, rows)
                if d is not None:
                    losses.append(f"{r['method']} ({r['ms']:.3g} ms, {front_psnr(r):.1f} dB) to {d['method']} "
                                  f"({d['ms']:.3g} ms, {front_psnr(d):.1f} dB)")
        if losses:
            lines += ["Loses: " + "; ".join(losses) + ".", ""]
    budget = [r for r in record["rows"] if r["part"] == "budget"]
    lines += scorecard_markdown(scenes, {(r["volume"], r["size"]): r["ao_effect_db"] for r in budget})
    counts = sorted({r["method"] for rows in scenes.values() for r in rows if r["kind"] != "full"})
    lines += ["On the front, of " + str(len(scenes)) + " scenes: "
              + "; ".join(f"{m} {on_front[m]}" for m in counts) + ".", ""]
    if budget:
        lines += ["### The budget policy against the best fixed setting", "",
                  "method: the policy's choice (probe_ms: its time in the probe); color_psnr and ms: what this "
                  "run measured for it; best_fixed: the best row within the budget here.", ""]
        lines += _table(budget, ["volume", "size", "budget_ms", "method", "fits", "probe_ms", "ms", "color_psnr",
                                 "color_psnr_scene",
                                 "best_fixed", "best_fixed_ms", "best_fixed_psnr", "psnr_gap", "ao_matters", "commit"]) + [""]
    return lines


def scorecard_markdown(scenes: dict[tuple[str, str], list[dict]], ao_effect: dict[tuple[str, str], float]) -> list[str]:
    """Where the learned methods win, per scene (:func:`isosr_bench.bench_pareto.learned_scorecard`);
    ``ao_effect``: the budget probe's AO effect per scene, dB (a scene at or above the policy's
    threshold is no goal: AO changes nothing visible there)."""
    from isosr_net.budget import AO_MATTERS_DB
    from .bench_pareto import GOAL_TOP_MS, learned_scorecard

    lines = ["### Where a learned method is the best there is", "",
             f"Budgets from 1.5 times the scene's cheapest full-resolution frame up to {GOAL_TOP_MS:g} ms, each "
             "sqrt(2) times the last: the best method that fits against the best learned one. Then the "
             "reconstruction against the non-learned filters (a-trous, SVGF, OIDN) at the same AO rays: its "
             "PSNR and time minus theirs, and both flicker ratios; and the fastest learned method at least as "
             "good as 64 AO rays (spp 1). A scene whose AO changes the colors by less than the policy's "
             f"threshold (the reference with and without AO at or above {AO_MATTERS_DB:g} dB) is no goal scene.", "",
             "| scene | learned best at | filter -> recon at the same rays (dB, ms; flicker ratios) "
             "| 64-ray AO match (speed-up) |",
             "|---|---|---|---|"]
    for (volume, size), rows in scenes.items():
        card = learned_scorecard(rows)
        if not card["budgets"]:
            continue
        won = [b for b in card["budgets"] if b["learned_best"]]
        lost = [f"{b['budget_ms']:.3g} ms ({b['best']}, {b['best_psnr']:.1f} dB)" for b in card["budgets"]
                if not b["learned_best"]]
        baselines = ", ".join(f"{a['method']}: {a['recon_psnr'] - a['psnr']:+.1f} dB {a['recon_ms'] - a['ms']:+.2f} ms"
                              f" ({_ratio(a['flicker_ratio'])} -> {_ratio(a['recon_flicker_ratio'])})"
                              for a in card["baselines"]) or "-"
        ao64 = card["ao64"]
        match = ("-" if ao64 is None else f"none reaches {ao64['psnr']:.1f} dB" if ao64["learned"] is None
                 else f"{ao64['learned']}: {ao64['learned_ms']:.3g} vs {ao64['ms']:.3g} ms ({ao64['speedup']:.1f}x)")
        notes = "" if any(r["kind"] == "reconstruct" for r in rows) else " (no reconstruction rows measured)"
        effect = ao_effect.get((volume, size))
        if effect is not None and effect >= AO_MATTERS_DB:
            notes += f" (AO changes nothing visible: {effect:.1f} dB; no goal scene)"
        lines.append(f"| {volume}, {size}{notes} | {len(won)} of {len(card['budgets'])} budgets"
                     + (f"; not at {'; '.join(lost)}" if lost else "") + f" | {baselines} | {match} |")
    return lines + [""]


def _ratio(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def plot_colors() -> dict[str, str]:
    """The Pareto plots' color by method kind: each registered kind's own
    (:attr:`~isosr_net.methods.FrameRunner.plot_color`; kinds without one are not plotted)."""
    return {kind: cls.plot_color for kind, cls in RUNNERS.items() if cls.plot_color is not None}


def pareto_plots(folder: Path, kind: str) -> list[Path]:
    """Per volume, one panel per size: time (log) against color PSNR, the front colored by kind and
    joined, dominated points grey, learned methods as stars."""
    import matplotlib.pyplot as plt

    from .bench_pareto import pareto_front

    record = _load(folder, "pareto", kind)
    if record is None:
        return []
    colors = plot_colors()
    by_volume = defaultdict(dict)
    for (volume, size), rows in _pareto_scenes(record).items():
        by_volume[volume][size] = rows
    written = []
    for volume, sizes in by_volume.items():
        fig, axes = plt.subplots(1, len(sizes), figsize=(6 * len(sizes), 4.5), squeeze=False)
        for ax, (size, rows) in zip(axes[0], sizes.items()):
            rows = [r for r in rows if front_psnr(r) is not None]
            front = pareto_front([(r["ms"], front_psnr(r)) for r in rows])
            for r, f in zip(rows, front):
                ax.scatter(r["ms"], front_psnr(r), color=colors[r["kind"]] if f else "0.75",
                           marker="*" if r["learned"] else "o", s=90 if r["learned"] else 25, zorder=3 if f else 2)
                if f or r["learned"]:
                    ax.annotate(r["method"], (r["ms"], front_psnr(r)), fontsize=6, xytext=(3, 2),
                                textcoords="offset points")
            best = [r for r, f in zip(rows, front) if f]
            if best:
                ax.plot([r["ms"] for r in best], [front_psnr(r) for r in best], color="0.3", lw=0.8, zorder=1)
            for k, c in colors.items():
                ax.scatter([], [], color=c, marker="*" if RUNNERS[k].network_class else "o", label=k)
            ax.scatter([], [], color="0.75", label="dominated")
            ax.set(xscale="log", xlabel="ms per frame (whole path)", ylabel="color PSNR, the scene's region (dB)",
                   title=f"{volume}, {rows[0].get('pixels', size) if rows else size}")
            ax.legend(fontsize=7)
        path = folder / f"pareto_{volume}_{kind}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    return written


def write(folder: Path, kind: str) -> list[Path]:
    """Write ``report_KIND.md`` and the plots (skipped, with a line saying so, without matplotlib)."""
    path = folder / f"report_{kind}.md"
    text = markdown(folder, kind)
    atomic_write(path, lambda f: f.write(text.encode()))
    try:
        return [path] + plots(folder, kind)
    except ImportError:
        print("matplotlib is not installed: plots skipped (run `python -m isosr_bench.report` where it is)")
        return [path]



# docs/performance.md: the main figures, made from the result files so that they cannot drift from them.

DOCS_PERFORMANCE = RESULTS_DIR.parent.parent / "docs" / "performance.md"
README = RESULTS_DIR.parent.parent / "README.md"
FIGURES_BEGIN = "<!-- figures: generated by `python -m isosr_bench.report --docs`; do not edit by hand -->"
FIGURES_END = "<!-- end of figures -->"
# The scenes' names as the docs write them, in the order the tables list them.
DOCS_VOLUMES = {"ct_pitch": "CT head (ct_pitch)", "headsq": "CT head (headsq)", "avg152t1": "MRI (avg152t1)",
                "chest_lidc": "chest CT (chest_lidc)", "bonsai": "bonsai 256^3", "bonsai1024": "bonsai 1024^3",
                "hydrogen": "simulation (hydrogen)"}
# The Pareto study's methods the summary table shows, with their column headings.
DOCS_METHODS = (("full, AO 0, spp 1", "full, no AO"), ("full, AO 2, a-trous", "full, AO 2, a-trous"),
                ("full, AO 2, svgf", "full, AO 2, SVGF"), ("full, AO 1, spp 1, recon fp16", "full, AO 1, recon"),
                ("full, AO 1, spp 4, recon fp16", "full, AO 1, spp 4, recon"), ("full, AO 64, spp 1", "full, AO 64"),
                ("x4 network bf16", "x4 network (bf16)"))
DOCS_FILTERS = (("svgf", "SVGF"), ("oidn high", "OIDN high"), ("oidn fast", "OIDN fast"), ("a-trous", "a-trous"))


def _num(value, digits: int = 3) -> str:
    """A figure as the docs write it: ``digits`` significant digits, '-' where there is none."""
    if value is None:
        return "-"
    return f"{value:.{digits}g}" if isinstance(value, float) else str(value)


def _rows_table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + \
        ["| " + " | ".join(r) + " |" for r in rows] + [""]


def _source(record: dict, name: str) -> str:
    """Where a section's figures come from: the file, its device and commit."""
    return f"Source: `benchmarks/results/{name}` ({record['device']}; commit {str(record['commit'])[:7]}, {record['date']})."


def _docs_scenes(record: dict) -> list[tuple[tuple[str, str], list[dict]]]:
    """The Pareto scenes in the docs' order: volumes as DOCS_VOLUMES lists them, 1080p before 4K."""
    scenes = _pareto_scenes(record)
    order = list(DOCS_VOLUMES)
    key = lambda item: (item[0][1] != "1080p", order.index(item[0][0]) if item[0][0] in order else len(order),  # noqa: E731
                        item[0][0])
    return sorted(scenes.items(), key=key)


def _scene_name(volume: str, size: str) -> str:
    return ("4K: " if size == "4k" else "") + DOCS_VOLUMES.get(volume, volume)


def docs_pareto(folder: Path) -> list[str]:
    """The Pareto study's summary: chosen methods per scene, where a learned method is the best that fits,
    the reconstruction against the filters, and the budget policy."""
    from .bench_pareto import GOAL_TOP_MS, learned_scorecard
    from isosr_net.budget import AO_MATTERS_DB

    record = _load(folder, "pareto", "cuda")
    if record is None:
        return []
    scenes = _docs_scenes(record)
    lines = ["## Every way to make a frame: time against quality", "",
             "Every way of making the final frame, timed as a whole path (render, reconstruction, shading; CUDA "
             "events after warm-up, in sequence over an 8-frame orbit) and scored against a reference with 4 rays "
             "per pixel and 512 AO rays (color PSNR on the scene's region: the reference's covered pixels and their "
             "neighbours, the same for every method; on the covered region in rows measured before it). "
             "Re-run one scene with "
             "`isosr bench --pareto --device cuda --volumes ct_pitch --sizes 1080p --out benchmarks/results` (rows merge into the file).", "",
             "Source: `benchmarks/results/pareto_cuda.json`; every row names its device and commit, and scenes "
             "were measured at different commits: compare methods within a row (within one commit), not across "
             "rows. The whole report, every method of every scene: "
             "[report_cuda.md](../benchmarks/results/report_cuda.md).", "",
             "ms per frame / color PSNR (dB) (\"recon\": the reconstruction network over the AO rays named, fp16):", ""]
    header = ["scene"] + [h for _, h in DOCS_METHODS] + ["device, commit"]
    table = []
    for (volume, size), rows in scenes:
        by_method = {r["method"]: r for r in rows}
        cells = []
        for method, _ in DOCS_METHODS:
            r = by_method.get(method)
            cells.append("-" if r is None or front_psnr(r) is None else f"{_num(r['ms'])} / {front_psnr(r):.1f}")
        device = rows[0].get("device", record["device"]).replace("NVIDIA ", "").replace(" 80GB HBM3", "")
        table.append([_scene_name(volume, size)] + cells + [f"{device}, {rows[0].get('commit', record['commit'])}"])
    lines += _rows_table(header, table)
    volumes = sorted({v for (v, _), _ in scenes}, key=lambda v: list(DOCS_VOLUMES).index(v) if v in DOCS_VOLUMES else 99)
    lines += ["Plots (time, log, against PSNR; the front joined, dominated points grey, learned methods as stars): "
              + ", ".join(f"[{DOCS_VOLUMES.get(v, v)}](../benchmarks/results/pareto_{v}_cuda.png)" for v in volumes
                          if (folder / f"pareto_{v}_cuda.png").is_file()) + ".", "",
              "![every method on the CT head (ct_pitch), 1080p and 4K](../benchmarks/results/pareto_ct_pitch_cuda.png)", ""]

    # Where a learned method is the best that fits.
    ao_effect = {(r["volume"], r["size"]): r["ao_effect_db"] for r in record["rows"] if r["part"] == "budget"}
    lines += ["## Where a learned method is the best that fits", "",
              f"Frame-time budgets from 1.5 times the scene's cheapest full-resolution frame up to {GOAL_TOP_MS:g} ms, "
              "each sqrt(2) times the last; at each, the best method that fits against the best learned one. "
              "\"64 AO rays for less\": the fastest learned method at least as good as 64 AO rays at 1 ray per "
              f"pixel. A scene whose AO changes the colors by less than the policy's threshold ({AO_MATTERS_DB:g} dB "
              "between the reference with and without AO) is no goal scene: no AO is the best there.", ""]
    table, won_all, total_all = [], 0, 0
    for (volume, size), rows in scenes:
        card = learned_scorecard(rows)
        if not card["budgets"]:
            continue
        won = sum(b["learned_best"] for b in card["budgets"])
        effect = ao_effect.get((volume, size))
        goal = effect is None or effect < AO_MATTERS_DB
        if goal:
            won_all, total_all = won_all + won, total_all + len(card["budgets"])
        ao64 = card["ao64"]
        match = ("-" if ao64 is None or ao64["learned"] is None
                 else f"{ao64['learned']}: {_num(ao64['learned_ms'])} against {_num(ao64['ms'])} ms "
                      f"({ao64['speedup']:.1f}x)")
        name = _scene_name(volume, size) + ("" if goal else f" (no goal scene: AO {effect:.1f} dB)")
        table.append([name, f"{won} of {len(card['budgets'])}", match])
    lines += _rows_table(["scene", "budgets a learned method wins", "64 AO rays for less"], table)
    lines += [f"Over the goal scenes: a learned method is the best that fits at **{won_all} of {total_all}** budgets.", ""]

    # The reconstruction against the filters at the same AO rays.
    lines += ["## The reconstruction against SVGF, OIDN and a-trous at the same AO rays", "",
              "Color PSNR (dB) at the whole path's ms, and the flicker ratio (the frames' change along the flow "
              "over the reference's own; 1 is the reference's). The reconstruction: 1 ray per pixel, fp16. "
              "SVGF and the ray history start from an empty history over the 8-frame orbit, as a viewer that "
              "just opened sees them.", ""]
    table = []
    for (volume, size), rows in scenes:
        by_method = {r["method"]: r for r in rows if front_psnr(r) is not None}
        for rays in (1, 4):
            recon = by_method.get(f"full, AO {rays}, spp 1, recon fp16")
            others = [by_method.get(f"full, AO {rays}, {m}") for m, _ in DOCS_FILTERS]
            if recon is None or not any(others):
                continue
            best = max(front_psnr(r) for r in [recon] + [o for o in others if o])
            cell = lambda r: "-" if r is None else (  # noqa: E731
                ("**{}**" if front_psnr(r) == best else "{}").format(
                    f"{front_psnr(r):.1f} at {_num(r['ms'], 2)}, {_ratio(r.get('flicker_ratio'))}"))
            table.append([f"{_scene_name(volume, size)}, {rays}", cell(recon)] + [cell(o) for o in others])
    lines += _rows_table(["scene, AO rays", "reconstruction"] + [h for _, h in DOCS_FILTERS], table)

    # The budget policy against the best fixed setting.
    budget = [r for r in record["rows"] if r["part"] == "budget"]
    if budget:
        budgets = sorted({r["budget_ms"] for r in budget})
        lines += ["## `auto`: the budget policy against the best fixed setting", "",
                  "`quality=\"auto\"` (`isosr render --budget-ms`, the service's `auto` mode) picks a method with a "
                  "short probe; here its choice at each budget, and how far its color PSNR fell below the best "
                  "fixed method that fits the budget in the same run (0: it chose that one).", ""]
        if "note" in record:
            lines += ["Note of the run: " + record["note"], ""]
        table, gaps = [], defaultdict(list)
        by_scene = defaultdict(dict)
        for r in budget:
            by_scene[(r["volume"], r["size"])][r["budget_ms"]] = r
        for (volume, size), _ in scenes:
            cells = []
            for b in budgets:
                r = by_scene[(volume, size)].get(b)
                if r is None:
                    cells.append("-")
                    continue
                gap = r.get("psnr_gap")
                gaps[size].append(gap)
                cells.append(f"{r['method']}{'' if r.get('fits', True) else ' (over)'}, "
                             f"{'-' if gap is None else f'{gap:.1f}'} dB")
            table.append([_scene_name(volume, size)] + cells)
        lines += _rows_table(["scene"] + [f"{b:g} ms: choice, shortfall" for b in budgets], table)
        for size, values in sorted(gaps.items()):
            values = sorted(v for v in values if v is not None)
            if values:
                lines += [f"At {size}: matched the best fixed setting in {sum(v <= 0.05 for v in values)} of "
                          f"{len(values)} cases, within 1 dB in {sum(v <= 1.0 for v in values)}, median shortfall "
                          f"{values[len(values) // 2]:.1f} dB.", ""]
    return lines


def docs_first_frame(folder: Path) -> list[str]:
    record = _load(folder, "bench_first_frame", "cpu")
    if record is None:
        return []
    lines = ["## The first frame", "",
             "A view session's first frame after the server started (the volume's first load included), and the "
             "frames after it. No frame waits for `auto`'s probe: the first hit is sent while the probe runs "
             "between frames. " + _source(record, "bench_first_frame_cpu.json")
             + f" `{record['command']}`", ""]
    rows = [[r["mode"], r["size"], _num(r["first_frame_s"]), r["first_method"], _num(r["latency_p50_s"]),
             _num(r["latency_max_s"]), r["last_method"]] for r in record["rows"] if "mode" in r]
    lines += _rows_table(["mode", "size", "first frame (s)", "its method", "later frames p50 (s)", "max (s)",
                          "last method"], rows)
    for r in record["rows"]:
        if r.get("study") == "start":
            lines += [f"The server was ready {_num(r['ready_s'])} s after its start.", ""]
        if r.get("study") == "shutdown":
            lines += [f"SIGTERM while the probe runs: the server exits in {_num(r['exit_s'])} s.", ""]
    return lines


def _server_table(record: dict, modes: list[str] | None = None) -> list[str]:
    cases = defaultdict(dict)
    for r in record["rows"]:
        if "mode" in r and (modes is None or r["mode"] in modes):
            cases[(r["mode"], r["ao"])][r["sessions"]] = r
    rows = []
    for (mode, ao), by_sessions in cases.items():
        one, many = by_sessions.get(1), by_sessions.get(max(by_sessions))
        n = max(by_sessions)
        methods = sorted({m for r in (one, many) if r for m in r.get("methods", [])})
        rows.append([f"`{mode}`" + (f", AO {ao}" if ao else ""),
                     "-" if one is None else f"{one['fps']:.0f} fps (p50 {_num(one['latency_p50_ms'], 2)} ms)",
                     f"{n}: {many['fps']:.0f} fps ({many['fps_per_session']:.1f} each, p99 "
                     f"{many['latency_p99_ms']:.0f} ms)", "; ".join(methods) or "-"])
    return _rows_table(["mode", "1 session", "sessions: frames/s in all", "methods the frames name"], rows)


def docs_service(folder: Path) -> list[str]:
    lines = ["## The service: frames/s of view sessions", "",
             "`python -m isosr_bench.bench_server --device cuda --volume bonsai --size 1080p`: closed-loop clients "
             "(send a camera, wait for the frame that includes it) in a second process on the same machine, JPEG "
             "frames; frames/s of one session (p50 latency), then of many together (per session, p99 latency).", ""]
    for name, title in (("bench_server_1080p_all_modes", "1920x1080, every mode"),
                        ("bench_server_1080p", "1920x1080, `auto` and `full` again"),
                        ("bench_server_4k", "3840x2160")):
        record = _load(folder, name, "cuda")
        if record is None:
            continue
        lines += [f"### {title}", "", _source(record, f"{name}_cuda.json"), ""] + _server_table(record)
    record = _load(folder, "bench_video_1080p", "cuda")
    if record is not None:
        lines += ["### Video against JPEG", "",
                  "Bytes per frame of each codec at JPEG quality 85's color PSNR, as a share of JPEG's, and the "
                  "encoder's time per frame (`python -m isosr_bench.bench_video --device cuda --volume shared:bonsai "
                  "--sizes 1080p`). " + _source(record, "bench_video_1080p_cuda.json"), ""]
        matched = [r for r in record["rows"] if r.get("study") == "matched"]
        methods = list(dict.fromkeys(r["method"] for r in matched))
        encodings = list(dict.fromkeys(r["encoding"] for r in matched))
        rows = []
        for m in methods:
            cells = {r["encoding"]: r for r in matched if r["method"] == m}
            jpeg = cells.get("jpeg")
            rows.append([f"{m} ({jpeg['psnr_db']:.1f} dB)" if jpeg else m] + [
                "-" if e not in cells else (f"{cells[e]['bytes_per_frame'] / 1000:.0f} KB, {cells[e]['encode_ms']:.0f} ms"
                                            if e == "jpeg" else
                                            f"{cells[e]['bytes_vs_jpeg']:.2f}, {cells[e]['encode_ms']:.0f} ms")
                for e in encodings])
        lines += _rows_table(["frames"] + encodings, rows)
        link = [r for r in record["rows"] if r.get("study") == "link"]
        if link:
            lines += ["One `auto` session through a throttled loopback link: " + "; ".join(
                f"{r['encoding']} {r['fps']:.1f} frames/s (p50 {r['latency_p50_ms']:.0f} ms, p99 "
                f"{r['latency_p99_ms']:.0f} ms) over {r['link_mbit']:g} Mbit/s" for r in link) + ".", ""]
    record = _load(folder, "bench_volume_memory", "cuda")
    if record is not None:
        lines += ["### Large volumes", "",
                  "Loading and the first hit at 1080p (`python -m isosr_bench.bench_volume_memory --device cuda`; "
                  "volumes computed box by box from a procedural field, standing in for a chunked store). "
                  + _source(record, "bench_volume_memory_cuda.json"), ""]
        rows = []
        for r in record["rows"]:
            shape = "x".join(map(str, r["shape"]))
            rows.append([f"{shape} {r['stored']}", f"{r['path']}, {r['mode']}" + (f", {r['step']}" if "step" in r else ""),
                         "-" if "load_s" not in r else _num(r["load_s"]),
                         "-" if "page_in_s" not in r else _num(r["page_in_s"]),
                         "-" if "host_added_gb" not in r else _num(r["host_added_gb"]),
                         _num(r["resident_gb"]), _num(r.get("first_hit_ms"))])
        lines += _rows_table(["volume", "path", "load (s)", "page-in (s)", "host memory added (GB)",
                              "on the device (GB)", "1080p first hit (ms)"], rows)
    return lines


def docs_gpus(folder: Path) -> list[str]:
    lines = ["## Several GPUs", "",
             "How the service is run on several GPUs, what bounds it, and failover: "
             "[several-gpus.md](several-gpus.md).", ""]
    record = _load(folder, "bench_cluster_gpus", "1080p_cuda")
    if record is not None:
        lines += ["### One replica per GPU (`isosr serve --replicas N --gpus-per-replica 1`)", "",
                  "Closed-loop view sessions at 1080p, bonsai; frames/s summed over all sessions, p99 latency, "
                  "and each GPU's busy fraction. " + _source(record, "bench_cluster_gpus_1080p_cuda.json"), ""]
        rows = [[r["server"], _num(r["gpus"]), f"`{r['mode']}`" + (f", AO {r['ao']}" if r["ao"] else ""),
                 str(r["sessions"]), f"{r['fps']:.0f}", f"{r['latency_p99_ms']:.0f}",
                 ", ".join(f"{g:.2f}" for g in r.get("gpu_busy", [])), r.get("lease", "-")]
                for r in record["rows"] if "study" not in r]
        lines += _rows_table(["server", "GPUs", "mode", "sessions", "frames/s", "p99 (ms)", "GPU busy", "lease"], rows)
        scaling = [r for r in record["rows"] if r.get("study") == "scaling"]
        if scaling:
            lines += ["Against one replica (efficiency: frames/s over N times one replica's): " + "; ".join(
                f"{r['replicas']} replicas, `{r['mode']}` at {r['sessions']} sessions {r['efficiency']:.2f}"
                for r in scaling) + ".", ""]
        failover = [r for r in record["rows"] if r.get("study") == "failover"]
        if failover:
            lines += ["Failover (one replica's process killed): " + "; ".join(
                f"{r['replicas']} replicas, {r['sessions']} sessions: {r['moved_sessions']} moved, framed again "
                f"within {r['failover_max_s']:.2f} s" + ("" if r.get("other_max_gap_s") is None else
                                                          f", the others' longest gap {r['other_max_gap_s']:.2f} s")
                for r in failover) + ".", ""]
    record = _load(folder, "bench_cluster_1080p", "cuda")
    if record is not None:
        lines += ["### What the Ray Serve path costs on one GPU", "",
                  "The plain server against replicas behind Serve's proxy sharing one GPU (`--gpus-per-replica 0.5`). "
                  + _source(record, "bench_cluster_1080p_cuda.json"), ""]
        cases = defaultdict(dict)
        for r in record["rows"]:
            if "study" not in r:
                cases[r["server"]][(r["mode"], r["sessions"])] = r
        keys = sorted({k for c in cases.values() for k in c}, key=lambda k: (k[0] != "full", k[1]))
        rows = [[server] + [("-" if k not in c else f"{c[k]['fps']:.0f}" + (
            f" (p50 {_num(c[k]['latency_p50_ms'], 2)} ms)" if k[1] == 1 else "")) for k in keys]
            for server, c in cases.items()]
        lines += _rows_table(["server"] + [f"`{m}`, {s}" for m, s in keys], rows)
    record = _load(folder, "bench_train_gpus", "cuda")
    if record is not None:
        lines += ["### Data-parallel training", "",
                  "`python -m isosr_bench.bench_train --device cuda --config configs/train_recon_history.json "
                  "--gpus 1,2`. " + _source(record, "bench_train_gpus_cuda.json"), ""]
        rows = [[r["study"], str(r["processes"]), str(r["batch_size"]), f"{r['ms_per_step']:.0f}",
                 f"{r['speedup']:.2f}", f"{r['val_color_psnr']:.1f}"] for r in record["rows"]]
        lines += _rows_table(["study", "GPUs", "global batch", "ms per step", "speed-up", "val color PSNR (dB)"], rows)
        if "note" in record:
            lines += [record["note"], ""]
    return lines


def performance_markdown(folder: Path) -> str:
    """The text of docs/performance.md, from the result files in ``folder``."""
    lines = ["# Performance", "",
             FIGURES_BEGIN.replace("figures: ", ""), "",
             "The main figures, made from the result files in `benchmarks/results/` (each names its device, "
             "commit, date and command) by `python -m isosr_bench.report --docs`, which also writes the README's "
             "figures table; `tests/test_docs.py` checks that both match the results. Between runs on different "
             "machines of one kind the same method moves by up to 20-30%: compare within a commit. The history of "
             "each change and its A/B is in [measurements.md](measurements.md).", ""]
    lines += docs_pareto(folder) + docs_first_frame(folder) + docs_service(folder) + docs_gpus(folder)
    while lines and lines[-1] == "":
        lines.pop()
    return "\n".join(lines) + "\n"


def readme_figures(folder: Path) -> str:
    """The README's one small table of main figures (between FIGURES_BEGIN and FIGURES_END)."""
    rows = []
    pareto = _load(folder, "pareto", "cuda")
    if pareto is not None:
        scenes = dict(_pareto_scenes(pareto))
        for volume, size in (("ct_pitch", "1080p"), ("ct_pitch", "4k")):
            by_method = {r["method"]: r for r in scenes.get((volume, size), [])}
            recon, ao64 = by_method.get("full, AO 1, spp 1, recon fp16"), by_method.get("full, AO 64, spp 1")
            if recon and ao64:
                rows.append([f"reconstructed frame, 1 AO ray ({_scene_name(volume, size)})",
                             f"{_num(recon['ms'])} ms, {front_psnr(recon):.1f} dB (64 AO rays: {_num(ao64['ms'])} ms, "
                             f"{front_psnr(ao64):.1f} dB)",
                             f"{recon['device'].replace('NVIDIA ', '').replace(' 80GB HBM3', '')}, "
                             f"{recon['commit']}"])
    for name, size in (("bench_server_1080p", "1080p"),):
        record = _load(folder, name, "cuda")
        if record is not None:
            auto = {r["sessions"]: r for r in record["rows"] if r.get("mode") == "auto"}
            if 1 in auto and 16 in auto:
                rows.append([f"service, `auto` mode, {size}",
                             f"1 session {auto[1]['fps']:.0f} fps (p50 {auto[1]['latency_p50_ms']:.0f} ms); 16 sessions "
                             f"{auto[16]['fps']:.0f} fps in all", f"{record['device'].replace('NVIDIA ', '').replace(' 80GB HBM3', '')}, "
                             f"{str(record['commit'])[:7]}"])
    record = _load(folder, "bench_first_frame", "cpu")
    if record is not None:
        first = next((r for r in record["rows"] if r.get("mode") == "auto"), None)
        if first:
            rows.append([f"first `auto` frame, {first['size']}, volume loaded on first use",
                         f"{first['first_frame_s']:.1f} s", f"{record['device']}, {record['commit']}"])
    record = _load(folder, "bench_cluster_gpus", "1080p_cuda")
    if record is not None:
        fours = [r for r in record["rows"] if "study" not in r and r["server"] == "ray4" and r["sessions"] == 64]
        for mode in ("full", "reconstruct"):  # the latest lease's
            four = max((r for r in fours if r["mode"] == mode), key=lambda r: r["lease"], default=None)
            if four:
                rows.append([f"service on 4 GPUs (4 replicas), `{mode}`, 64 sessions, 1080p",
                             f"{four['fps']:.0f} fps in all, p99 {four['latency_p99_ms']:.0f} ms",
                             f"H200 x4, {four.get('commit', record['commit'])[:7]}, lease {four['lease']}"])
    table = _rows_table(["what", "figure", "measured on"], rows)
    return "\n".join([FIGURES_BEGIN, ""] + table + [FIGURES_END])


def cost_table_json(folder: Path, kind: str) -> str | None:
    """The auto mode's committed prior for ``kind`` (:class:`isosr_net.budget.CostTable`) from the
    Pareto study's results in ``folder``, as JSON text; None without them."""
    pareto = _load(folder, "pareto", kind)
    if pareto is None:
        return None
    rows = CostTable.from_pareto([r for r in pareto["rows"] if "ms" in r and "kind" in r])
    record = {"device": pareto["device"], "commit": pareto["commit"], "source": f"benchmarks/results/pareto_{kind}.json",
              "made_by": "python -m isosr_bench.report --docs", "rows": rows}
    return json.dumps(record, indent=1) + "\n"


def write_docs(folder: Path = RESULTS_DIR, docs: Path = DOCS_PERFORMANCE, readme: Path = README,
               priors: Path = PRIORS_DIR) -> list[Path]:
    """Write docs/performance.md, the README's figures table (between its markers) and the auto
    mode's cost tables (``priors``/KIND.json) from ``folder``."""
    text = performance_markdown(folder)
    atomic_write(docs, lambda f: f.write(text.encode()))
    written = [docs]
    for kind in ("cuda", "cpu"):
        if (table := cost_table_json(folder, kind)) is not None:
            priors.mkdir(parents=True, exist_ok=True)
            atomic_write(priors / f"{kind}.json", lambda f, t=table: f.write(t.encode()))
            written.append(priors / f"{kind}.json")
    if readme.is_file():
        current = readme.read_text()
        start, end = current.find(FIGURES_BEGIN), current.find(FIGURES_END)
        if start >= 0 and end > start:
            updated = current[:start] + readme_figures(folder) + current[end + len(FIGURES_END):]
            if updated != current:
                atomic_write(readme, lambda f: f.write(updated.encode()))
            written.append(readme)
    return written


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", nargs="?", type=Path, default=RESULTS_DIR)
    parser.add_argument("--kind", default="cuda", choices=("cuda", "cpu"))
    parser.add_argument("--docs", action="store_true",
                        help="instead: write docs/performance.md and the README's figures table from the results")
    args = parser.parse_args(argv)
    if args.docs:
        print("wrote " + ", ".join(str(p) for p in write_docs(args.folder)))
        return
    print("wrote " + ", ".join(str(p) for p in write(args.folder, args.kind)))


if __name__ == "__main__":
    main()
