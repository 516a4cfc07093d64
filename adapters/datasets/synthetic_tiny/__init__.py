"""A synthetic RGBT-Tiny-like set: paired visible and 8-bit thermal sequences of tiny targets, written in the
layout of the unpacked RGBT-Tiny release so that the ``rgbt-tiny`` adapter reads it unchanged.

It stands in for RGBT-Tiny as ``m3t-synth`` stands in for M3T (``harness synth --family rgbt-tiny``). The model
(details and its limits in ``docs/datasets.md``):

* **Sequences** over sky, sea and ground backgrounds, by day and by night, split into train and test by sequence;
  the camera pans slowly, so the background moves under the targets.
* **Targets** of the release's seven classes (ship, car, cyclist, pedestrian, bus, drone, plane; which ones by
  scene), mostly tiny: each split's tracks are drawn in SAFit's size bins in fixed shares (85 % of the tracks
  under 16x16 px, every bin present), moving smoothly (constant speed, slowly turning heading, slowly changing
  size).
* **Two annotation sources** (``instances_01_*`` thermal, ``instances_00_*`` visible), each drawn on its own
  image: the visible frame is off by the sequence's registration offset (mostly vertical: the lenses sit one above
  the other), a per-object parallax (airborne objects more) and a sub-pixel jitter; objects at ambient temperature
  have no thermal signature and no thermal box; at night only lit objects are seen (and boxed) in the visible frame.
* **Thermal signature**: an extended blob, a soft core the object's size plus a warm Gaussian halo 0.7-1.5 times
  the object's size (at least 2.5 px), not a sharp-edged patch.
* **Sensors**: thermal optics blur, vignetting, column and temporal noise, per-frame automatic gain control to
  8 bit; visible exposure, vignetting and noise (strong at night); JPEG files for both.

Deterministic in the seed: the plan draws from ``SeedSequence((seed, 0, ...))``, each sequence's background from
``(seed, 1, sequence)`` and each frame from ``(seed, 2, sequence, frame)``, whatever the number of workers.
"""

from __future__ import annotations

from adapters.datasets.synthetic_tiny.generation import (
    GENERATOR,
    GENERATOR_VERSION,
    MARKER,
    TinySynthSummary,
    default_root,
    generate,
)
from adapters.datasets.synthetic_tiny.model import (
    BIN_SHARES,
    CATEGORIES,
    PROFILES,
    SIZE_BINS,
    Plan,
    Profile,
    coco_documents,
    get_profile,
    plan_dataset,
)

__all__ = [
    "GENERATOR",
    "GENERATOR_VERSION",
    "MARKER",
    "TinySynthSummary",
    "default_root",
    "generate",
    "BIN_SHARES",
    "CATEGORIES",
    "PROFILES",
    "SIZE_BINS",
    "Plan",
    "Profile",
    "coco_documents",
    "get_profile",
    "plan_dataset",
]
