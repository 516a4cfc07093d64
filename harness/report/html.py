"""One self-contained HTML page: inline CSS, figures as inline SVG, gallery thumbnails as inline JPEG (data URIs),
no script, no external request.

Best value of a column in bold, summary rows (support, means) in grey italics, Pareto members marked, a red banner
on every table whose rows were not sample-matched, and a dashed box for every absent section with the command
that would fill it. The page can be mailed or archived on its own.
"""

from __future__ import annotations

import base64
from html import escape
from typing import Any

from harness.report.document import Report, Section
from harness.report.plots import inline_svg
from harness.report.tables import Table

CSS = """
:root { --fg: #1d2329; --muted: #5b6670; --line: #d5dbe1; --head: #eef2f6; --warn: #b00020; --best: #0b4f8a; }
* { box-sizing: border-box; }
body { font: 14px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif; color: var(--fg);
       margin: 0 auto; padding: 24px 32px 48px; max-width: 1400px; background: #fff; }
h1 { font-size: 24px; margin: 0 0 4px; }
h2 { font-size: 20px; margin: 36px 0 8px; padding-bottom: 4px; border-bottom: 2px solid var(--line); }
h3 { font-size: 16px; margin: 24px 0 6px; }
.meta { color: var(--muted); margin: 0 0 16px; }
nav { background: var(--head); border-radius: 6px; padding: 10px 16px; margin: 12px 0 20px; columns: 2; }
nav a { color: var(--best); text-decoration: none; display: block; }
nav a.off { color: var(--muted); }
.table-wrap { overflow-x: auto; margin: 6px 0 4px; }
table { border-collapse: collapse; font-variant-numeric: tabular-nums; }
th, td { border: 1px solid var(--line); padding: 3px 6px; white-space: nowrap; }
th, td.l { white-space: normal; }
th { font-size: 12.5px; }
th { background: var(--head); font-weight: 600; }
th.group { text-align: center; border-bottom-color: #aeb8c2; }
td.r, th.r { text-align: right; }
td.l, th.l { text-align: left; }
td.best { font-weight: 700; color: var(--best); }
tr.block th { background: #fff; color: var(--best); font-style: italic; border-top: 2px solid #aeb8c2; }
tr.summary td { color: var(--muted); font-style: italic; background: #fafbfc; }
td.pareto { color: #1b7f3b; font-weight: 700; text-align: center; }
.loud { border: 3px solid var(--warn); background: #fff1f3; color: var(--warn); padding: 8px 12px; margin: 8px 0;
        border-radius: 4px; font-weight: 700; text-transform: uppercase; letter-spacing: 0.02em; }
.loud ul { margin: 4px 0 0; padding-left: 20px; text-transform: none; font-weight: 400; color: #5a0010; }
.absent { border: 2px dashed var(--line); color: var(--muted); padding: 8px 12px; border-radius: 4px; margin: 8px 0; }
.absent b { color: var(--fg); }
p.lead { border-left: 4px solid var(--best); background: var(--head); padding: 6px 10px; margin: 8px 0; }
ul.notes { color: var(--muted); font-size: 12.5px; margin: 4px 0 12px; padding-left: 18px; }
code { background: var(--head); padding: 1px 4px; border-radius: 3px; font-size: 12.5px; }
figure { margin: 10px 0; }
figure svg.figure { width: 100%; max-width: 1200px; height: auto; display: block; }
figcaption { color: var(--muted); font-size: 12.5px; max-width: 1200px; }
.gallery { display: flex; flex-wrap: wrap; gap: 10px 14px; margin: 6px 0 14px; }
figure.thumb { margin: 0; max-width: 100%; }
figure.thumb img { display: block; max-width: 100%; height: auto; border: 1px solid var(--line); }
figure.thumb figcaption { font-size: 11.5px; max-width: 640px; }
footer { margin-top: 40px; color: var(--muted); font-size: 12px; border-top: 1px solid var(--line); padding-top: 8px; }
"""


def _code(text: str) -> str:
    """Escape ``text`` and turn `backtick` spans into <code>."""
    parts = escape(text).split("`")
    return "".join(f"<code>{p}</code>" if i % 2 else p for i, p in enumerate(parts))


def _header(t: Table) -> str:
    """One header row, or two when columns are grouped (a spanning group cell over the columns' short labels)."""
    if not any(c.group for c in t.columns):
        return "<tr>" + "".join(f'<th class="{c.align}">{escape(c.label)}</th>' for c in t.columns) + "</tr>"
    top, bottom = [], []
    i = 0
    while i < len(t.columns):
        c = t.columns[i]
        if not c.group:
            top.append(f'<th rowspan="2" class="{c.align}">{escape(c.label)}</th>')
            i += 1
            continue
        j = i
        while j < len(t.columns) and t.columns[j].group == c.group:
            bottom.append(f'<th class="{t.columns[j].align}">{escape(t.columns[j].short or t.columns[j].label)}</th>')
            j += 1
        top.append(f'<th colspan="{j - i}" class="group">{escape(c.group)}</th>')
        i = j
    return f"<tr>{''.join(top)}</tr><tr>{''.join(bottom)}</tr>"


def render_table(t: Table) -> str:
    out = [f'<h3 id="{escape(t.name)}">{escape(t.title)}</h3>']
    if t.warning:
        items = "".join(f"<li>{escape(d)}</li>" for d in t.warning_details)
        out.append(f'<div class="loud" role="alert">⚠ {escape(t.warning)}{f"<ul>{items}</ul>" if items else ""}</div>')
    best = {c.key: t.best_rows(c) for c in t.columns}
    head = _header(t)
    body = []
    starts = t.block_starts()
    for i, r in enumerate(t.rows):
        if i in starts:
            body.append(f'<tr class="block"><th class="l" colspan="{len(t.columns)}">{escape(starts[i])}</th></tr>')
        cells = []
        for c in t.columns:
            text = t.cell(r, c)
            cls = [c.align]
            if i in best[c.key] and text not in ("", "-"):
                cls.append("best")
            if c.key == "pareto":
                text = "●" if text == "yes" else ""
                if text:
                    cls.append("pareto")
            cells.append(f'<td class="{" ".join(cls)}">{escape(text)}</td>')
        row_cls = ' class="summary"' if r.get("_summary") else ""
        body.append(f"<tr{row_cls}>{''.join(cells)}</tr>")
    out.append(f'<div class="table-wrap"><table><thead>{head}</thead><tbody>{"".join(body)}</tbody></table></div>')
    if t.notes:
        out.append('<ul class="notes">' + "".join(f"<li>{_code(n)}</li>" for n in t.notes) + "</ul>")
    return "\n".join(out)


def render_gallery(s: Section, g: Any) -> str:
    """One detector's gallery: its thumbnails inline (JPEG data URIs), each with its caption."""
    out = [f'<h3 id="{escape(s.anchor)}-{escape(_anchor(g.name))}">{escape(s.title)}: {escape(g.name)}</h3>']
    if g.notes:
        out.append('<ul class="notes">' + "".join(f"<li>{_code(n)}</li>" for n in g.notes) + "</ul>")
    thumbs = []
    for t in g.thumbs:
        data = base64.b64encode(t.data).decode("ascii")
        thumbs.append(
            f'<figure class="thumb"><img src="data:image/jpeg;base64,{data}" alt="{escape(t.caption)}">'
            f"<figcaption>{escape(t.caption)}</figcaption></figure>"
        )
    if thumbs:
        out.append(f'<div class="gallery">{"".join(thumbs)}</div>')
    return "\n".join(out)


def _anchor(text: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in text)


def render_section(s: Section) -> str:
    out = [f'<section id="{escape(s.anchor)}">']
    if s.absent:
        out.append(f"<h3>{escape(s.title)}</h3>")
        out.append(f'<div class="absent"><b>Absent.</b> {_code(s.absent)}</div>')
    if s.lead and not s.absent:
        out.append(f'<p class="lead"><b>{escape(s.title)}.</b> {" ".join(_code(x) for x in s.lead)}</p>')
    for t in s.tables:
        out.append(render_table(t))
    for f in s.figures:
        out.append(f"<h3>{escape(f.title)}</h3>")
        links = " · ".join(f'<a href="figures/{escape(p.name)}">{escape(p.suffix[1:].upper())}</a>' for p in f.files)
        out.append(
            f"<figure>{inline_svg(f.svg)}<figcaption>Conventions as printed on the figure."
            f"{f' Files: {links}.' if links else ''}</figcaption></figure>"
        )
    for g in s.galleries:
        out.append(render_gallery(s, g))
    if s.notes:
        out.append('<ul class="notes">' + "".join(f"<li>{_code(n)}</li>" for n in s.notes) + "</ul>")
    out.append("</section>")
    return "\n".join(out)


def render_html(report: Report) -> str:
    nav, body = [], []
    current = object()
    for s in report.sections:
        if s.dataset != current:
            current = s.dataset
            title = s.dataset or "All datasets"
            body.append(f'<h2 id="ds-{escape(str(s.dataset or "all"))}">{escape(title)}</h2>')
            nav.append(f"<b>{escape(title)}</b>")
        cls = ' class="off"' if s.absent else ""
        warn = " ⚠" if any(t.warning for t in s.tables) else ""
        nav.append(f'<a{cls} href="#{escape(s.anchor)}">{escape(s.title)}{warn}{" (absent)" if s.absent else ""}</a>')
        body.append(render_section(s))
    warned = [t.title for t in report.tables if t.warning]
    banner = f'<p class="absent">{_code(report.references_note)}</p>' if report.references_note else ""
    if report.problems:
        banner += (
            f'<div class="loud" role="alert">⚠ unreadable files in the store (skipped)<ul>'
            f"{''.join(f'<li>{escape(p)}</li>' for p in report.problems)}</ul></div>"
        )
    if warned:
        banner += (
            f'<div class="loud" role="alert">⚠ {len(warned)} table(s) compare rows that were not scored on the '
            f"same samples<ul>{''.join(f'<li>{escape(w)}</li>' for w in warned)}</ul></div>"
        )
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<meta name="generator" content="harness report">
<title>{escape(report.title)}</title>
<style>{CSS}</style>
</head>
<body>
<h1>{escape(report.title)}</h1>
<p class="meta">Results store <code>{escape(report.store)}</code> · generated {escape(report.generated)} ·
datasets: {escape(", ".join(report.datasets))} · AP in % unless stated; every number with its support (images,
instances).</p>
{banner}
<nav>{"".join(nav)}</nav>
{"".join(body)}
<footer>Generated by <code>harness report</code> from the results store alone (metrics.json, predictions.json,
gt.json, _sensing). Definitions: docs/evaluation.md and docs/reports.md.</footer>
</body>
</html>
"""
