"""The plan of an RGBT-Tiny-like set: profiles, sequences, tracks and both modalities' boxes, without any pixels.

Everything the annotation files hold comes from here, so the statistics of a profile (sizes, categories, objects
seen in one modality only) can be computed in milliseconds (``plan_dataset`` + ``coco_documents``); the renderer
draws the same tracks at the same places.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from harness.errors import DataError

#: The release's seven classes in the order of its 0-based JSON ids (``adapters.datasets.rgbt_tiny.CATEGORIES``).
CATEGORIES = ("ship", "car", "cyclist", "pedestrian", "bus", "drone", "plane")
SCENES = ("sky", "sea", "ground")
#: SAFit's size bins on the box area (``harness.evaluation.safit.TINY_AREA_RANGES``), as ranges of sqrt(area) in px.
SIZE_BINS = {
    "extremely_tiny": (0.0, 8.0),
    "tiny": (8.0, 16.0),
    "small": (16.0, 32.0),
    "medium": (32.0, 96.0),
    "large": (96.0, math.inf),
}
#: Share of the tracks drawn in each size bin (the release: more than 81 % of the targets under 16x16).
BIN_SHARES = {"extremely_tiny": 0.38, "tiny": 0.47, "small": 0.10, "medium": 0.04, "large": 0.01}
#: sqrt(area) in px each bin draws from (log-uniform); the medium bin leans to its small end, as in aerial footage.
_BIN_DRAW = {
    "extremely_tiny": (3.0, 7.6),
    "tiny": (8.4, 15.6),
    "small": (16.5, 31.0),
    "medium": (34.0, 70.0),
    "large": (100.0, 140.0),
}


@dataclass(frozen=True)
class SequenceSpec:
    split: str  # train | test
    scene: str  # sky | sea | ground
    light: str  # day | night


@dataclass(frozen=True)
class Profile:
    name: str
    size: tuple[int, int]  # (width, height) of both modalities
    frames: int  # frames per sequence
    sequences: tuple[SequenceSpec, ...]
    description: str = ""

    @property
    def total(self) -> int:
        return self.frames * len(self.sequences)


def _seqs(split: str, *specs: str) -> tuple[SequenceSpec, ...]:
    out = []
    for s in specs:
        scene, _, light = s.partition("-")
        out.append(SequenceSpec(split, scene, light or "day"))
    return tuple(out)


PROFILES: dict[str, Profile] = {
    p.name: p
    for p in (
        Profile(
            "tiny",
            (320, 256),
            4,
            _seqs("train", "sky", "sea", "ground-night") + _seqs("test", "sky", "ground"),
            "20 pairs at 320x256, for tests",
        ),
        Profile(
            "small",
            (640, 512),
            24,
            _seqs("train", "sky", "sky", "sea", "sea", "ground", "ground-night")
            + _seqs("test", "sky", "sea", "ground", "ground-night"),
            "240 pairs at 640x512 (6 train / 4 test sequences): CPU benchmarks",
        ),
        Profile(
            "small-320",
            (320, 256),
            24,
            _seqs("train", "sky", "sky", "sea", "sea", "ground", "ground-night")
            + _seqs("test", "sky", "sea", "ground", "ground-night"),
            "240 pairs at 320x256 (small's sequences on a quarter of the frame, the targets at their own size): "
            "CPU benchmarks at 320 px without halving the targets",
        ),
        Profile(
            "full",
            (640, 512),
            40,
            _seqs("train", *(["sky"] * 6 + ["sea"] * 7 + ["ground"] * 8 + ["ground-night"] * 3 + ["sea-night"] * 2))
            + _seqs("test", *(["sky"] * 2 + ["sea"] * 3 + ["ground"] * 3 + ["ground-night"] * 1)),
            "1,400 pairs at 640x512 (26 train / 9 test sequences, about the release's 85:30 ratio)",
        ),
    )
}


def get_profile(name: str) -> Profile:
    if name not in PROFILES:
        raise DataError(f"unknown rgbt-tiny-synth profile {name!r}; available: {', '.join(PROFILES)}")
    return PROFILES[name]


# ---------------------------------------------------------------------------------------------- what lives where
#: Tracks per sequence (min, max) by scene; night ground scenes are quieter.
TRACKS = {"sky": (2, 5), "sea": (6, 12), "ground": (16, 30), "ground-night": (8, 14), "sea-night": (4, 8)}
#: Category weights by scene for tracks up to the small bin, and the categories that can be medium or large there.
SCENE_CATEGORIES = {
    "sky": ({"drone": 0.7, "plane": 0.3}, {"plane": 1.0}),
    "sea": ({"ship": 0.85, "drone": 0.15}, {"ship": 1.0}),
    "ground": ({"pedestrian": 0.4, "car": 0.35, "cyclist": 0.15, "bus": 0.1}, {"car": 0.55, "bus": 0.45}),
}
#: Box width / height range by category (oblique aerial view).
ASPECT = {
    "ship": (1.6, 3.2),
    "car": (0.55, 2.0),
    "cyclist": (0.6, 1.0),
    "pedestrian": (0.4, 0.7),
    "bus": (1.8, 3.0),
    "drone": (1.2, 2.0),
    "plane": (1.2, 2.0),
}
#: Speed in px per frame at 640x512 (min, max), and the chance that the object stands still.
SPEED = {
    "ship": ((0.1, 0.8), 0.3),
    "car": ((0.5, 3.0), 0.3),
    "cyclist": ((0.6, 1.5), 0.0),
    "pedestrian": ((0.2, 0.8), 0.2),
    "bus": ((0.5, 2.0), 0.2),
    "drone": ((0.5, 3.0), 0.1),
    "plane": ((1.0, 4.0), 0.0),
}
#: Chance that an object is at the temperature of its surroundings (parked car, cold hull): no thermal signature,
#: no thermal annotation.
COLD = {"ship": 0.10, "car": 0.12, "cyclist": 0.02, "pedestrian": 0.02, "bus": 0.08, "drone": 0.08, "plane": 0.0}
#: Chance that an object carries lights, the only way it is seen in a night-time visible frame.
LIT = {"ship": 0.5, "car": 0.7, "cyclist": 0.4, "pedestrian": 0.25, "bus": 0.6, "drone": 0.3, "plane": 0.8}
#: Chance that a day-time object is lost in shadow or against a matching background in the visible frame.
HIDDEN_DAY = 0.03
#: Thermal amplitude of the target over its surroundings in degrees C (min, max).
WARMTH = {
    "ship": (2.0, 7.0),
    "car": (3.0, 10.0),
    "cyclist": (4.0, 8.0),
    "pedestrian": (4.0, 9.0),
    "bus": (3.0, 8.0),
    "drone": (2.0, 6.0),
    "plane": (6.0, 15.0),
}


@dataclass
class Track:
    """One object through its sequence. Positions are box centres in thermal pixels per frame."""

    id: int
    category: str
    size_bin: str
    size: tuple[float, float]  # (w, h) at the middle of the sequence
    centres: np.ndarray  # [frames, 2] thermal-frame box centres
    scales: np.ndarray  # [frames] size factor
    thermal: bool  # has a thermal signature (annotated in 01)
    visible: bool  # seen in the visible frame (annotated in 00)
    parallax: tuple[float, float]  # this object's extra visible-vs-thermal offset (height above the ground plane)
    warmth: float  # signed amplitude, degrees C
    core: float  # core sigma as a fraction of the box size
    halo: float  # halo sigma as a multiple of the box size (at least HALO_MIN_PX)
    halo_share: float  # halo amplitude / core amplitude
    colour: tuple[float, float, float]  # visible-frame reflectance
    vis_size: float  # the visible outline's size relative to the thermal one

    def box(self, t: int) -> tuple[float, float, float, float]:
        """True thermal-frame box ``(x0, y0, x1, y1)`` at frame ``t``."""
        (cx, cy), s = self.centres[t], self.scales[t]
        w, h = self.size[0] * s, self.size[1] * s
        return cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2


@dataclass
class Sequence:
    index: int
    name: str  # DJI_<clip>_<part>
    spec: SequenceSpec
    offset: tuple[float, float]  # visible-vs-thermal registration offset of the sequence, px
    pan: tuple[float, float]  # camera motion, px per frame
    tracks: list[Track]
    jitter: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [frames, 2] residual misregistration

    @property
    def kind(self) -> str:
        return f"{self.spec.scene}-night" if self.spec.light == "night" else self.spec.scene

    def visible_box(self, track: Track, t: int) -> tuple[float, float, float, float]:
        """True visible-frame box: the thermal one moved by the registration offset, the object's parallax and the
        frame's jitter, with the visible outline's own size."""
        x0, y0, x1, y1 = track.box(t)
        cx = (x0 + x1) / 2 + self.offset[0] + track.parallax[0] + self.jitter[t, 0]
        cy = (y0 + y1) / 2 + self.offset[1] + track.parallax[1] + self.jitter[t, 1]
        hw, hh = (x1 - x0) / 2 * track.vis_size, (y1 - y0) / 2 * track.vis_size
        return cx - hw, cy - hh, cx + hw, cy + hh


@dataclass
class Plan:
    profile: Profile
    seed: int
    sequences: list[Sequence]


def _allocate(n: int, shares: dict[str, float]) -> list[str]:
    """``n`` bin labels in the given shares (largest remainder), each bin at least once when ``n`` allows."""
    names = list(shares)
    raw = [n * shares[b] for b in names]
    counts = [int(r) for r in raw]
    for i in sorted(range(len(names)), key=lambda i: raw[i] - counts[i], reverse=True)[: n - sum(counts)]:
        counts[i] += 1
    if n >= len(names):
        for i in range(len(names)):
            while counts[i] == 0:
                j = max(range(len(names)), key=lambda k: counts[k])
                counts[j] -= 1
                counts[i] += 1
    return [b for b, c in zip(names, counts) for _ in range(c)]


def _pick(rng: np.random.Generator, weights: dict[str, float]) -> str:
    names = list(weights)
    p = np.array([weights[k] for k in names], float)
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def _track(
    rng: np.random.Generator, tid: int, spec: SequenceSpec, size_bin: str, frames: int, size: tuple[int, int]
) -> Track:
    small_cats, big_cats = SCENE_CATEGORIES[spec.scene]
    cat = _pick(rng, big_cats if size_bin in ("medium", "large") else small_cats)
    lo, hi = _BIN_DRAW[size_bin]
    hi = min(hi, 0.4 * min(size))
    side = float(np.exp(rng.uniform(np.log(lo), np.log(max(hi, lo)))))
    aspect = float(rng.uniform(*ASPECT[cat]))
    w, h = side * math.sqrt(aspect), side / math.sqrt(aspect)
    scale_rate = float(rng.uniform(-0.3, 0.3))
    t = np.arange(frames, dtype=np.float64)
    scales = np.exp(scale_rate * (t - (frames - 1) / 2) / max(frames, 1))
    # motion: the middle of the track inside the frame, constant speed with a slowly turning heading
    speed_range, still = SPEED[cat]
    res = min(size[0] / 640, size[1] / 512)
    speed = 0.0 if rng.random() < still else float(rng.uniform(*speed_range)) * res
    heading = float(rng.uniform(0, 2 * math.pi))
    turn = float(rng.normal(0, 0.01))
    margin_x, margin_y = min(w, size[0] / 3), min(h, size[1] / 3)
    mid = np.array([rng.uniform(margin_x, size[0] - margin_x), rng.uniform(margin_y, size[1] - margin_y)])
    ang = heading + turn * (t - (frames - 1) / 2)
    step = np.stack([np.cos(ang), np.sin(ang)], 1) * speed
    path = np.cumsum(step, 0)
    centres = mid + path - path[(frames - 1) // 2]
    night = spec.light == "night"
    thermal = rng.random() >= COLD[cat]
    visible = rng.random() < LIT[cat] if night else rng.random() >= HIDDEN_DAY
    if not (thermal or visible):
        thermal = True  # nobody annotates what neither camera shows
    airborne = cat in ("drone", "plane")
    parallax = (float(rng.normal(0, 0.6)), float(rng.uniform(2.0, 9.0) if airborne else rng.uniform(0.0, 1.5)))
    sign = -1.0 if (spec.scene == "ground" and not night and rng.random() < 0.08) else 1.0  # cooler than hot asphalt
    colour = tuple(float(c) for c in rng.uniform(0.05, 0.95, 3))
    return Track(
        id=tid,
        category=cat,
        size_bin=size_bin,
        size=(w, h),
        centres=centres,
        scales=scales,
        thermal=bool(thermal),
        visible=bool(visible),
        parallax=parallax,
        warmth=sign * float(rng.uniform(*WARMTH[cat])),
        core=float(rng.uniform(0.25, 0.4)),
        halo=float(rng.uniform(0.7, 1.5)),
        halo_share=float(rng.uniform(0.35, 0.7)),
        colour=colour,  # type: ignore[arg-type]
        vis_size=float(np.clip(rng.normal(1.0, 0.06), 0.85, 1.15)),
    )


def plan_dataset(profile: str | Profile, seed: int) -> Plan:
    """Every sequence and track of ``profile`` for ``seed`` (deterministic; no pixels)."""
    prof = get_profile(profile) if isinstance(profile, str) else profile
    rng = np.random.default_rng(np.random.SeedSequence((seed, 0)))
    specs = list(prof.sequences)
    counts = []
    for spec in specs:
        kind = f"{spec.scene}-night" if spec.light == "night" else spec.scene
        lo, hi = TRACKS.get(kind, TRACKS[spec.scene])
        counts.append(int(rng.integers(lo, hi + 1)))
    # size bins per split, so that each split has every bin (its test sequences are scored per bin)
    slots: dict[int, list[str]] = {}
    for split in ("train", "test"):
        idx = [i for i, s in enumerate(specs) if s.split == split]
        labels = _allocate(sum(counts[i] for i in idx), BIN_SHARES)
        order = rng.permutation(len(labels))
        labels = [labels[k] for k in order]
        pos = 0
        for i in idx:
            slots[i] = labels[pos : pos + counts[i]]
            pos += counts[i]
    sequences = []
    tid = 0
    for i, spec in enumerate(specs):
        srng = np.random.default_rng(np.random.SeedSequence((seed, 0, i)))
        tracks = []
        for b in slots[i]:
            tid += 1
            tracks.append(_track(srng, tid, spec, b, prof.frames, prof.size))
        res = min(prof.size[0] / 640, prof.size[1] / 512)
        offset = (float(srng.normal(0, 1.5)), float(srng.uniform(1.0, 4.0)))  # lenses one above the other
        pan_speed, pan_dir = float(srng.uniform(0.0, 1.0)) * res, float(srng.uniform(0, 2 * math.pi))
        pan = (pan_speed * math.cos(pan_dir), pan_speed * math.sin(pan_dir))
        phase = srng.uniform(0, 2 * math.pi, 2)
        t = np.arange(prof.frames)
        jitter = 0.5 * np.stack([np.sin(0.3 * t + phase[0]), np.sin(0.23 * t + phase[1])], 1)
        name = f"DJI_{i + 1:04d}_{1 + i % 2}"
        sequences.append(Sequence(i, name, spec, offset, pan, tracks, jitter))
    return Plan(prof, seed, sequences)


# ---------------------------------------------------------------------------------------------- annotations
def annotate(box: tuple[float, float, float, float], rng: np.random.Generator, size: tuple[int, int]) -> list[int]:
    """How an annotator boxes a true extent: each edge off by a fraction of a pixel, integer corners, clamped to
    the frame (the release's boxes are integer VOC corners clamped to 639x511); ``[]`` when the object is less
    than half inside the frame or the box would be under 2 px."""
    x0, y0, x1, y1 = (b + float(rng.normal(0, 0.35)) for b in box)
    full = max(x1 - x0, 0) * max(y1 - y0, 0)
    cx0, cy0 = max(round(x0), 0), max(round(y0), 0)
    cx1, cy1 = min(round(x1), size[0] - 1), min(round(y1), size[1] - 1)
    if cx1 - cx0 < 2 or cy1 - cy0 < 2:
        return []
    inside = max(min(x1, size[0]) - max(x0, 0), 0) * max(min(y1, size[1]) - max(y0, 0), 0)
    if full <= 0 or inside < 0.5 * full:
        return []
    return [int(cx0), int(cy0), int(cx1 - cx0), int(cy1 - cy0)]


MODALITY_DIR = {"visible": "00", "thermal": "01"}


def coco_documents(plan: Plan) -> dict[tuple[str, str], dict[str, Any]]:
    """The four annotation files, ``{(modality dir "00"|"01", split): COCO dict}``.

    Every frame is listed in both modalities' files (paired by file name, numbered independently: the visible
    files' ids start at 100001). Annotations carry the object's ``track_id`` (the VOC files' ``<id>``).
    """
    prof = plan.profile
    cats = [{"id": i, "name": n, "supercategory": "none"} for i, n in enumerate(CATEGORIES)]
    docs: dict[tuple[str, str], dict[str, Any]] = {}
    for split in ("train", "test"):
        for mdir in ("00", "01"):
            docs[mdir, split] = {
                "info": {
                    "description": f"rgbt-tiny-synth {prof.name}, seed {plan.seed}: "
                    f"{'visible' if mdir == '00' else 'thermal'} annotations, {split}",
                },
                "images": [],
                "annotations": [],
                "categories": cats,
            }
    for seq in plan.sequences:
        split = seq.spec.split
        for t in range(prof.frames):
            arng = np.random.default_rng(np.random.SeedSequence((plan.seed, 3, seq.index, t)))
            for mdir in ("00", "01"):
                doc = docs[mdir, split]
                iid = len(doc["images"]) + (100001 if mdir == "00" else 1)
                doc["images"].append(
                    {
                        "id": iid,
                        "file_name": f"{seq.name}/{mdir}/{t:05d}.jpg",
                        "width": prof.size[0],
                        "height": prof.size[1],
                    }
                )
                for tr in seq.tracks:
                    shown = tr.visible if mdir == "00" else tr.thermal
                    true_box = seq.visible_box(tr, t) if mdir == "00" else tr.box(t)
                    bbox = annotate(true_box, arng, prof.size)  # drawn for every track: the same noise either way
                    if not shown or not bbox:
                        continue
                    doc["annotations"].append(
                        {
                            "id": len(doc["annotations"]) + 1,
                            "image_id": iid,
                            "category_id": CATEGORIES.index(tr.category),
                            "bbox": bbox,
                            "area": bbox[2] * bbox[3],
                            "iscrowd": 0,
                            "track_id": tr.id,
                        }
                    )
    return docs
