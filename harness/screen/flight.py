"""A flight folder as the drone writes it: which files pair into captures, which are ignored, which are bad.

DJI names every capture ``DJI_<yyyymmddHHMMSS>_<nnnn>_<W|Z|T|V>.<JPG|MP4>`` (wide RGB, zoom, thermal R-JPEG,
video). A capture to screen is a wide image ``<capture>_W.<jpg|jpeg>`` with its thermal partner
``<capture>_T.<ext>`` (an R-JPEG, or a decoded temperature file ``.png``/``.tif``/``.tiff``/``.npy`` with its
sidecar), found by capture name in the same folder, as the M3T adapter pairs them; sub-folders are searched too.
Zoom and video captures (``_Z``, ``_V``, any ``.MP4``/``.MOV``/``.SRT``/``.LRF``) and files of other names are
ignored and counted. A wide image without its thermal partner, or a thermal file without its wide image, is a bad
capture: named, skipped, and the screen ends with exit status 1.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Sequence

from harness.errors import DataError

RGB_SUFFIX = "_W"
THERMAL_SUFFIX = "_T"
RGB_EXTENSIONS = (".jpg", ".jpeg")
#: the thermal file types ``harness.sensing.pipeline.read_capture_thermal`` reads, in the order they are preferred
THERMAL_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".npy")
#: captures of the other cameras and video streams: never screened
IGNORED_SUFFIXES = ("_Z", "_V", "_S")
IGNORED_EXTENSIONS = (".mp4", ".mov", ".srt", ".lrf", ".json", ".txt", ".dat", ".obs", ".mrk", ".bin", ".nav")
_DJI_TIME = re.compile(r"DJI_(\d{14})_")
_NAME = re.compile(r"^(?P<capture>.+?)(?P<suffix>_[A-Za-z])(?P<ext>\.[A-Za-z0-9]+)$")


@dataclass(frozen=True)
class Capture:
    """One wide + thermal pair: ``name`` is the capture (``DJI_20240512094000_0001``, with its sub-folder)."""

    name: str
    rgb: Path
    thermal: Path


@dataclass
class Flight:
    """What ``find_captures`` found: the pairs to screen (sorted by name), the bad files with their reasons, and
    how many files were ignored."""

    folder: Path
    captures: list[Capture] = field(default_factory=list)
    bad: list[tuple[str, str]] = field(default_factory=list)
    ignored: int = 0
    #: the first ignored files (relative to the folder), to say what was found when nothing pairs
    ignored_examples: list[str] = field(default_factory=list)

    def ignore(self, path: Path) -> None:
        self.ignored += 1
        if len(self.ignored_examples) < 5:
            self.ignored_examples.append(path.relative_to(self.folder).as_posix())

    def why_empty(self) -> str:
        """Why the flight gives nothing to screen (when it has no capture)."""
        if not self.ignored and not self.bad:
            return f"{self.folder} holds no files"
        text = (
            f"{self.folder} holds no wide/thermal pair: a capture is <name>{RGB_SUFFIX}.JPG beside "
            f"<name>{THERMAL_SUFFIX}.JPG (or a decoded <name>{THERMAL_SUFFIX}.png/.tif/.tiff/.npy), as DJI names them"
        )
        if self.ignored:
            text += (
                f"; {self.ignored} file(s) ignored (zoom {', '.join(IGNORED_SUFFIXES[:2])} and video captures, other "
                f"names), e.g. {', '.join(self.ignored_examples[:3])}"
            )
        if self.bad:
            text += f"; {len(self.bad)} file(s) without a partner"
        return text


def find_captures(folder: str | Path) -> Flight:
    """Pair the wide and thermal images of ``folder`` (and its sub-folders) by capture name."""
    root = Path(folder)
    if not root.is_dir():
        raise DataError(f"{root}: the flight folder does not exist (give the folder the drone's images are in)")
    flight = Flight(root)
    rgb: dict[str, Path] = {}
    thermal: dict[str, list[Path]] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        here = Path(dirpath)
        for fname in sorted(filenames):
            if fname.startswith("."):
                continue
            m = _NAME.match(fname)
            ext = Path(fname).suffix.lower()
            if m is None or ext in IGNORED_EXTENSIONS:
                flight.ignore(here / fname)
                continue
            rel = (here / m["capture"]).relative_to(root).as_posix()
            suffix = m["suffix"].upper()
            if suffix == RGB_SUFFIX and ext in RGB_EXTENSIONS:
                rgb[rel] = here / fname
            elif suffix == THERMAL_SUFFIX and ext in THERMAL_EXTENSIONS:
                thermal.setdefault(rel, []).append(here / fname)
            else:
                flight.ignore(here / fname)
    for name in sorted(set(rgb) | set(thermal)):
        if name not in thermal:
            flight.bad.append((str(rgb[name]), f"no thermal partner: no {Path(name).name}{THERMAL_SUFFIX}.* beside it"))
            continue
        if name not in rgb:
            for t in thermal[name]:
                flight.bad.append((str(t), f"no wide partner: no {Path(name).name}{RGB_SUFFIX}.JPG beside it"))
            continue
        partner = min(thermal[name], key=lambda p: THERMAL_EXTENSIONS.index(p.suffix.lower()))
        flight.captures.append(Capture(name, rgb[name], partner))
    return flight


def capture_time(cap: Capture) -> datetime | None:
    """When a capture was taken: the time in its DJI name, else its wide image's EXIF ``DateTimeOriginal``."""
    from harness.errors import HarnessError
    from harness.sensing.registration import capture_time as exif_time

    m = _DJI_TIME.search(cap.rgb.name)
    if m:
        try:
            return datetime.strptime(m.group(1), "%Y%m%d%H%M%S")
        except ValueError:
            pass
    try:
        return exif_time(cap.rgb)
    except HarnessError:
        return None


def inspection_groups(captures: Sequence[Capture], gap_s: float) -> dict[str, str]:
    """``{capture: group}``: a new group wherever consecutive capture times are more than ``gap_s`` apart
    (``group_by_capture_time``, the datasets' rule); a capture without a time is a group of its own."""
    from harness.sensing.registration import group_by_capture_time

    times = {c.name: capture_time(c) for c in captures}
    timed = {k: v for k, v in times.items() if v is not None}
    groups = group_by_capture_time(timed, gap_s=gap_s, prefix="G") if timed else {}
    return {c.name: groups.get(c.name, f"single:{c.name}") for c in captures}
