"""``build_report``: every table, the accuracy-versus-GFLOPs figure and the paired comparisons of a results store,
written as Markdown, CSV and one self-contained HTML page.

The report reads only the store (and, for the galleries' pixels, the prepared cache its runs name). For each dataset it
has, in order: the project-grouped table, the training budget (epochs, selection protocol, plateau), the per-category
table, the encoding ablation, object sizes (counts, and AP per size bin), paired comparisons, error types (TIDE),
confusion matrices, precision-recall curves, one gallery per detector (``harness.report.evidence``,
``harness.report.gallery``), the registration-error table and the C2 displacement table; then the accuracy-versus-GFLOPs
figure and the cross-dataset table; last, the training curves of each dataset (``harness.report.curves``). A section
whose data the store does not hold is kept and says so, with the command that would fill it. A table whose rows were not
scored on the same samples carries a loud label (and the list of differences) in every format.

Output folder (``out``)::

    report.md  report.html  report.txt          the whole report in three formats
    tidy.csv                                    every number as one long-format record, with its support
    csv/<table>.csv                             each table, wide, raw numbers (fractions)
    figures/accuracy_vs_gflops.png / .svg       the figure
    figures/training_curves_<dataset>.png / .svg
    figures/errors_<dataset>.png / .svg         error types (TIDE)
    figures/confusion_<dataset>.png / .svg      confusion matrices
    figures/pr_<dataset>.png / .svg             precision-recall curves per category
    gallery/<dataset>/<detector>/*.jpg          the galleries' thumbnails (also inline in report.html)
"""

from __future__ import annotations

import logging
import platform
import time
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from harness.errors import HarnessError
from harness.report.curves import curves_section
from harness.report.document import FigureOut, Report, Section
from harness.report.plots import PlotPoint, accuracy_vs_gflops, pareto_front
from harness.report.reader import REFERENCE_PREFIX as REF_PREFIX
from harness.report.reader import Entry, StoreView, label_notes
from harness.report.sizes import size_tables
from harness.report.stats import BootstrapScorer, PairedComparison, paired_comparison
from harness.report.tables import (
    ABLATION_CATEGORIES,
    _entry_names,
    ablation_tables,
    budget_table,
    category_table,
    cross_dataset_table,
    displacement_table,
    held_out_note,
    main_entries,
    paired_table,
    project_table,
    records_csv,
    registration_table,
    screening_route_table,
)
from harness.store import EXTERNAL, Store

log = logging.getLogger(__name__)

#: the detector whose entry the paired comparisons hold against every other detector's
REFERENCE = "ours"

FORMATS = ("md", "csv", "html")
#: Bootstrap resamples per paired comparison in a report (``harness compare-detectors`` defaults to 1000).
REPORT_RESAMPLES = 200


# -------------------------------------------------------------------------------------------------- hardware
def _hardware(entries: Sequence[Entry]) -> str:
    runs = set()
    for e in entries:
        env = e.environment()
        if env:
            dev = env.get("gpu") or env.get("device") or "?"
            runs.add(f"{dev}, {env.get('threads', '?')} thread(s), torch {env.get('torch', '?')}")
    parts = []
    if runs:
        parts.append("runs on " + "; ".join(sorted(runs)))
    return ", ".join(parts) or "hardware not recorded"


# -------------------------------------------------------------------------------------------------- sections
def _points(dataset: str, rows: Sequence[Entry]) -> list[PlotPoint]:
    names = _entry_names(rows)
    points = []
    for e in rows:
        prof = e.complexity()
        if not prof or prof.get("gflops") is None:
            continue
        agg = e.aggregate()["metrics"]
        for metric in ("mAP50_95", "mAP50"):
            m = agg.get(metric) or {}
            if m.get("mean") is None:
                continue
            points.append(
                PlotPoint(
                    dataset,
                    names[e.label],
                    e.detector,
                    metric,
                    float(prof["gflops"]),
                    float(m["mean"]),
                    m.get("sd"),
                    int(m.get("n") or 0),
                )
            )
    return points


def _remedy(labels: Sequence[str]) -> str:
    """How to give these entries a complexity: trained runs measure it when re-run; predictions scored from
    elsewhere (``external/NAME``) carry what ``harness score --params --gflops`` was given."""
    external = [lab for lab in labels if lab.startswith(EXTERNAL)]
    trained = [lab for lab in labels if not lab.startswith(EXTERNAL)]
    out = []
    if trained:
        out.append(
            f"re-run {'them' if not external else ', '.join(trained)} with `harness run ... --force` to measure it"
        )
    if external:
        out.append(
            f"re-score {'them' if not trained else ', '.join(external)} with `harness score ... --params M "
            f"--gflops G --force` to give it"
        )
    return "; ".join(out) + "."


def _conventions(view: StoreView, entries: Sequence[Entry]) -> str:
    profs = [c for c in (e.complexity() for e in entries) if c.get("gflops") is not None]
    sizes = sorted({p["imgsz"] for p in profs if p.get("imgsz")})
    run_sizes = sorted({s for s in (e.train_imgsz() for e in entries) if s})
    folds = sorted({len(e.folds) for e in entries})
    return (
        f"x: GFLOPs, 'paper' convention (BatchNorm folded, 1 multiply-add = 2 FLOPs, network up to the raw head "
        f"outputs, no decoding or NMS) at {'/'.join(f'{s}x{s}' for s in sizes) or '?'} input, batch 1, both "
        f"inputs for dual-stream detectors, log scale. y: COCO box AP in % (mAP50:95 over IoU 0.50:0.05:0.95, "
        f"mAP50 at IoU 0.50; 101 recall points, maxDets 100), mean over {'/'.join(map(str, folds))} held-out "
        f"fold(s); error bars: ± 1 sample SD over folds. Runs trained and evaluated at "
        f"{'/'.join(f'{s}x{s}' for s in run_sizes) or '?'} px; {_hardware(entries)}. Dashed: Pareto "
        f"front. Store: {view.root}."
    )


def _plot_section(view: StoreView, datasets: Sequence[str], out: Path | None) -> Section:
    sec = Section("accuracy-vs-gflops", "Accuracy versus GFLOPs")
    points: list[PlotPoint] = []
    used: list[Entry] = []
    unprofiled: list[str] = []
    for ds in datasets:
        rows, _, _ = main_entries(view.entries(ds))
        used.extend(rows)
        points.extend(_points(ds, rows))
        unprofiled.extend(e.label for e in rows if e.complexity().get("gflops") is None)
    unprofiled = list(dict.fromkeys(unprofiled))
    if not used:
        sec.absent = (
            "no finished runs in the store; fill with `harness run --detector D --dataset X --store "
            f"{view.root}` (each run measures the complexity of the model it trained)."
        )
        return sec
    if not points:
        sec.absent = f"no run recorded the complexity of its model ({', '.join(unprofiled)}); {_remedy(unprofiled)}"
        return sec
    conventions = _conventions(view, used)
    svg, files = accuracy_vs_gflops(
        points,
        conventions,
        out / "figures" / "accuracy_vs_gflops" if out else None,
        title="Held-out accuracy versus GFLOPs",
    )
    sec.figures.append(FigureOut("accuracy_vs_gflops", "Accuracy versus GFLOPs", svg, conventions, files, points))
    if unprofiled:
        sec.notes.append(
            f"Not plotted (no complexity recorded in their runs): {', '.join(unprofiled)}; {_remedy(unprofiled)}"
        )
    sec.notes += label_notes([e.notes_item(f"{e.dataset} {e.label}") for e in used if e.complexity().get("gflops")])
    return sec


def _pareto_labels(dataset: str, rows: Sequence[Entry]) -> set[str] | None:
    """The entries on the accuracy-versus-GFLOPs Pareto front, the store's own and the reference results' (``ref:``)
    each their own front."""
    refs = [e for e in rows if e.detector.startswith(REF_PREFIX)]
    own = [e for e in rows if not e.detector.startswith(REF_PREFIX)]
    if refs and own:
        parts = [_front(own), _front(refs)]
        return None if all(p is None for p in parts) else set().union(*(p or set() for p in parts))
    return _front(rows)


def _front(rows: Sequence[Entry]) -> set[str] | None:
    pts = [(e.label, e.complexity().get("gflops"), e.aggregate()["metrics"].get("mAP50_95")) for e in rows]
    pts = [(lab, g, m["mean"]) for lab, g, m in pts if g is not None and m and m.get("mean") is not None]
    if not pts:
        return None
    idx = pareto_front([p[1] for p in pts], [p[2] for p in pts])
    return {pts[i][0] for i in idx}


def _refs_option(view: Any) -> str:
    """`` --reference-results shipped`` (or the folder) when the report reads reference results, so a suggested
    ``harness compare-detectors`` command finds the ``ref:`` entries it names; empty otherwise."""
    refs = getattr(view, "references", None)
    if refs is None:
        return ""
    from harness.references import resolve

    try:
        shipped = Path(refs.root).resolve() == resolve("shipped").resolve()
    except HarnessError:
        shipped = False
    return f" --reference-results {'shipped' if shipped else refs.root}"  # siblings: read with `shipped` too


def _paired_section(
    view: StoreView,
    dataset: str,
    rows: Sequence[Entry],
    resamples: int,
    seed: int,
    progress: Any,
    workers: int = 1,
    reference: str | None = REFERENCE,
    scorer: BootstrapScorer | None = None,
) -> tuple[Section, list[PairedComparison]]:
    """Paired comparisons: the ``reference`` detector's main entry against every other detector's (the most accurate
    entry when the reference was not run), then, within one detector, its best encoding against the others.
    ``scorer``: the dataset's bootstrap scorer, shared with the claims section (made here when None)."""
    sec = Section("paired", "Paired comparisons", dataset)
    entries = view.entries(dataset)
    if view.references is not None and not view.pairs_with_references(dataset):
        # reference results trained at another budget are shown beside the store's runs, never paired with them
        entries = [e for e in entries if not e.detector.startswith(REF_PREFIX)]
        rows = [e for e in rows if not e.detector.startswith(REF_PREFIX)]
    pairs: list[tuple[Entry, Entry]] = []
    skipped: list[str] = []

    def best(candidates: Sequence[Entry]) -> Entry:
        return max(candidates, key=lambda e: (e.aggregate()["metrics"].get("mAP50_95") or {}).get("mean") or -1.0)

    if len(rows) >= 2:
        ref = (
            next((e for e in rows if e.detector == reference), None)
            or next((e for e in rows if e.detector == f"{REF_PREFIX}{reference}"), None)
            or best(rows)
        )
        pairs += [(ref, e) for e in rows if e is not ref]
    if view.references is not None and view.pairs_with_references(dataset):
        # the store's own entries on fewer folds than the references (a new detector on one fold) are paired with
        # the reference detector on the folds they share
        refs = [e for e in entries if e.detector.startswith(REF_PREFIX)]
        anchor = next((e for e in refs if e.detector == f"{REF_PREFIX}{reference}"), None) if refs else None
        anchor = anchor or (best(refs) if refs else None)
        for e in entries:
            if anchor is None or e.detector.startswith(REF_PREFIX) or any(e in p for p in pairs):
                continue
            if set(e.fold_names) & set(anchor.fold_names):
                pairs.append((e, anchor))  # A - B: the store's detector minus the reference, as compare-detectors
    by_det: dict[str, list[Entry]] = {}
    for e in entries:
        by_det.setdefault(e.detector, []).append(e)
    for det, group in by_det.items():
        if len(group) >= 2:
            common = set.intersection(*(set(e.fold_names) for e in group))
            if common:
                ref = best(group)
                pairs += [(ref, e) for e in group if e is not ref and (ref, e) not in pairs and (e, ref) not in pairs]
    if not pairs:
        sec.absent = (
            f"fewer than two detectors (or encodings) evaluated on the same folds of {dataset}; fill with "
            f"`harness run --detector OTHER --dataset {dataset} --store {view.root}`, then "
            f"`harness compare-detectors A B --dataset {dataset} --store {view.root}{_refs_option(view)}`."
        )
        return sec, []
    from harness.evaluation import SampleMismatchError

    scorer = scorer or BootstrapScorer(max(resamples, 0), seed, progress.advance if progress else None, workers)
    comps: list[PairedComparison] = []
    if progress is not None and resamples > 0:
        runs = {
            str(r.path) for a, b in pairs for f in set(a.folds) & set(b.folds) for e in (a, b) for r in e.folds[f].runs
        }
        progress.start(len(runs) * (1 + resamples), f"bootstrap {dataset}")
    for a, b in pairs:
        try:
            comps.append(paired_comparison(a, b, resamples, seed, scorer))
        except (SampleMismatchError, HarnessError) as exc:
            lines = str(exc).splitlines()
            detail = "; ".join(ln.strip() for ln in lines[1:] if ln.startswith("  "))
            skipped.append(f"{a.label} vs {b.label}: {lines[0].rstrip(':')}" + (f" ({detail})" if detail else ""))
    if comps:
        sec.tables.append(
            paired_table(
                comps,
                f"{dataset}-paired".replace("/", "-"),
                f"{dataset}: paired comparisons (A - B, percentage points; against a reference result, A is the "
                "store's detector and B the reference, as in `harness compare-detectors A B`)",
            )
        )
        _split(sec.tables[-1], lambda r: str(r.get("a", "")).startswith(REF_PREFIX))
        compared = list({id(e): e for a, b in pairs for e in (a, b)}.values())
        sec.tables[-1].notes += [n for n in [held_out_note(compared)] if n]
    if skipped:
        sec.notes += [f"Not compared: {s}" for s in skipped]
        if not comps:
            sec.absent = "no pair of entries was scored on the same samples: " + "; ".join(skipped)
    sec.notes.append(
        f"Single pairs with more resamples: `harness compare-detectors A B --dataset {dataset} --store "
        f"{view.root}{_refs_option(view)} --resamples 1000`."
    )
    return sec, comps


def _cross_section(view: StoreView, datasets: Sequence[str]) -> Section:
    sec = Section("cross-dataset", "Cross-dataset comparison")
    try:
        table = cross_dataset_table(view, datasets)
    except HarnessError as exc:
        sec.absent = f"the cross-dataset table could not be built: {exc}"
        return sec
    if not table.rows:
        sec.absent = (
            f"no finished runs in the store; fill with `harness run --detector D --dataset X --store "
            f"{view.root}` for each dataset."
        )
    else:
        with_runs = [d for d in datasets if view.entries(d)]
        if len(with_runs) < 2:
            table.notes.append(
                f"Only {', '.join(with_runs)} has runs in this store; add another dataset with "
                f"`harness run --dataset OTHER --store {view.root}` to compare across datasets."
            )
        sec.tables.append(table)
    return sec


def _read_sensing(view: StoreView, dataset: str, analysis: str) -> tuple[dict[str, Any] | None, str | None]:
    try:
        return view.sensing(dataset, analysis), None
    except HarnessError as exc:
        return None, f"unreadable: {exc}"


#: Profiles whose runs check the pipeline and do not rank detectors; a report says so beside their tables.
PIPELINE_CHECK_PROFILES = {"demo": "5 epochs at 128 px", "smoke": "10 epochs at 160 px"}


def _scale_note(view: StoreView, dataset: str) -> str | None:
    """A note when the store's runs were trained at a pipeline-check profile (``make demo``): its numbers check the
    pipeline and do not rank detectors."""
    profiles = sorted(
        {
            str((r.config.get("meta") or {}).get("profile"))
            for r in view.finished_runs(dataset)
            if not r.key.detector.startswith(REF_PREFIX) and not r.metrics.get("external")
        }
    )
    small = [p for p in profiles if p in PIPELINE_CHECK_PROFILES]
    if not small:
        return None
    what = ", ".join(f"{p} ({PIPELINE_CHECK_PROFILES[p]})" for p in small)
    refs = (
        " The reference results (ref:DETECTOR, `make benchmark`'s profile, three seeds) are shown beside them for "
        "scale."
        if view.references_for(dataset) is not None
        else " `make benchmark` runs the reference benchmark, at a scale "
        "where detectors learn, with three seeds; `harness report --reference-results shipped` shows its results "
        "beside these."
    )
    return (
        f"Scale: runs of profile {what} check that the pipeline works end to end; at this scale the detectors "
        f"learn little beyond windows, so these numbers do not rank detectors.{refs}"
    )


#: The labels of a table's two blocks when it holds the store's runs and reference results (``Table.split_blocks``).
OWN_BLOCK, REFERENCE_BLOCK = "this store's runs", "reference results (ref:DETECTOR)"


def _split(table: Any, is_reference: Callable[[Mapping[str, Any]], bool]) -> None:
    table.split_blocks(is_reference, OWN_BLOCK, REFERENCE_BLOCK)


def _budget_section(entries: Sequence[Entry], dataset: str, run_cmd: str) -> Section:
    """The training budget of each detector and encoding (``tables.budget_table``), with a sentence under it for each
    whose runs had not stopped improving and one for the runs that recorded no plateau."""
    sec = Section("budget", "Training budget", dataset)
    table, sentences = budget_table(entries, dataset)
    if table is None:
        sec.absent = f"no finished runs of {dataset}; fill with {run_cmd}."
        return sec
    _split(table, lambda r: str(r.get("detector", "")).startswith(REF_PREFIX))
    sec.tables.append(table)
    sec.notes += sentences
    return sec


def _claim_categories(view: StoreView, dataset: str) -> list[str]:
    """The categories of ``dataset``'s stored runs when they include the paper's (delamination), else none: the
    claims section is only for data with the paper's categories."""
    cats: list[str] = []
    for e in view.entries(dataset):
        for f in e.folds.values():
            cats += [c for c in (f.metrics.get("per_category") or {}) if c not in cats]
    return cats if "delamination" in cats else []


def _claims_section(view: StoreView, dataset: str, scorer: BootstrapScorer, progress: Any = None) -> Section:
    """The paper's claims tested on the data (``harness.report.claims``), on ``scorer``'s resamples (the paired
    comparisons' scorer, with the categories' AP50 columns: runs it scored already are not scored again)."""
    from harness.report.claims import claim_entries, claims_records, evaluate_claims, is_synthetic, standin_lead
    from harness.report.tables import Column, Table

    where = "on the synthetic stand-in" if is_synthetic(view, dataset) else "on these data"
    sec = Section("claims", f"The paper's claims, tested {where}", dataset)
    start = (lambda n: progress.start(n, f"claims {dataset}")) if progress is not None else None
    claims, notes = evaluate_claims(view, dataset, scorer, on_total=start)
    rows = [{"n": c.number, "claim": c.text, "verdict": c.verdict, "evidence": "; ".join(c.evidence)} for c in claims]
    table = Table(
        f"{dataset}-claims".replace("/", "-"),
        f"{dataset}: the paper's claims, tested {where} at the benchmark's model sizes",
        [
            Column("n", "#", "int"),
            Column("claim", "claim"),
            Column("verdict", "verdict"),
            Column("evidence", "evidence: value [95 % interval]"),
        ],
        rows,
        records=list(claims_records(claims)),
    )
    table.notes += [n for n in [held_out_note(claim_entries(view, dataset)[1])] if n]
    sec.tables.append(table)
    sec.lead.append(standin_lead(view, dataset))
    sec.notes += notes
    return sec


def _tiny_section(view: StoreView, dataset: str, scorer: BootstrapScorer, progress: Any = None) -> Section:
    """A dataset with RGBT-Tiny's folds (one per annotation source): the seed's table per source with paired
    intervals against ours, SAFit-AP per size bin, and the paper's four RGBT-Tiny claims (``harness.report.tiny``)."""
    from harness.report.tables import Column, Table
    from harness.report.tiny import evaluate_tiny_claims, tiny_lead, tiny_records, tiny_standin, tiny_tables

    where = "on the synthetic stand-in" if tiny_standin(view, dataset) else "on these data"
    sec = Section("rgbt-tiny", f"RGBT-Tiny: per annotation source, and the paper's claims, tested {where}", dataset)
    start = (lambda n: progress.start(n, f"rgbt-tiny claims {dataset}")) if progress is not None else None
    claims, notes = evaluate_tiny_claims(view, dataset, scorer, on_total=start)
    tables, table_notes = tiny_tables(view, dataset, scorer)
    sec.tables += tables
    sec.tables.append(
        Table(
            f"{dataset}-rgbt-tiny-claims".replace("/", "-"),
            f"{dataset}: the paper's RGBT-Tiny claims, tested {where} at the benchmark's model sizes",
            [
                Column("n", "#"),
                Column("claim", "claim"),
                Column("verdict", "verdict"),
                Column("evidence", "evidence: value [95 % interval]"),
            ],
            [
                {
                    "n": chr(ord("a") + c.number - 1),
                    "claim": c.text,
                    "verdict": c.verdict,
                    "evidence": "; ".join(c.evidence),
                }
                for c in claims
            ],
            records=list(tiny_records(claims)),
        )
    )
    sec.lead.append(tiny_lead(view, dataset))
    sec.notes += table_notes + notes
    return sec


def dataset_sections(
    view: StoreView,
    dataset: str,
    resamples: int,
    seed: int,
    ablation_categories: Sequence[str],
    progress: Any = None,
    workers: int = 1,
    reference: str | None = REFERENCE,
    out: Path | None = None,
    cache_root: str | Path | None = None,
    gallery: bool = True,
) -> tuple[list[Section], list[PairedComparison]]:
    """The sections of one dataset (see the module docstring for the order). ``out``: where figures and thumbnails
    are written (none when None); ``cache_root``: the prepared cache the galleries draw from (default
    ``$HARNESS_CACHE``); ``gallery=False`` leaves the galleries out."""
    from harness.report.evidence import evidence_sections
    from harness.report.gallery import gallery_section

    root = view.root
    entries = view.entries(dataset)
    rows, _, _ = main_entries(entries)
    shown = rows
    if view.references is not None and not view.pairs_with_references(dataset):
        # references trained at another budget: in the tables for scale, not in this store's error analysis
        shown = [e for e in rows if not e.detector.startswith(REF_PREFIX)]
    evidence_secs, size_ap, evidence = evidence_sections(dataset, shown, _entry_names(shown), out, root)
    if len(shown) < len(rows) and evidence_secs and view.references is not None:
        evidence_secs[0].notes.append(
            "The reference results' error analysis (each run's analysis.json.gz, stored beside its metrics): "
            f"`harness report --store {view.references_for(dataset).root} --resamples 0 --print` shows it (TIDE, "
            "confusion, PR "
            "curves per reference detector)."
        )
    sections: list[Section] = []
    run_cmd = f"`harness run --detector D --dataset {dataset} --folds all --store {root}`"

    sec = Section("folds", "Project-grouped folds", dataset)
    table = project_table(view, dataset, pareto=_pareto_labels(dataset, rows))
    if table is None:
        sec.absent = f"no finished runs of {dataset}; fill with {run_cmd}."
    else:
        _split(table, lambda r: str(r.get("detector", "")).startswith(REF_PREFIX))
        table.notes += [n for n in [held_out_note(rows)] if n]
        sec.tables.append(table)
    sec.notes += view.reference_notes.get(dataset, [])
    scale = _scale_note(view, dataset)
    if scale:
        sec.notes.insert(0, scale)
    unfinished = view.unfinished(dataset)
    if unfinished:
        sec.notes.append(
            "Runs in the store that are not finished (not shown): " + ", ".join(f"{k} ({s})" for k, s in unfinished)
        )
    sections.append(sec)
    sections.append(_budget_section(entries, dataset, run_cmd))

    sec = Section("categories", "Per category", dataset)
    table = category_table(view, dataset)
    if table is None:
        sec.absent = f"no finished runs of {dataset}; fill with {run_cmd}."
    else:
        sec.tables.append(table)
    sections.append(sec)

    sec = Section("ablation", "Encoding ablation", dataset)
    abl, notes = ablation_tables(view, dataset, ablation_categories)
    sec.tables += abl
    sec.notes += notes
    if not abl:
        sec.absent = (
            f"no detector of {dataset} was run with two or more encodings on a common fold; fill with "
            f"`harness ablate --detector D --dataset {dataset} --encodings none,ir8,linear16,c2 --folds F "
            f"--store {root}`." + (" " + " ".join(notes) if notes else "")
        )
    sections.append(sec)

    sec = Section("sizes", "Object sizes", dataset, tables=size_tables(view, dataset) + size_ap)
    if not sec.tables:
        sec.absent = f"no finished run of {dataset} stored its ground truth (gt.json); fill with {run_cmd}."
    elif rows and not size_ap:
        sec.notes.append(f"AP per size bin: {evidence_secs[0].absent or 'not stored'}")
    sections.append(sec)

    sec = Section("screening-route", "Accuracy under the screening route", dataset)
    table = screening_route_table(view.finished_runs(dataset), dataset)
    if table is not None:
        sec.tables.append(table)
    else:
        sec.absent = (
            f"no run of {dataset} was scored under the screening route; fill with "
            f"`harness score-route RUN_DIR` (a finished run of the store)."
        )
    if table is not None or view.sensing_stage(dataset):
        sections.append(sec)

    claim_categories = _claim_categories(view, dataset)
    scorer = BootstrapScorer(
        max(resamples, 0), seed, progress.advance if progress else None, workers, categories=claim_categories
    )
    sec, comps = _paired_section(view, dataset, rows, resamples, seed, progress, workers, reference, scorer)
    sections.append(sec)
    if claim_categories:
        sections.append(_claims_section(view, dataset, scorer, progress))
    from harness.report.tiny import is_tiny_layout

    if is_tiny_layout(view, dataset):
        sections.append(_tiny_section(view, dataset, scorer, progress))
    sections += evidence_secs
    if gallery:
        sections.append(gallery_section(dataset, evidence, out, cache_root))

    sensing = [
        _sensing_section(
            view,
            dataset,
            "registration",
            "Registration error",
            "registration_error",
            registration_table,
            f"no registration-error analysis of {dataset}",
            f"harness sensing registration-error ... --dataset {dataset} --store {root}",
            f"harness sensing registration-error --landmarks LANDMARKS.csv --homographies H.yaml --dataset {dataset} "
            f"--store {root}",
        ),
        _sensing_section(
            view,
            dataset,
            "displacement",
            "C2 under thermal displacement",
            "displacement",
            displacement_table,
            f"no displacement study of {dataset}",
            f"harness sensing displacement --dataset {dataset} --store {root}",
            f"harness sensing displacement --dataset {dataset} --store {root}",
        ),
    ]
    # sensor-level sections belong to datasets with a sensing stage; a stored analysis is shown whatever the dataset
    keep_absent = view.sensing_stage(dataset)
    sections += [s for s in sensing if keep_absent or not s.absent]
    for s in sections:  # every table with a row per detector: the store's runs and the references apart
        for t in s.tables:
            if s.key != "paired" and any("detector" in r for r in t.rows):
                _split(t, lambda r: str(r.get("detector", "")).startswith(REF_PREFIX))
    return sections, comps


def _sensing_section(
    view: StoreView,
    dataset: str,
    key: str,
    title: str,
    analysis: str,
    make_table: Callable[[Mapping[str, Any], str], Any],
    missing: str,
    rerun: str,
    fill: str,
) -> Section:
    """The section of one stored sensing analysis: its table, or why it is absent and the command that fills it."""
    sec = Section(key, title, dataset)
    result, problem = _read_sensing(view, dataset, analysis)
    if problem:
        sec.absent = f"{problem}; re-run `{rerun}`."
    elif result is None:
        sec.absent = f"{missing}; fill with `{fill}`."
    else:
        sec.tables.append(make_table(result, dataset))
    return sec


# -------------------------------------------------------------------------------------------------- the report
class _Progress:
    """The bootstrap's progress bar (``harness.progress``: on stderr, only on a terminal): one task per comparison."""

    def __init__(self, enabled: bool):
        from harness.progress import bar

        self._bar = bar("bootstrap", enabled=enabled)

    def __enter__(self) -> "_Progress":
        self._bar.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._bar.__exit__(*exc)

    def start(self, total: int, label: str) -> None:
        self._bar.restart(label, total)

    def advance(self, k: int = 1) -> None:
        self._bar.advance(k)


def build_report(
    store: Store | str | Path,
    datasets: Sequence[str] | None = None,
    out: str | Path | None = None,
    formats: Sequence[str] = FORMATS,
    resamples: int = REPORT_RESAMPLES,
    seed: int = 0,
    ablation_categories: Sequence[str] = ABLATION_CATEGORIES,
    title: str | None = None,
    progress: bool = False,
    workers: int = 1,
    reference: str | None = REFERENCE,
    cache_root: str | Path | None = None,
    gallery: bool = True,
    references: Any = None,
    references_optional: bool = False,
    references_note: str | None = None,
) -> Report:
    """Build the report of ``store`` (all its datasets unless ``datasets``) and write it under ``out``.

    ``formats``: any of ``md``, ``csv``, ``html``. ``resamples``: paired-bootstrap resamples per comparison (0: per-fold
    differences only); ``workers``: processes for the bootstrap; ``reference``: the detector compared with each
    other one (the most accurate when absent); ``cache_root``: the prepared cache the galleries draw their pixels
    from (default ``$HARNESS_CACHE``, else ``./cache``); ``gallery=False`` leaves the galleries out;
    ``references``: reference results (``harness.references.ReferenceSet``) read beside the store, as
    ``ref:<detector>`` entries; ``references_optional``: when the store's runs used other samples than theirs
    (``ReferenceMismatchError``) the report is written without them, saying why in one line
    (``unavailable_references_line``; also logged); ``references_note``: such a line from the caller (reference
    results that could not be read). Returns the ``Report`` (its ``files`` lists what was written).
    """
    bad = [f for f in formats if f not in FORMATS]
    if bad:
        raise HarnessError(f"unknown report format(s) {', '.join(bad)}; use any of {', '.join(FORMATS)}")
    view = StoreView(store, references=references)
    if references is not None and references_optional:
        from harness.references import ReferenceMismatchError

        unread = []
        for refs in view.reference_sets():  # each dataset's references on that dataset's samples
            try:
                view.finished_runs(refs.dataset)  # checks the store's runs against the references' samples
            except ReferenceMismatchError as exc:
                view.drop_references(refs.dataset)  # nothing of theirs was read: the check comes first
                unread.append(unavailable_references_line(exc))
        if unread:
            references_note = " ".join(unread)
    if references_note:
        log.warning("%s", references_note)
    available = view.datasets()
    if datasets:
        missing = [d for d in datasets if d not in available]
        if missing:
            raise HarnessError(
                f"{view.root}: nothing stored for dataset(s) {', '.join(missing)} (the store has: "
                f"{', '.join(available) or 'nothing'}); run `harness run --dataset NAME --store "
                f"{view.root}` first"
            )
        chosen = list(datasets)
    else:
        chosen = available
    if not chosen:
        raise HarnessError(
            f"{view.root}: the results store holds no finished runs or analyses; fill it with "
            f"`harness run --store {view.root} ...` first"
        )
    out_dir = Path(out) if out is not None else None
    report = Report(
        title or f"Benchmark report: {', '.join(chosen)}",
        str(view.root),
        chosen,
        time.strftime("%Y-%m-%d %H:%M:%S"),
        environment={"python": platform.python_version(), "machine": platform.machine()},
        references_note=references_note,
    )
    with _Progress(progress) as bar:
        for ds in chosen:
            sections, comps = dataset_sections(
                view, ds, resamples, seed, ablation_categories, bar, workers, reference, out_dir, cache_root, gallery
            )
            report.sections += sections
            report.comparisons += comps
    report.sections.append(_plot_section(view, chosen, out_dir))
    report.sections.append(_cross_section(view, chosen))
    report.sections += [curves_section(view, ds, out_dir) for ds in chosen]  # diagnostics, after the results
    report.problems = list(view.problems)
    if out_dir is not None:
        report.files += write_report(report, out_dir, formats)
    return report


def _top_level(text: str, sep: str) -> list[str]:
    """``text`` split at each ``sep`` outside parentheses and backticks."""
    parts, depth, quoted, start, i = [], 0, False, 0, 0
    while i < len(text):
        ch = text[i]
        if ch == "`":
            quoted = not quoted
        elif not quoted and ch in "([":
            depth += 1
        elif not quoted and ch in ")]":
            depth = max(depth - 1, 0)
        elif depth == 0 and not quoted and text.startswith(sep, i):
            parts.append(text[start:i])
            start = i = i + len(sep)
            continue
        i += 1
    return parts + [text[start:]]


def _sentences(text: str) -> list[str]:
    """``text``'s sentences: split at ``. `` before a capital letter, outside parentheses (``e.g. x`` stays)."""
    out: list[str] = []
    for part in _top_level(text, ". "):
        if out and not part[:1].isupper():
            out[-1] += ". " + part
        else:
            out.append(part)
    return [s.strip().rstrip(".") for s in out if s.strip()]


def _without_asides(text: str) -> str:
    """``text`` without its parenthesised asides (`` (...)``; ``run(s)`` stays)."""
    out, depth = [], 0
    for i, ch in enumerate(text):
        if ch == "(" and (depth or text[i - 1 : i] == " "):
            depth += 1
        elif ch == ")" and depth:
            depth -= 1
        elif not depth:
            out.append(ch)
    return " ".join("".join(out).split())


def unavailable_references_line(error: BaseException) -> str:
    """One line saying why reference results are not beside the store's runs, from the error that refused them:
    its first sentence up to the details (the runs and digests that differ, the references' description) and the fix
    it ends with (its last sentence, or the last clause of a one-sentence error). "Leave out --reference-results",
    which the report has just done, is left out of the fix."""
    sentences = _sentences(" ".join(str(error).split()))
    if not sentences:
        return "Reference results not shown."
    first = _top_level(sentences[0], "; ")
    head = _without_asides(_top_level(first[0], ": ")[0])
    if len(sentences) > 1:
        fix = _top_level(sentences[-1], ": ")[-1]
    else:
        fix = first[-1] if len(first) > 1 else ""
    fix = fix.strip().removesuffix("or leave out --reference-results").rstrip(" ,;").removesuffix(" or")
    return f"Reference results not shown: {head}" + (f"; to compare with them, {fix}." if fix else ".")


def write_report(report: Report, out: Path, formats: Sequence[str] = FORMATS) -> list[Path]:
    """Write the formats asked for (the figure files are written while building)."""
    from harness.io import atomic_write_text

    written: list[Path] = [p for s in report.sections for f in s.figures for p in f.files]
    written += [t.path for s in report.sections for g in s.galleries for t in g.thumbs if t.path is not None]
    written.append(atomic_write_text(out / "report.txt", report.to_text()))
    if "md" in formats:
        written.append(atomic_write_text(out / "report.md", report.to_markdown()))
    if "csv" in formats:
        written.append(atomic_write_text(out / "tidy.csv", records_csv(report.records())))
        for t in report.tables:
            written.append(atomic_write_text(out / "csv" / f"{t.name}.csv", t.to_csv()))
    if "html" in formats:
        from harness.report.html import render_html

        written.append(atomic_write_text(out / "report.html", render_html(report)))
    return written
