"""Paired comparisons of two detectors (or two encodings) evaluated on the same held-out images.

Two views of the same question, "is A better than B on these data?":

1. **Per-fold differences**: ``d_f = m_A(f) - m_B(f)`` for every held-out fold ``f`` both were evaluated on (each
   fold's value the mean over its seeds), summarised as mean ± sample SD and the number of folds A wins. With the
   seed's four folds this is a small sample; it shows consistency, not significance.

2. **Paired bootstrap over images** (the PASCAL VOC organisers' procedure: resample test images with replacement
   and score both methods on the same resamples)::

       for r in 1..R:
           for every fold f:  I_f^r = n_f images drawn with replacement from fold f's held-out images
                              (seeded per fold: SeedSequence([seed, crc32(f)]), so a fold's resamples do not
                              depend on which other folds take part)
           S_X^r = mean over folds f of [ mean over X's seeds of mAP(X's predictions on I_f^r) ]   for X in {A, B}
           D^r   = S_A^r - S_B^r
       95 % CI of D = [2.5th, 97.5th percentile of D^r]  (percentile bootstrap)

   ``mAP(...)`` is computed by ``harness.evaluation.evaluate`` from the run's stored ``predictions.json`` and
   ``gt.json``: the resampled ground truth and detections get **new, unique image ids** (1..n_f in draw order), so
   an image drawn twice counts twice (its objects twice in the recall denominator, its detections twice in the
   ranking), which a plain id filter would silently collapse. The statistic on the original images (identity
   resample) equals the table's mean over folds, which ties the interval to the number it qualifies. Resamples in
   which a statistic is undefined (no ground truth drawn at all) are dropped and counted (``valid``).

3. **Training seeds.** The image bootstrap holds the trained models fixed: it says how sure we are about these two
   trained models, not about the two detectors, whose retraining with another seed moves the score too (training-seed
   variance is often the larger part; Bouthillier et al., "Accounting for Variance in Machine Learning Benchmarks",
   MLSys 2021; Agarwal et al., rliable, NeurIPS 2021). So the verdict depends on the training runs behind each fold:

   * **fewer than three seeds per fold** (either side): the image interval is shown, labelled as such, and **no
     significance verdict** is given (``PairedComparison.verdict_allowed`` is False; ``SEED_NOTE`` says why);
   * **three or more seeds per fold** (both sides): a **two-level bootstrap**, within each fold::

         for r in 1..R:
             for every fold f:  seeds   s_X,f^r = k_X,f seeds drawn with replacement from X's seeds of fold f
                                images  I_f^r   (as above, shared by A and B)
             S_X^r = mean over folds f of [ mean over s in s_X,f^r of mAP(run s on I_f^r) ]
             D^r   = S_A^r - S_B^r            95 % CI: percentile; verdict: the CI excludes 0

     plus ``P(A > B)``, the probability that **a new training run** of A beats one of B (Bouthillier et al.'s
     probability of outperforming): the share of resamples in which one seed drawn per fold for each (on the
     resampled images) gives A the higher mean over folds, ties counted half; and the **seeds needed**: the fewest
     seeds per fold (for each detector) with which a difference as large as the observed one would be resolved
     (95 % interval excluding 0) in 80 % of benchmarks, the usual sample-size rule under a normal approximation:
     ``(z_0.975 + z_0.8) * sqrt(V_img + V_seed / n) <= |delta|``, with ``V_seed = sum_f (s_A,f^2 + s_B,f^2) / F^2``
     from the sample SDs over seeds within each fold and ``V_img`` the variance of D over the image resamples with
     the seeds held at their mean; none when ``V_img`` alone is too large (more held-out images are needed, not
     more seeds). Seed draws are seeded per fold and side
     (``SeedSequence([seed, crc32(f), 1, crc32("a" | "b")])``), so they do not depend on the other folds.

Both detectors must have been scored on the same samples (``check_sample_matched`` per fold, plus identical image
ids in their ``gt.json``); otherwise the paired comparison is refused: pairing different images is meaningless.

Kept in one module: resampling, scoring, the per-fold differences and the two-level interval are one procedure,
read top to bottom (``paired_comparison``).
"""

from __future__ import annotations

import contextlib
import logging
import math
import zlib
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from harness.errors import StoreError
from harness.evaluation import mean_sd
from harness.report.cells import Stat
from harness.report.reader import Entry, ResultLabel, StoreView, label_notes, marks, natural_key
from harness.textable import text_table

log = logging.getLogger(__name__)

METRICS = ("mAP50", "mAP50_95")
#: Resamples used when none are given.
DEFAULT_RESAMPLES = 1000
CONFIDENCE = 0.95
#: Training seeds per fold (on both sides) from which a comparison resamples seeds and gives a verdict.
MIN_SEEDS = 3
#: The power of the "seeds needed" rule: the share of benchmarks in which the observed difference is resolved.
POWER = 0.8
#: Bootstrap levels: images only (the trained models fixed), or training seeds and then images within each fold.
IMAGES, SEEDS_IMAGES = "images", "seeds+images"


# ---------------------------------------------------------------------------------------------- resampling
def _key(value: Any) -> Any:
    """An image id as a dict key: ``12``, ``"12"`` and ``12.0`` are the same image (as in harness.evaluation)."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return int(value)
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, str) and value.strip().lstrip("+-").isdigit():
        return int(value.strip())
    return value


@dataclass
class IndexedRun:
    """A run's ground truth and detections grouped by image, ready to be resampled many times."""

    gt: dict[str, Any]
    image_ids: list[Any]  # sorted: position i is the image that resample index i refers to
    images: dict[Any, dict[str, Any]]
    anns: dict[Any, list[dict[str, Any]]]
    dets: dict[Any, list[dict[str, Any]]]

    @classmethod
    def from_coco(cls, gt: Mapping[str, Any], detections: Sequence[Mapping[str, Any]]) -> "IndexedRun":
        images = {_key(im["id"]): im for im in gt.get("images", [])}
        anns: dict[Any, list[dict[str, Any]]] = {}
        for a in gt.get("annotations", []):
            anns.setdefault(_key(a["image_id"]), []).append(a)
        dets: dict[Any, list[dict[str, Any]]] = {}
        for d in detections:
            dets.setdefault(_key(d["image_id"]), []).append(d)
        ids = sorted(images, key=lambda k: (isinstance(k, str), k))
        return cls(dict(gt), ids, images, anns, dets)

    def resample(self, indices: Sequence[int]) -> tuple[dict[str, Any], list[dict[str, Any]]]:
        """The ground truth and detections of the images at ``indices`` (repeats allowed), renumbered 1..n."""
        return resample_coco(self, [self.image_ids[i] for i in indices])


def resample_coco(
    run: IndexedRun | Mapping[str, Any], image_ids: Sequence[Any], detections: Sequence[Mapping[str, Any]] | None = None
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """COCO ground truth and detections restricted to ``image_ids`` in that order, duplicates kept.

    Image ``k`` of the list (1-based) gets the new id ``k``; its annotations (with new unique annotation ids) and
    its detections follow it, so an image drawn twice is two images. ``run`` is an ``IndexedRun`` or a COCO GT dict
    (then ``detections`` are given). The original id is kept in ``images[k]["source_id"]``.
    """
    idx = run if isinstance(run, IndexedRun) else IndexedRun.from_coco(run, detections or [])
    images, anns, dets = [], [], []
    ann_id = 1
    for new_id, old in enumerate(image_ids, start=1):
        key = _key(old)
        if key not in idx.images:
            raise StoreError(f"image id {old!r} is not in the ground truth being resampled")
        images.append({**idx.images[key], "id": new_id, "source_id": idx.images[key]["id"]})
        for a in idx.anns.get(key, ()):
            anns.append({**a, "id": ann_id, "image_id": new_id})
            ann_id += 1
        dets.extend({**d, "image_id": new_id} for d in idx.dets.get(key, ()))
    gt = {k: v for k, v in idx.gt.items() if k not in ("images", "annotations")}
    gt.update(images=images, annotations=anns)
    return gt, dets


def bootstrap_indices(n: int, resamples: int, seed: int, stream: str = "") -> np.ndarray:
    """``[resamples, n]`` indices drawn with replacement; reproducible per (seed, stream) (stream: the fold)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), zlib.crc32(stream.encode())]))
    return rng.integers(0, n, size=(int(resamples), int(n)), dtype=np.int64)


def percentile_ci(values: np.ndarray, confidence: float = CONFIDENCE) -> tuple[float | None, float | None]:
    """Percentile bootstrap interval of the finite ``values``."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None, None
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.percentile(v, [100 * alpha, 100 * (1 - alpha)])
    return float(lo), float(hi)


@contextlib.contextmanager
def _quiet_evaluation() -> Iterator[None]:
    """Resamples without ground truth of a category are normal here: keep the evaluator's warnings out of the log."""
    logger = logging.getLogger("harness.evaluation")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


# ---------------------------------------------------------------------------------------------- scoring
def score_resamples(
    indexed: IndexedRun,
    rows: np.ndarray,
    engine: str = "faster-coco-eval",
    progress: Callable[[int], None] | None = None,
    categories: Sequence[str] = (),
) -> np.ndarray:
    """``[len(rows), 2 + len(categories)]`` mAP50, mAP50:95 and the AP50 of each of ``categories`` from
    ``harness.evaluation.evaluate`` on each resample (a row of image positions); NaN where a metric is undefined
    (no ground truth drawn, none of a category)."""
    from harness.evaluation import evaluate

    out = np.full((len(rows), len(METRICS) + len(categories)), np.nan)
    with _quiet_evaluation():
        for i, row in enumerate(rows):
            gt, dets = indexed.resample(row)
            res = evaluate(gt, dets, engine=engine)
            m = res["metrics"]
            values = [m.get(k) for k in METRICS]
            values += [(res["per_category"].get(c) or {}).get("AP50") for c in categories]
            out[i] = [np.nan if v is None else v for v in values]
            if progress:
                progress(1)
    return out


def _score_chunk(
    gt_path: str, predictions_path: str, engine: str, rows: np.ndarray, categories: Sequence[str] = ()
) -> np.ndarray:
    """Worker process: read the run's files and score a chunk of resamples."""
    from harness.io import read_json

    indexed = IndexedRun.from_coco(read_json(gt_path), read_json(predictions_path))
    return score_resamples(indexed, rows, engine, categories=categories)


class BootstrapScorer:
    """Scores entries on shared image resamples; each (run, fold) is evaluated once per resample and cached.

    ``scores(entry, folds)`` -> array ``[1 + resamples, 2 + len(categories)]``: row 0 the original images, rows 1..
    the resamples; columns mAP50, mAP50:95 (and each of ``categories``' AP50) as the mean over ``folds`` of the
    seed-averaged fold values (NaN where undefined).
    ``workers > 1`` scores chunks of resamples in that many processes (same numbers, in the same order).
    """

    def __init__(
        self,
        resamples: int = DEFAULT_RESAMPLES,
        seed: int = 0,
        progress: Callable[[int], None] | None = None,
        workers: int = 1,
        categories: Sequence[str] = (),
    ):
        if resamples < 0:
            raise ValueError("resamples must be >= 0")
        self.resamples, self.seed, self.progress = int(resamples), int(seed), progress
        self.workers = max(1, int(workers))
        #: per-category AP50 columns after mAP50 and mAP50:95 (``harness.report.claims`` tests claims on them)
        self.categories = tuple(categories)
        self._fold_ids: dict[tuple[str, str], list[Any]] = {}
        self._run_scores: dict[str, np.ndarray] = {}

    def evaluations(self, entries: Sequence[Entry], folds: Sequence[str]) -> int:
        """How many evaluator calls scoring ``entries`` on ``folds`` still needs (for progress bars)."""
        todo = 0
        for e in entries:
            for f in folds:
                todo += sum(1 for r in e.folds[f].runs if str(r.path) not in self._run_scores)
        return todo * (1 + self.resamples)

    def _load(self, run: Any) -> tuple[IndexedRun, str]:
        from harness.io import read_json

        for path in (run.gt_path, run.predictions_path):
            if not path.exists():
                raise StoreError(
                    f"{path}: missing; the paired bootstrap re-scores a run's predictions.json against "
                    f"its gt.json. Re-run this fold with `harness run ... --force` to write them"
                )
        engine = (run.metrics.get("metrics") or {}).get("engine") or "faster-coco-eval"
        return IndexedRun.from_coco(read_json(run.gt_path), read_json(run.predictions_path)), engine

    def _fold_images(self, dataset: str, fold: str, indexed: IndexedRun, where: str) -> None:
        ids = self._fold_ids.setdefault((dataset, fold), indexed.image_ids)
        if ids != indexed.image_ids:
            from harness.evaluation import SampleMismatchError

            raise SampleMismatchError(
                f"{where}: its gt.json holds other images than the other runs of fold {fold!r} "
                f"({len(indexed.image_ids)} vs {len(ids)} images); a paired comparison needs "
                f"the same held-out images"
            )

    def run_scores(self, dataset: str, fold: str, run: Any) -> np.ndarray:
        """``[1 + resamples, 2 + len(categories)]`` mAP50, mAP50:95 (and the categories' AP50) of one run on the
        original images and on each resample."""
        cache_key = str(run.path)
        if cache_key in self._run_scores:
            return self._run_scores[cache_key]
        indexed, engine = self._load(run)
        self._fold_images(dataset, fold, indexed, str(run.path))
        n = len(indexed.image_ids)
        if n == 0:
            raise StoreError(f"{run.gt_path}: no images; nothing to resample")
        rows = np.concatenate([np.arange(n)[None, :], bootstrap_indices(n, self.resamples, self.seed, fold)])
        if self.workers > 1 and len(rows) >= 4 * self.workers:
            from harness.workers import worker_pool  # workers ignore Ctrl-C: the parent stops them

            chunks = np.array_split(rows, 4 * self.workers)
            with worker_pool(self.workers) as pool:
                futures = [
                    pool.submit(_score_chunk, str(run.gt_path), str(run.predictions_path), engine, c, self.categories)
                    for c in chunks
                ]
                parts = []
                for fut, c in zip(futures, chunks):
                    parts.append(fut.result())
                    if self.progress:
                        self.progress(len(c))
            out = np.concatenate(parts)
        else:
            out = score_resamples(indexed, rows, engine, self.progress, self.categories)
        self._run_scores[cache_key] = out
        return out

    def fold_runs(self, entry: Entry, fold: str) -> np.ndarray:
        """``[seeds, 1 + resamples, 2]``: each seed's run of ``fold`` on the original images and each resample."""
        return np.stack([self.run_scores(entry.dataset, fold, r) for r in entry.folds[fold].runs])

    def scores(self, entry: Entry, folds: Sequence[str]) -> np.ndarray:
        # NaN stays NaN: an undefined resample is dropped
        per_fold = [np.mean(self.fold_runs(entry, f), axis=0) for f in folds]
        return np.mean(np.stack(per_fold), axis=0)


# ---------------------------------------------------------------------------------------------- results
#: What a comparison with fewer than ``MIN_SEEDS`` training seeds per fold says in place of a verdict.
SEED_NOTE = (
    "{seeds}: this compares trained models, not detectors (the spread between training runs is not "
    "measured), so no significance verdict is given; the image interval holds the trained models fixed. "
    "Train both with --seeds 0,1,2 (or more) for the two-level bootstrap over seeds and images."
)


@dataclass
class BootstrapResult:
    """Paired bootstrap of one metric: observed values, the difference and its percentile CI.

    ``level``: ``IMAGES`` (the trained models fixed) or ``SEEDS_IMAGES`` (the two-level bootstrap). The last four
    fields are set by the two-level bootstrap only: ``p_a_beats_b``, the probability that a new training run of A
    beats one of B; ``seeds_needed``, the seeds per fold at which the observed spread resolves the difference (None:
    not with these images, ``seeds_note`` says why); ``seed_sd``, the pooled sample SD over seeds within a fold of
    each side (``{"a", "b"}``)."""

    metric: str
    a: float | None
    b: float | None
    delta: float | None
    ci_low: float | None
    ci_high: float | None
    a_ci: tuple[float | None, float | None]
    b_ci: tuple[float | None, float | None]
    resamples: int
    valid: int
    seed: int
    #: fraction of valid resamples with D <= 0 (small: A is rarely not better)
    p_not_better: float | None
    confidence: float = CONFIDENCE
    level: str = IMAGES
    p_a_beats_b: float | None = None
    seeds_needed: int | None = None
    seeds_note: str | None = None
    seed_sd: dict[str, float | None] = field(default_factory=dict)

    @property
    def excludes_zero(self) -> bool:
        return self.ci_low is not None and self.ci_high is not None and (self.ci_low > 0 or self.ci_high < 0)


@dataclass
class FoldDifference:
    metric: str
    folds: list[str]
    a: list[float | None]
    b: list[float | None]
    diffs: list[float | None]
    stat: Stat
    wins: int


@dataclass
class PairedComparison:
    dataset: str
    a: str
    b: str
    folds: list[str]
    images: int
    instances: int
    fold_differences: dict[str, FoldDifference]
    bootstrap: dict[str, BootstrapResult] | None = None
    notes: list[str] = field(default_factory=list)
    #: A's and B's labels on the compared folds (``{"a": [...], "b": [...]}``, ``harness.report.reader``), their
    #: marks per fold and what the marks mean: empty when neither rests on a labelled result
    labels: dict[str, list[ResultLabel]] = field(default_factory=dict)
    fold_marks: dict[str, list[str]] = field(default_factory=dict)
    label_notes: list[str] = field(default_factory=list)
    #: training seeds behind each fold of each side (``{"a": [k per fold], "b": [...]}``)
    seeds: dict[str, list[int]] = field(default_factory=dict)

    @property
    def training_runs(self) -> int:
        """The fewest training seeds behind a fold of either side (0 when unknown)."""
        counts = [k for side in self.seeds.values() for k in side]
        return min(counts) if counts else 0

    @property
    def verdict_allowed(self) -> bool:
        """Whether the comparison may say that A and B differ: both sides trained with ``MIN_SEEDS`` or more seeds
        in every fold (the two-level bootstrap)."""
        return self.training_runs >= MIN_SEEDS

    @property
    def seed_note(self) -> str | None:
        """Why there is no verdict (``SEED_NOTE``), or None when one is allowed."""
        if self.verdict_allowed:
            return None
        k = self.training_runs
        what = "one training seed per fold" if k <= 1 else f"only {k} training seeds per fold"
        return SEED_NOTE.format(seeds=what[0].upper() + what[1:])

    def verdict(self, metric: str) -> str | None:
        """``"yes"``/``"no"``: whether the two-level interval of ``metric`` excludes 0; None where no verdict is
        allowed or there is no bootstrap."""
        b = (self.bootstrap or {}).get(metric)
        if b is None or not self.verdict_allowed or b.level != SEEDS_IMAGES:
            return None
        return "yes" if b.excludes_zero else "no"

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        for key in ("labels", "fold_marks", "label_notes"):  # the keys appear only where there is something to say
            d.pop(key)
        if self.label_notes:
            d["labels"] = {
                side: [{"kind": lab.kind, "text": lab.text, "runs": list(lab.runs)} for lab in labs]
                for side, labs in self.labels.items()
            }
            d["fold_marks"], d["label_notes"] = self.fold_marks, self.label_notes
        d["training_runs"] = self.training_runs
        d["verdict"] = {k: self.verdict(k) for k in METRICS} if self.verdict_allowed and self.bootstrap else None
        d["seed_note"] = self.seed_note
        return d

    def to_text(self) -> str:
        """Per-fold table and bootstrap summary, aligned."""
        pct = lambda v: "-" if v is None or not math.isfinite(v) else f"{100 * v:.1f}"  # noqa: E731
        pp = lambda v: "-" if v is None or not math.isfinite(v) else f"{100 * v:+.1f}"  # noqa: E731
        header = [
            "fold",
            f"{self.a} mAP50",
            f"{self.b} mAP50",
            "Δ mAP50",
            f"{self.a} mAP50:95",
            f"{self.b} mAP50:95",
            "Δ mAP50:95",
        ]
        f50, f95 = self.fold_differences["mAP50"], self.fold_differences["mAP50_95"]
        ma, mb = (self.fold_marks.get(k) or [""] * len(self.folds) for k in ("a", "b"))

        def mark(text: str, m: str) -> str:
            return f"{text} {m}" if m and text != "-" else text

        rows = [
            [
                f,
                mark(pct(f50.a[i]), ma[i]),
                mark(pct(f50.b[i]), mb[i]),
                pp(f50.diffs[i]),
                mark(pct(f95.a[i]), ma[i]),
                mark(pct(f95.b[i]), mb[i]),
                pp(f95.diffs[i]),
            ]
            for i, f in enumerate(self.folds)
        ]
        sd = lambda s: "" if s.sd is None else f" ± {100 * s.sd:.1f}"  # noqa: E731
        rows.append(["mean ± SD", "", "", pp(f50.stat.mean) + sd(f50.stat), "", "", pp(f95.stat.mean) + sd(f95.stat)])
        seeds = "/".join(str(k) for k in sorted(set(self.seeds.get("a", []) + self.seeds.get("b", [])))) or "?"
        out = [
            f"{self.dataset}: {self.a} (A) vs {self.b} (B), {len(self.folds)} held-out fold(s), {self.images} "
            f"images, {self.instances} instances, {seeds} training seed(s) per fold; AP in %, Δ = A - B in "
            f"percentage points",
            text_table(header, rows),
            "",
            f"A has the higher mAP50:95 in {f95.wins} of {len(self.folds)} fold(s).",
        ]
        if self.bootstrap:
            b0 = next(iter(self.bootstrap.values()))
            if b0.level == SEEDS_IMAGES:
                out.append(
                    f"two-level bootstrap (training seeds, then images, within each fold): {b0.resamples} "
                    f"resamples ({b0.valid} valid), seed {b0.seed}, percentile {int(100 * b0.confidence)} % CI "
                    f"of the mean over folds"
                )
                bh = [
                    "metric",
                    "A",
                    "A 95% CI",
                    "B",
                    "B 95% CI",
                    "Δ (A - B)",
                    "Δ 95% CI",
                    "P(A > B), new run",
                    "seeds needed",
                    "CI excludes 0",
                ]
            else:
                out.append(
                    f"paired bootstrap over images, the trained models fixed: {b0.resamples} resamples "
                    f"({b0.valid} valid), seed {b0.seed}, percentile {int(100 * b0.confidence)} % CI of the "
                    f"mean over folds"
                )
                bh = ["metric", "A", "A 95% CI", "B", "B 95% CI", "Δ (A - B)", "Δ 95% CI (images)"]
            brows = []
            for key, b in self.bootstrap.items():
                row = [
                    key.replace("_", ":"),
                    pct(b.a),
                    f"[{pct(b.a_ci[0])}, {pct(b.a_ci[1])}]",
                    pct(b.b),
                    f"[{pct(b.b_ci[0])}, {pct(b.b_ci[1])}]",
                    pp(b.delta),
                    f"[{pp(b.ci_low)}, {pp(b.ci_high)}]",
                ]
                if b.level == SEEDS_IMAGES:
                    row += [
                        "-" if b.p_a_beats_b is None else f"{b.p_a_beats_b:.2f}",
                        "-" if b.seeds_needed is None else str(b.seeds_needed),
                        self.verdict(key) or "-",
                    ]
                brows.append(row)
            out.append(text_table(bh, brows))
            notes = [
                f"{k.replace('_', ':')}: seeds needed: {b.seeds_note}"
                for k, b in self.bootstrap.items()
                if b.seeds_note
            ]
            out += notes
        else:
            out.append("no bootstrap (resamples = 0)")
        if self.seed_note:
            out.append(self.seed_note)
        out += self.label_notes
        out += self.notes
        from harness.textable import fit_text

        return fit_text("\n".join(out))


def fold_differences(a: Entry, b: Entry, folds: Sequence[str]) -> dict[str, FoldDifference]:
    """Per-fold differences A - B of mAP50 and mAP50:95 (each fold's value averaged over its seeds)."""
    out = {}
    for key in METRICS:
        va = [a.folds[f].metrics["metrics"].get(key) for f in folds]
        vb = [b.folds[f].metrics["metrics"].get(key) for f in folds]
        diffs = [None if x is None or y is None else float(x) - float(y) for x, y in zip(va, vb)]
        stat = Stat.from_mean_sd(mean_sd(diffs))
        wins = sum(1 for d in diffs if d is not None and d > 0)
        out[key] = FoldDifference(key, list(folds), va, vb, diffs, stat, wins)
    return out


def common_folds(a: Entry, b: Entry) -> list[str]:
    folds = sorted(set(a.fold_names) & set(b.fold_names), key=natural_key)
    if not folds:
        raise StoreError(
            f"{a.label} (folds {', '.join(a.fold_names)}) and {b.label} (folds {', '.join(b.fold_names)}) "
            f"share no held-out fold of {a.dataset!r}; a paired comparison needs the same held-out images"
        )
    return folds


#: What a refused pair can do: a paired comparison has no meaning on different images, so there is no option to
#: force it; the side-by-side table can show the rows, labelled.
PAIR_HINT = (
    "A paired comparison needs both scored on the same held-out images: re-run them on the same prepared "
    "split. To see their rows side by side, labelled as not sample-matched: "
    "`harness compare --datasets DATASET --allow-mismatched` or `harness report`."
)


def check_pair_matched(a: Entry, b: Entry, folds: Sequence[str]) -> None:
    """Refuse (``SampleMismatchError``) a pair scored on different samples in any of ``folds``."""
    from harness.evaluation import check_sample_matched

    for f in folds:
        check_sample_matched(
            {f"{a.label}@{f}": a.folds[f].metrics, f"{b.label}@{f}": b.folds[f].metrics}, hint=PAIR_HINT
        )
        for e in (a, b):
            if e.folds[f].seed_mismatch:
                from harness.evaluation import SampleMismatchError

                raise SampleMismatchError(
                    f"{e.label} fold {f}: its seeds were scored on different samples ({e.folds[f].seed_mismatch})"
                )


# ---------------------------------------------------------------------------------------------- two levels
def _z(confidence: float) -> float:
    from statistics import NormalDist

    return NormalDist().inv_cdf(1.0 - (1.0 - confidence) / 2.0)


def seeds_needed(
    delta: float | None,
    v_img: float,
    v_seed: float,
    confidence: float = CONFIDENCE,
    power: float = POWER,
    limit: int = 10_000,
) -> tuple[int | None, str | None]:
    """The fewest seeds per fold ``n`` with ``(z_conf + z_power) * sqrt(v_img + v_seed / n) <= |delta|`` (module
    docstring), or (None, why not)."""
    from statistics import NormalDist

    if delta is None or not math.isfinite(delta) or delta == 0.0:
        return None, "no difference to resolve"
    if not (math.isfinite(v_img) and math.isfinite(v_seed)):
        return None, "the spread is undefined (a metric without a value in some run)"
    z = _z(confidence) + NormalDist().inv_cdf(power)
    room = (abs(delta) / z) ** 2 - v_img
    if room <= 0.0:
        return None, (
            f"not with these held-out images: their sampling spread alone (SD {100 * math.sqrt(v_img):.2f} "
            f"points) is too large for a difference of {100 * abs(delta):.2f} points; more images are "
            f"needed"
        )
    n = max(1, math.ceil(v_seed / room - 1e-9)) if v_seed > 0.0 else 1
    if n > limit:
        return None, f"more than {limit} seeds per fold"
    return n, None


def _seed_draws(k: int, resamples: int, seed: int, fold: str, side: str) -> np.ndarray:
    """``[resamples, k]`` seed positions drawn with replacement for one side of one fold."""
    rng = np.random.default_rng(
        np.random.SeedSequence([int(seed), zlib.crc32(fold.encode()), 1, zlib.crc32(side.encode())])
    )
    return rng.integers(0, k, size=(int(resamples), int(k)), dtype=np.int64)


def two_level(
    a_runs: Sequence[np.ndarray],
    b_runs: Sequence[np.ndarray],
    folds: Sequence[str],
    seed: int,
    confidence: float = CONFIDENCE,
) -> list[dict[str, Any]]:
    """The two-level bootstrap (module docstring) from per-run scores.

    ``a_runs[f]``, ``b_runs[f]``: ``[seeds, 1 + R, metrics]`` scores of each seed's run of fold ``folds[f]`` on the
    original images (row 0) and on the fold's image resamples (rows 1..R, the same for every run of the fold).
    Returns, per metric, the resampled A, B and D (two levels), D with the seeds held at their mean (images only),
    the single-run differences behind ``P(A > B)`` and the seed variances."""
    resamples = a_runs[0].shape[1] - 1
    cols = np.arange(1, resamples + 1)
    sa, sb, fixed, single, v_seed = [], [], [], [], []
    for f, fold in enumerate(folds):
        xa, xb = np.asarray(a_runs[f], dtype=np.float64), np.asarray(b_runs[f], dtype=np.float64)
        da = _seed_draws(xa.shape[0], resamples, seed, fold, "a")
        db = _seed_draws(xb.shape[0], resamples, seed, fold, "b")
        pa = xa[da, cols[:, None]]  # [R, k_a, metrics]: each resample's drawn seeds on its images
        pb = xb[db, cols[:, None]]
        sa.append(pa.mean(axis=1))
        sb.append(pb.mean(axis=1))
        single.append(pa[:, 0] - pb[:, 0])
        fixed.append(xa[:, 1:].mean(axis=0) - xb[:, 1:].mean(axis=0))
        v_seed.append(_seed_var(xa[:, 0]) + _seed_var(xb[:, 0]))
    n_folds = len(folds)
    out = []
    for j in range(a_runs[0].shape[2]):
        out.append(
            {
                "a": np.mean([s[:, j] for s in sa], axis=0),
                "b": np.mean([s[:, j] for s in sb], axis=0),
                "fixed": np.mean([s[:, j] for s in fixed], axis=0),
                "single": np.mean([s[:, j] for s in single], axis=0),
                "v_seed": float(sum(v[j] for v in v_seed)) / n_folds**2,
                "seed_sd": {
                    side: _pooled_sd([x[:, 0, j] for x in runs]) for side, runs in (("a", a_runs), ("b", b_runs))
                },
            }
        )
    return out


def _seed_var(x: np.ndarray) -> np.ndarray:
    """Per metric, the sample variance over the seeds (rows) of ``x``; NaN with a single seed (no warning)."""
    if x.shape[0] < 2:
        return np.full(x.shape[1:], np.nan)
    return x.var(axis=0, ddof=1)


def _pooled_sd(per_fold: Sequence[np.ndarray]) -> float | None:
    """Square root of the mean over folds of the sample variance over seeds (None with fewer than two seeds)."""
    vs = [float(np.var(v, ddof=1)) for v in per_fold if len(v) >= 2 and np.all(np.isfinite(v))]
    return math.sqrt(sum(vs) / len(vs)) if vs else None


def paired_comparison(
    a: Entry,
    b: Entry,
    resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
    scorer: BootstrapScorer | None = None,
    folds: Sequence[str] | None = None,
) -> PairedComparison:
    """Per-fold differences and (``resamples > 0``) the paired bootstrap of A - B: over images when either side has
    fewer than ``MIN_SEEDS`` seeds in a fold, else over seeds and images; see the module docstring."""
    if a.dataset != b.dataset:
        raise StoreError(f"{a.label} is on {a.dataset!r} and {b.label} on {b.dataset!r}: pair runs of one dataset")
    folds = list(folds) if folds is not None else common_folds(a, b)
    check_pair_matched(a, b, folds)
    images = sum(a.folds[f].images for f in folds)
    instances = sum(a.folds[f].instances for f in folds)
    comp = PairedComparison(a.dataset, a.label, b.label, folds, images, instances, fold_differences(a, b, folds))
    comp.seeds = {k: [len(e.folds[f].runs) for f in folds] for k, e in zip("ab", (a, b))}
    shown = [a.restricted(folds), b.restricted(folds)]
    comp.label_notes = label_notes([e.notes_item() for e in shown])
    if comp.label_notes:
        comp.labels = {k: e.labels for k, e in zip("ab", shown)}
        comp.fold_marks = {k: [marks(e.folds[f].labels) for f in folds] for k, e in zip("ab", shown)}
    if resamples <= 0:
        return comp
    scorer = scorer or BootstrapScorer(resamples, seed)
    if scorer.resamples != resamples or scorer.seed != seed:
        raise ValueError("the scorer was made for other resamples or another seed")
    sa, sb = scorer.scores(a, folds), scorer.scores(b, folds)
    levels = None
    if comp.verdict_allowed:
        levels = two_level(
            [scorer.fold_runs(a, f) for f in folds], [scorer.fold_runs(b, f) for f in folds], folds, seed
        )
    boot: dict[str, BootstrapResult] = {}
    for j, key in enumerate(METRICS):
        obs_a, obs_b = sa[0, j], sb[0, j]
        if levels is None:
            da, db = sa[1:, j], sb[1:, j]
        else:
            da, db = levels[j]["a"], levels[j]["b"]
        valid = np.isfinite(da) & np.isfinite(db)
        d = da[valid] - db[valid]
        lo, hi = percentile_ci(d)
        res = BootstrapResult(
            key,
            _f(obs_a),
            _f(obs_b),
            _f(obs_a - obs_b),
            lo,
            hi,
            percentile_ci(da[valid]),
            percentile_ci(db[valid]),
            resamples,
            int(valid.sum()),
            seed,
            float(np.mean(d <= 0)) if d.size else None,
        )
        if levels is not None:
            lv = levels[j]
            one = lv["single"][np.isfinite(lv["single"])]
            fixed = lv["fixed"][np.isfinite(lv["fixed"])]
            res.level = SEEDS_IMAGES
            res.p_a_beats_b = float(np.mean(one > 0) + 0.5 * np.mean(one == 0)) if one.size else None
            v_img = float(np.var(fixed, ddof=1)) if fixed.size >= 2 else 0.0
            res.seeds_needed, res.seeds_note = seeds_needed(res.delta, v_img, lv["v_seed"])
            res.seed_sd = lv["seed_sd"]
        boot[key] = res
        for label, entry, observed in ((a.label, a, res.a), (b.label, b, res.b)):
            stored = _stored_mean(entry, folds, key)
            if stored is not None and observed is not None and abs(stored - observed) > 1e-6:
                comp.notes.append(
                    f"note: re-scored {key} of {label} ({observed:.4f}) differs from its stored "
                    f"metrics ({stored:.4f}); were the runs evaluated with other settings?"
                )
    comp.bootstrap = boot
    return comp


def _stored_mean(entry: Entry, folds: Sequence[str], key: str) -> float | None:
    """The stored metric of ``entry`` as the bootstrap statistic defines it: mean over folds of the seed means."""
    values = [entry.folds[f].metrics["metrics"].get(key) for f in folds]
    return None if any(v is None for v in values) else mean_sd(values)["mean"]


def _f(x: Any) -> float | None:
    return None if x is None or not math.isfinite(float(x)) else float(x)


def compare_detectors(
    store: Any,
    dataset: str,
    a: str,
    b: str,
    resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
    progress: Callable[[int], None] | None = None,
    on_total: Callable[[int], None] | None = None,
    workers: int = 1,
) -> PairedComparison:
    """``harness compare-detectors``: A and B are ``DETECTOR`` or ``DETECTOR/ENCODING`` on ``dataset``."""
    view = store if isinstance(store, StoreView) else StoreView(store)
    ea, eb = view.entry(dataset, a), view.entry(dataset, b)
    if ea.label == eb.label:
        raise StoreError(f"{a!r} and {b!r} name the same runs ({ea.label}); compare two different entries")
    folds = common_folds(ea, eb)
    check_pair_matched(ea, eb, folds)
    scorer = BootstrapScorer(resamples, seed, progress, workers)
    if on_total is not None:
        on_total(scorer.evaluations([ea, eb], folds) if resamples > 0 else 0)
    return paired_comparison(ea, eb, resamples, seed, scorer, folds)
