"""What the sources of paired visible/thermal releases share (LLVIP, M3FD, FLIR-aligned, RGBT-Tiny, coco-rgbt).

* ``SkipPair``: a pair that cannot be used, raised by a source's ``_sample`` and turned into a counted skip (the M3T
  adapter raises it too).
* ``PairedSource``: the skeleton of such a source: the pairs dropped while opening and the opening notes go to the
  prepare report first, then one sample per item, a ``SkipPair`` becoming a counted skip (an error in strict mode),
  and the closing notes (``BoxStats``) even when the preparation stops early; the fingerprint's first parts.
* ``SplitSource``: a release with an official ``train``/``test`` split, which is its one fold, whose infrared and
  visible images pair by name.
* ``read_pair``: the 8-bit thermal and visible images of a pair, which must have one size.
* ``eightbit_spec``: the ``DatasetSpec`` of a release that ships 8-bit thermal images.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, TypeVar

import numpy as np

from adapters.datasets._eightbit import BoxStats, ImageReadError, read_rgb, read_thermal8, source_parts
from harness.api import DatasetSpec, Fold, PrepareReport
from harness.errors import DataError
from harness.sample import AlignedSample

T = TypeVar("T")

SPLITS = ("train", "test")


class SkipPair(Exception):
    """A pair that cannot be used: a counted skip with this reason, of ``path`` (the caller's item when ``None``)."""

    def __init__(self, reason: str, path: str | Path | None = None):
        super().__init__(reason)
        self.reason, self.path = reason, path


class PairedSource:
    """The part of a ``DatasetSource`` that every paired release shares (see the module docstring).

    A subclass sets ``name`` (the dataset), ``log_name`` (how its log lines name it), ``root``, ``strict``,
    ``dropped`` (``(path, reason)`` of the pairs left out while opening) and ``notes``, and implements
    ``_closing_notes``.
    """

    name: str
    log_name: str
    root: Path
    strict: bool = False
    dropped: list[tuple[str, str]]
    notes: list[str]
    #: How a log line names a skipped pair ("skipped", "dropped").
    skip_verb = "skipped"

    @property
    def _log(self) -> logging.Logger:
        return logging.getLogger(type(self).__module__)

    def _check_drops(self) -> None:
        """Log the last opening note when pairs were dropped; in strict mode the first drop is an error."""
        if self.dropped:
            self._log.warning("%s: %s", self.log_name, self.notes[-1])
            if self.strict:
                path, reason = self.dropped[0]
                raise DataError(f"dataset {self.name!r} (strict): {path}: {reason}")

    def _skip(self, report: PrepareReport, path: str | Path, reason: str) -> None:
        if self.strict:
            raise DataError(f"{path}: {reason}")
        self._log.warning("%s: %s %s (%s)", self.log_name, self.skip_verb, path, reason)
        report.skip(path, reason)

    def _samples(
        self, report: PrepareReport, items: Iterable[T], make: Callable[[T], tuple[AlignedSample, BoxStats]]
    ) -> Iterator[AlignedSample]:
        """The opening drops and notes, then ``make(item)`` for every item; a ``SkipPair`` is a counted skip of its
        path (else of ``str(item)``). The closing notes are written even when the preparation stops early."""
        for path, reason in self.dropped:
            report.skip(path, reason)
        for note in self.notes:
            report.note(note)
        stats = BoxStats()
        try:
            for item in items:
                try:
                    sample, item_stats = make(item)
                except SkipPair as exc:
                    self._skip(report, exc.path if exc.path is not None else str(item), exc.reason)
                    continue
                stats.add(item_stats)
                yield sample
        finally:
            self._closing_notes(report, stats)

    def _closing_notes(self, report: PrepareReport, stats: BoxStats) -> None:
        raise NotImplementedError

    def _fingerprint_parts(self, version: int, *options: Any) -> list[Any]:
        """``source_parts`` of this source: its name, the adapter's ``version``, its root, then ``options``."""
        return source_parts(self.name, version, self.root, *options)


class SplitSource(PairedSource):
    """A release with the official ``train``/``test`` split: ``frames`` are tuples whose first item is the split;
    the groups are the splits and the one fold ``test`` holds ``test`` out."""

    frames: list[tuple[Any, ...]]

    def __len__(self) -> int:
        return len(self.frames)

    def groups(self) -> list[str]:
        return [s for s in SPLITS if any(f[0] == s for f in self.frames)]

    def folds(self) -> list[Fold]:
        return [Fold("test", ("train",), ("test",))] if self.groups() == list(SPLITS) else []

    def _pairs_by_name(
        self, ir: Mapping[str, Path], vis: Mapping[str, Path], not_found: Callable[[str, str], str]
    ) -> Iterator[tuple[str, Path, Path]]:
        """``(name, infrared image, visible image)`` of the names that have both images, in name order; a name with
        one image only is dropped as ``missing <modality> frame: <not_found(modality, name)>``."""
        for name in sorted(set(ir) | set(vis)):
            if name not in ir:
                self.dropped.append((str(vis[name]), f"missing infrared frame: {not_found('infrared', name)}"))
            elif name not in vis:
                self.dropped.append((str(ir[name]), f"missing visible frame: {not_found('visible', name)}"))
            else:
                yield name, ir[name], vis[name]

    def _split_note(self) -> str:
        counts = {s: sum(f[0] == s for f in self.frames) for s in SPLITS}
        return f"{counts['train']} train / {counts['test']} test pairs, {len(self.dropped)} dropped"


def read_pair(
    thermal: Path, visible: Path, where: Path, names: tuple[str, str] = ("visible", "infrared")
) -> tuple[np.ndarray, bool, np.ndarray]:
    """The 8-bit thermal image (uint8 HxW), whether it was converted from colour, and the visible image (uint8
    HxWx3); ``SkipPair`` on ``where`` when either cannot be decoded or their sizes differ (``names`` name the
    visible and thermal sides in the message)."""
    try:
        ir8, was_colour = read_thermal8(thermal)
        rgb = read_rgb(visible)
    except ImageReadError as exc:
        raise SkipPair(f"unreadable image: {exc}", where) from None
    h, w = ir8.shape
    if rgb.shape[:2] != (h, w):
        raise SkipPair(f"size mismatch: {names[0]} {rgb.shape[1]}x{rgb.shape[0]}, {names[1]} {w}x{h}", where)
    return ir8, was_colour, rgb


def eightbit_spec(
    name: str,
    open: Callable[..., Any],
    categories: tuple[str, ...],
    description: str,
    root_env: str,
    default_encoding: str = "proxy8",
) -> DatasetSpec:
    """The spec of a release with 8-bit thermal images; its protocol is named like the dataset."""
    return DatasetSpec(
        name=name,
        open=open,
        categories=categories,
        description=description,
        thermal="8bit",
        default_encoding=default_encoding,
        protocol=name,
        root_env=root_env,
    )
