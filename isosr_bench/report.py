"""The benchmarks' report: Markdown tables and PNG plots made from their JSON results.

    python -m isosr_bench.report [RESULTS_DIR] [--kind cuda|cpu]
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

from isosr_render.atomic import atomic_write

from .common import RESULTS_DIR


def _load(folder: Path, name: str, kind: str) -> dict | None:
    path = folder / f"{name}_{kind}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def _table(rows: list[dict], columns: list[str]) -> list[str]:
    def fmt(v):
        return f"{v:.3g}" if isinstance(v, float) else ("" if v is None else str(v))
    return ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)] + \
        ["| " + " | ".join(fmt(r.get(c)) for c in columns) + " |" for r in rows]


def markdown(folder: Path, kind: str) -> str:
    """The report's text: one section per study that has results."""
    lines = [f"# Benchmarks ({kind})", ""]
    sections = (("bench_network", "The network's fast path",
                 ["variant", "size", "ms", "wall_ms", "max |diff| vs fp32", "GFLOP/frame", "floor ms"]),
                ("bench_pipeline", "The paper's table, the interactive path and how cost grows",
                 ["part", "role", "volume", "case", "size", "ms", "speedup vs AO"]),
                ("bench_knobs", "What accuracy costs in time",
                 ["knob", "setting", "size", "ms", "error", "error unit", "mask mismatch"]),
                ("bench_render", "The renderer",
                 ["volume", "case", "size", "ms", "kernel_ms", "samples/pixel", "max samples/pixel", "skip speedup"]))
    for name, title, columns in sections:
        record = _load(folder, name, kind)
        if record is None:
            continue
        lines += [f"## {title}", "", f"{record['device']}, commit {record['commit']}, {record['date']}: "
                  f"`{record['command']}`", ""] + _table(record["rows"], columns) + [""]
    return "\n".join(lines)


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
        fig, axes = plt.subplots(1, len(groups), figsize=(4 * len(groups), 3.6))
        for ax, (knob, rows) in zip(axes, groups.items()):
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
    return written


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
