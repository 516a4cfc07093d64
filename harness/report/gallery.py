"""Galleries: one per detector, held-out samples drawn with their ground truth and the detector's predictions.

Each picture is ``harness.report.pictures.draw_sample``: the RGB, the thermal image (°C colour map with a scale
bar; grey levels for 8-bit thermal) and the detector's fourth channel side by side, the ground truth (green) and the
predictions at the run's operating point (``metrics.conf_threshold``) drawn on each panel, the object a picture is
about outlined in magenta. Per dataset, for the entries of the project-grouped table, in this order:

1. **where the detectors disagree most** (the same samples in every gallery, so they can be compared): held-out
   images ranked by the objects that some detectors find and others miss at their operating points (from each
   run's ``gt_found``), then by the spread of their false-positive counts (``images.fp``);
2. **the worst misses and false positives per category** of that detector: its worst miss of each category over the
   folds (the analysis's order: nothing of the category near it first, then by IoU with the nearest detection of
   the category, then the largest) and its most confident false positive kept at the operating point.

A sample is shown once per gallery. The first run (lowest seed) of each fold with an analysis supplies the
predictions and the evidence. The pixels come from the prepared cache the runs were trained on (``harness.cache.
cached`` with the run's ``meta.prepared_key``; no dataset plugin needed): a store moved without its cache keeps its
tables and says where the pictures would come from. Thumbnails are JPEG (quality ``QUALITY``), ``HEIGHT`` pixels per
panel, written under ``gallery/`` and inlined in the HTML page.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from harness.errors import HarnessError
from harness.report.reader import StoredRun

log = logging.getLogger(__name__)

HEIGHT = 150  # pixels per panel of a thumbnail
QUALITY = 80  # JPEG quality of the thumbnails
DISAGREE = 4  # samples where the detectors disagree most, at the head of every gallery
PER_CATEGORY = 1  # worst misses and worst false positives shown per category
HIGHLIGHT = (255, 0, 255)


@dataclass
class Thumb:
    """One picture of a gallery: its caption, the JPEG bytes, and where it was written (None: not written)."""

    caption: str
    data: bytes
    path: Path | None = None
    kind: str = ""  # "disagree", "miss" or "false positive"
    rel: str = ""  # the path relative to the report folder (``gallery/...``)
    fourth: str = ""  # the encoding whose channel is the third panel ("" when none is drawn)


@dataclass
class Gallery:
    """The gallery of one detector (entry)."""

    name: str
    thumbs: list[Thumb] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


@dataclass
class Pick:
    """A sample chosen for a gallery and why: the fold, the image, a caption and the box it is about."""

    fold: str
    image_id: int
    caption: str
    kind: str
    box: list[float] | None = None  # COCO [x, y, w, h]
    category: str | None = None
    score: float | None = None


# ------------------------------------------------------------------------------------------------ choosing samples
def _first_runs(ev: Any) -> dict[str, tuple[StoredRun, dict[str, Any]]]:
    """fold -> (the lowest seed's run with an analysis, its analysis)."""
    return {f: (runs[0], ev.folds[f][0]) for f, runs in ev.runs.items() if runs}


def disagreements(evidence: Sequence[Any], gts: dict[str, dict[str, Any]]) -> tuple[list[Pick], list[str]]:
    """Held-out images where the detectors disagree most (module docstring), best first, and the folds that could
    not be compared (named, with why)."""
    if len(evidence) < 2:
        return [], []
    scored: list[tuple[tuple[int, int], Pick]] = []
    problems = []
    folds = [f for f in gts if all(f in ev.runs for ev in evidence)]
    for f in folds:
        gt = gts[f]
        analyses = [_first_runs(ev)[f][1] for ev in evidence]
        anns = gt.get("annotations") or []
        found = [np.asarray(a.get("gt_found") or [], dtype=np.int64) for a in analyses]
        if any(len(x) != len(anns) for x in found):
            problems.append(f"fold {f}: the runs' analyses do not cover the same ground truth; not compared")
            continue
        image_ids = [a.get("images", {}).get("image_id") for a in analyses]
        if any(ids != image_ids[0] for ids in image_ids):
            problems.append(f"fold {f}: the runs' analyses list other images; not compared")
            continue
        table = np.stack(found)  # detectors x annotations
        real = np.all(table >= 0, axis=0)
        split = real & (table.max(axis=0) == 1) & (table.min(axis=0) == 0)
        per_image: dict[Any, int] = {}
        for a, s in zip(anns, split.tolist()):
            if s:
                per_image[a["image_id"]] = per_image.get(a["image_id"], 0) + 1
        fps = np.array([a["images"]["fp"] for a in analyses], dtype=np.int64)  # detectors x images
        spread = fps.max(axis=0) - fps.min(axis=0)
        for k, iid in enumerate(image_ids[0] or []):
            n, fp = per_image.get(iid, 0), int(spread[k])
            if n == 0 and fp == 0:
                continue
            what = [f"{n} object{'s' if n != 1 else ''} found by some detectors, missed by others"] if n else []
            if fp:
                what.append(f"false positives {int(fps[:, k].min())}-{int(fps[:, k].max())}")
            scored.append(((n, fp), Pick(f, int(iid), f"disagree: {'; '.join(what)}", "disagree")))
    scored.sort(key=lambda t: (-t[0][0], -t[0][1]))
    return [p for _, p in scored], problems


_REASONS = ("missed", "localisation", "classification", "below_threshold")


def worst_picks(ev: Any) -> list[Pick]:
    """Per category, the detector's worst misses and most confident kept false positives over its folds."""
    firsts = _first_runs(ev)
    cats: list[str] = []
    for _, a in firsts.values():
        cats.extend(c for c in a.get("worst") or {} if c not in cats)
    picks: list[Pick] = []
    for cat in cats:
        misses = [
            (f, m) for f, (_, a) in firsts.items() for m in ((a.get("worst") or {}).get(cat) or {}).get("misses") or []
        ]
        misses.sort(
            key=lambda fm: (
                _REASONS.index(fm[1].get("reason")) if fm[1].get("reason") in _REASONS else 9,
                fm[1].get("best_iou") or 0.0,
                -(fm[1].get("area") or 0.0),
            )
        )
        for f, m in misses:
            why = str(m.get("reason") or "missed").replace("_", " ")
            iou = f", nearest IoU {m['best_iou']:.2f}" if m.get("best_iou") else ""
            picks.append(Pick(f, int(m["image_id"]), f"worst miss, {cat}: {why}{iou}", "miss", m.get("bbox"), cat))
        fps = [
            (f, p)
            for f, (_, a) in firsts.items()
            for p in ((a.get("worst") or {}).get(cat) or {}).get("false_positives") or []
            if p.get("kept")
        ]
        fps.sort(key=lambda fp: -(fp[1].get("score") or 0.0))
        for f, p in fps:
            err = str(p.get("error") or "")
            on = f" on a {p['gt_category']}" if p.get("gt_category") and p.get("gt_category") != cat else ""
            picks.append(
                Pick(
                    f,
                    int(p["image_id"]),
                    f"worst false positive, {cat} {p.get('score', 0):.2f}: {err}{on}",
                    "false positive",
                    p.get("bbox"),
                    cat,
                    p.get("score"),
                )
            )
    return picks


def choose(
    common: Sequence[Pick], own: Sequence[Pick], per_category: int = PER_CATEGORY, disagree: int = DISAGREE
) -> list[Pick]:
    """The pictures of one gallery: the first ``disagree`` common picks, then per category and kind the first
    ``per_category`` picks of an image not shown yet."""
    out = list(common[:disagree])
    shown = {(p.fold, p.image_id) for p in out}
    taken: dict[tuple[str | None, str], int] = {}
    for p in own:
        key = (p.category, p.kind)
        if taken.get(key, 0) >= per_category or (p.fold, p.image_id) in shown:
            continue
        taken[key] = taken.get(key, 0) + 1
        shown.add((p.fold, p.image_id))
        out.append(p)
    return out


# ------------------------------------------------------------------------------------------------ pixels
@dataclass
class Source:
    """Where the pixels of a run's samples come from: its prepared cache and the encoding of its fourth channel."""

    prepared: Any
    encoding: Any = None
    params: dict[str, Any] = field(default_factory=dict)
    note: str | None = None


def _same_samples(run: StoredRun, root: Path) -> Any:
    """A prepared dataset in the cache ``root`` whose held-out samples of ``run``'s fold have the content digest the
    run recorded (``metrics.samples.aligned.held_out``): the same samples prepared under another key (the shipped
    references were prepared on another machine, so their key names no folder here), or None."""
    from harness.cache.folds import resolve_folds
    from harness.cache.reader import PreparedDataset
    from harness.plugins import get_host

    metrics = run.metrics if isinstance(run.metrics, dict) else {}
    want = ((metrics.get("samples") or {}).get("aligned") or {}).get("held_out")
    if not want:
        return None
    for manifest in sorted((root / run.key.dataset).glob("*/manifest.json")):
        try:
            ds = PreparedDataset(manifest.parent)
            folds = resolve_folds(get_host().dataset(run.key.dataset), ds, run.config)
            fold = next((f for f in folds if f.name == run.key.fold), None)
            if fold is not None and ds.content_digest(ds.indices(fold.val_groups)) == want:
                return ds
        except (HarnessError, OSError, ValueError, KeyError):
            continue
    return None


def prepared_of(run: StoredRun, cache_root: str | Path | None = None) -> tuple[Any, str | None]:
    """The prepared samples a run was scored on, from the cache (``harness.cache.cached``), or (None, why not)."""
    from harness.cache import cache_root as default_root
    from harness.cache import cached

    meta = run.config.get("meta") or {}
    key = meta.get("prepared_key")
    if not key:
        return None, f"{run.key}: its config.yaml records no prepared data (meta.prepared_key)"
    try:
        prepared = cached(run.key.dataset, str(key), cache_root)
    except HarnessError as exc:
        return None, f"{run.key}: the prepared data in the cache is unreadable ({exc})"
    where = Path(cache_root) if cache_root is not None else default_root()
    if prepared is None:
        # prepared elsewhere (the shipped references): the same samples under another key serve as well
        same = _same_samples(run, where)
        if same is not None:
            return same, None
        return None, (
            f"the prepared samples of {run.key.dataset} (key {key}) are not in the cache {where} "
            f"(HARNESS_CACHE), and no prepared {run.key.dataset} there holds the samples its fold {run.key.fold} "
            f"was scored on; prepare them (for the reference results: `harness synth`, then `harness prepare "
            f"--dataset {run.key.dataset}` with default settings) or point HARNESS_CACHE at the cache the runs "
            "used, then rebuild the report"
        )
    stored = meta.get("prepared_fingerprint")
    if stored and stored != prepared.manifest.get("fingerprint"):
        return None, (
            f"{run.key}: the cached samples of {run.key.dataset} changed since the run (fingerprint "
            f"{stored} then, {prepared.manifest.get('fingerprint')} now)"
        )
    then, now = meta.get("prepared_samples"), (prepared.manifest.get("report") or {}).get("samples_identity")
    if then and now and then != now:
        return None, (
            f"{run.key}: the cache key {key} of {run.key.dataset} now holds other samples under the run's "
            f"image ids (samples {then} then, {now} now: the dataset plugin's sample order changed), so "
            "its boxes would be drawn on other pictures; prepare the run's samples again or re-run it"
        )
    return prepared, None


def source_of(run: StoredRun, prepared: Any) -> Source:
    """The pixels of ``run``'s samples: ``prepared`` and the run's encoding (its fourth channel) with its
    parameters, when the encoding is installed here and adds a channel."""
    src = Source(prepared)
    enc_name = run.key.encoding
    try:
        from harness.plugins import get_host

        enc = get_host().encoding(enc_name)
    except HarnessError:
        src.note = f"encoding {enc_name!r} is not installed here: its channel is not drawn"
        return src
    if getattr(enc, "channels", 0) and not (getattr(enc, "needs", None) == "thermal" and not prepared.radiometric):
        src.encoding = enc
        src.params = dict(((run.config.get("encoding") or {}).get(enc_name) or {}))
    return src


def _boxes(
    records: Sequence[dict[str, Any]],
    image_id: int,
    categories: Sequence[str],
    name: str,
    colour: tuple[int, int, int] | None,
    threshold: float | None = None,
) -> Any:
    from harness.report.pictures import coco_boxes

    return coco_boxes(records, image_id, name, colour).above(threshold)


def draw(
    pick: Pick,
    src: Source,
    gt: dict[str, Any],
    predictions: Sequence[dict[str, Any]],
    conf: float | None,
    detector: str,
    height: int = HEIGHT,
) -> np.ndarray:
    """The picture of one pick (module docstring)."""
    from harness.report.pictures import GT_COLOUR, BoxSet, draw_sample

    prepared = src.prepared
    i = prepared.index_of(pick.image_id)
    sample = prepared[i]
    cats = list(prepared.categories)
    gt_set = _boxes(gt.get("annotations") or [], pick.image_id, cats, "ground truth", GT_COLOUR)
    name = f"{detector}" + (f" >= {conf:.2f}" if conf is not None else "")
    sets = [_boxes(predictions, pick.image_id, cats, name, (255, 64, 64), conf)]
    if pick.box is not None:
        x, y, w, h = (float(v) for v in pick.box)
        label = cats.index(pick.category) if pick.category in cats else -1
        sets.append(
            BoxSet(
                np.array([[x, y, x + w, y + h]]),
                np.array([max(label, 0)]),
                None if pick.score is None else np.array([pick.score]),
                pick.kind,
                HIGHLIGHT,
            )
        )
    fourth = None
    if src.encoding is not None:
        fourth = prepared.channel(i, src.encoding, dict(src.params))
    return draw_sample(
        sample,
        fourth=fourth,
        fourth_name=getattr(src.encoding, "name", ""),
        categories=cats,
        gt=gt_set,
        predictions=sets,
        height=height,
        title=f"{pick.fold} · image {pick.image_id}",
    )


# ------------------------------------------------------------------------------------------------ the section
def gallery_section(
    dataset: str,
    evidence: Sequence[Any],
    out: Path | None,
    cache_root: str | Path | None = None,
    disagree: int = DISAGREE,
    per_category: int = PER_CATEGORY,
) -> Any:
    """The "Galleries" section of ``dataset``: one gallery per entry with an analysis (``evidence.Evidence``)."""
    from harness.evaluation.analysis import NO_ANALYSIS
    from harness.io import atomic_write_bytes
    from harness.report.document import Section
    from harness.report.pictures import encode_image
    from harness.report.tables import _slug

    sec = Section("gallery", "Galleries", dataset)
    have = [ev for ev in evidence if not ev.empty]
    if not have:
        sec.absent = f"{NO_ANALYSIS} (the galleries are chosen from each run's analysis)."
        return sec
    if out is None:
        sec.absent = "pictures are drawn only when the report is written (--out)."
        return sec
    folder = out / "gallery" / _slug(dataset)
    if folder.is_dir():  # pictures of an earlier build of this report: replaced, never mixed with the new ones
        import shutil

        shutil.rmtree(folder)
    # the ground truth of each fold, from the first run with one
    gts: dict[str, dict[str, Any]] = {}
    for ev in have:
        for f, (run, _) in _first_runs(ev).items():
            if f not in gts:
                try:
                    gts[f] = run.ground_truth()
                except HarnessError as exc:
                    sec.notes.append(f"{run.key}: {exc}")
    common, problems = disagreements(have, gts)
    sec.notes += problems
    prepared: dict[str, tuple[Any, str | None]] = {}  # prepared key -> (samples or None, why not)
    for ev in evidence:
        gallery = Gallery(ev.name)
        sec.galleries.append(gallery)
        if ev.empty:
            gallery.notes.append(NO_ANALYSIS)
            continue
        firsts = _first_runs(ev)
        picks = choose(common, worst_picks(ev), per_category, disagree)
        preds: dict[str, dict[int, list[dict[str, Any]]]] = {}
        for k, pick in enumerate(picks):
            if pick.fold not in gts or pick.fold not in firsts:
                continue
            run, analysis = firsts[pick.fold]
            key = str(run.config.get("meta", {}).get("prepared_key"))
            if key not in prepared:
                prepared[key] = prepared_of(run, cache_root)
            samples, why = prepared[key]
            if samples is None:
                if why not in gallery.notes:
                    gallery.notes.append(why or "no pixels")
                continue
            src = source_of(run, samples)
            if src.note and src.note not in gallery.notes:
                gallery.notes.append(src.note)
            if pick.fold not in preds:
                by_image: dict[int, list[dict[str, Any]]] = {}
                try:
                    for p in run.predictions():
                        by_image.setdefault(int(p["image_id"]), []).append(p)
                except HarnessError as exc:
                    gallery.notes.append(str(exc))
                preds[pick.fold] = by_image
            conf = analysis.get("conf_threshold")
            try:
                img = draw(pick, src, gts[pick.fold], preds[pick.fold].get(pick.image_id, []), conf, ev.name)
            except (HarnessError, KeyError, ValueError) as exc:
                gallery.notes.append(f"{pick.fold} image {pick.image_id}: not drawn ({exc})")
                continue
            data = encode_image(img, "jpeg", QUALITY)
            path = folder / _slug(ev.name) / f"{k:02d}_{_slug(pick.fold)}_{pick.image_id}.jpg"
            atomic_write_bytes(path, data)
            gallery.thumbs.append(
                Thumb(
                    f"{pick.fold} · image {pick.image_id} · {pick.caption}",
                    data,
                    path,
                    pick.kind,
                    path.relative_to(out).as_posix(),
                    getattr(src.encoding, "name", ""),
                )
            )
    sec.notes.append(
        f"Per detector: first the {disagree} held-out samples where the detectors disagree most (the "
        f"same in every gallery), then per category its worst miss and its most confident false "
        f"positive (docs/reports.md). Green: ground truth; red: the detector's predictions at its "
        f"operating point (score shown); magenta: the object the picture is about. Thermal in °C "
        f"(1st-99th percentile of the sample), the fourth channel of the detector's encoding in grey."
    )
    if not any(g.thumbs for g in sec.galleries):
        reasons = list(dict.fromkeys(n for g in sec.galleries for n in g.notes))
        sec.absent = "no picture could be drawn: " + "; ".join(reasons or ["no sample to show"])
    return sec
