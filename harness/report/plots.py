"""Accuracy versus complexity: held-out mAP against GFLOPs, one panel per dataset (rows) and metric (columns).

* x: GFLOPs each entry's runs measured on the model they trained (``metrics.json`` ``complexity``, the "paper"
  convention at 640), on a **log** axis shared by all panels;
* y: mAP in %, the mean over held-out folds, with error bars of ± one sample SD over the folds;
* one marker (shape and colour) per detector, the same in every panel, labelled with its short name;
* the **Pareto front** (points that no other point beats with fewer or equal GFLOPs and a higher mAP) drawn as a
  dashed step line: the best accuracy reachable at a given cost;
* the conventions printed on the figure: FLOP convention, input size and batch of the measurement, the metric and
  how it is aggregated, and the hardware the runs were measured on.

matplotlib with the Agg canvas only (no pyplot, no display), written as PNG and SVG.
"""

from __future__ import annotations

import io
import logging
import math
import re
import textwrap
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

log = logging.getLogger(__name__)

MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">", "h", "*", "p")
METRIC_LABELS = {"mAP50_95": "mAP50:95 (%)", "mAP50": "mAP50 (%)"}


@dataclass(frozen=True)
class PlotPoint:
    dataset: str
    label: str  # what the legend shows (detector, or detector/encoding when a detector has several rows)
    detector: str
    metric: str  # "mAP50" | "mAP50_95"
    gflops: float
    value: float  # fraction 0..1
    sd: float | None
    folds: int


def pareto_front(costs: Sequence[float], values: Sequence[float]) -> list[int]:
    """Indices of the points on the front, sorted by cost: a point is on it when no other point has a cost at most
    its own and a strictly higher value (sort by cost ascending, value descending; keep running-maximum records).
    Of several points with the same cost and value only the first is kept."""
    order = sorted(range(len(costs)), key=lambda i: (costs[i], -values[i], i))
    front: list[int] = []
    best = -math.inf
    for i in order:
        if values[i] > best:
            front.append(i)
            best = values[i]
    return front


def pareto_steps(
    costs: Sequence[float], values: Sequence[float], x_max: float | None = None
) -> tuple[list[float], list[float]]:
    """Vertices of the front's step line (post-steps: the value holds until the next front point's cost)."""
    idx = pareto_front(costs, values)
    xs = [costs[i] for i in idx]
    ys = [values[i] for i in idx]
    if x_max is not None and xs and x_max > xs[-1]:
        xs.append(x_max)
        ys.append(ys[-1])
    return xs, ys


LABEL_FONT_PT = 8
LABEL_CHAR_PT = 0.56 * LABEL_FONT_PT  # average advance of a character of the default sans-serif font
LABEL_LINE_PT = 1.25 * LABEL_FONT_PT
#: where a point's label may sit, as (dx, dy) offset in points from the marker and horizontal alignment, in order of
#: preference: right and above, right and below, left and above, left and below
LABEL_SLOTS = ((6.0, 5.0, "left"), (6.0, -13.0, "left"), (-6.0, 5.0, "right"), (-6.0, -13.0, "right"))
MARKER_HALF_PT = 5.0


def _overlap(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> float:
    """Area shared by two (x0, y0, x1, y1) boxes."""
    return max(0.0, min(a[2], b[2]) - max(a[0], b[0])) * max(0.0, min(a[3], b[3]) - max(a[1], b[1]))


def place_labels(
    anchors: Sequence[tuple[float, float]],
    sizes: Sequence[tuple[float, float]],
    slots: Sequence[tuple[float, float, str]] = LABEL_SLOTS,
) -> list[tuple[float, float, str]]:
    """A slot (dx, dy, ha) for each point's label: anchors are marker positions and sizes label extents (width,
    height), both in points. Labels are placed from left to right; each takes the first slot that covers no label
    placed before it and no marker, or the slot covering the least area of them."""
    markers = [(x - MARKER_HALF_PT, y - MARKER_HALF_PT, x + MARKER_HALF_PT, y + MARKER_HALF_PT) for x, y in anchors]
    placed: list[tuple[float, float, float, float]] = []
    chosen: list[tuple[float, float, str]] = [slots[0]] * len(anchors)
    for i in sorted(range(len(anchors)), key=lambda k: (anchors[k][0], -anchors[k][1], k)):
        (x, y), (w, h) = anchors[i], sizes[i]
        best, best_cost = None, math.inf
        for dx, dy, ha in slots:
            x0 = x + dx if ha == "left" else x + dx - w
            box = (x0, y + dy, x0 + w, y + dy + h)
            cost = sum(_overlap(box, o) for o in placed) + sum(
                _overlap(box, m) for j, m in enumerate(markers) if j != i
            )
            if cost < best_cost:
                best, best_cost = ((dx, dy, ha), box), cost
            if cost == 0.0:
                break
        chosen[i] = best[0]
        placed.append(best[1])
    return chosen


def _short_labels(labels: Sequence[str]) -> dict[str, str]:
    """What a marker is labelled with: the legend's label without its bracketed model options (the legend keeps
    them), unless two labels would then read the same."""
    short = {lab: re.sub(r"\s*\[.*\]$", "", lab) for lab in labels}
    counts = Counter(short.values())
    return {lab: (v if counts[v] == 1 else lab) for lab, v in short.items()}


def _style(labels: Sequence[str]) -> dict[str, tuple[str, str]]:
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return {lab: (MARKERS[i % len(MARKERS)], cmap(i % 10)) for i, lab in enumerate(labels)}


def accuracy_vs_gflops(
    points: Sequence[PlotPoint],
    conventions: str,
    out_base: Path | None = None,
    title: str = "Accuracy versus complexity",
) -> tuple[str, list[Path]]:
    """Draw the figure; returns (SVG text, written files). ``out_base`` without suffix gets ``.png`` and ``.svg``."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter, LogLocator

    if not points:
        raise ValueError("no points to plot")
    datasets = list(dict.fromkeys(p.dataset for p in points))
    metrics = [m for m in ("mAP50_95", "mAP50") if any(p.metric == m for p in points)]
    labels = list(dict.fromkeys(p.label for p in points))
    style = _style(labels)

    with matplotlib.rc_context({"svg.hashsalt": "harness-report", "font.size": 9, "axes.titlesize": 10}):
        ncols, nrows = len(metrics), len(datasets)  # one row per dataset, one column per metric
        width = 4.8 * ncols + 1.8
        caption = textwrap.wrap(conventions, int(15 * width))
        caption_h = 0.16 * len(caption) + 0.15  # inches
        height = 3.4 * nrows + 0.7 + caption_h
        fig = Figure(figsize=(width, height), layout="constrained")
        FigureCanvasAgg(fig)
        axes = fig.subplots(nrows, ncols, squeeze=False, sharex=True)
        xs_all = [p.gflops for p in points]
        lo, hi = min(xs_all), max(xs_all)
        x_lo, x_hi = lo / 1.8, hi * 1.8
        panels: list[tuple[object, list[PlotPoint]]] = []
        for r, ds in enumerate(datasets):
            for c, metric in enumerate(metrics):
                ax = axes[r][c]
                pts = [p for p in points if p.dataset == ds and p.metric == metric]
                for p in pts:
                    marker, color = style[p.label]
                    yerr = None if p.sd is None else 100 * p.sd
                    ax.errorbar(
                        p.gflops,
                        100 * p.value,
                        yerr=yerr,
                        fmt=marker,
                        color=color,
                        markersize=8,
                        capsize=3,
                        elinewidth=1,
                        markeredgecolor="black",
                        markeredgewidth=0.6,
                        zorder=3,
                    )
                if pts:
                    sx, sy = pareto_steps([p.gflops for p in pts], [100 * p.value for p in pts], x_hi)
                    ax.step(sx, sy, where="post", linestyle="--", color="0.35", linewidth=1.2, zorder=2)
                ax.set_xscale("log")
                ax.set_xlim(x_lo, x_hi)
                ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
                ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
                ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))
                vals = [100 * p.value for p in pts] or [0.0]
                errs = [100 * (p.sd or 0.0) for p in pts] or [0.0]
                y_top = max(v + e for v, e in zip(vals, errs))
                y_bot = min(v - e for v, e in zip(vals, errs))
                pad = max(0.15 * (y_top - y_bot), 0.1 * y_top, 0.2)
                ax.set_ylim(max(0.0, y_bot - pad), min(105.0, y_top + pad))
                ax.grid(True, which="major", linestyle=":", linewidth=0.6)
                ax.set_title(f"{ds}: {METRIC_LABELS[metric].split(' ')[0]}")
                ax.set_ylabel(METRIC_LABELS[metric])
                if r == nrows - 1:
                    ax.set_xlabel("GFLOPs (log scale)")
                panels.append((ax, pts))
        handles = [
            Line2D(
                [],
                [],
                marker=style[lab][0],
                color=style[lab][1],
                linestyle="none",
                markersize=8,
                markeredgecolor="black",
                markeredgewidth=0.6,
                label=lab,
            )
            for lab in labels
        ]
        handles.append(Line2D([], [], linestyle="--", color="0.35", label="Pareto front"))
        fig.legend(handles=handles, loc="outside right upper", frameon=False, title="detector")
        fig.suptitle(title, fontsize=11)
        bottom = caption_h / height
        fig.text(0.01, 0.01, "\n".join(caption), fontsize=7.5, ha="left", va="bottom", color="0.2")
        fig.get_layout_engine().set(rect=(0, bottom, 1, 1 - bottom))
        fig.draw_without_rendering()  # lay the panels out, so that marker positions in points are final
        names = _short_labels(labels)
        to_pt = 72.0 / fig.dpi
        for ax, pts in panels:
            anchors = [tuple(v * to_pt for v in ax.transData.transform((p.gflops, 100 * p.value))) for p in pts]
            sizes = [(LABEL_CHAR_PT * len(names[p.label]), LABEL_LINE_PT) for p in pts]
            for p, (dx, dy, ha) in zip(pts, place_labels(anchors, sizes)):
                ax.annotate(
                    names[p.label],
                    (p.gflops, 100 * p.value),
                    textcoords="offset points",
                    xytext=(dx, dy),
                    ha=ha,
                    fontsize=LABEL_FONT_PT,
                    zorder=4,
                )

        return save_figure(fig, out_base, dpi=150)


def save_figure(fig: Any, out_base: Path | None, dpi: int) -> tuple[str, list[Path]]:
    """The figure as SVG text (no date: deterministic), and written as ``out_base`` .png and .svg when given."""
    buf = io.StringIO()
    fig.savefig(buf, format="svg", metadata={"Date": None})
    svg = buf.getvalue()
    written: list[Path] = []
    if out_base is not None:
        from harness.io import atomic_write_bytes, atomic_write_text

        png = io.BytesIO()
        fig.savefig(png, format="png", dpi=dpi, metadata={"Software": None})
        written.append(atomic_write_bytes(out_base.with_suffix(".png"), png.getvalue()))
        written.append(atomic_write_text(out_base.with_suffix(".svg"), svg))
    return svg, written


def inline_svg(svg: str) -> str:
    """An SVG document as an element to embed in HTML (XML declaration, DOCTYPE and comments removed)."""
    svg = re.sub(r"<\?xml[^>]*\?>", "", svg)
    svg = re.sub(r"<!DOCTYPE[^>]*>", "", svg, flags=re.S)
    svg = re.sub(r"<!--.*?-->", "", svg, flags=re.S)
    svg = re.sub(r"<metadata>.*?</metadata>", "", svg, flags=re.S)
    svg = re.sub(r'(<svg\b[^>]*?)\swidth="[^"]*"\s+height="[^"]*"', r'\1 class="figure"', svg, count=1)
    return svg.strip()
