"""Housekeeping of the prepared-sample cache: what is in it, how big it is, and removing what is no longer used
(``harness cache``).

The cache holds ``<root>/<dataset>/<folder>/manifest.json`` (``harness.cache.preparation``). A prepared dataset
is *unused* when it has not been used (prepared or reused, ``.last-used``) for ``days`` days, when it refers to
source files whose folder is gone, or when it is a half-written leftover (``.<name>.*.tmp`` / ``.old-*``) of an
interrupted preparation older than an hour.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from harness.errors import DataError

LEFTOVER_AGE_S = 3600.0
#: Touched whenever a prepared dataset is prepared or reused.
USED_MARK = ".last-used"


def mark_used(folder: Path) -> None:
    """Touch ``<folder>/.last-used`` (what ``harness cache rm --unused`` goes by); a read-only cache is fine."""
    try:
        (folder / USED_MARK).touch()
    except OSError:
        pass


def folder_bytes(path: Path) -> int:
    """Bytes of the files under ``path`` (links not followed)."""
    total = 0
    for p in path.rglob("*"):
        try:
            if p.is_file() and not p.is_symlink():
                total += p.stat().st_size
        except OSError:
            pass
    return total


def human(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"  # pragma: no cover


@dataclass
class Entry:
    """One prepared dataset (or leftover) in the cache."""

    dataset: str
    name: str
    path: Path
    form: str
    count: int
    bytes: int
    source_bytes: int | None
    created: str
    last_used: float
    why_unused: str = ""

    @property
    def ref(self) -> str:
        return f"{self.dataset}/{self.name}"


def _read(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads((path / "manifest.json").read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def entries(root: Path, days: float = 30.0, now: float | None = None) -> list[Entry]:
    """Every prepared dataset and leftover under ``root``, with ``why_unused`` filled in for the unused ones."""
    now = time.time() if now is None else now
    out: list[Entry] = []
    if not root.is_dir():
        return out
    for ds_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        for folder in sorted(p for p in ds_dir.iterdir() if p.is_dir()):
            st = folder.stat().st_mtime
            manifest = None if folder.name.startswith(".") else _read(folder)
            if manifest is None:
                e = Entry(ds_dir.name, folder.name, folder, "-", 0, folder_bytes(folder), None, "-", st)
                if folder.name.startswith(".") and now - st > LEFTOVER_AGE_S:
                    e.why_unused = "left over from an interrupted preparation"
                elif not folder.name.startswith("."):
                    e.why_unused = "no manifest.json (not a prepared dataset)"
                out.append(e)
                continue
            mark = folder / USED_MARK
            used = mark.stat().st_mtime if mark.exists() else (folder / "manifest.json").stat().st_mtime
            e = Entry(
                ds_dir.name,
                folder.name,
                folder,
                manifest.get("form", "raw"),
                int(manifest.get("count", 0)),
                folder_bytes(folder),
                manifest.get("source_bytes"),
                str(manifest.get("created", "-"))[:10],
                used,
            )
            gone = [s for s in manifest.get("sources", []) if not Path(s).is_dir()]
            if gone:
                e.why_unused = f"its source folder is gone ({gone[0]})"
            elif now - used > days * 86400:
                e.why_unused = f"not used for {(now - used) / 86400:.0f} days"
            out.append(e)
    return out


def table(items: list[Entry], now: float | None = None) -> str:
    """The ``harness cache list`` table (fits 100 columns)."""
    from harness.textable import text_table

    now = time.time() if now is None else now
    rows = []
    for e in items:
        src = human(e.source_bytes) if e.source_bytes else "-"
        ago = (now - e.last_used) / 86400
        rows.append(
            [
                e.ref[:44],
                e.form,
                f"{e.count:,}",
                human(e.bytes),
                src,
                "today" if ago < 1 else f"{ago:.0f} d ago",
                "unused" if e.why_unused else "",
            ]
        )
    total = sum(e.bytes for e in items)
    body = text_table(["prepared dataset", "form", "samples", "size", "source", "last used", ""], rows, "llrrrll")
    return body + f"\n{len(items)} prepared, {human(total)} in all"


def size_line(ds: Any) -> str:
    """``cache 21.2 MB (compact form) beside 44.4 MB of source files (0.48x)`` for a prepared dataset."""
    m = ds.manifest
    size = folder_bytes(ds.folder)
    text = f"cache {human(size)} ({m.get('form', 'raw')} form)"
    src = m.get("source_bytes")
    if src:
        text += f" beside {human(src)} of source files ({size / src:.2f}x)"
    if m.get("referenced_bytes"):
        text += f"; pixels read from {human(m['referenced_bytes'])} of referenced source images"
    return text


def select(items: list[Entry], names: list[str], unused: bool) -> list[Entry]:
    """The entries ``harness cache rm`` removes: named (``dataset`` or ``dataset/folder``) or unused."""
    if unused:
        return [e for e in items if e.why_unused]
    picked: list[Entry] = []
    for name in names:
        hit = [e for e in items if name in (e.dataset, e.ref)]
        if not hit:
            known = ", ".join(sorted({e.ref for e in items})) or "nothing"
            raise DataError(f"no prepared dataset {name!r} in the cache (it holds: {known})")
        picked.extend(e for e in hit if e not in picked)
    return picked


def remove(items: list[Entry]) -> int:
    """Delete the folders; the bytes freed."""
    freed = 0
    for e in items:
        shutil.rmtree(e.path, ignore_errors=True)
        if not e.path.exists():
            freed += e.bytes
    return freed
