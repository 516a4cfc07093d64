"""How often the claims' verdicts flip with the bootstrap seed, at several resample counts, on the shipped references.

For each resample count R and each bootstrap seed 0..S-1, the six claims of ``harness.report.claims`` are evaluated on
the shipped reference results (``references/m3t-synth-benchmark``, read beside an empty store, as ``harness report
--reference-results shipped`` reads them) by ``evaluate_claims`` itself. A claim's flip rate at R is the share of
seeds whose verdict differs from the most common verdict at that R (0 %: every seed gives the same verdict).

Scoring 57 runs on 2000 image resamples for 20 seeds through the report's evaluator would take hours on two cores, so
the resamples are scored by a weighted form of the same COCO computation: the matching of every detection at every
IoU threshold is pycocotools' ``evaluateImg`` on the original held-out images (an image drawn twice is matched
twice the same way), and a resample is a count per image: the accumulation (precision envelope, 101 recall points,
categories without ground truth left out) weighs each image's detections and ground truth by its count. The
resamples are the report's own (``bootstrap_indices``, the same seed and fold streams), and the claims, the
two-level bootstrap and the intervals are the report's code. ``--check`` first scores seed 0 at ``--check-resamples``
through the report's evaluator (``BootstrapScorer``) and prints the largest difference from the weighted scores,
with the report's wall time (the anchor of the time column: ``report s`` is that time scaled by R).

    .venv/bin/python benchmarks/verdict_stability.py [--seeds 20] [--resamples 50,200,1000,2000] [--check]

Prints the table claim x resamples -> flip rate (and the verdicts seen) and the time each column took.
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import on_path  # noqa: E402

on_path()

from harness.report.stats import METRICS, BootstrapScorer, bootstrap_indices  # noqa: E402

IOU_THRS = np.linspace(0.5, 0.95, 10)
REC_THRS = np.linspace(0.0, 1.00, 101)
MAX_DETS = 100
SHORT = {"supported": "supp", "contradicted": "contra", "inconclusive": "incon", "not tested": "n/t"}


class _Matched:
    """One run's detections matched on its original held-out images, per category, in the accumulation's order."""

    def __init__(self, gt: dict[str, Any], predictions: list[dict[str, Any]], categories: tuple[str, ...]):
        import contextlib
        import io

        from pycocotools.coco import COCO
        from pycocotools.cocoeval import COCOeval

        with contextlib.redirect_stdout(io.StringIO()):
            cg = COCO()
            cg.dataset = gt
            cg.createIndex()
            cd = cg.loadRes(predictions) if predictions else COCO()
            ev = COCOeval(cg, cd, "bbox")
            ev.params.iouThrs = IOU_THRS
            ev.evaluate()
        self.image_ids = sorted(ev.params.imgIds)
        pos = {i: k for k, i in enumerate(self.image_ids)}
        names = {c["id"]: c["name"] for c in gt["categories"]}
        self.cat_ids = sorted(ev.params.catIds)
        self.by_name = {names[c]: k for k, c in enumerate(self.cat_ids)}
        self.columns = [self.by_name.get(c) for c in categories]
        n_area = len(ev.params.areaRng)
        n_img = len(self.image_ids)
        self.cats: list[tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]] = []
        for k in range(len(self.cat_ids)):
            evs = [ev.evalImgs[k * n_area * n_img + i] for i in range(n_img)]  # area "all"
            npig = np.zeros(n_img, dtype=np.int64)
            scores, imgs, tps, fps = [], [], [], []
            for e in evs:
                if e is None:
                    continue
                i = pos[e["image_id"]]
                npig[i] = int(np.count_nonzero(e["gtIgnore"] == 0))
                d = e["dtMatches"][:, :MAX_DETS]
                ig = e["dtIgnore"][:, :MAX_DETS].astype(bool)
                scores.append(np.asarray(e["dtScores"][:MAX_DETS], dtype=np.float64))
                imgs.append(np.full(d.shape[1], i, dtype=np.int64))
                tps.append((d != 0) & ~ig)
                fps.append((d == 0) & ~ig)
            if scores:
                s = np.concatenate(scores)
                order = np.argsort(-s, kind="mergesort")
                img = np.concatenate(imgs)[order]
                tp = np.concatenate(tps, axis=1)[:, order]
                fp = np.concatenate(fps, axis=1)[:, order]
            else:
                img = np.zeros(0, dtype=np.int64)
                tp = fp = np.zeros((len(IOU_THRS), 0), dtype=bool)
            onehot = np.zeros((n_img, img.size), dtype=np.int64)
            onehot[img, np.arange(img.size)] = 1
            per_t = []
            for t in range(len(IOU_THRS)):
                # only the true positives' points matter: a false positive's precision is below the point before
                # it, so it never raises the envelope, and a recall level is first reached at a true positive
                at = np.flatnonzero(tp[t])
                tpc = np.cumsum(onehot * tp[t], axis=1)[:, at].astype(np.float64)  # [images, TPs]
                fpc = np.cumsum(onehot * fp[t], axis=1)[:, at].astype(np.float64)
                per_t.append((tpc, fpc))
            self.cats.append((npig.astype(np.float64), per_t))

    def score(self, rows: np.ndarray) -> np.ndarray:
        """``[len(rows), 2 + categories]`` as ``harness.report.stats.score_resamples`` returns them."""
        n_img = len(self.image_ids)
        w = np.stack([np.bincount(r, minlength=n_img) for r in rows]).astype(np.float64)  # [B, images]
        ap = np.stack([_weighted_ap(w, *c) for c in self.cats], axis=-1)  # [B, T, K] (NaN: no ground truth)
        out = np.full((len(rows), len(METRICS) + len(self.columns)), np.nan)
        ok = np.isfinite(ap[:, 0, :])
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            out[:, 0] = np.where(ok.any(1), np.nanmean(np.where(ok, ap[:, 0, :], np.nan), 1), np.nan)
            out[:, 1] = np.where(ok.any(1), np.nanmean(np.nanmean(ap, 1), 1), np.nan)
        for j, k in enumerate(self.columns):
            if k is not None:
                out[:, 2 + j] = ap[:, 0, k]
        return out


def _weighted_ap(w: np.ndarray, npig_img: np.ndarray, per_t: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """``[B, T]`` COCO AP of one category on B resamples given as image counts ``w`` ([B, images])."""
    b = w.shape[0]
    npig = w @ npig_img  # [B]
    ap = np.full((b, len(per_t)), np.nan)
    has = npig > 0
    if not has.any():
        return ap
    # the fewest true positives whose float recall tp / npig reaches each threshold, as the accumulation compares
    n = np.maximum(npig, 1.0)[:, None]
    need = np.ceil(REC_THRS[None, :] * n)
    need = np.where((need - 1) / n >= REC_THRS[None, :], need - 1, need)
    need = np.where(need / n >= REC_THRS[None, :], need, need + 1)
    for t, (tpm, fpm) in enumerate(per_t):
        d = tpm.shape[1]
        if d == 0:
            ap[has, t] = 0.0
            continue
        tpc, fpc = w @ tpm, w @ fpm  # [B, TPs]: cumulative counts at each true positive
        pr = tpc / (tpc + fpc + np.spacing(1))
        env = np.maximum.accumulate(pr[:, ::-1], axis=1)[:, ::-1]
        big = float(tpc.max() + need.max() + 2)
        offs = np.arange(b, dtype=np.float64)[:, None] * big
        idx = np.searchsorted((tpc + offs).ravel(), (need + offs).ravel(), side="left").reshape(b, -1)
        idx -= np.arange(b)[:, None] * d
        q = np.where(idx < d, np.take_along_axis(env, np.minimum(idx, d - 1), axis=1), 0.0)
        ap[has, t] = q.mean(1)[has]
    return ap


class WeightedScorer(BootstrapScorer):
    """A ``BootstrapScorer`` whose runs are scored by ``_Matched`` (the same resamples, the same columns). The
    matching of a run is kept across seeds; a seed's scores for R resamples are the first R of its largest count."""

    matched: dict[str, _Matched] = {}
    largest: dict[tuple[str, int], np.ndarray] = {}

    def __init__(self, resamples: int, seed: int, categories: tuple[str, ...], largest: int):
        super().__init__(resamples, seed, categories=categories)
        self.largest_r = largest

    def run_scores(self, dataset: str, fold: str, run: Any) -> np.ndarray:
        key = str(run.path)
        if key not in self.matched:
            indexed, _ = self._load(run)
            self.matched[key] = _Matched(indexed.gt, run.predictions(), self.categories)
        m = self.matched[key]
        full = self.largest.get((key, self.seed))
        if full is None:
            n = len(m.image_ids)
            rows = np.concatenate([np.arange(n)[None, :], bootstrap_indices(n, self.largest_r, self.seed, fold)])
            full = self.largest[(key, self.seed)] = m.score(rows)
        return full[: 1 + self.resamples]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20, help="bootstrap seeds 0..N-1")
    ap.add_argument("--resamples", default="50,200,1000,2000", help="comma-separated resample counts")
    ap.add_argument("--check", action="store_true", help="check the weighted scores against the report's evaluator")
    ap.add_argument("--check-resamples", type=int, default=20)
    args = ap.parse_args()
    counts = sorted(int(x) for x in args.resamples.split(","))

    from harness.benchmark import cpu_name
    from harness.references import load_references
    from harness.report.build import _claim_categories
    from harness.report.claims import evaluate_claims
    from harness.report.reader import StoreView

    refs = load_references("shipped")
    view = StoreView(tempfile.mkdtemp(prefix="verdicts-"), references=refs)
    dataset = refs.dataset
    cats = tuple(_claim_categories(view, dataset))
    report_s_per_eval = None
    n_runs = sum(len(fr.runs) for e in view.entries(dataset) for fr in e.folds.values())
    if args.check:
        t0 = time.perf_counter()
        real = BootstrapScorer(args.check_resamples, 0, categories=cats)
        evaluate_claims(view, dataset, real)
        real_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        fast = WeightedScorer(args.check_resamples, 0, cats, args.check_resamples)
        evaluate_claims(view, dataset, fast)
        fast_s = time.perf_counter() - t0
        worst = 0.0
        for e in view.entries(dataset):
            for f, fr in e.folds.items():
                for r in fr.runs:
                    a, b = real.run_scores(dataset, f, r), fast.run_scores(dataset, f, r)
                    both = np.isfinite(a) & np.isfinite(b)
                    if not np.array_equal(np.isfinite(a), np.isfinite(b)):
                        print(f"defined cells differ: {r.path}", file=sys.stderr)
                    worst = max(worst, float(np.max(np.abs(a[both] - b[both]), initial=0.0)))
        report_s_per_eval = real_s / (n_runs * (1 + args.check_resamples))
        print(
            f"check, seed 0, {args.check_resamples} resamples: largest |report - weighted| score "
            f"{worst:.2e}; the report's evaluator {real_s:.1f} s, weighted {fast_s:.1f} s (with the matching)"
        )
        WeightedScorer.largest.clear()

    verdicts: dict[int, list[list[str]]] = {}
    claim_s: dict[int, float] = {}
    top = counts[-1]
    t0 = time.perf_counter()
    for seed in range(args.seeds):  # scored once at the largest count: a smaller count takes its first rows
        fill = WeightedScorer(top, seed, cats, top)
        for e in view.entries(dataset):
            for f, fr in e.folds.items():
                for r in fr.runs:
                    fill.run_scores(dataset, f, r)
    scoring_s = time.perf_counter() - t0
    for r in counts:
        t0 = time.perf_counter()
        verdicts[r] = []
        for seed in range(args.seeds):
            claims, _ = evaluate_claims(view, dataset, WeightedScorer(r, seed, cats, top))
            verdicts[r].append([c.verdict for c in claims])
        claim_s[r] = (time.perf_counter() - t0) / args.seeds

    print(f"verdict flips over bootstrap seeds 0..{args.seeds - 1} (shipped references, {dataset}): flips/seeds, the")
    print("most common verdict and, in brackets, the others with their counts")
    print("claim " + "".join(f"{f'R={r}':>23}" for r in counts))
    for c in range(len(verdicts[counts[0]][0])):
        cells = []
        for r in counts:
            seen = collections.Counter(v[c] for v in verdicts[r])
            mode, k = seen.most_common(1)[0]
            others = " ".join(f"{SHORT[name]} {m}" for name, m in seen.items() if name != mode)
            cells.append(f"{args.seeds - k}/{args.seeds} {SHORT[mode]}" + (f" ({others})" if others else ""))
        print(f"{c + 1:<6}" + "".join(f"{x:>23}" for x in cells))
    print("claims s/seed" + "".join(f"{claim_s[r]:>23.2f}" for r in counts)[7:])
    if report_s_per_eval is not None:
        est = "".join(f"{report_s_per_eval * n_runs * (1 + r):>23.0f}" for r in counts)
        print("report s/seed" + est[7:] + "  (estimated)")
    print(
        f"weighted scoring: {scoring_s:.1f} s for {args.seeds} seeds x {n_runs} runs x {top} resamples, the "
        f"matching included ({cpu_name()}, one process)"
    )


if __name__ == "__main__":
    main()
