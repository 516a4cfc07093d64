"""Inspection groups: captures split wherever consecutive capture times are far apart."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path
from typing import Mapping

from harness.errors import DataError


def capture_time(path: str | Path) -> datetime | None:
    """EXIF ``DateTimeOriginal`` (+ sub-seconds) of a JPEG, or None when it has none."""
    from harness.sensing import jpeg

    exif = jpeg.read_exif(path)
    return jpeg.parse_exif_datetime(
        exif.get("DateTimeOriginal") or exif.get("DateTime"), exif.get("SubSecTimeOriginal")
    )


def group_by_capture_time(
    times: Mapping[str, datetime | str | None], gap_s: float = 300.0, prefix: str = "G"
) -> dict[str, str]:
    """Split captures into inspection groups wherever consecutive capture times are more than ``gap_s`` apart.

    ``times``: ``{capture key: datetime or EXIF 'YYYY:MM:DD HH:MM:SS'}``. Returns ``{key: group}`` with groups
    named ``<prefix>01``, ``<prefix>02``, ... in time order. A capture without a time is a ``DataError`` naming it
    (give its group explicitly instead).
    """
    from harness.sensing.jpeg import parse_exif_datetime

    parsed: list[tuple[datetime, str]] = []
    missing = []
    for key, value in times.items():
        dt = parse_exif_datetime(value) if value is not None else None
        if dt is None:
            missing.append(str(key))
        else:
            parsed.append((dt, str(key)))
    if missing:
        raise DataError(
            f"no capture time for {len(missing)} capture(s) ({', '.join(missing[:5])}"
            f"{', ...' if len(missing) > 5 else ''}); give their groups explicitly"
        )
    parsed.sort()
    out: dict[str, str] = {}
    group = 0
    prev: datetime | None = None
    for dt, key in parsed:
        if prev is None or (dt - prev).total_seconds() > gap_s:
            group += 1
        out[key] = f"{prefix}{group:02d}"
        prev = dt
    return out
