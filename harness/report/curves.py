"""Training curves: per detector (and encoding), the loss components and the held-out mAP per epoch.

Read from each finished run's ``log.jsonl`` (one record per epoch, written by the trainer): ``loss`` (the mean of
each loss component over the epoch's batches) and ``metrics`` (the EMA weights scored on the held-out fold after
the epoch, the same images the run's final score uses). One row per entry of the dataset (``detector/encoding``),
two panels: the loss components, and mAP50 and mAP50:95 in %. Lines are the mean over the runs (folds x seeds) that
reached that epoch; the shaded band spans their minimum to maximum. Epochs a run did not validate (``val_period``)
or did not reach (early stopping) are left out, never drawn as zero.

matplotlib with the Agg canvas only, written as PNG and SVG like the accuracy-versus-GFLOPs figure.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

log = logging.getLogger(__name__)

COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf")
METRICS = (("mAP50", "mAP50", "#006d5b"), ("mAP50_95", "mAP50:95", "#b35900"))


@dataclass
class Curve:
    """Per-epoch values of one quantity over several runs: ``values[epoch] = [one value per run]``."""

    values: dict[int, list[float]] = field(default_factory=dict)

    def add(self, epoch: int, value: Any) -> None:
        try:
            v = float(value)
        except (TypeError, ValueError):
            return
        if math.isfinite(v):
            self.values.setdefault(int(epoch), []).append(v)

    def series(self) -> tuple[list[int], list[float], list[float], list[float]]:
        """Epochs, mean, minimum and maximum over the runs."""
        epochs = sorted(self.values)
        vals = [self.values[e] for e in epochs]
        return epochs, [sum(v) / len(v) for v in vals], [min(v) for v in vals], [max(v) for v in vals]


@dataclass
class EntryCurves:
    label: str
    runs: int = 0
    losses: dict[str, Curve] = field(default_factory=dict)
    metrics: dict[str, Curve] = field(default_factory=dict)

    @property
    def empty(self) -> bool:
        return not any(c.values for c in (*self.losses.values(), *self.metrics.values()))


def read_log(path: Path) -> list[dict[str, Any]]:
    """The records of one ``log.jsonl``; a line that is not JSON is skipped with a warning naming the file."""
    out = []
    from harness.io import read_packed_text

    for i, line in enumerate(read_packed_text(path).splitlines(), 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            log.warning("%s line %d: not JSON, skipped", path, i)
            continue
        if isinstance(rec, dict) and isinstance(rec.get("epoch"), int):
            out.append(rec)
    return out


def entry_curves(label: str, logs: Sequence[Sequence[Mapping[str, Any]]]) -> EntryCurves:
    """The curves of one entry from its runs' records (a later record of the same epoch replaces an earlier one)."""
    ec = EntryCurves(label)
    for records in logs:
        by_epoch = {int(r["epoch"]): r for r in records}
        if not by_epoch:
            continue
        ec.runs += 1
        for epoch, rec in sorted(by_epoch.items()):
            for k, v in (rec.get("loss") or {}).items():
                ec.losses.setdefault(k, Curve()).add(epoch, v)
            for k, _, _ in METRICS:
                ec.metrics.setdefault(k, Curve()).add(epoch, (rec.get("metrics") or {}).get(k))
    return ec


def collect(view: Any, dataset: str) -> tuple[list[EntryCurves], list[str]]:
    """Curves of every entry of ``dataset`` in a ``StoreView``, and the problems met (unreadable logs)."""
    out, problems = [], []
    for e in view.entries(dataset):
        logs = []
        for fold in e.folds.values():
            for run in fold.runs:
                path = run.log_path
                if not path.exists():
                    problems.append(f"{run.key}: no log.jsonl")
                    continue
                try:
                    logs.append(read_log(path))
                except OSError as exc:
                    problems.append(f"{path}: unreadable ({exc.strerror})")
        ec = entry_curves(e.label, logs)
        if not ec.empty:
            out.append(ec)
    return out, problems


def training_curves(
    curves: Sequence[EntryCurves], out_base: Path | None = None, title: str = "Training curves"
) -> tuple[str, list[Path]]:
    """Draw one row per entry (loss components | held-out mAP); returns (SVG text, written files)."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    from harness.report.plots import save_figure

    if not curves:
        raise ValueError("no curves to draw")
    with matplotlib.rc_context({"svg.hashsalt": "harness-report", "font.size": 8.5, "axes.titlesize": 9.5}):
        rows = len(curves)
        fig = Figure(figsize=(10.0, 2.3 * rows + 0.9), layout="constrained")
        FigureCanvasAgg(fig)
        axes = fig.subplots(rows, 2, squeeze=False)
        for r, ec in enumerate(curves):
            ax_loss, ax_map = axes[r]
            for i, (name, curve) in enumerate(sorted(ec.losses.items())):
                _draw(ax_loss, curve, COLORS[i % len(COLORS)], name)
            ax_loss.set_title(f"{ec.label}: training loss (mean of {ec.runs} run{'s' if ec.runs != 1 else ''})")
            ax_loss.set_ylabel("loss")
            for key, name, color in METRICS:
                curve = ec.metrics.get(key)
                if curve is not None and curve.values:
                    _draw(ax_map, curve, color, name, scale=100.0)
            ax_map.set_title(f"{ec.label}: held-out mAP (EMA weights, each epoch)")
            ax_map.set_ylabel("mAP (%)")
            ax_map.set_ylim(bottom=0.0)
            for ax in (ax_loss, ax_map):
                ax.xaxis.set_major_locator(MaxNLocator(integer=True))
                ax.grid(True, linestyle=":", linewidth=0.6)
                if ax.lines:
                    ax.legend(loc="best", fontsize=7.5, frameon=False)
                if r == rows - 1:
                    ax.set_xlabel("epoch")
        fig.suptitle(f"{title}: mean over folds (and seeds); band: min to max", fontsize=10.5)
        return save_figure(fig, out_base, dpi=120)


def _draw(ax: Any, curve: Curve, color: str, label: str, scale: float = 1.0) -> None:
    epochs, mean, lo, hi = curve.series()
    ax.plot(epochs, [scale * v for v in mean], color=color, linewidth=1.4, marker="o", markersize=2.5, label=label)
    if any(h > low for low, h in zip(lo, hi)):
        ax.fill_between(epochs, [scale * v for v in lo], [scale * v for v in hi], color=color, alpha=0.18, linewidth=0)


def curves_section(view: Any, dataset: str, out: Path | None) -> Any:
    """The report section of ``dataset``'s training curves (a ``harness.report.document.Section``)."""
    from harness.report.document import FigureOut, Section

    sec = Section("curves", "Training curves", dataset)
    curves, problems = collect(view, dataset)
    if not curves:
        sec.absent = (
            f"no finished run of {dataset} has a training log (log.jsonl); fill with `harness run "
            f"--detector D --dataset {dataset} --store {view.root}`."
        )
        return sec
    name = f"training_curves_{dataset}".replace("/", "-")
    svg, files = training_curves(curves, out / "figures" / name if out else None, f"Training curves, {dataset}")
    caption = (
        f"{dataset}: per entry (detector/encoding), the mean of each loss component over the epoch's "
        f"batches and the held-out mAP50 / mAP50:95 (%) of the EMA weights after each epoch; lines: mean over "
        f"the runs (folds x seeds) that reached the epoch; band: their minimum to maximum."
    )
    sec.figures.append(FigureOut(name, "Training curves", svg, caption, files))
    sec.notes += [f"Left out: {p}" for p in problems]
    return sec
