"""The report's object-size table: scored boxes per category and SAFit size bin (``harness.summary``).

Built from the ``gt.json`` the runs were scored against (the report reads only the store): each held-out fold's
ground truth is read once, from its first finished run. Folds whose held-out images are disjoint (project-grouped
folds) are summed into one table, which is then the same table ``harness prepare`` prints when the folds cover the
dataset; folds that share images (the same test images under two annotation sources) get one table each.
"""

from __future__ import annotations

from typing import Any

from harness.errors import HarnessError
from harness.io import read_json
from harness.report.reader import StoreView, natural_key
from harness.report.tables import Column, Table, _slug, record
from harness.summary import SIZE_BINS, SizeSummary, bin_label


def _fold_ground_truth(view: StoreView, dataset: str) -> dict[str, dict[str, Any]]:
    """fold -> the COCO ground truth of its first finished run with a readable ``gt.json``."""
    out: dict[str, dict[str, Any]] = {}
    for run in sorted(view.finished_runs(dataset), key=lambda r: (natural_key(r.key.fold), str(r.key))):
        if run.key.fold in out or not run.gt_path.is_file():
            continue
        try:
            gt = read_json(run.gt_path)
        except HarnessError as exc:
            view.problem(f"{run.key}: object sizes skip {run.gt_path} ({exc})")
            continue
        if isinstance(gt, dict) and isinstance(gt.get("annotations"), list):
            out[run.key.fold] = gt
    return out


def size_table(dataset: str, summary: SizeSummary, folds: list[str]) -> Table:
    """One table: a row per category (and ``all``), a column per size bin, counts of boxes."""
    suffix = "" if len(folds) > 1 else f"-{_slug(folds[0])}"
    name = f"{_slug(dataset)}-sizes{suffix}"
    where = f"held-out folds {', '.join(folds)}" if len(folds) > 1 else f"fold {folds[0]}"
    cols = [Column("category", "Category")]
    cols += [Column(f"bin{k}", bin_label(k), "int") for k in range(len(SIZE_BINS))]
    cols += [Column("total", "Total", "int")]
    table = Table(name, f"{dataset}: scored boxes per size bin ({where})", cols)
    for row in summary.rows()[:-1]:  # the category rows and "all"; shares go into the note
        table.rows.append({"category": row[0], **{f"bin{k}": v for k, v in enumerate(row[1:-1])}, "total": row[-1]})
        for k, v in enumerate(row[1:-1]):
            table.records.append(
                record(
                    name,
                    f"boxes {SIZE_BINS[k][0]}",
                    v,
                    dataset=dataset,
                    fold=",".join(folds),
                    category=row[0],
                    unit="boxes",
                    images=summary.images,
                    instances=summary.total,
                )
            )
    table.notes.append(summary.headline() + ".")
    table.notes.append(
        "SAFit bins on the box side sqrt(w*h), px of the prepared frame; each held-out fold's "
        "scored ground truth (gt.json) counted once."
    )
    return table


def size_tables(view: StoreView, dataset: str) -> list[Table]:
    """The object-size table(s) of ``dataset`` (empty when no finished run stored its ground truth)."""
    gts = _fold_ground_truth(view, dataset)
    if not gts:
        return []
    ids = {f: {int(i["id"]) for i in gt.get("images") or []} for f, gt in gts.items()}
    seen: set[int] = set()
    disjoint = True
    for f in gts:
        disjoint = disjoint and not (ids[f] & seen)
        seen |= ids[f]
    if not disjoint:
        return [size_table(dataset, SizeSummary.of_coco(gt), [f]) for f, gt in gts.items()]
    total: SizeSummary | None = None
    for gt in gts.values():
        s = SizeSummary.of_coco(gt)
        if total is None:
            total = s
        elif s.categories == total.categories:
            total.counts += s.counts
            total.images += s.images
        else:  # different category lists cannot be summed: one table per fold
            return [size_table(dataset, SizeSummary.of_coco(g), [f]) for f, g in gts.items()]
    assert total is not None
    return [size_table(dataset, total, list(gts))]
