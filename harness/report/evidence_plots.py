"""Figures of the error analysis (``harness.report.evidence``): error types, confusion matrices, PR curves.

Each detector keeps one colour in every figure (tab10, in the order of the project-grouped table). matplotlib with
the Agg canvas only, written as PNG and SVG like the accuracy-versus-GFLOPs figure (``plots.save_figure``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from harness.evaluation.analysis import ERROR_LABELS, ERROR_TYPES, SPECIAL_TYPES
from harness.report.plots import save_figure

#: panels per row of the confusion-matrix and PR figures
PER_ROW = 4


def colours(names: Sequence[str]) -> dict[str, Any]:
    """One tab10 colour per detector, in table order (the same in every figure of the report)."""
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return {n: cmap(i % 10) for i, n in enumerate(names)}


def _style() -> Any:
    """The figures' matplotlib settings (deterministic SVG, the training curves' font sizes)."""
    import matplotlib

    return matplotlib.rc_context({"svg.hashsalt": "harness-report", "font.size": 8.5, "axes.titlesize": 9.5})


def _figure(width: float, height: float) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def tide_figure(
    rows: Sequence[tuple[str, Mapping[str, Any]]], order: Sequence[str], out_base: Path | None, title: str
) -> tuple[str, list[Path]]:
    """Grouped bars: per error type (and the two bounds), one bar per detector, ± SD over folds.

    ``rows``: (detector, {type: Stat}); values are fractions, drawn in points."""

    types = [*ERROR_TYPES, *SPECIAL_TYPES]
    col = colours(order)
    with _style():
        fig = _figure(max(7.0, 0.55 * len(types) * max(1, len(rows)) ** 0.5 + 3.0), 3.4)
        ax = fig.subplots()
        n = max(1, len(rows))
        width = 0.8 / n
        x = np.arange(len(types), dtype=float)
        for i, (name, stats) in enumerate(rows):
            means = [100 * (stats[t].mean or 0.0) if stats[t].mean is not None else np.nan for t in types]
            sds = [100 * stats[t].sd if stats[t].sd is not None else 0.0 for t in types]
            ax.bar(
                x + (i - (n - 1) / 2) * width,
                means,
                width,
                yerr=sds,
                color=col[name],
                label=name,
                error_kw={"elinewidth": 0.8, "capsize": 2},
                edgecolor="black",
                linewidth=0.4,
            )
        ax.axvline(len(ERROR_TYPES) - 0.5, color="0.6", linestyle=":", linewidth=1.0)
        ax.set_xticks(x, [ERROR_LABELS[t] for t in types])
        ax.set_ylabel("mAP50 gained (points)")
        ax.set_ylim(bottom=0.0)
        ax.grid(True, axis="y", linestyle=":", linewidth=0.6)
        ax.text(
            len(ERROR_TYPES) - 0.45, ax.get_ylim()[1] * 0.97, "bounds", va="top", ha="left", fontsize=7.5, color="0.35"
        )
        ax.legend(loc="upper left", fontsize=7.5, frameon=False, ncols=min(4, n))
        ax.set_title(f"{title}: fix one error type alone (TIDE)")
        return save_figure(fig, out_base, dpi=120)


def confusion_figure(
    mats: Sequence[tuple[str, Sequence[str], np.ndarray, int]], out_base: Path | None, title: str
) -> tuple[str, list[Path]]:
    """One heat map per detector: rows predicted, columns ground truth (both ending with background), each cell
    with its count, coloured by its share of the ground-truth column."""
    with _style():
        k = max(len(m[1]) for m in mats)
        cols = min(PER_ROW if k <= 6 else 2, len(mats))  # many categories: larger matrices, two to a row
        rows = math.ceil(len(mats) / cols)
        side = 0.34 * k + 1.5
        fig = _figure(side * cols + 0.6, side * rows + 0.5)
        axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
        image = None
        for ax, (name, labels, matrix, seeds) in zip(axes, mats):
            totals = matrix.sum(axis=0, keepdims=True)
            share = np.divide(matrix, totals, out=np.zeros_like(matrix), where=totals > 0)
            image = ax.imshow(share, cmap="Blues", vmin=0.0, vmax=1.0, interpolation="nearest")
            integer = np.allclose(matrix, np.round(matrix))
            for i in range(matrix.shape[0]):
                for j in range(matrix.shape[1]):
                    v = matrix[i, j]
                    if v == 0:
                        continue
                    text = f"{int(round(v))}" if integer else f"{v:.1f}"
                    ax.text(
                        j,
                        i,
                        text,
                        ha="center",
                        va="center",
                        fontsize=6.5 if k > 6 else 7.5,
                        color="white" if share[i, j] > 0.55 else "black",
                    )
            short = [_short(c) for c in labels]
            ax.set_xticks(range(len(labels)), short, rotation=60, ha="right", fontsize=7)
            ax.set_yticks(range(len(labels)), short, fontsize=7)
            ax.set_xlabel("ground truth")
            ax.set_ylabel("predicted")
            ax.set_title(name + (f" (mean of {seeds} seeds)" if seeds > 1 else ""))
        for ax in axes[len(mats) :]:
            ax.set_axis_off()
        if image is not None:
            fig.colorbar(image, ax=list(axes[: len(mats)]), shrink=0.6, label="share of the ground-truth column")
        fig.suptitle(f"{title}: IoU 0.50, operating point, summed over folds", fontsize=10)
        return save_figure(fig, out_base, dpi=120)


def _short(name: str, limit: int = 12) -> str:
    return name if len(name) <= limit else name[: limit - 1] + "…"


def pr_figure(
    curves: Mapping[str, Sequence[Any]], order: Sequence[str], out_base: Path | None, title: str
) -> tuple[str, list[Path]]:
    """One panel per category, every detector's mean curve on it (``evidence.Curve``), its AP50 in the legend."""
    col = colours(order)
    cats = list(curves)
    with _style():
        cols = min(PER_ROW, len(cats))
        rows = math.ceil(len(cats) / cols)
        fig = _figure(3.1 * cols + 0.4, 2.7 * rows + 0.5)
        axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False, sharex=True, sharey=True)).ravel()
        for ax, cat in zip(axes, cats):
            for c in curves[cat]:
                ax.step(
                    c.recall,
                    c.precision,
                    where="post",
                    color=col.get(c.name),
                    linewidth=1.4,
                    label=f"{c.name} {100 * c.ap50:.1f}",
                )
            ax.set_title(cat)
            ax.set_xlim(0.0, 1.0)
            ax.set_ylim(0.0, 1.02)
            ax.grid(True, linestyle=":", linewidth=0.6)
            ax.legend(loc="upper right", fontsize=6.5, frameon=False, title="AP50 (%)", title_fontsize=6.5)
        for ax in axes[len(cats) :]:
            ax.set_axis_off()
        for ax in axes[(rows - 1) * cols :]:
            ax.set_xlabel("recall")
        for ax in axes[::cols]:
            ax.set_ylabel("precision")
        fig.suptitle(title, fontsize=10)
        return save_figure(fig, out_base, dpi=120)
