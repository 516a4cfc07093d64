"""RGBT-Tiny: the seed's table per annotation source and the paper's four RGBT-Tiny claims, tested on stored results.

A dataset read with the RGBT-Tiny protocol has one held-out fold per annotation source: ``test-T`` (thermal-source
boxes, ``dataset.gt=thermal``) and ``test-RGB`` (visible-source boxes). For such a dataset the report adds:

* **the seed's table** (``tiny_tables``): per source and method, the held-out images and instances, mAP50 and
  mAP50:95 (seed-averaged), each baseline's paired difference from ``ours`` with its 95 % interval (the two-level
  bootstrap of ``harness.report.stats``, on the same image resamples for both), and beside it SAFit-AP and AP per
  SAFit size bin (``metrics.json`` ``metrics.safit``, the evaluation's ``eval.matching: safit`` block). Every row of a
  source is checked to be scored on the same samples (``check_sample_matched``: image ids and instances); a source
  whose rows are not is labelled and gets no paired intervals. The seed's own table could not say that (its
  loaders kept different test images).
* **the four claims** (``evaluate_tiny_claims``), with the verdict words and interval rules of
  ``harness.report.claims`` (a bound decides only when clear of the threshold by its Monte-Carlo error; "not tested"
  when an entry is absent or learned nothing).

Thresholds, in mAP50:95 (the paper's gaps: thermal-source EME 0.249 vs ours 0.060; visible-source ours 0.195 vs
EME 0.213 and ICAFusion 0.208): "well below" is a paired difference whose interval lies above ``WELL_BELOW`` (5
points); "close" is a paired difference whose interval lies within +-``CLOSE`` (5 points).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from harness.report.cells import Interval as CellInterval
from harness.report.cells import Stat
from harness.report.claims import (
    CONTRADICTED,
    INCONCLUSIVE,
    NOT_TESTED,
    SUPPORTED,
    Claim,
    ColumnScorer,
    Interval,
    above,
    bound_bands,
    claim_entries,
)
from harness.report.reader import Entry, StoreView
from harness.report.stats import BootstrapScorer, percentile_ci

#: The held-out fold of each annotation source, as the rgbt-tiny adapter names them.
SOURCES = {"test-T": "T", "test-RGB": "RGB"}
THERMAL, VISIBLE = "test-T", "test-RGB"
DETECTORS = ("ours", "eme", "icafusion", "cmadet")
#: The ablation of claim (d): ours with no thermal channel, the intensity local-contrast proxy, the 8-bit frame.
ENCODINGS = ("none", "proxy8", "ir8")
#: "Well below": the difference's interval above this (mAP50:95, 5 points).
WELL_BELOW = 0.05
#: "Close": the difference's interval within +- this (mAP50:95, 5 points).
CLOSE = 0.05
#: SAFit's size bins as ``metrics.safit`` names them, with their column headers.
SAFIT_BINS = (("AP_et", "AP et"), ("AP_t", "AP t"), ("AP_s", "AP s"), ("AP_m", "AP m"), ("AP_l", "AP l"))

TINY_CLAIMS = (
    (
        "a",
        "With thermal-source annotations ours is well below EME, ICAFusion and CMA-Det ('well below': each "
        f"baseline - ours mAP50:95 interval above {WELL_BELOW * 100:.0f} points)",
    ),
    (
        "b",
        "With visible-source annotations ours comes close to EME and ICAFusion ('close': each baseline - ours "
        f"mAP50:95 interval within +-{CLOSE * 100:.0f} points)",
    ),
    (
        "c",
        "CMA-Det drops with visible-source annotations (its thermal-source - visible-source mAP50:95 interval above 0)",
    ),
    (
        "d",
        "For tiny targets the proxy channel does no better than no thermal channel (ours proxy8 - none mAP50:95 "
        "not above 0), while the 8-bit thermal frame the proxy is computed from does better (ir8 - proxy8 above 0)",
    ),
)


def is_tiny_layout(view: StoreView, dataset: str) -> bool:
    """Whether ``dataset``'s entries use the RGBT-Tiny folds (one per annotation source)."""
    return any(f in SOURCES for e in view.entries(dataset) for f in e.folds)


def _main(entries: Sequence[Entry], detector: str, fold: str) -> Entry | None:
    """The detector's entry on ``fold`` with the most folds (its grid encoding, not an ablation's)."""
    cands = [e for e in entries if e.detector == detector and fold in e.folds]
    return max(cands, key=lambda e: (len(e.folds), e.encoding not in ("none", "ir8"))) if cands else None


def _find(entries: Sequence[Entry], detector: str, encoding: str, fold: str) -> Entry | None:
    return next((e for e in entries if e.detector == detector and e.encoding == encoding and fold in e.folds), None)


def _matched(rows: Sequence[Entry], fold: str) -> str | None:
    """None when every row's runs of ``fold`` were scored on the same samples, else the label saying what differs."""
    from harness.evaluation import check_sample_matched

    items = {f"{e.label}/seed{r.key.seed}": r.metrics for e in rows for r in e.folds[fold].runs}
    return check_sample_matched(items, allow=True) if len(items) > 1 else None


def _safit(entry: Entry, fold: str, key: str) -> float | None:
    """``metrics.safit[key]`` of the entry's runs of ``fold``, averaged over seeds (None when not recorded)."""
    vals = [((r.metrics.get("metrics") or {}).get("safit") or {}).get(key) for r in entry.folds[fold].runs]
    got = [float(v) for v in vals if isinstance(v, (int, float)) and v >= 0]  # COCO writes -1 for an empty bin
    return float(np.mean(got)) if got else None


def tiny_tables(
    view: StoreView, dataset: str, scorer: BootstrapScorer, prefix: str | None = None
) -> tuple[list[Any], list[str]]:
    """(the seed's table and the SAFit table of ``dataset``, notes). ``prefix``: ``ref:`` to show the reference
    results' entries, ``""`` the store's own (default: as the claims choose, ``claim_entries``)."""
    from harness.report.tables import Column, Table, _merge_warning

    chosen, entries = claim_entries(view, dataset)
    prefix = chosen if prefix is None else prefix
    cols = ColumnScorer(scorer)
    main = Table(
        f"{dataset}-rgbt-tiny",
        f"{dataset}: per annotation source (held-out mAP, %; Δ vs {prefix}ours in points [95 % CI])",
        [
            Column("source", "GT"),
            Column("method", "Method"),
            Column("seeds", "Seeds", "int"),
            Column("images", "Images", "int"),
            Column("instances", "Instances", "int"),
            Column("mAP50", "mAP50", "pct"),
            Column("mAP50_95", "mAP50:95", "pct"),
            Column("d50", "Δ mAP50", "pp"),
            Column("d5095", "Δ mAP50:95", "pp"),
        ],
    )
    sizes = Table(
        f"{dataset}-rgbt-tiny-safit",
        f"{dataset}: SAFit-AP and AP per SAFit size bin (%, seed-averaged)",
        [
            Column("source", "GT"),
            Column("method", "Method"),
            Column("safit50", "SAFit-AP50", "pct"),
            Column("safit5095", "SAFit-AP50:95", "pct"),
            *(Column(k, head, "pct") for k, head in SAFIT_BINS),
        ],
    )
    notes: list[str] = []
    for fold, source in SOURCES.items():
        rows = [e for d in DETECTORS if (e := _main(entries, prefix + d, fold)) is not None]
        if not rows:
            continue
        label = _matched(rows, fold)
        _merge_warning(main, label, [f"GT {source}: {label}"] if label else [])
        _merge_warning(sizes, label, [f"GT {source}: {label}"] if label else [])
        ours = next((e for e in rows if e.detector == prefix + "ours"), None)
        for e in rows:
            f = e.folds[fold]
            m = f.metrics.get("metrics") or {}
            name = e.label + ("" if label is None else " !")
            row: dict[str, Any] = {
                "source": source,
                "method": name,
                "seeds": len(f.seeds),
                "images": f.images,
                "instances": f.instances,
                "mAP50": Stat(m.get("mAP50"), None, len(f.seeds)),
                "mAP50_95": Stat(m.get("mAP50_95"), None, len(f.seeds)),
            }
            if ours is not None and e is not ours and label is None:
                for key, col in (("mAP50", "d50"), ("mAP50_95", "d5095")):
                    d = cols.difference(e, ours, key, [fold])
                    row[col] = CellInterval(d.value, d.lo, d.hi)
            main.rows.append(row)
            srow: dict[str, Any] = {"source": source, "method": name}
            srow["safit50"], srow["safit5095"] = _safit(e, fold, "mAP50"), _safit(e, fold, "mAP50_95")
            srow.update({k: _safit(e, fold, k) for k, _ in SAFIT_BINS})
            sizes.rows.append(srow)
    main.notes.append(
        "The seed's layout, every row of a source scored on the same held-out images and instances (checked: image "
        "ids and instance counts; a source whose rows differ is marked ! and gets no intervals). Δ = method - ours, "
        "paired: the two-level bootstrap (training seeds, then held-out images) on the same resamples for both "
        f"({scorer.resamples} resamples, seed {scorer.seed}). GT: T thermal-source, RGB visible-source boxes."
    )
    sizes.notes.append(
        "SAFit-AP: RGBT-Tiny's scale-adaptive matching (eval.matching: safit); AP et/t/s/m/l: SAFit-AP50:95 in its "
        "size bins (extremely tiny, tiny, small, medium, large); '-' where a bin holds no instance or the runs were "
        "not evaluated with SAFit."
    )
    if not any(r.get("safit50") is not None for r in sizes.rows):
        notes.append(
            "No run recorded SAFit-AP (they were evaluated with eval.matching: iou); `--set eval.matching=safit` "
            "records it, as the RGBT-Tiny protocol and the rgbt-tiny-synth suite do."
        )
    return [t for t in (main, sizes) if t.rows], notes


# ---------------------------------------------------------------------------------------------------- claims
def _within(iv: Interval, half: float) -> str:
    """The verdict on "``iv`` lies within +-``half``"."""
    if iv.above(-half) and iv.below(half):
        return SUPPORTED
    if iv.above(half) or iv.below(-half):
        return CONTRADICTED
    return INCONCLUSIVE


def _unpaired(cols: ColumnScorer, a: Entry, fa: str, b: Entry, fb: str, column: str) -> Interval:
    """``a`` on fold ``fa`` minus ``b`` on fold ``fb`` (other annotations: not paired), each side's two-level
    resamples drawn independently (``b``'s shuffled against ``a``'s)."""
    j = cols.column(column)
    la = cols._levels(a, a, [fa])[j]["a"]
    lb = cols._levels(b, b, [fb])[j]["a"]
    la, lb = la[np.isfinite(la)], lb[np.isfinite(lb)]
    n = min(la.size, lb.size)
    rng = np.random.default_rng(cols.seed)
    v = la[:n] - rng.permutation(lb)[:n]
    lo, hi = percentile_ci(v)
    oa, ob = cols._observed(a, [fa], j), cols._observed(b, [fb], j)
    return Interval(None if oa is None or ob is None else oa - ob, lo, hi, *bound_bands(v))


def evaluate_tiny_claims(
    view: StoreView, dataset: str, scorer: BootstrapScorer, on_total: Callable[[int], None] | None = None
) -> tuple[list[Claim], list[str]]:
    """The four RGBT-Tiny claims on ``dataset`` (module docstring), on ``scorer``'s resamples. Returns (claims,
    notes)."""
    prefix, entries = claim_entries(view, dataset)
    source = "the reference results (ref:DETECTOR)" if prefix else "this store's runs"
    if on_total is not None:
        on_total(sum(scorer.evaluations([e], list(e.folds)) for e in entries))
    cols = ColumnScorer(scorer)
    claims: list[Claim] = []
    texts = dict(TINY_CLAIMS)

    def idle(e: Entry, fold: str) -> str | None:
        return cols.learned_nothing(e.restricted([fold]), [fold])

    def against_ours(letter: str, fold: str, others: Sequence[str], judge: Callable[[Interval], str]) -> Claim:
        c = Claim(0, texts[letter])
        c.entries = f"GT {SOURCES[fold]}: " + ", ".join(prefix + d for d in ("ours", *others))
        found = {d: _main(entries, prefix + d, fold) for d in ("ours", *others)}
        missing = [prefix + d for d, e in found.items() if e is None]
        if missing:
            c.not_tested(f"no runs of {', '.join(missing)} on {fold} in {source}")
            return c
        ours = found["ours"]
        assert ours is not None
        if _matched([e for e in found.values() if e is not None], fold):
            c.not_tested(f"the entries on {fold} were not scored on the same samples")
            return c
        checks = []
        for d in others:
            e = found[d]
            assert e is not None
            why = idle(e, fold) or idle(ours, fold)
            diff = cols.difference(e, ours, "mAP50_95", [fold])
            line = f"{d} - ours mAP50:95 on {fold}: {diff.text()}"
            checks.append((NOT_TESTED, f"{line}, not tested ({why})") if why else (judge(diff), line))
        for d, e in found.items():
            if e is not None:
                c.evidence.append(f"{d}: mAP50:95 {cols.single(e, 'mAP50_95', [fold]).text()}")
        evidence, c.evidence = c.evidence, []
        c.decide(checks)
        c.evidence += evidence
        return c

    claims.append(against_ours("a", THERMAL, ("eme", "icafusion", "cmadet"), lambda d: above(d, WELL_BELOW)))
    claims.append(against_ours("b", VISIBLE, ("eme", "icafusion"), lambda d: _within(d, CLOSE)))

    c = Claim(0, texts["c"], entries=f"{prefix}cmadet on {THERMAL} and {VISIBLE}")
    t, v = _main(entries, prefix + "cmadet", THERMAL), _main(entries, prefix + "cmadet", VISIBLE)
    if t is None or v is None:
        c.not_tested(f"no runs of {prefix}cmadet on both {THERMAL} and {VISIBLE} in {source}")
    else:
        why = idle(t, THERMAL) or idle(v, VISIBLE)
        d = _unpaired(cols, t, THERMAL, v, VISIBLE, "mAP50_95")
        line = f"T - RGB mAP50:95: {d.text()} (unpaired: other annotations)"
        c.decide([(NOT_TESTED, f"{line}, not tested ({why})") if why else (above(d, 0.0), line)])
    claims.append(c)

    c = Claim(0, texts["d"], entries=f"{prefix}ours x {', '.join(ENCODINGS)} on {THERMAL}")
    E = {enc: _find(entries, prefix + "ours", enc, THERMAL) for enc in ENCODINGS}
    missing = [enc for enc, e in E.items() if e is None]
    if missing:
        c.not_tested(f"no {prefix}ours run with encoding(s) {', '.join(missing)} on {THERMAL} in {source}")
    elif _matched([e for e in E.values() if e is not None], THERMAL):
        c.not_tested(f"the ablation's entries on {THERMAL} were not scored on the same samples")
    else:
        A = {k: e for k, e in E.items() if e is not None}
        whys = [w for w in (idle(A[k], THERMAL) for k in ENCODINGS) if w]
        proxy = cols.difference(A["proxy8"], A["none"], "mAP50_95", [THERMAL])
        frame = cols.difference(A["ir8"], A["proxy8"], "mAP50_95", [THERMAL])
        no_better = CONTRADICTED if proxy.above(0.0) else SUPPORTED  # "no better": not significantly higher
        lines = [f"proxy8 - none mAP50:95: {proxy.text()}", f"ir8 - proxy8 mAP50:95: {frame.text()}"]
        if whys:
            c.decide((NOT_TESTED, f"{line}, not tested ({'; '.join(whys)})") for line in lines)
        else:
            c.decide([(no_better, lines[0]), (above(frame, 0.0), lines[1])])
        c.evidence += [f"{k}: mAP50:95 {cols.single(A[k], 'mAP50_95', [THERMAL]).text()}" for k in ENCODINGS]
    claims.append(c)
    for c, (letter, _) in zip(claims, TINY_CLAIMS):
        c.number = ord(letter) - ord("a") + 1
    notes = [
        f"Claims tested on {source}; 95 % intervals from the two-level bootstrap ({scorer.resamples} resamples, seed "
        f"{scorer.seed}), paired within a source; a bound decides a part only when clear of the threshold by its "
        "Monte-Carlo error (else inconclusive)."
    ]
    rising = _still_rising(entries)
    if rising:
        notes.append(
            f"Trained short of a plateau (the training-budget table): {'; '.join(rising)}. A verdict that rests on "
            "these entries compares detectors at this budget, and may change with more epochs."
        )
    return claims, notes


def _still_rising(entries: Sequence[Entry]) -> list[str]:
    """Per entry with runs still improving when they stopped (``run_still_rising``), '<label> N of M runs'."""
    from harness.report.tables import run_still_rising

    out = []
    for e in entries:
        flags = [f for f in (run_still_rising(r.metrics) for r in e.runs()) if f is not None]
        if any(flags):
            out.append(f"{e.label} {sum(flags)} of {len(flags)} runs")
    return out


def tiny_standin(view: StoreView, dataset: str) -> bool:
    """Whether ``dataset``'s runs (or the reference results read for it) were made from a synthetic set: a
    ``synth.json`` in the data folder they name, or a generator in the references' manifest."""
    refs = view.references_for(dataset)
    if refs is not None and (refs.manifest or {}).get("generator"):
        return True
    for e in view.entries(dataset):
        for r in e.runs():
            root = (r.config.get("dataset") or {}).get("root") if isinstance(r.config, dict) else None
            if root and (Path(str(root)) / "synth.json").is_file():
                return True
    return False


def tiny_lead(view: StoreView, dataset: str) -> str:
    """What the RGBT-Tiny verdicts are about."""
    if tiny_standin(view, dataset):
        return (
            f"The paper's RGBT-Tiny claims, tested on the RGBT-Tiny-like synthetic stand-in ({dataset} read from "
            "`harness synth --family rgbt-tiny` data) at the benchmark's model sizes: a verdict says whether the "
            "claimed effect appears on data built to show its mechanism (extended thermal blobs, registration "
            "offsets between the annotation sources), at this budget; it neither confirms nor refutes the paper's "
            "numbers on the real RGBT-Tiny release."
        )
    return (
        f"The paper's RGBT-Tiny claims, tested on {dataset} at the model sizes its runs trained: a verdict says "
        "whether the claimed effect appears on these data at this budget, not whether the paper's own numbers hold."
    )


def tiny_records(claims: Sequence[Claim]) -> list[Mapping[str, Any]]:
    return [{**c.to_dict(), "claim": TINY_CLAIMS[c.number - 1][0]} for c in claims]


__all__ = [
    "CLOSE",
    "SOURCES",
    "TINY_CLAIMS",
    "WELL_BELOW",
    "evaluate_tiny_claims",
    "is_tiny_layout",
    "tiny_lead",
    "tiny_tables",
]
