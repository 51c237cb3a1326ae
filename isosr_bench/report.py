"""The benchmarks' report: Markdown tables and PNG plots made from their JSON results.

    python -m isosr_bench.report [RESULTS_DIR] [--kind cuda|cpu]
"""

from __future__ import annotations

import argparse
import json
from collections import Counter, defaultdict
from pathlib import Path

from isosr_render.atomic import atomic_write
from isosr_net.frame_methods import RUNNERS

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
    replica's (dashed) and the plain server on one GPU (crosses): the lease with the most rows
    (a comparison is drawn within one lease)."""
    cases = [r for r in record["rows"] if "fps" in r and "study" not in r]
    lease = Counter(r.get("lease") for r in cases).most_common(1)[0][0]
    cases = [r for r in cases if r.get("lease") == lease]
    modes = sorted({(r["mode"], r["ao"]) for r in cases if r["replicas"] > 0})
    colour = {n: f"C{k}" for k, n in enumerate(sorted({r["sessions"] for r in cases}))}
    fig, axes = plt.subplots(1, len(modes), figsize=(5 * len(modes), 3.8), squeeze=False)
    for ax, (mode, ao) in zip(axes[0], modes):
        rows = [r for r in cases if (r["mode"], r["ao"]) == (mode, ao)]
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
        ax.set(xlabel="GPUs (one replica each)", ylabel="frames/s, all sessions", xticks=[1, 2, 4],
               title=f"{mode}, AO {ao}: dashed N x one replica")
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
             "color on the covered region (image_psnr: the whole image); empty: nothing covered. flicker: the mean "
             "absolute color change between frames along the flow; flicker_ratio: over the reference's own. "
             "front: no method is both at least as fast and at least as good.", ""]
    scenes = _pareto_scenes(record)
    on_front = defaultdict(int)
    for (volume, size), rows in scenes.items():
        front = pareto_front([(r["ms"], r["color_psnr"]) for r in rows])
        for r, f in zip(rows, front):
            r["front"] = "yes" if f else ""
            on_front[r["method"]] += f
        winners = [r for r in rows if r["front"]]
        run = f" ({rows[0]['device']}, {rows[0]['commit']})" if "device" in rows[0] else ""
        lines += [f"### {volume}, {rows[0].get('pixels', size)}{run}", ""]
        lines += _table(rows, ["method", "learned", "ms", "color_psnr", "color_ssim", "image_psnr", "ao_rmse",
                               "flicker", "flicker_ratio", "front"]) + [""]
        wins = [f"{r['method']} from {r['ms']:.3g} ms ({r['color_psnr']:.1f} dB)" for r in winners]
        lines += ["Wins (the best there is from that frame time on, up to the next): " + "; ".join(wins) + ".", ""]
        losses = []
        for r in rows:
            if r["kind"] != "full" and not r["front"]:
                d = dominator(r, rows)
                if d is not None:
                    losses.append(f"{r['method']} ({r['ms']:.3g} ms, {r['color_psnr']:.1f} dB) to {d['method']} "
                                  f"({d['ms']:.3g} ms, {d['color_psnr']:.1f} dB)")
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


def pareto_plots(folder: Path, kind: str) -> list[Path]:
    """Per volume, one panel per size: time (log) against color PSNR, the front colored by kind and
    joined, dominated points grey, learned methods as stars."""
    import matplotlib.pyplot as plt

    from .bench_pareto import pareto_front

    record = _load(folder, "pareto", kind)
    if record is None:
        return []
    colors = {"full": "C0", "atrous": "C1", "svgf": "C5", "oidn": "C6", "reconstruct": "C4", "upscale": "C2",
              "network": "C3"}
    by_volume = defaultdict(dict)
    for (volume, size), rows in _pareto_scenes(record).items():
        by_volume[volume][size] = rows
    written = []
    for volume, sizes in by_volume.items():
        fig, axes = plt.subplots(1, len(sizes), figsize=(6 * len(sizes), 4.5), squeeze=False)
        for ax, (size, rows) in zip(axes[0], sizes.items()):
            rows = [r for r in rows if r["color_psnr"] is not None]
            front = pareto_front([(r["ms"], r["color_psnr"]) for r in rows])
            for r, f in zip(rows, front):
                ax.scatter(r["ms"], r["color_psnr"], color=colors[r["kind"]] if f else "0.75",
                           marker="*" if r["learned"] else "o", s=90 if r["learned"] else 25, zorder=3 if f else 2)
                if f or r["learned"]:
                    ax.annotate(r["method"], (r["ms"], r["color_psnr"]), fontsize=6, xytext=(3, 2),
                                textcoords="offset points")
            best = [r for r, f in zip(rows, front) if f]
            if best:
                ax.plot([r["ms"] for r in best], [r["color_psnr"] for r in best], color="0.3", lw=0.8, zorder=1)
            for k, c in colors.items():
                ax.scatter([], [], color=c, marker="*" if RUNNERS[k].network_class else "o", label=k)
            ax.scatter([], [], color="0.75", label="dominated")
            ax.set(xscale="log", xlabel="ms per frame (whole path)", ylabel="color PSNR, covered region (dB)",
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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", nargs="?", type=Path, default=RESULTS_DIR)
    parser.add_argument("--kind", default="cuda", choices=("cuda", "cpu"))
    args = parser.parse_args(argv)
    print("wrote " + ", ".join(str(p) for p in write(args.folder, args.kind)))


if __name__ == "__main__":
    main()
