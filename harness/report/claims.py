"""The paper's claims, each tested on stored results and given a verdict from the data.

The claims are those of "Aligned Radiometric RGB-Thermal Fusion for UAV Facade Anomaly Screening" about its encoding
ablation (``ours`` with ``none``, ``ir8``, ``linear16``, ``c2`` on ``P4+P5``) and its four-fold comparison (ours, EME,
ICAFusion, CMA-Det). Each is tested on the entries of one dataset: the store's own when it holds them, else the
reference results read beside it (``ref:<detector>``).

Every number comes with a 95 % interval of the two-level bootstrap of ``harness.report.stats`` (training seeds, then
held-out images within each fold; images only where a fold has fewer than three seeds): the statistic is the mean
over folds of the seed-averaged metric, and a difference A - B is paired (the same image resamples for both). The
metrics resampled are mAP50, mAP50:95 and AP50 of each category (``ColumnScorer``; a resample without an instance
of a category leaves that category's AP undefined there, and it is dropped).

Verdicts do not flip with the bootstrap seed or the number of resamples: a bound decides a part only when it clears
the threshold by ``MC_Z`` (3) Monte-Carlo standard errors of its percentile (``bound_band``: the order statistics that
far either side); within them, where another seed would put the bound on the other side, the part is inconclusive.

Verdicts:

* **supported**: every part of the claim holds with its intervals on the claimed side;
* **contradicted**: some part holds the other way with its interval (e.g. the difference's interval lies entirely on
  the other side of 0);
* **inconclusive**: neither (an interval straddles the boundary);
* **not tested**: the entries the claim is about are not there, or a part about low AP ("0.000", "below 0.001",
  "near zero") rests on runs that learned nothing (``learned_nothing``: every per-category AP50 exactly 0, or the upper
  bound of the mAP50 interval below ``LEARNED_NOTHING``), where a low AP says nothing about the category.

"Near zero" is AP50 below ``NEAR_ZERO`` (0.05); the paper's own thresholds (0.000, 0.001) are tested as written.

What a verdict is about (``standin_lead``): the claims are tested on the data the store holds, at the model sizes its
runs trained. On the synthetic stand-in (``m3t-synth``, made to show each claim's mechanism) at the benchmark's budget
and sizes, a verdict says whether the claimed effect appears there; it neither confirms nor refutes the paper's
numbers on the real M3T data. A part of a claim that depends on the architecture alone (claim 6's "fewest GFLOPs") is
judged at the sizes the paper states (``PAPER_COMPLEXITY``), the accuracy parts at the sizes trained.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from harness.report.reader import REFERENCE_PREFIX, Entry, StoreView
from harness.report.stats import METRICS, BootstrapScorer, percentile_ci, two_level

SUPPORTED, CONTRADICTED, INCONCLUSIVE = "supported", "contradicted", "inconclusive"
#: The verdict of a claim whose entries are not in the store (nor in the references read beside it).
NOT_TESTED = "not tested"
NEAR_ZERO = 0.05
ABLATION_FOLD = "P4+P5"
ENCODINGS = ("none", "ir8", "linear16", "c2")
DETECTORS = ("ours", "eme", "icafusion", "cmadet")
EASY = ("window", "ac_unit", "vent")
HARD = ("crack", "efflorescence", "water_seepage")
#: The paper's four-fold mAP50:95 (mean ± SD) where it states them.
PAPER_MAP50_95 = {"icafusion": "0.191 ± 0.021", "ours": "0.168 ± 0.018", "eme": "0.131", "cmadet": "0.091"}
#: The paper's parameters (M) and GFLOPs at 640 x 640 (the detectors' ``Reference`` figures, docs/detectors.md): the
#: sizes at which the architecture-only part of claim 6 is judged.
PAPER_COMPLEXITY = {
    "ours": (11.13, 28.50),
    "eme": (46.15, 109.20),
    "icafusion": (120.24, 191.68),
    "cmadet": (33.47, 33.67),
}
#: Runs whose mAP50 interval lies below this (or whose every category has AP50 exactly 0) learned nothing: a part of
#: a claim about low AP is not tested on them.
LEARNED_NOTHING = 0.01


#: How many standard errors of a percentile's order statistic a bound must clear a threshold by to decide a verdict.
MC_Z = 3.0


@dataclass
class Interval:
    """A value with its 95 % interval; ``lo_band``/``hi_band``: the range each bound takes within ``MC_Z`` Monte-Carlo
    standard errors (another bootstrap seed or resample count moves a bound within it, ``bound_band``)."""

    value: float | None
    lo: float | None
    hi: float | None
    lo_band: tuple[float, float] | None = None
    hi_band: tuple[float, float] | None = None

    def above(self, x: float) -> bool:
        """The interval lies above ``x``, its lower bound clear of ``x`` by its Monte-Carlo error."""
        return self.lo is not None and (self.lo_band[0] if self.lo_band else self.lo) > x

    def below(self, x: float) -> bool:
        return self.hi is not None and (self.hi_band[1] if self.hi_band else self.hi) < x

    def text(self, digits: int = 3) -> str:
        if self.value is None:
            return "n/a"
        if self.lo is None or self.hi is None:
            return f"{self.value:.{digits}f}"
        return f"{self.value:.{digits}f} [{self.lo:.{digits}f}, {self.hi:.{digits}f}]"


@dataclass
class Claim:
    number: int
    text: str
    verdict: str = INCONCLUSIVE
    evidence: list[str] = field(default_factory=list)
    entries: str = ""

    def to_dict(self) -> dict[str, Any]:
        """The fields in order, ``number`` written as ``claim``."""
        return {"claim": self.number, **{k: v for k, v in asdict(self).items() if k != "number"}}

    def decide(self, checks: Iterable[tuple[str, str]]) -> None:
        """The verdict of the ``(verdict, evidence line)`` checks taken together (``combine``); their lines become
        the evidence."""
        parts = []
        for verdict, line in checks:
            parts.append(verdict)
            self.evidence.append(line)
        self.verdict = combine(parts)

    def not_tested(self, why: str) -> None:
        self.verdict = NOT_TESTED
        self.evidence.append(why)


def below(iv: Interval, x: float) -> str:
    """The verdict on "``iv`` lies below ``x``": supported, contradicted (above it) or inconclusive (straddling)."""
    return SUPPORTED if iv.below(x) else CONTRADICTED if iv.above(x) else INCONCLUSIVE


def above(iv: Interval, x: float) -> str:
    """The verdict on "``iv`` lies above ``x``"."""
    return SUPPORTED if iv.above(x) else CONTRADICTED if iv.below(x) else INCONCLUSIVE


def combine(verdicts: Sequence[str]) -> str:
    """Contradicted when a part is; supported when every part is; not tested when no part was; else inconclusive."""
    if verdicts and all(v == NOT_TESTED for v in verdicts):
        return NOT_TESTED
    if any(v == CONTRADICTED for v in verdicts):
        return CONTRADICTED
    if verdicts and all(v == SUPPORTED for v in verdicts):
        return SUPPORTED
    return INCONCLUSIVE


class ColumnScorer:
    """The claims' view of a ``BootstrapScorer`` made with per-category columns: per run, mAP50, mAP50:95 and the AP50
    of each of its ``categories`` on the original held-out images (row 0) and on the bootstrap's image resamples
    (rows 1..R, the paired comparisons' own: a run they scored is not scored again)."""

    def __init__(self, scorer: BootstrapScorer):
        self.scorer, self.seed = scorer, scorer.seed
        self.columns = [*METRICS, *(f"AP50:{c}" for c in scorer.categories)]

    def column(self, name: str) -> int:
        return self.columns.index(name)

    def fold_runs(self, entry: Entry, fold: str) -> np.ndarray:
        return self.scorer.fold_runs(entry, fold)

    def _levels(self, a: Entry, b: Entry, folds: Sequence[str]) -> list[dict[str, Any]]:
        return two_level([self.fold_runs(a, f) for f in folds], [self.fold_runs(b, f) for f in folds], folds, self.seed)

    def _observed(self, e: Entry, folds: Sequence[str], j: int) -> float | None:
        vals = []
        for f in folds:
            x = self.fold_runs(e, f)[:, 0, j]
            x = x[np.isfinite(x)]
            if x.size:
                vals.append(float(x.mean()))
        return float(np.mean(vals)) if vals else None

    def single(self, e: Entry, column: str, folds: Sequence[str]) -> Interval:
        """The entry's statistic with its two-level interval."""
        j = self.column(column)
        lv = self._levels(e, e, folds)[j]["a"]
        v = lv[np.isfinite(lv)]
        lo, hi = percentile_ci(v)
        return Interval(self._observed(e, folds, j), lo, hi, *bound_bands(v))

    def learned_nothing(self, e: Entry, folds: Sequence[str]) -> str | None:
        """Why ``e``'s runs on ``folds`` learned nothing (every category's AP50 exactly 0 on the held-out images, or
        the mAP50 interval below ``LEARNED_NOTHING``), or None when they learned something."""
        cats = [c for c in self.columns if c.startswith("AP50:")]
        seen = [v for v in (self._observed(e, folds, self.column(c)) for c in cats) if v is not None]
        if seen and all(v == 0.0 for v in seen):
            return f"{e.label} learned nothing: every category's AP50 is 0"
        m = self.single(e, "mAP50", folds)
        if m.hi is not None and m.hi < LEARNED_NOTHING:
            return f"{e.label} learned nothing: mAP50 {m.text()} below {LEARNED_NOTHING}"
        return None

    def difference(self, a: Entry, b: Entry, column: str, folds: Sequence[str]) -> Interval:
        """A - B, paired, with its two-level interval."""
        j = self.column(column)
        lv = self._levels(a, b, folds)[j]
        ok = np.isfinite(lv["a"]) & np.isfinite(lv["b"])
        v = lv["a"][ok] - lv["b"][ok]
        lo, hi = percentile_ci(v)
        oa, ob = self._observed(a, folds, j), self._observed(b, folds, j)
        return Interval(None if oa is None or ob is None else oa - ob, lo, hi, *bound_bands(v))


def bound_band(values: np.ndarray, q: float, z: float = MC_Z) -> tuple[float, float] | None:
    """The range of the ``q`` percentile of ``values`` (R bootstrap resamples) within ``z`` Monte-Carlo standard
    errors: the order statistics ``z * sqrt(R q (1 - q))`` ranks either side of its position. A verdict decided by a
    bound inside this range would flip with the bootstrap seed or resample count; one decided outside it does not."""
    v = np.sort(np.asarray(values, dtype=np.float64))
    n = v.size
    if n == 0:
        return None
    pos, se = q * (n - 1), z * float(np.sqrt(n * q * (1.0 - q)))
    return float(v[max(int(np.floor(pos - se)), 0)]), float(v[min(int(np.ceil(pos + se)), n - 1)])


def bound_bands(values: np.ndarray) -> tuple[tuple[float, float] | None, tuple[float, float] | None]:
    """``bound_band`` of the lower and upper bound of the 95 % interval."""
    return bound_band(values, 0.025), bound_band(values, 0.975)


def _find(entries: Sequence[Entry], detector: str, encoding: str | None = None) -> Entry | None:
    for e in entries:
        if e.detector == detector and (encoding is None or e.encoding == encoding):
            return e
    return None


def claim_entries(view: StoreView, dataset: str) -> tuple[str, list[Entry]]:
    """(prefix, entries): the reference results' entries when they are read beside a store trained at another budget,
    else the store's own when it holds the four detectors (or there are no references), else the references'."""
    entries = view.entries(dataset)
    own = [e for e in entries if not e.detector.startswith(REFERENCE_PREFIX)]
    refs = [e for e in entries if e.detector.startswith(REFERENCE_PREFIX)]
    if refs and not view.pairs_with_references(dataset):  # the store's runs are at another budget (the demo)
        return REFERENCE_PREFIX, refs
    if all(_find(own, d) for d in DETECTORS) or not refs:
        return "", own
    return REFERENCE_PREFIX, refs


def evaluate_claims(
    view: StoreView, dataset: str, scorer: BootstrapScorer, on_total: Callable[[int], None] | None = None
) -> tuple[list[Claim], list[str]]:
    """The six claims on ``dataset`` (see the module docstring), on the resamples of ``scorer`` (a
    ``BootstrapScorer`` made with the dataset's categories); ``on_total`` is told how many evaluations are left.
    Returns (claims, notes on what was used)."""
    prefix, entries = claim_entries(view, dataset)
    notes: list[str] = []
    source = "the reference results (ref:DETECTOR)" if prefix else "this store's runs"
    if on_total is not None:
        on_total(sum(scorer.evaluations([e], list(e.folds)) for e in entries))
    resamples, seed = scorer.resamples, scorer.seed
    cats = list(scorer.categories)
    cols = ColumnScorer(scorer)
    ours = prefix + "ours"
    claims: list[Claim] = []

    # ------------------------------------------------------------------ the ablation (claims 1-4)
    abl = {enc: _find(entries, ours, enc) for enc in ENCODINGS}
    abl_ok = all(e is not None and ABLATION_FOLD in e.folds for e in abl.values())
    folds = [ABLATION_FOLD]
    if not abl_ok:
        missing = [enc for enc, e in abl.items() if e is None or ABLATION_FOLD not in e.folds]
        why = f"no {ours} run with encoding(s) {', '.join(missing)} on {ABLATION_FOLD} in {source}"
        for n, text in ABLATION_CLAIMS:
            claims.append(Claim(n, text, NOT_TESTED, [why]))
    else:
        E = {k: v for k, v in abl.items() if v is not None}

        def has(cat: str) -> bool:
            return f"AP50:{cat}" in cols.columns

        # 1. RGB-only misses delamination (0.000) while the thermal encodings find some
        c = Claim(1, ABLATION_CLAIMS[0][1], entries=f"{ours} x 4 encodings on {ABLATION_FOLD}")
        if has("delamination"):
            none = cols.single(E["none"], "AP50:delamination", folds)
            # "0.000": below 0.0005 (what rounds to 0.000), with the interval on one side or the other
            idle = cols.learned_nothing(E["none"], folds)
            checks = [
                (NOT_TESTED, f"none: delamination AP50 {none.text()}, not tested ({idle})")
                if idle
                else (below(none, 0.0005), f"none: delamination AP50 {none.text()}")
            ]
            for enc in ("ir8", "linear16", "c2"):
                d = cols.difference(E[enc], E["none"], "AP50:delamination", folds)
                v = cols.single(E[enc], "AP50:delamination", folds)
                checks.append((above(d, 0.0), f"{enc}: {v.text()}, {enc} - none {d.text()}"))
            c.decide(checks)
        else:
            c.not_tested("no delamination instances in the held-out fold")
        claims.append(c)

        # 2. C2 gives the highest delamination AP50 of the thermal encodings
        c = Claim(2, ABLATION_CLAIMS[1][1], entries=f"{ours} on {ABLATION_FOLD}")
        if has("delamination"):
            diffs = {enc: cols.difference(E["c2"], E[enc], "AP50:delamination", folds) for enc in ("ir8", "linear16")}
            c.decide((above(d, 0.0), f"c2 - {enc}: {d.text()}") for enc, d in diffs.items())
        else:
            c.not_tested("no delamination instances in the held-out fold")
        claims.append(c)

        # 3. C2 keeps RGB-only's mAP50 while ir8 and linear16 lower it
        c = Claim(3, ABLATION_CLAIMS[2][1], entries=f"{ours} on {ABLATION_FOLD}")
        d = cols.difference(E["c2"], E["none"], "mAP50", folds)
        keeps = CONTRADICTED if d.below(0.0) else SUPPORTED  # "keeps": not significantly lower
        checks = [(keeps, f"c2 - none mAP50: {d.text()}")]
        for enc in ("ir8", "linear16"):
            d = cols.difference(E[enc], E["none"], "mAP50", folds)
            checks.append((below(d, 0.0), f"{enc} - none mAP50: {d.text()}"))
        c.decide(checks)
        claims.append(c)

        # 4. water seepage below 0.001 AP50 for every encoding
        c = Claim(4, ABLATION_CLAIMS[3][1], entries=f"{ours} x 4 encodings on {ABLATION_FOLD}")
        if has("water_seepage"):
            aps = {enc: cols.single(E[enc], "AP50:water_seepage", folds) for enc in ENCODINGS}
            idle = {enc: cols.learned_nothing(E[enc], folds) for enc in ENCODINGS}
            c.decide(
                (NOT_TESTED, f"{enc}: water seepage AP50 {v.text()}, not tested ({idle[enc]})")
                if idle[enc]
                else (below(v, 0.001), f"{enc}: water seepage AP50 {v.text()}")
                for enc, v in aps.items()
            )
        else:
            c.not_tested("no water-seepage instances in the held-out fold")
        claims.append(c)

    # ------------------------------------------------------------------ per-category ordering (claim 5)
    main = _main(entries, ours)
    c = Claim(5, OTHER_CLAIMS[0][1])
    if main is None:
        c.not_tested(f"no {ours} runs in {source}")
    else:
        folds5 = list(main.folds)
        c.entries = f"{main.label}, folds {', '.join(folds5)}"
        present = [k for k in cats if f"AP50:{k}" in cols.columns]
        ivs = {k: cols.single(main, f"AP50:{k}", folds5) for k in present}
        ranked = sorted((k for k in ivs if ivs[k].value is not None), key=lambda k: -(ivs[k].value or 0.0))
        c.evidence.append("AP50 by category: " + ", ".join(f"{k} {ivs[k].text(2)}" for k in ranked))
        easy = [k for k in EASY if k in ivs]
        rest = [k for k in ivs if k not in easy]
        top = set(ranked[: len(easy)])
        if top == set(easy) and easy and rest:
            low = min(ivs[k].lo if ivs[k].lo is not None else -1.0 for k in easy)
            high = max(ivs[k].hi if ivs[k].hi is not None else 2.0 for k in rest)
            part_a = SUPPORTED if low > high else INCONCLUSIVE
        else:
            beaten = [
                (o, k)
                for k in easy
                for o in rest
                if ivs[o].lo is not None and ivs[k].hi is not None and ivs[o].lo > ivs[k].hi
            ]
            part_a = CONTRADICTED if beaten else INCONCLUSIVE
            if beaten:
                c.evidence.append("easier than an 'easiest' category: " + ", ".join(f"{o} > {k}" for o, k in beaten))
        idle = cols.learned_nothing(main, folds5)
        if idle:  # a ranking of zeros and "near zero" on runs that found nothing say nothing about the categories
            part_a = part_b = NOT_TESTED
            c.evidence.append(idle)
        else:
            part_b = combine([below(ivs[k], NEAR_ZERO) for k in HARD if k in ivs])
        c.evidence.append(f"easiest three: {part_a}; {', '.join(HARD)} below {NEAR_ZERO}: {part_b}")
        c.verdict = combine([part_a, part_b])
    claims.append(c)

    # ------------------------------------------------------------------ four-fold comparison (claim 6)
    c = Claim(6, OTHER_CLAIMS[1][1])
    mains = {d: _main(entries, prefix + d) for d in DETECTORS}
    if any(v is None for v in mains.values()):
        missing = [d for d, v in mains.items() if v is None]
        c.not_tested(f"no runs of {', '.join(prefix + m for m in missing)} in {source}")
    else:
        M = {k: v for k, v in mains.items() if v is not None}
        common = [f for f in M["ours"].folds if all(f in e.folds for e in M.values())]
        c.entries = ", ".join(e.label for e in M.values()) + f"; folds {', '.join(common)}"
        parts = []
        c.evidence.append(f"accuracy at the sizes trained ({_sizes(M.values())})")
        for d, side in (("icafusion", above), ("eme", below), ("cmadet", below)):
            diff = cols.difference(M[d], M["ours"], "mAP50_95", common)
            parts.append(side(diff, 0.0))
            c.evidence.append(
                f"{d} - ours mAP50:95: {diff.text()} (paper: {d} {PAPER_MAP50_95[d]}, ours {PAPER_MAP50_95['ours']})"
            )
        for d in DETECTORS:
            c.evidence.append(f"{d}: mAP50:95 {cols.single(M[d], 'mAP50_95', common).text()}")
        # "fewest GFLOPs" depends on the architecture alone: judged at the sizes the paper states
        fewest = min(PAPER_COMPLEXITY, key=lambda d: PAPER_COMPLEXITY[d][1])
        parts.append(SUPPORTED if fewest == "ours" else CONTRADICTED)
        c.evidence.append(
            "fewest GFLOPs, judged at the paper's sizes (architecture only; GFLOPs at 640): "
            + ", ".join(f"{d} {PAPER_COMPLEXITY[d][1]:.2f}" for d in DETECTORS)
            + f" (fewest: {fewest})"
        )
        gf_vals = {d: _gflops(e) for d, e in M.items()}
        if all(v is not None for v in gf_vals.values()):
            small = min(gf_vals, key=lambda d: gf_vals[d] or 0.0)
            c.evidence.append(
                "not judged, the models trained here: "
                + ", ".join(f"{d} {gf_vals[d]:.2f}" for d in DETECTORS)
                + f" (fewest: {small})"
            )
        c.verdict = combine(parts)
    claims.append(c)
    notes.append(
        f"Claims tested on {source}; 95 % intervals from the two-level bootstrap ({resamples} resamples, "
        f"seed {seed}); a bound decides a part only when it clears the threshold by {MC_Z:g} Monte-Carlo standard "
        f"errors of its percentile (else inconclusive), so the verdicts do not flip with the bootstrap seed or the "
        f"resample count; 'near zero' is AP50 < {NEAR_ZERO}."
    )
    return claims, notes


def _sizes(entries: Iterable[Entry]) -> str:
    """The model sizes (``model.scale``) and training image sizes of the entries' runs, e.g. ``scale n, 192 px``."""
    scales, px = set(), set()
    for e in entries:
        for r in e.runs():
            model = r.config.get("model")
            if isinstance(model, dict) and model.get("scale"):
                scales.add(str(model["scale"]))
        if e.train_imgsz():
            px.add(int(e.train_imgsz() or 0))
    out = [f"scale {'/'.join(sorted(scales))}" if scales else "default scale"]
    if px:
        out.append("/".join(f"{p} px" for p in sorted(px)))
    return ", ".join(out)


def is_synthetic(view: StoreView, dataset: str) -> bool:
    """Whether ``dataset`` is a synthetic stand-in: its name says so (``m3t-synth``), or the reference results read
    for it record the generator that made them."""
    if "synth" in dataset.lower():
        return True
    refs = view.references_for(dataset)
    return bool(refs is not None and (refs.manifest or {}).get("generator"))


def standin_lead(view: StoreView, dataset: str) -> str:
    """What the verdicts of ``dataset`` are about: its data (the synthetic stand-in or not), the model sizes the claims'
    runs trained, and what that does and does not say about the paper."""
    prefix, entries = claim_entries(view, dataset)
    sizes = _sizes(entries)
    if is_synthetic(view, dataset):
        return (
            f"Claims tested on the synthetic stand-in data ({dataset}) at the benchmark's model sizes ({sizes}): a "
            "verdict says whether the claimed effect appears on data built to show its mechanism, at this training "
            "budget and these sizes; it neither confirms nor refutes the paper's numbers on the real M3T data. "
            "Architecture-only parts (claim 6's fewest GFLOPs) are judged at the sizes the paper states."
        )
    return (
        f"Claims tested on {dataset} at the model sizes its runs trained ({sizes}): a verdict says whether the "
        "claimed effect appears on these data at this budget and these sizes, not whether the paper's own numbers "
        "hold. Architecture-only parts (claim 6's fewest GFLOPs) are judged at the sizes the paper states."
    )


def _gflops(entry: Entry) -> float | None:
    """GFLOPs (paper convention, 640 px) of the model the entry's runs trained, as they recorded it."""
    v = entry.complexity().get("gflops")
    return float(v) if isinstance(v, (int, float)) else None


def _main(entries: Sequence[Entry], detector: str) -> Entry | None:
    """The detector's entry with the most folds (its main encoding)."""
    cands = [e for e in entries if e.detector == detector]
    return max(cands, key=lambda e: (len(e.folds), e.encoding == "c2")) if cands else None


ABLATION_CLAIMS = (
    (1, "RGB-only misses delamination (AP50 0.000) while the thermal encodings find some"),
    (2, "Of the thermal encodings, C2 gives the highest delamination AP50"),
    (3, "C2 keeps RGB-only's aggregate mAP50 while ir8 and linear16 lower it"),
    (4, "Water seepage stays below 0.001 AP50 for every encoding"),
)
OTHER_CLAIMS = (
    (5, "Windows, AC units and vents are easiest; cracks, efflorescence and water seepage near zero"),
    (6, "ICAFusion most accurate; ours next with the fewest GFLOPs; EME and CMA-Det below ours"),
)


def claims_markdown(claims: Sequence[Claim]) -> str:
    lines = ["| # | claim | verdict | evidence (value [95 % interval]) |", "| --- | --- | --- | --- |"]
    for c in claims:
        lines.append(f"| {c.number} | {c.text} | **{c.verdict}** | {'; '.join(c.evidence)} |")
    return "\n".join(lines)


def claims_records(claims: Sequence[Claim]) -> list[Mapping[str, Any]]:
    return [c.to_dict() for c in claims]


__all__ = [
    "CONTRADICTED",
    "INCONCLUSIVE",
    "NOT_TESTED",
    "SUPPORTED",
    "Claim",
    "ColumnScorer",
    "claims_markdown",
    "evaluate_claims",
    "standin_lead",
]
