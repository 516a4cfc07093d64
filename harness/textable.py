"""Plain-text tables whose columns line up: the one formatter every command and report uses."""

from __future__ import annotations

from typing import Any, Sequence


def text_table(header: Sequence[Any], rows: Sequence[Sequence[Any]], align: str | None = None) -> str:
    """Header, a rule and the rows, columns separated by two spaces.

    ``align`` has one ``l`` or ``r`` per column; by default the first column is left-aligned and the others right.
    Cells are formatted with ``str``; trailing blanks are stripped.
    """
    cols = len(header)
    align = align or ("l" + "r" * (cols - 1))
    if len(align) != cols:
        raise ValueError(f"align {align!r} has {len(align)} letters for {cols} columns")
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(cols)]

    def line(row: Sequence[Any]) -> str:
        return "  ".join(str(c).ljust(w) if a == "l" else str(c).rjust(w)
                         for c, w, a in zip(row, widths, align)).rstrip()

    return "\n".join([line(header), "  ".join("-" * w for w in widths), *(line(r) for r in rows)])
