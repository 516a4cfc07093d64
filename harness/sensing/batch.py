"""Decode a whole flight: R-JPEG files and folders to temperature files, finishing what it can.

``decode_batch(inputs, out_dir, options)`` takes files and folders (folders are searched recursively for
``.jpg``/``.jpeg`` files; a JPEG there without a radiometric payload, such as the visible-camera picture of the
same capture, is passed over and counted, not failed; a radiometric JPEG of another make, such as a FLIR file with
its APP1 ``FLIR`` container, is not passed over: it fails, naming the camera, as it does when named directly).
Every readable file is decoded; each output (the
temperature file, its sidecar and the optional preview) is written to a temporary name in the output folder and
renamed into place, so an interrupted batch leaves whole files only. A file that cannot be decoded is recorded
as ``(file, reason)`` and the batch goes on, unless ``fail_fast``, which raises the first error as it comes; a
``ConfigError`` (a setting wrong for every file, such as an override out of range or a converter that cannot be
started) stops the batch either way. A value wrong in one file (an emissivity of about 0 in its APP4 block) is that
file's failure. A folder without any ``.jpg``/``.jpeg`` file is a failure too, and a batch that decodes nothing is
not a success. ``workers > 1`` decodes in that many processes.

Each file's route (``radiometry.route_label``: DJI's correction, the converter, the labelled approximate route, or
blackbody when asked for) is in its table row and its sidecar (``decoder``, ``decoder_route``, and ``approximate``
or ``converter`` with what was applied).

Outputs keep the inputs' layout: ``<out>/<stem>.<ext>`` for a file named directly, and
``<out>/<path below the folder>/<stem>.<ext>`` for a file found in a folder, so two flights' ``DJI_0001_T.JPG``
do not overwrite each other. The sidecar records the measurement parameters exactly as the file's APP4 block
stores them (float32 values written with the shortest decimal that reads back to the same float32).
"""

from __future__ import annotations

import logging
import os
import struct
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass, field
from decimal import Decimal
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from harness.errors import ConfigError, DataError, HarnessError

log = logging.getLogger(__name__)

RJPEG_SUFFIXES = (".jpg", ".jpeg")
#: APP4 parameters in file order: (name, factor to the reported unit); humidity is stored as a fraction.
APP4_PARAMS = (("ambient", 1), ("distance", 1), ("emissivity", 1), ("humidity", 100), ("reflected", 1))


@dataclass(frozen=True)
class DecodeOptions:
    """How each file is decoded and written (the ``harness sensing decode`` options)."""

    unit: str = "centikelvin"
    fmt: str | None = None  # png for centikelvin, tiff otherwise
    preview: bool = False
    decoder: str = "auto"
    overrides: Mapping[str, float | None] = field(default_factory=dict)
    approximate: bool = False  # allow the labelled approximate route (``dji_approximate``)
    converter: Any = None  # a ``dji_converter.Converter`` for the files the harness cannot correct

    @property
    def suffix(self) -> str:
        fmt = self.fmt or ("png" if self.unit == "centikelvin" else "tiff")
        return "tif" if fmt == "tiff" else fmt


@dataclass
class BatchResult:
    """What a batch did: one row per decoded file, the failures ``(file, reason)`` and the JPEGs passed over."""

    decoded: list[dict[str, Any]] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)
    passed_over: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failed and bool(self.decoded)


@dataclass(frozen=True)
class _Job:
    source: Path
    target: Path
    from_folder: bool


def collect_jobs(
    inputs: Iterable[str | Path], out_dir: str | Path, suffix: str
) -> tuple[list[_Job], list[tuple[str, str]]]:
    """The files to decode with their targets, and the inputs that already fail (missing, or a second input
    with the same target)."""
    out_dir = Path(out_dir)
    jobs: list[_Job] = []
    failed: list[tuple[str, str]] = []
    seen: dict[Path, Path] = {}

    def add(src: Path, target: Path, from_folder: bool) -> None:
        if target in seen:
            failed.append((str(src), f"same output {target} as {seen[target]}"))
            return
        seen[target] = src
        jobs.append(_Job(src, target, from_folder))

    for item in inputs:
        p = Path(item)
        if p.is_dir():
            found = sorted(f for f in p.rglob("*") if f.is_file() and f.suffix.lower() in RJPEG_SUFFIXES)
            if not found:
                failed.append(
                    (str(p), "a folder without any .jpg/.jpeg file (give R-JPEG files or folders holding them)")
                )
            for f in found:
                rel = f.relative_to(p)
                add(f, out_dir / rel.parent / f"{f.stem}.{suffix}", True)
        elif p.is_file():
            add(p, out_dir / f"{p.stem}.{suffix}", False)
        else:
            failed.append((str(p), "file not found"))
    return jobs, failed


def exact_params(data: bytes, name: str | Path, layout: Any = None) -> dict[str, float]:
    """The five APP4 measurement parameters as stored (float32), each the shortest decimal that reads back to
    the same float32; humidity in % (stored as a fraction). Empty when the file has no iirp APP4 block.
    ``layout``: the file's ``jpeg.read_segments`` result, when already at hand."""
    from harness.sensing import dji_dirp, jpeg
    from harness.sensing.radiometry import APP4_MAGIC

    layout = layout or jpeg.read_segments(data, name, require_eoi=False)
    app4 = layout.payloads(jpeg.APP4)
    if not app4:
        return {}
    payload = app4[0]
    if dji_dirp.is_dirp_block(payload):  # H20T: the block's own parameters (the decoder's ``params``)
        return {}
    base = 32 if payload.startswith(APP4_MAGIC) else 0
    if base and payload[4:8].split(b"\x00", 1)[0] != b"iirp":
        return {}
    if len(payload) < base + 20:
        return {}
    values = struct.unpack("<5f", payload[base : base + 20])
    out = {}
    for (key, factor), v in zip(APP4_PARAMS, values):
        shortest = Decimal(str(np.float32(v)))  # the shortest decimal that reads back to this float32
        out[key] = float(shortest * Decimal(int(factor)))  # decimal scaling: 0.55 -> 55.0, not 55.00000000000001
    return out


def flir_payload(layout: Any) -> bool:
    """Whether a JPEG carries FLIR's radiometric container (APP1 segments starting ``FLIR\\0``): a thermal
    picture of another make, which a folder search must not pass over as a visible-camera JPEG."""
    from harness.sensing import jpeg

    return any(p.startswith(b"FLIR\x00") for p in layout.payloads(jpeg.APP1))


def _temporary(target: Path) -> Path:
    """A hidden name beside ``target`` with the same suffix (the writers choose the format by it)."""
    return target.with_name(f".{target.stem}.{os.getpid()}.tmp{target.suffix}")


def decode_one(source: Path, target: Path, options: DecodeOptions, from_folder: bool = False) -> dict[str, Any]:
    """Decode one R-JPEG to ``target`` (+ sidecar, + preview), each written whole and renamed into place.

    Returns the table row (``{"file", "size", "route", ...}``), or ``{"passed_over": True}`` for a JPEG found in
    a folder without a radiometric payload. Errors are ``HarnessError``s naming the file."""
    from harness.sensing import jpeg
    from harness.sensing.radiometry import read_rjpeg, rjpeg_temperature, sidecar_path, write_thermal

    try:
        data = source.read_bytes()
    except OSError as exc:
        raise DataError(f"{source}: cannot read ({exc.strerror or exc})") from None
    layout = jpeg.read_segments(data, source, require_eoi=False)  # a damaged header fails here, naming the file
    if from_folder and not layout.payloads(jpeg.APP3) and not flir_payload(layout):
        return {"passed_over": True}  # no radiometric counts: e.g. the visible camera's JPEG
    rj = read_rjpeg(source, options.decoder, options.approximate, options.converter)
    t, info = rjpeg_temperature(rj, dict(options.overrides))
    # the parameters the route applied: none for blackbody (the columns would show values that were not used)
    used = info.get("correction") or (info["converter"]["params"] if "converter" in info else {})
    route = info["route"]
    # only an iirp APP4 block holds the five float32 parameters (an XT S keeps raw words there)
    params = (exact_params(data, source, layout) if rj.fmt == "iirp" else {}) or dict(rj.params)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary(target)
    moves = [(tmp, target), (sidecar_path(tmp), sidecar_path(target))]
    try:
        write_thermal(
            tmp,
            t,
            unit=options.unit,
            params=params,
            extra={
                "source": str(source),
                "decoder": route,
                "decoder_route": rj.decoder,
                **({"decoder_note": rj.decoder_note} if rj.decoder_note else {}),
                **{k: info[k] for k in ("correction", "approximate", "converter") if k in info},
                **({"temperatures": info["approximate"]["label"]} if "approximate" in info else {}),
                "exif": {k: v for k, v in rj.exif.items() if isinstance(v, (str, int, float))},
            },
        )
        if options.preview:
            import cv2

            ir8 = target.with_name(f"{target.stem}_ir8.png")
            tmp_ir8 = _temporary(ir8)
            moves.append((tmp_ir8, ir8))
            if not cv2.imwrite(str(tmp_ir8), rj.preview(grayscale=True)):
                raise DataError(f"{ir8}: could not write the preview")
        for a, b in moves:
            os.replace(a, b)
    finally:
        for a, _ in moves:
            a.unlink(missing_ok=True)
    return {
        "file": source.name,
        "source": str(source),
        "size": f"{t.shape[1]}x{t.shape[0]}",
        "route": rj.decoder,
        "route_label": route,
        "approximate": info.get("approximate"),
        "min": float(np.nanmin(t)),
        "max": float(np.nanmax(t)),
        "mean": float(np.nanmean(t)),
        "emissivity": float(used.get("emissivity", float("nan"))),
        "distance": float(used.get("distance", float("nan"))),
        "written": str(target),
    }


def _run(job: _Job, options: DecodeOptions) -> tuple[dict[str, Any] | None, str | None]:
    """``decode_one`` with its error as text (what a worker process sends back)."""
    try:
        return decode_one(job.source, job.target, options, job.from_folder), None
    except ConfigError:
        raise  # a wrong setting (e.g. an override out of range) is not a property of one file: the batch stops
    except HarnessError as exc:
        return None, _reason(exc, job.source)
    except Exception as exc:  # a damaged file can make a decoder library raise anything; the batch goes on
        return None, _reason(exc, job.source, unexpected=True)


def _reason(exc: BaseException, source: Path, unexpected: bool = False) -> str:
    text = str(exc).removeprefix(f"{source}: ")
    return f"{type(exc).__name__}: {text}" if unexpected else text


def decode_batch(
    inputs: Iterable[str | Path],
    out_dir: str | Path,
    options: DecodeOptions | None = None,
    workers: int = 1,
    fail_fast: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> BatchResult:
    """Decode every R-JPEG among ``inputs`` (files and folders) into ``out_dir``; see the module docstring.

    ``progress(done, total)`` is called after each file. With ``fail_fast`` the first failure raises (a
    ``DataError`` naming the file); files already written stay."""
    options = options or DecodeOptions()
    jobs, failed = collect_jobs(inputs, out_dir, options.suffix)
    if fail_fast and failed:
        raise DataError(f"{failed[0][0]}: {failed[0][1]}")
    result = BatchResult(failed=list(failed))
    total = len(jobs)
    outcomes: dict[int, tuple[dict[str, Any] | None, str | None]] = {}

    def record(i: int, outcome: tuple[dict[str, Any] | None, str | None]) -> None:
        outcomes[i] = outcome
        if fail_fast and outcome[1] is not None:
            raise DataError(f"{jobs[i].source}: {outcome[1]}")
        if progress is not None:
            progress(len(outcomes), total)

    if workers <= 1 or total <= 1:
        for i, job in enumerate(jobs):
            if fail_fast:  # the original error, traceback-free, as a single file would give
                outcomes[i] = (decode_one(job.source, job.target, options, job.from_folder), None)
                if progress is not None:
                    progress(len(outcomes), total)
            else:
                record(i, _run(job, options))
    else:
        from harness.workers import worker_pool  # workers ignore Ctrl-C: the parent stops them, no tracebacks

        with worker_pool(min(workers, total)) as pool:
            pending: dict[Future, int] = {}
            it = iter(enumerate(jobs))
            try:
                # keep at most 2 jobs per worker queued, so a fail-fast stop leaves little work behind
                for i, job in it:
                    pending[pool.submit(_run, job, options)] = i
                    if len(pending) >= 2 * workers:
                        break
                while pending:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in done:
                        record(pending.pop(fut), fut.result())
                        nxt = next(it, None)
                        if nxt is not None:
                            pending[pool.submit(_run, nxt[1], options)] = nxt[0]
            except BaseException:
                for fut in pending:
                    fut.cancel()
                raise
    for i in range(total):
        row, error = outcomes[i]
        if error is not None:
            result.failed.append((str(jobs[i].source), error))
        elif row is not None and row.get("passed_over"):
            result.passed_over.append(str(jobs[i].source))
        elif row is not None:
            result.decoded.append(row)
    return result


def format_failures(result: BatchResult) -> str:
    """``decoded N of M file(s); K failed:`` then one ``file: reason`` line per failure; a batch that decoded
    nothing says so."""
    n = len(result.decoded)
    total = n + len(result.failed)
    head = f"decoded {n} of {total} file(s)"
    if result.passed_over:
        head += f"; {len(result.passed_over)} JPEG(s) without a radiometric payload passed over"
    approx = [r for r in result.decoded if r.get("approximate")]
    if approx:
        worst = max(r["approximate"]["bound_c"] for r in approx)
        head += (
            f"; {len(approx)} with approximate temperatures (within {worst:g} C of DJI's SDK at worst; "
            "see each sidecar)"
        )
    if not n and not result.failed:
        return head + ": nothing to decode (no R-JPEG among the inputs)"
    if not result.failed:
        return head
    return head + f"; {len(result.failed)} failed:\n" + "\n".join(f"  {f}: {r}" for f, r in result.failed)
