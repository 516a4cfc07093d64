"""The report as a document: its sections (tables, figures, or why they are absent) and their text renderings.

``harness.report.build`` fills a ``Report`` from a results store; ``harness.report.html`` and the Markdown/text
writers render it. Neither renderer needs the builder.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from harness.report.plots import PlotPoint
from harness.report.stats import PairedComparison
from harness.report.tables import Table
from harness.textable import fit_text


@dataclass
class FigureOut:
    name: str
    title: str
    svg: str
    caption: str
    files: list[Path] = field(default_factory=list)
    points: list[PlotPoint] = field(default_factory=list)


@dataclass
class Section:
    """A part of the report: tables and figures, or the reason it is absent and the command that would fill it."""

    key: str
    title: str
    dataset: str | None = None
    tables: list[Table] = field(default_factory=list)
    figures: list[FigureOut] = field(default_factory=list)
    absent: str | None = None
    notes: list[str] = field(default_factory=list)
    #: what the section's numbers are about, shown above its tables (the claims: the data and sizes tested)
    lead: list[str] = field(default_factory=list)
    #: pictures (``harness.report.gallery.Gallery``): one gallery per detector
    galleries: list[Any] = field(default_factory=list)

    @property
    def anchor(self) -> str:
        return f"{self.dataset or 'all'}-{self.key}".replace(" ", "-").replace("/", "-").replace("+", "-")


@dataclass
class Report:
    title: str
    store: str
    datasets: list[str]
    generated: str
    sections: list[Section] = field(default_factory=list)
    comparisons: list[PairedComparison] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    environment: dict[str, Any] = field(default_factory=dict)
    #: store files that could not be read (skipped, named with the reason)
    problems: list[str] = field(default_factory=list)
    #: one line: why the reference results asked for are not beside the store's runs (``--references-optional``)
    references_note: str | None = None

    @property
    def tables(self) -> list[Table]:
        return [t for s in self.sections for t in s.tables]

    def records(self) -> list[dict[str, Any]]:
        return [r for t in self.tables for r in t.records]

    def _by_dataset(self) -> Iterator[tuple[bool, Section]]:
        """The sections in order, each with whether it begins the part of another dataset than the one before (the
        first section does unless it is about all datasets)."""
        current = None
        for s in self.sections:
            yield s.dataset != current, s
            current = s.dataset

    def to_text(self) -> str:
        """Every table and note, aligned for the terminal (``harness report --print``)."""
        out = [self.title, f"store: {self.store}   generated: {self.generated}", ""]
        if self.references_note:
            out += [self.references_note, ""]
        if self.problems:
            out += ["!!! UNREADABLE FILES IN THE STORE (skipped) !!!", *[f"!!!   {p}" for p in self.problems], ""]
        for new_dataset, s in self._by_dataset():
            if new_dataset:
                out += [f"# {s.dataset}" if s.dataset else "# all datasets", ""]
            if s.absent:
                out += [f"{s.title}: ABSENT. {s.absent}", ""]
                continue
            if s.lead:
                out += [f"{s.title}: {s.lead[0]}", *s.lead[1:], ""]
            for t in s.tables:
                out += [t.to_text(), ""]
            for f in s.figures:
                where = ", ".join(str(p) for p in f.files) or "not written (no --out)"
                out += [f"{f.title}: {where}", f"  {f.caption}", ""]
            for g in s.galleries:
                where = str(g.thumbs[0].path.parent) if g.thumbs and g.thumbs[0].path else "no picture"
                out += [f"{s.title}, {g.name}: {len(g.thumbs)} picture(s) in {where}", *[f"  {n}" for n in g.notes]]
            if s.galleries:
                out.append("")
            out += [f"  {n}" for n in s.notes]
            if s.notes:
                out.append("")
        return fit_text("\n".join(out).rstrip()) + "\n"

    def to_markdown(self, figure_dir: str = "figures") -> str:
        out = [f"# {self.title}", "", f"Results store `{self.store}`, generated {self.generated}.", ""]
        if self.references_note:
            out += [f"> {self.references_note}", ""]
        if self.problems:
            out += ["> **⚠ Unreadable files in the store (skipped)**", *[f"> - {p}" for p in self.problems], ""]
        for new_dataset, s in self._by_dataset():
            if new_dataset:
                out += [f"## {s.dataset or 'All datasets'}", ""]
            if s.absent:
                out += [f"### {s.title}", "", f"*Absent.* {s.absent}", ""]
                continue
            if s.lead:
                out += [f"**{s.title}.** " + " ".join(s.lead), ""]
            for t in s.tables:
                out += [t.to_markdown(), ""]
            for f in s.figures:
                out += [f"### {f.title}", "", f"![{f.title}]({figure_dir}/{f.name}.png)", "", f.caption, ""]
            for g in s.galleries:
                out += [f"### {s.title}: {g.name}", ""]
                out += [f"- {n}" for n in g.notes] + ([""] if g.notes else [])
                for t in g.thumbs:
                    if t.rel:
                        out += [f"![{t.caption}]({t.rel})", "", f"*{t.caption}*", ""]
            if s.notes:
                out += [f"- {n}" for n in s.notes] + [""]
        return "\n".join(out).rstrip() + "\n"
