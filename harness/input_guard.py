"""The plausibility guard at the dataset input boundary: implausible labels stop a preparation with what was seen.

The sample-matched guard checks what goes out of a run; this one checks what comes in. After a dataset is prepared
(or read back from the cache), ``check(prepared, folds, cfg)`` looks for these findings:

* ``no-labels``: the dataset, or the training or held-out part of a fold, holds no box at all;
* ``unlabelled-images``: more than ``inputs.max_unlabelled`` (default 20 %), and at least 5, of the images of the
  dataset or of a fold part have no box (a wrong label layout reads as "images without objects");
* ``dropped-annotations``: annotations the dataset's files state but the adapter could not use (unknown image or
  category id, malformed box, box outside the image, duplicate id: the prepare report's skips whose label starts
  with ``annotation``). A dropped box leaves an unlabelled object, which training learns as background;
* ``category-order``: the plugin's ``DatasetSpec.categories`` and its opened source's ``categories`` hold the same
  names in another order (labels follow the source, so a name the spec gives label 0 may be label 1);
* ``temperature-range``: samples whose temperatures lie mostly outside ``radiometry.PLAUSIBLE_C`` (-100..800 C),
  such as 8-bit counts read as centi-Kelvin (-273 C); a few pixels outside are made missing at preparation and
  counted, not a finding;
* ``empty-folds``: folds of the dataset's own whose held-out groups have no prepared sample (the plugin's
  ``groups()`` or ``folds()`` name them, ``samples()`` yielded none): they are left out of every fold list;
* ``invalid-samples``: samples the dataset yielded that break the sample contract (boxes outside the frame, labels
  past the class list, a thermal map of another shape: the prepare report's skips ``invalid sample``, except frames
  mostly without valid temperatures, which are counted skips of the data). Each takes its objects with it, and a
  plugin that breaks the contract for one sample usually does for many;
* ``duplicate-boxes``: more than ``agreement.DUPLICATE_SHARE`` of the boxes repeat another one of their image exactly
  (the same label and box): every annotation listed twice, the check ``harness.scoring.agreement`` makes of a
  prediction set;
* ``normalised-boxes``: every box lies within 0..1 while the frames are larger: coordinates given as fractions of
  the image size instead of pixels;
* ``mismatched-pairs``: more than 40 % of the compared samples' RGB frames agree clearly better with another
  sample's thermal frame than with their own (edges compared at 64 px, ``pair_statistics``): RGB and thermal files
  paired with the wrong partner, such as every thermal file name shifted by one image. Consecutive frames of a
  video sequence (RGBT-Tiny) are near copies of each other, so a shift by one there is not seen;
* ``misplaced-boxes``: the boxes sit on image structure clearly better read another way than as given
  (``harness.box_fit``: in-box contrast against the ring around each box, on the thermal picture and the RGB
  luminance of at most 32 samples): as centre x, centre y, w, h, or as the previous or next image's (image ids
  shifted by one). In a video sequence (RGBT-Tiny) the next frame's boxes fit about as well, so a shift of the image
  ids there is not seen.

Each finding is a line with the counts and a few examples. An unaccepted one raises a ``DataError`` listing them all
and naming the option; ``inputs.accept`` (a list of kinds, or ``all``) accepts them, and the accepted findings are
returned so that the caller labels the result (``PreparedDataset.input_risks``, the run's ``meta.input_risks`` and
``metrics.json`` ``input_risks``, and the printed tables). The prepared samples are kept either way: rerunning with
the option reads them from the cache.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from harness.errors import ConfigError, DataError

KINDS = (
    "no-labels",
    "unlabelled-images",
    "dropped-annotations",
    "category-order",
    "temperature-range",
    "empty-folds",
    "invalid-samples",
    "duplicate-boxes",
    "normalised-boxes",
    "mismatched-pairs",
    "misplaced-boxes",
)
#: What the contract's refusal of a map mostly without valid temperatures says (``harness.contracts``): such a frame
#: is a counted skip of the data, not an ``invalid-samples`` finding.
UNMEASURED = "non-finite temperature values"
#: Share of images without any box above which a dataset or fold part is implausible...
DEFAULT_MAX_UNLABELLED = 0.2
#: ... once at least this many of its images have none (a share of a handful of images says little).
MIN_UNLABELLED = 5
#: How many examples a finding quotes.
EXAMPLES = 3
#: Columns of an example line (the rest is cut with an ellipsis).
WIDTH = 100


@dataclass(frozen=True)
class Finding:
    """One implausible property of a prepared dataset: its kind, a line with the counts, and a few examples."""

    kind: str
    message: str
    examples: tuple[str, ...] = ()
    more: int = 0  # examples not quoted

    def as_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "message": self.message}

    def __str__(self) -> str:
        return f"{self.kind}: {self.message}"

    def lines(self, indent: str = "  ") -> list[str]:
        """The finding, then one ``e.g.`` line per example (each cut to ``WIDTH`` columns)."""
        from harness.textable import fit_text

        out = fit_text(f"{indent}{self}", WIDTH).splitlines()
        for k, ex in enumerate(self.examples):
            tail = f" (and {self.more} more)" if self.more and k == len(self.examples) - 1 else ""
            out.append(_cut(f"{indent}  e.g. {ex}", WIDTH - len(tail)) + tail)
        return out


def settings(cfg: Mapping[str, Any] | None) -> tuple[set[str], float]:
    """(accepted kinds, max share of unlabelled images) from the config's ``inputs`` section; a bad value is a
    ``ConfigError`` naming the key."""
    section = dict((cfg or {}).get("inputs") or {})
    raw = section.get("accept") or []
    items = [raw] if isinstance(raw, str) else list(raw)
    kinds = {str(k).strip() for k in items if str(k).strip()}
    if "all" in kinds:
        kinds = set(KINDS)
    unknown = sorted(kinds - set(KINDS))
    if unknown:
        raise ConfigError(
            f"inputs.accept: unknown finding(s) {', '.join(map(repr, unknown))}; use any of {', '.join(KINDS)}, or all"
        )
    share = section.get("max_unlabelled", DEFAULT_MAX_UNLABELLED)
    if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0 <= share <= 1:
        raise ConfigError(f"inputs.max_unlabelled must be a share between 0 and 1, got {share!r}")
    return kinds, float(share)


def _cut(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 3] + "..."


def _finding(kind: str, message: str, examples: Sequence[str]) -> Finding:
    return Finding(kind, message, tuple(examples[:EXAMPLES]), max(0, len(examples) - EXAMPLES))


def _name(record: Mapping[str, Any]) -> str:
    meta = record.get("meta")
    if not isinstance(meta, dict):
        meta = {}
    return str(meta.get("file_name") or f"image {record['image_id']}")


def _parts(prepared: Any, folds: Iterable[Any]) -> list[tuple[str, list[int]]]:
    """(what, sample indices): the whole dataset, then the training and held-out part of every fold."""
    parts = [("the dataset", list(range(len(prepared.records))))]
    for f in folds:
        parts.append(
            (
                f"fold {f.name!r} training part ({'+'.join(f.train_groups) or 'no group'})",
                prepared.indices(f.train_groups),
            )
        )
        parts.append((f"fold {f.name!r} held-out part ({'+'.join(f.val_groups)})", prepared.indices(f.val_groups)))
    return parts


def inspect(
    prepared: Any, folds: Iterable[Any], max_unlabelled: float = DEFAULT_MAX_UNLABELLED, own_folds: bool = True
) -> list[Finding]:
    """Every finding on ``prepared`` and its ``folds`` (see the module docstring), in a fixed order. ``own_folds``:
    the folds are the dataset's own (recorded at preparation), not ``protocol.folds``."""
    folds = list(folds)
    records = prepared.records
    out: list[Finding] = []
    covered: set[int] = set()  # images of the parts without labels: not counted again as unlabelled elsewhere
    parts = [(what, idx) for what, idx in _parts(prepared, folds) if idx]
    for what, idx in parts:
        if all(int(records[i]["n"]) == 0 for i in idx):
            out.append(
                _finding("no-labels", f"{what}: {len(idx)} image(s) and not one box", [_name(records[i]) for i in idx])
            )
            covered.update(idx)
    for what, idx in parts:
        rest = [i for i in idx if i not in covered]
        empty = [i for i in rest if int(records[i]["n"]) == 0]
        if rest and len(empty) / len(rest) > max_unlabelled and len(empty) >= MIN_UNLABELLED:
            out.append(
                _finding(
                    "unlabelled-images",
                    f"{what}: {len(empty)} of {len(rest)} images "
                    f"({len(empty) / len(rest):.0%}) have no box, more than "
                    f"{max_unlabelled:.0%}",
                    [_name(records[i]) for i in empty],
                )
            )
    report = prepared.manifest.get("report") or {}
    dropped = {k: v for k, v in (report.get("skip_reasons") or {}).items() if k.startswith("annotation")}
    if dropped:
        total = sum(dropped.values())
        listed = [
            f"{where}: {reason}"
            for where, reason in report.get("skipped_files") or []
            if reason.startswith("annotation")
        ]
        counts = ", ".join(f"{k}: {v}" for k, v in sorted(dropped.items(), key=lambda kv: -kv[1]))
        kept = int(prepared.manifest.get("instances", 0))
        finding = _finding("dropped-annotations", f"{total} annotation(s) dropped, {kept} kept ({counts})", listed)
        out.append(Finding(finding.kind, finding.message, finding.examples, total - len(finding.examples)))
    order = report.get("category_order")
    if isinstance(order, dict):
        out.append(
            _finding(
                "category-order",
                f"the dataset's spec lists its categories as {', '.join(order['spec'])} but the opened source as "
                f"{', '.join(order['source'])}; labels follow the source, so {len(order['moved'])} label(s) name "
                f"another category than the spec says",
                list(order.get("moved") or []),
            )
        )
    temps = report.get("implausible_temperatures")
    if isinstance(temps, dict) and temps.get("kelvin_like") and not temps.get("samples"):
        out.append(
            _finding(
                "temperature-range",
                f"the coolest pixel of all {len(records)} sample(s) is {temps.get('coolest', 0):.2f} C: every "
                f"temperature is above {temps['range_c'][0]:g} C + 273.15, as Kelvin read as C would be",
                [],
            )
        )
    if isinstance(temps, dict) and temps.get("samples"):
        lo, hi = (temps.get("range_c") or [None, None])[:2]
        out.append(
            _finding(
                "temperature-range",
                f"{temps['samples']} of {len(records)} sample(s) hold temperatures mostly outside the plausible "
                f"{lo:g}..{hi:g} C (thermal read in the wrong unit or scale?)",
                list(temps.get("examples") or []),
            )
        )
    out += _sample_findings(prepared, report)
    out += _pair_findings(prepared)
    if own_folds:
        present = set(prepared.groups)
        in_use = {f.name for f in folds}
        left_out = [
            f"fold {f['name']!r} holds out {', '.join(map(repr, f['val_groups']))}: no prepared sample"
            for f in prepared.manifest.get("folds") or []
            if f.get("name") not in in_use and not any(g in present for g in f.get("val_groups") or [])
        ]
        if left_out:
            out.append(
                _finding(
                    "empty-folds",
                    f"{len(left_out)} of the dataset's folds hold out only groups without prepared samples and are "
                    f"left out (groups with samples: {', '.join(sorted(present)) or 'none'})",
                    left_out,
                )
            )
    return out


def _sample_findings(prepared: Any, report: Mapping[str, Any]) -> list[Finding]:
    """``invalid-samples``, ``duplicate-boxes``, ``normalised-boxes`` and ``misplaced-boxes`` (module docstring)."""
    import numpy as np

    from harness import box_fit
    from harness.scoring.agreement import duplicate_findings, duplicate_key

    out: list[Finding] = []
    # a frame mostly without valid temperatures (the camera could not measure it) is a counted skip of the data, not
    # a break of the contract by the plugin
    invalid = [
        (w, r)
        for w, r in report.get("skipped_files") or []
        if str(r).startswith("invalid sample") and UNMEASURED not in str(r)
    ]
    if invalid:
        total = len(invalid) + len(prepared.records)
        out.append(
            _finding(
                "invalid-samples",
                f"{len(invalid)} of the {total} samples the dataset yielded break the sample contract and were "
                f'left out with their boxes (fix the plugin\'s samples(); docs/datasets.md, "The sample contract")',
                [f"{w}: {r}" for w, r in invalid],
            )
        )
    preds, frames, top = [], [], 0.0
    for i in range(len(prepared.records)):
        boxes, labels = prepared.targets(i)
        preds += [(i, box, 1.0, int(lab)) for box, lab in zip(boxes.tolist(), labels.tolist())]
        if len(boxes):
            top = max(top, float(np.abs(boxes).max()))
            r = prepared.records[i]
            frames.append(min(int(r.get("width") or 0), int(r.get("height") or 0)))
    for f in duplicate_findings(preds):
        seen: set[tuple[Any, ...]] = set()
        repeated: dict[int, None] = {}  # the images holding a repeat, in order: the finding's examples
        for pred in preds:
            if (key := duplicate_key(pred)) in seen:
                repeated[pred[0]] = None
            seen.add(key)
        said = f.message.replace("predictions", "boxes", 1).replace(" and score", "").replace("detection", "box")
        out.append(_finding("duplicate-boxes", f"the dataset's {said}", [_name(prepared.records[k]) for k in repeated]))
    if preds and top <= 1.0 and min(frames) > 2:
        out.append(
            _finding(
                "normalised-boxes",
                f"all {len(preds)} boxes lie within 0..{top:.2f} px in frames of at least {min(frames)} px: "
                f"coordinates normalised to 0..1? Boxes are pixels of the thermal frame (multiply by its width "
                f"and height)",
                [],
            )
        )
    elif preds and (fits := box_fit.misplaced(prepared)) is not None:
        out.append(_finding("misplaced-boxes", fits.advice(), []))
    return out


# ------------------------------------------------------------------------------------------- mismatched pairs
#: ``mismatched-pairs``: at most this many samples of one frame size are compared, in runs of ``PAIR_RUN``
#: consecutive samples spread evenly over the dataset (a shift by one in the file order keeps a sample's true
#: partner next to it), ...
PAIR_SAMPLES = 32
PAIR_RUN = 4
#: ... and fewer than this many comparable samples of one size are not compared at all.
MIN_PAIRS = 4
#: The frames are compared at this many pixels on their longer side (area-averaged).
PAIR_GRID = 64
#: A sample is beaten when its RGB frame agrees with another sample's thermal frame by at least ``BEATEN_BY`` more
#: (Pearson r of the gradient magnitudes) than either given pair of the two, and by at least ``BEATEN_AT``; ...
BEATEN_BY = 0.1
BEATEN_AT = 0.2
#: ... the finding needs more than this share of the compared samples beaten.
MAX_BEATEN = 0.4
# Measured (benchmarks/pair_agreement.py; share of the compared samples, at most 32, beaten; correct -> thermal frames
# shifted by 1, 2, 5 samples, randomly permuted): make_coco_rgbt 12 and 64 pairs 0 % -> 83..100 %, 91..92 %;
# m3t-synth small seeds 0 and 1 (112 pairs) 0 % -> 84 %, 69..75 %, 47..50 %, 47..53 %; rgbt-tiny synth small seeds 0
# and 1 (240 pairs) 0..9 % -> 0..6 % (missed: the next frames of a video sequence are near copies), random 50..72 %.
# No correct set comes near 40 %; a shift by one of frames that are not near copies is well above it.


def _structure(frame: np.ndarray) -> np.ndarray:
    """The gradient magnitude of ``frame`` (2-D, float; NaN missing) area-averaged to ``PAIR_GRID`` px on its
    longer side: the edges of a scene, which RGB and thermal frames of the same scene share whatever the contrast's
    sign. A missing pixel makes its cells missing (NaN), never zero."""
    import cv2

    img: np.ndarray = np.asarray(frame, np.float32)
    h, w = img.shape
    scale = PAIR_GRID / max(h, w)
    if scale < 1:
        size = (max(2, round(w * scale)), max(2, round(h * scale)))
        img = np.asarray(cv2.resize(img, size, interpolation=cv2.INTER_AREA), np.float32)
    gx, gy = np.diff(img, axis=1)[:-1, :], np.diff(img, axis=0)[:, :-1]
    return np.hypot(gx, gy).ravel()


def pair_agreement(rgbs: Sequence[np.ndarray], thermals: Sequence[np.ndarray]) -> np.ndarray:
    """``r[i, j]``: Pearson correlation of the structure (``_structure``) of RGB frame ``i`` (its luminance) and of
    thermal frame ``j`` (temperatures or 8-bit), over the pixels where thermal ``j`` is valid; NaN where either is
    flat or thermal ``j`` is mostly missing. All frames have one size."""
    import cv2

    x = np.stack([_structure(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)) for rgb in rgbs])
    y = np.stack([_structure(t) for t in thermals]).astype(np.float64)
    x = x.astype(np.float64)
    m = np.isfinite(y)
    y = np.where(m, y, 0.0)
    mf = m.astype(np.float64)
    n = mf.sum(1)[None, :]
    # numpy's own loops, not BLAS: a few million products, and a BLAS thread pool waits for busy cores
    sx, sxx, sxy = (np.einsum("ip,jp->ij", a, b) for a, b in ((x, mf), (x * x, mf), (x, y)))
    sy, syy = y.sum(1)[None, :], (y * y).sum(1)[None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = sxy - sx * sy / n
        vx, vy = sxx - sx * sx / n, syy - sy * sy / n
        r = cov / np.sqrt(vx * vy)
    flat = (vx <= 1e-9 * np.maximum(sxx, 1e-30)) | (vy <= 1e-9 * np.maximum(syy, 1e-30)) | (n < 0.5 * y.shape[1])
    return np.where(flat, np.nan, r)


def pair_statistics(r: np.ndarray) -> dict[str, Any]:
    """What ``mismatched-pairs`` decides on, from ``pair_agreement``'s matrix: the samples compared (own agreement
    and some other agreement defined), the agreements of the given pairs (``own``), of the other pairings
    (``shuffled``) and of each RGB frame's best other thermal frame (``best_other``), and which samples are beaten:
    RGB frame ``i`` agrees with another sample's thermal frame ``j`` by ``BEATEN_BY`` more than with its own *and*
    than that thermal frame agrees with its own RGB frame, and by ``BEATEN_AT`` in all (a thermal frame that agrees
    with every RGB frame, a sharper frame of a video sequence, beats no one). ``beaten`` lists (i, j, own r, r)."""
    own = np.diag(r).copy()
    other = r.copy()
    np.fill_diagonal(other, np.nan)
    ok = np.isfinite(own) & np.isfinite(other).any(1)
    empty: dict[str, Any] = {"compared": 0, "own": [], "shuffled": [], "best_other": [], "beaten": []}
    if not ok.any():
        return empty
    # how much RGB i with thermal j beats the better of the two given pairs (RGB i's own, thermal j's own)
    gain = other - np.fmax(own[:, None], own[None, :])
    gain = np.where(np.isfinite(gain) & ok[:, None] & ok[None, :], gain, -np.inf)
    best = gain.argmax(1)
    top = np.nanmax(np.where(np.isfinite(other), other, -np.inf), 1)
    rows = np.arange(len(r))
    beaten = ok & (gain[rows, best] >= BEATEN_BY) & (other[rows, best] >= BEATEN_AT)
    return {
        "compared": int(ok.sum()),
        "own": own[ok].tolist(),
        "shuffled": other[ok][np.isfinite(other[ok])].tolist(),
        "best_other": top[ok].tolist(),
        "beaten": [(int(i), int(best[i]), float(own[i]), float(other[i, best[i]])) for i in np.flatnonzero(beaten)],
    }


def _pair_selection(indices: Sequence[int]) -> list[int]:
    """At most ``PAIR_SAMPLES`` of ``indices``: all of them, or runs of ``PAIR_RUN`` consecutive ones spread evenly."""
    if len(indices) <= PAIR_SAMPLES:
        return list(indices)
    starts = np.linspace(0, len(indices) - PAIR_RUN, PAIR_SAMPLES // PAIR_RUN).round().astype(int)
    return [indices[k] for k in sorted({int(s) + d for s in starts for d in range(PAIR_RUN)})]


def pair_summary(prepared: Any) -> dict[str, Any]:
    """``pair_statistics`` pooled over the frame sizes of ``prepared`` (anything with ``records`` and samples by
    index), on at most ``PAIR_SAMPLES`` samples of each size (``_pair_selection``); sizes with fewer than
    ``MIN_PAIRS`` comparable samples are left out. ``beaten`` holds dataset indices."""
    sizes: dict[tuple[int, int], list[int]] = {}
    for i, rec in enumerate(prepared.records):
        sizes.setdefault((int(rec["height"]), int(rec["width"])), []).append(i)
    out: dict[str, Any] = {"compared": 0, "own": [], "shuffled": [], "best_other": [], "beaten": []}
    for indices in sizes.values():
        if len(indices) < MIN_PAIRS:
            continue
        chosen = _pair_selection(indices)
        rgbs, thermals = [], []
        for i in chosen:
            sample = prepared[i]
            rgbs.append(np.asarray(sample.rgb))
            thermals.append(np.asarray(sample.thermal if sample.thermal is not None else sample.ir8))
        stats = pair_statistics(pair_agreement(rgbs, thermals))
        if stats["compared"] < MIN_PAIRS:
            continue
        for key in ("compared", "own", "shuffled", "best_other"):
            out[key] += stats[key]
        out["beaten"] += [(chosen[i], chosen[j], a, b) for i, j, a, b in stats["beaten"]]
    return out


def _pair_findings(prepared: Any) -> list[Finding]:
    """``mismatched-pairs`` (module docstring; the measurements under ``BEATEN_BY``)."""
    summary = pair_summary(prepared)
    compared, beaten, own, shuffled = (summary[k] for k in ("compared", "beaten", "own", "shuffled"))
    if not compared or len(beaten) <= MAX_BEATEN * compared:
        return []
    records = prepared.records

    def thermal_name(k: int) -> str:
        meta = records[k].get("meta")
        name = meta.get("thermal_file") if isinstance(meta, dict) else None
        return str(name or f"the thermal frame of {_name(records[k])}")

    return [
        _finding(
            "mismatched-pairs",
            f"{len(beaten)} of {compared} compared RGB frames agree better with another image's thermal frame than "
            f"with their own (edge agreement r, median: own pairs {np.median(own):.2f}, other pairings "
            f"{np.median(shuffled):.2f}): RGB and thermal files paired with the wrong partner (shifted by one?)",
            [f"{_name(records[i])}: r {a:.2f} with its own, {b:.2f} with {thermal_name(j)}" for i, j, a, b in beaten],
        )
    ]


def check(prepared: Any, folds: Iterable[Any], cfg: Mapping[str, Any] | None) -> list[Finding]:
    """The accepted findings on ``prepared``; unaccepted ones raise a ``DataError`` that lists every finding with its
    counts and examples and names the option that accepts them."""
    accept, share = settings(cfg)
    own_folds = not ((cfg or {}).get("protocol") or {}).get("folds")
    findings = inspect(prepared, folds, share, own_folds)
    refused = [f for f in findings if f.kind not in accept]
    if refused:
        kinds = sorted({f.kind for f in refused})
        lines = "\n".join(line for f in refused for line in f.lines())
        raise DataError(
            f"dataset {prepared.name!r}: implausible inputs in {prepared.folder}:\n{lines}\n"
            f"Check the dataset's layout, annotation files and plugin (docs/datasets.md). To use these samples\n"
            f"anyway, accept the risk with --set 'inputs.accept=[{', '.join(kinds)}]' (the results are labelled\n"
            f"with it; the prepared samples are kept)."
        )
    return findings


def describe(findings: Sequence[Finding | Mapping[str, Any] | str]) -> list[str]:
    """One ``accepted input risk: ...`` line per finding (what the printed tables add under a labelled result)."""
    out = []
    for f in findings:
        text = str(f) if not isinstance(f, Mapping) else f"{f.get('kind')}: {f.get('message')}"
        out.append(f"accepted input risk: {text}")
    return out
