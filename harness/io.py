"""Crash-safe file writing: every result file is written to a temporary file in the same folder, flushed to disk,
then renamed over the target, so a crash at any moment leaves either the previous file or the new one, never a
truncated mix.

Files and folders get the modes the user's umask gives, as ``open()`` and ``mkdir()`` would (``0o666 & ~umask``
and ``0o777 & ~umask``), not the owner-only ``0600``/``0700`` of ``mkstemp``/``mkdtemp``: a cache or results
store on a shared server stays readable by the colleagues the umask admits. ``make_temp_dir`` is ``mkdtemp`` with
that mode, for folders built under a temporary name and renamed into place."""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import IO, Any, Callable, Iterator


def current_umask() -> int:
    """The process's umask, read without changing it: Linux reports it in ``/proc/self/status`` (``Umask:``);
    elsewhere it is set and restored at once (``os.umask`` has no read-only form)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """The mode ``open()`` gives a new file: ``0o666 & ~umask``."""
    return 0o666 & ~current_umask()


def dir_mode() -> int:
    """The mode ``mkdir()`` gives a new folder: ``0o777 & ~umask``."""
    return 0o777 & ~current_umask()


def make_temp_dir(prefix: str, suffix: str, dir: str | Path) -> Path:
    """``tempfile.mkdtemp`` in ``dir``, with the mode a plain ``mkdir`` would give (``0o777 & ~umask``)."""
    tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=suffix, dir=dir))
    os.chmod(tmp, dir_mode())
    return tmp


@contextlib.contextmanager
def atomic_folder(out: str | Path) -> Iterator[Path]:
    """A temporary folder beside ``out`` to fill; on leaving the block it replaces ``out`` (an earlier ``out`` is
    moved aside first and deleted after), and on any exception it is deleted and ``out`` is left as it was."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = make_temp_dir(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    try:
        yield tmp
        if out.exists():
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            os.replace(out, old)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def atomic_write(path: str | Path, write: Callable[[IO[bytes]], Any]) -> Path:
    """Call ``write(f)`` on a temporary binary file beside ``path``, fsync it, and rename it onto ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, file_mode())  # mkstemp creates 0600; the target gets what open() would give it
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError) and exc.filename is None and exc.errno is not None:
            # a failed write() names no file ("[Errno 28] No space left on device"): say which one it was
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise
    try:  # make the rename itself durable
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError:
        pass
    return path


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    return atomic_write(path, lambda f: f.write(data))


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def dumps_json(obj: Any, indent: int | None = 2) -> str:
    return json.dumps(obj, indent=indent, default=_json_default, allow_nan=True) + "\n"


def atomic_write_json(path: str | Path, obj: Any, indent: int | None = 2) -> Path:
    return atomic_write_text(path, dumps_json(obj, indent))


def file_digest(path: str | Path, algorithm: str = "sha1") -> str:
    """The hex digest of a file's bytes (read in 1 MiB chunks)."""
    import hashlib

    h = hashlib.new(algorithm)
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_text(path: str | Path, error: type[Exception] | None = None, what: str = "file") -> str:
    """The UTF-8 text of ``path``; a missing or unreadable file is an ``error`` (default ``DataError``) naming it
    (``"<path>: <what> not found"``, ``"<path>: cannot read (<reason>)"``)."""
    from harness.errors import DataError

    fail = error or DataError
    try:
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise fail(f"{path}: {what} not found") from None
    except OSError as exc:
        raise fail(f"{path}: cannot read ({exc.strerror})") from None


def read_packed_text(path: str | Path) -> str:
    """The UTF-8 text of ``path``, decompressed when its name ends in ``.gz`` (the shipped reference results keep
    their training logs, predictions and ground truth so); errors are ``OSError`` as from ``Path.read_text`` (a
    gzip stream cut short too, its ``strerror`` saying so)."""
    path = Path(path)
    if path.suffix == ".gz":
        import errno
        import gzip

        try:
            with gzip.open(path, "rt", encoding="utf-8") as f:
                return f.read()
        except EOFError as exc:
            raise OSError(errno.EIO, f"gzip stream cut short: {exc}", str(path)) from None
    return path.read_text(encoding="utf-8")


#: The keys of a detection ``pack_detections`` packs (a COCO result record as the harness writes it).
DETECTION_KEYS = ("image_id", "category_id", "bbox", "score")
#: ``pack_detections``' format version (the ``format`` array of the file).
DETECTIONS_FORMAT = 1


def pack_detections(dets: Any) -> bytes | None:
    """COCO detections (``[{"image_id", "category_id", "bbox": [x, y, w, h], "score"}, ...]``) as a compressed numpy
    archive of columns: ids as integers, the corners ``x, y, x + w, y + h`` and the score as float32. The harness's
    detectors give float32 corners and scores, and ``w``, ``h`` are their float64 differences, so the columns give
    back every value exactly (``unpack_detections``); a set they would not give back exactly, or with other keys, is
    None (keep it as JSON). A third the size of the gzip-compressed JSON."""
    import io

    import numpy as np

    if not isinstance(dets, list) or not all(isinstance(d, dict) and tuple(d) == DETECTION_KEYS for d in dets):
        return None
    try:
        ids = np.asarray([d["image_id"] for d in dets], dtype=np.int64)
        cats = np.asarray([d["category_id"] for d in dets], dtype=np.int64)
        boxes = np.asarray([d["bbox"] for d in dets], dtype=np.float64).reshape(-1, 4)
        scores = np.asarray([d["score"] for d in dets], dtype=np.float64)
    except (TypeError, ValueError):
        return None
    corners = np.concatenate([boxes[:, :2], boxes[:, :2] + boxes[:, 2:]], axis=1).astype(np.float32)
    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        format=np.asarray([DETECTIONS_FORMAT]),
        image_id=ids,
        category_id=cats,
        corners=corners,
        score=scores.astype(np.float32),
    )
    data = buf.getvalue()
    try:
        same = unpack_detections(data) == dets
    except ValueError:
        same = False
    return data if same else None


def unpack_detections(data: bytes) -> list[dict[str, Any]]:
    """The detections ``pack_detections`` packed, value for value; ``ValueError`` when ``data`` is not such a file."""
    import io
    import zipfile

    import numpy as np

    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            if int(z["format"][0]) != DETECTIONS_FORMAT:
                raise ValueError(f"packed detections of format {int(z['format'][0])}, not {DETECTIONS_FORMAT}")
            ids, cats, corners, scores = z["image_id"], z["category_id"], z["corners"], z["score"]
    except (OSError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"not packed detections ({type(exc).__name__}: {exc})") from None
    c = corners.astype(np.float64)
    wh = c[:, 2:] - c[:, :2]
    return [
        {"image_id": int(i), "category_id": int(k), "bbox": [x, y, w, h], "score": float(s)}
        for i, k, (x, y), (w, h), s in zip(ids, cats, c[:, :2].tolist(), wh.tolist(), scores.astype(np.float64))
    ]


def read_json(path: str | Path) -> Any:
    """Read JSON; a malformed file is a ``DataError`` naming the file and the position. A ``.gz`` file is
    gzip-compressed JSON, a ``.npz`` one detections ``pack_detections`` packed (the shipped reference results')."""
    from harness.errors import DataError

    path = Path(path)
    if path.suffix == ".npz":
        try:
            return unpack_detections(path.read_bytes())
        except FileNotFoundError:
            raise DataError(f"{path}: file not found") from None
        except (OSError, ValueError) as exc:
            raise DataError(f"{path}: cannot read the packed detections ({exc})") from None
    if path.suffix == ".gz":  # gzip-compressed JSON (the shipped reference results' predictions and ground truth)
        try:
            text = read_packed_text(path)
        except FileNotFoundError:
            raise DataError(f"{path}: file not found") from None
        except OSError as exc:
            raise DataError(f"{path}: cannot read gzip-compressed JSON ({exc.strerror or exc})") from None
    else:
        text = read_text(path)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None


def safe_join(root: Path, rel: str | os.PathLike[str], what: str) -> Path:
    """``root / rel``, refused with a ``DataError`` when the path written in a manifest or annotation file leaves
    ``root``: an absolute path, or ``..`` steps climbing out. The check is on the path as written (``..`` folded),
    so symbolic links the user placed inside the dataset folder (images kept on another disk) are followed."""
    from harness.errors import DataError

    rel_s = str(rel)
    if not rel_s or "\x00" in rel_s:
        raise DataError(f"{what}: empty or invalid path {rel_s!r}")
    root_a = Path(os.path.abspath(root))
    target = Path(os.path.normpath(root_a / rel_s))
    if os.path.isabs(rel_s) and root_a in target.parents:  # inside the folder, but written absolute: not portable
        raise DataError(
            f"{what}: path {rel_s!r} is absolute; write it relative to the dataset root {root_a} "
            f"({target.relative_to(root_a).as_posix()!r}), so the folder can be moved"
        )
    if os.path.isabs(rel_s) or (target != root_a and root_a not in target.parents):
        raise DataError(
            f"{what}: path {rel_s!r} leads outside the dataset root {root_a} (to {target}); "
            "paths in the manifest and the annotation files must stay inside the dataset folder"
        )
    return target


def nan_to_none(obj: Any) -> Any:
    """JSON-safe copy: NaN/inf become null (strict JSON has no NaN or Infinity)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [nan_to_none(v) for v in obj]
    return obj
