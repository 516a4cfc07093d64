"""Plain-text tables whose columns line up: the one formatter every command and report uses."""

from __future__ import annotations

from typing import Any, Sequence

#: Default output width: everything a command prints fits a 100-column terminal.
WIDTH = 100


def text_table(
    header: Sequence[Any],
    rows: Sequence[Sequence[Any]],
    align: str | None = None,
    width: int | None = WIDTH,
    keep: int = 1,
) -> str:
    """Header, a rule and the rows, columns separated by two spaces.

    ``align`` has one ``l`` or ``r`` per column; by default the first column is left-aligned and the others right.
    Cells are formatted with ``str``; trailing blanks are stripped. A table wider than ``width`` is split into
    panels of columns printed one below the other, each repeating the first ``keep`` columns (``width=None``: one
    table however wide).
    """
    cols = len(header)
    align = align or ("l" + "r" * (cols - 1))
    if len(align) != cols:
        raise ValueError(f"align {align!r} has {len(align)} letters for {cols} columns")
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(cols)]

    def render(idx: Sequence[int]) -> str:
        def line(row: Sequence[Any]) -> str:
            return "  ".join(
                str(row[i]).ljust(widths[i]) if align[i] == "l" else str(row[i]).rjust(widths[i]) for i in idx
            ).rstrip()

        return "\n".join([line(header), "  ".join("-" * widths[i] for i in idx), *(line(r) for r in rows)])

    return "\n\n".join(render(p) for p in column_panels(widths, width, keep))


def column_panels(widths: Sequence[int], width: int | None = WIDTH, keep: int = 1) -> list[list[int]]:
    """Column indices of each panel of a table with these column ``widths`` (two spaces between columns): one
    panel when it fits in ``width``, else as many as needed, each starting with the first ``keep`` columns."""
    cols = len(widths)
    keep = min(keep, cols)
    if width is None or sum(widths) + 2 * (cols - 1) <= width or cols <= keep + 1:
        return [list(range(cols))]
    panels: list[list[int]] = []
    base = sum(widths[:keep]) + 2 * keep
    current: list[int] = []
    used = base
    for i in range(keep, cols):
        if current and used + widths[i] > width:
            panels.append([*range(keep), *current])
            current, used = [], base
        current.append(i)
        used += widths[i] + 2
    panels.append([*range(keep), *current])
    return panels


def fit_text(text: str, width: int = WIDTH) -> str:
    """Lines longer than ``width`` wrapped at spaces, continuation lines indented two more than the line; a rule
    (dashes) is cut to ``width``."""
    import textwrap

    out = []
    for line in text.splitlines():
        if len(line) <= width:
            out.append(line)
            continue
        if line.strip() and set(line) <= set("-= "):  # a table's rule: cut to the width, not wrapped into several
            out.append(line[:width].rstrip())
            continue
        indent = " " * (len(line) - len(line.lstrip()))
        out.extend(
            textwrap.wrap(
                line.strip(),
                width,
                initial_indent=indent,
                subsequent_indent=indent + "  ",
                break_long_words=True,
                break_on_hyphens=False,
            )
            or [""]
        )
    return "\n".join(out)
