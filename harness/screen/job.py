"""``screen(request)``: a flight through a run's sensing, encoding and model, into findings (the package docstring
describes the whole).

Kept in one module: the settings, the front end in workers and the resumable loop are the steps of one screen, read
in order from ``ScreenRequest`` to ``screen``."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from collections import Counter, deque
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

from harness.errors import ConfigError, DataError, HarnessError
from harness.io import file_digest
from harness.screen import outputs as out
from harness.screen.findings import frame_findings, registration_note
from harness.screen.flight import Capture, Flight, find_captures, inspection_groups
from harness.screen.frontend import Frame, FrontEnd, FrontEndSettings, RegistrationRejected
from harness.screen.model import Predictor, ScreenModel, from_run, from_weights

log = logging.getLogger(__name__)

SCHEMA = 3  # 2: positions carry gps_source (XMP, EXIF); 3: inspection groups registered pooled


@dataclass
class ScreenRequest:
    """What ``harness screen`` asks for (see ``harness screen --help``)."""

    flight: str | Path
    out: str | Path
    run: str | Path | None = None
    weights: str | Path | None = None
    detector: str | None = None
    dataset: str | None = None
    encoding: str | None = None
    profile: str | None = "smoke"
    config_files: Sequence[str | Path] = ()
    overrides: Sequence[str] = ()
    backend: str = "torch"
    device: str = "cpu"
    conf: float | None = None
    homography: str | Path | None = None
    group: str | None = None
    rgb_camera: str | Path | None = None
    thermal_camera: str | Path | None = None
    no_undistort: bool = False
    focal_35mm: tuple[float, float] | None = None
    fallback: str = "prior"
    rgb_decode: str = "auto"
    register: str = "group"
    workers: int = 1
    threads: int | None = None
    #: routes for R-JPEGs the harness cannot correct itself (``harness sensing decode``'s options): they set the
    #: run's ``sensing.radiometry`` ``approximate``, ``converter``, ``dji_irp`` and ``converter_timeout_s``
    approximate: bool = False
    converter: str | None = None
    dji_irp: str | None = None
    converter_timeout: float | None = None
    #: with ``workers`` 1: the front end of the next captures runs in a thread while the model works on this one
    overlap: bool = True
    fail_fast: bool = False
    force: bool = False
    progress: bool = True
    overlays: bool = True


@dataclass
class ScreenResult:
    """What a screen did: the counts, the failures and where everything is."""

    out: Path
    frames: int  # captures in the flight
    screened: int  # screened now
    skipped_done: int  # screened by an earlier call with the same settings
    with_findings: int
    findings: dict[str, int]
    failures: list[tuple[str, str]] = field(default_factory=list)
    rejected: list[tuple[str, str]] = field(default_factory=list)  # (frame, route and reason) not by auto or file
    timings: dict[str, float] = field(default_factory=dict)
    threshold: float = 0.0
    threshold_source: str = ""
    #: screened frames by where their GPS position came from: ``xmp``, ``exif``, ``none``
    positions: dict[str, int] = field(default_factory=dict)
    #: the manifest's ``temperatures``: frames per decoding route, approximate frames and their largest bound
    temperatures: dict[str, Any] = field(default_factory=dict)
    #: the manifest's counts (``captures`` = ``screened`` + ``failed`` + ``rejected_not_screened`` + ``not_reached``)
    counts: dict[str, int] = field(default_factory=dict)
    #: why nothing was screened, when nothing was
    why_nothing: str = ""

    @property
    def nothing_screened(self) -> bool:
        return self.screened + self.skipped_done == 0

    @property
    def ok(self) -> bool:
        return not self.failures


# ------------------------------------------------------------------------------------------------ settings
def load_model(req: ScreenRequest) -> ScreenModel:
    if req.conf is not None and not 0.0 <= float(req.conf) <= 1.0:  # NaN fails too
        raise ConfigError(f"--conf {req.conf}: a score threshold lies between 0 and 1")
    if (req.run is None) == (req.weights is None):
        raise ConfigError("give either --run RUN_DIR (a finished run) or --weights FILE with --detector and --dataset")
    if req.run is not None:
        if req.detector or req.dataset or req.encoding or req.config_files or req.overrides:
            raise ConfigError(
                "--run takes everything from the run's stored configuration; --detector, --dataset, "
                "--encoding, --config and --set go with --weights only"
            )
        return from_run(req.run, req.conf)
    if not req.detector or not req.dataset:
        raise ConfigError("--weights needs --detector NAME and --dataset NAME (its categories, protocol and encoding)")
    return from_weights(
        req.weights,
        req.detector,
        req.dataset,
        req.encoding,
        req.profile,  # type: ignore[arg-type]
        req.config_files,
        req.overrides,
        req.conf,
    )


def decode_routes(sensing: dict[str, Any], req: ScreenRequest) -> dict[str, Any]:
    """The ``sensing`` section with the request's decoding routes (``--approximate``, ``--converter``,
    ``--dji-irp``, ``--converter-timeout``) set in its ``radiometry``; a wrong converter is a ``ConfigError``."""
    rad = dict(sensing.get("radiometry") or {})
    if req.approximate:
        rad["approximate"] = True
    if req.converter or req.dji_irp:
        from harness.sensing.dji_converter import resolve

        resolve(req.converter, req.dji_irp, req.converter_timeout)  # checked here, once, with the options' names
        rad["converter"] = req.converter or "dji_irp"
        if req.dji_irp:
            rad["dji_irp"] = str(req.dji_irp)
    if req.converter_timeout:
        rad["converter_timeout_s"] = float(req.converter_timeout)
    return {**sensing, "radiometry": rad}


def recorded_cameras(sm: ScreenModel) -> tuple[dict[str, Any] | None, dict[str, Any] | None, str] | None:
    """The cameras the run's prepared data was undistorted with (``AlignedSample.meta["cameras"]``), from the cache
    (``$HARNESS_CACHE``), found by the run's prepared fingerprint; None when that data is not there."""
    from harness.cache.key import cache_root, preparation_sensing
    from harness.io import read_json

    meta = sm.config.get("meta") or {}
    fingerprint, dataset = meta.get("prepared_fingerprint"), meta.get("dataset")
    if not fingerprint or not dataset:
        return None
    sensing = json.loads(json.dumps(preparation_sensing(sm.config.get("sensing")), default=str))
    for manifest in sorted((cache_root() / str(dataset)).glob("*/manifest.json")):
        try:
            m = read_json(manifest)
        except HarnessError:
            continue
        if m.get("fingerprint") != fingerprint or m.get("sensing") != sensing:
            continue
        samples = read_json(manifest.parent / "samples.json")
        seen: dict[str, dict[str, Any] | None] = {}
        for sensor in ("rgb", "thermal"):
            cams = {
                json.dumps((s.get("meta", {}).get("cameras") or {}).get(sensor, {}).get("camera"), sort_keys=True)
                for s in samples
            }
            if len(cams) > 1:
                raise ConfigError(
                    f"{manifest.parent}: the run's data was undistorted with {len(cams)} different "
                    f"{sensor} calibrations; give the flight's with --{sensor}-camera FILE"
                )
            seen[sensor] = json.loads(cams.pop()) if cams else None
        return seen["rgb"], seen["thermal"], str(manifest.parent)
    return None


def resolve_cameras(
    req: ScreenRequest, sm: ScreenModel
) -> tuple[dict[str, Any] | None, dict[str, Any] | None, dict[str, str]]:
    """(wide camera, thermal camera, where each came from): ``--rgb-camera``/``--thermal-camera``, else the
    configuration's ``sensing.undistort``, else (a run) the cameras its prepared data records; ``--no-undistort``
    for none."""
    from harness.sensing.calibration import CameraModel
    from harness.sensing.options import SensingOptions

    und = SensingOptions.from_config(sm.sensing).undistort
    given = {"rgb": req.rgb_camera, "thermal": req.thermal_camera}
    configured = {"rgb": und.rgb_camera, "thermal": und.thermal_camera}
    cams: dict[str, dict[str, Any] | None] = {}
    source: dict[str, str] = {}
    recorded: Any = "unread"
    for sensor in ("rgb", "thermal"):
        if given[sensor] is not None:
            cams[sensor], source[sensor] = CameraModel.load(given[sensor]).to_dict(), str(given[sensor])
        elif req.no_undistort:
            cams[sensor], source[sensor] = None, "--no-undistort"
        elif configured[sensor]:
            path = Path(str(configured[sensor])).expanduser()
            cams[sensor] = CameraModel.load(path).to_dict()
            source[sensor] = f"sensing.undistort.{sensor}_camera ({path})"
        elif req.run is None:
            cams[sensor], source[sensor] = None, "none configured"
        else:
            if recorded == "unread":
                recorded = recorded_cameras(sm)
            if recorded is None:
                raise ConfigError(_unknown_camera(sensor, given))
            cams[sensor] = recorded[0 if sensor == "rgb" else 1]
            source[sensor] = (
                f"the run's prepared data ({recorded[2]})"
                if cams[sensor]
                else "none (the run's prepared data used none)"
            )
    if cams["rgb"] is None and source["rgb"] == "none configured":
        log.warning(
            "no wide-camera calibration (--rgb-camera, sensing.undistort.rgb_camera): the wide images are "
            "not undistorted; give the one the model's training data was undistorted with"
        )
    return cams["rgb"], cams["thermal"], source


def _unknown_camera(sensor: str, given: Mapping[str, Any]) -> str:
    """Why ``sensor``'s calibration is unknown (the run's prepared data is not in the cache) and what to give: the
    option of that sensor, not of the other one, which may have been given already."""
    option, camera = ("--rgb-camera", "wide") if sensor == "rgb" else ("--thermal-camera", "thermal")
    other, other_camera = ("--thermal-camera", "thermal") if sensor == "rgb" else ("--rgb-camera", "wide")
    example = " (e.g. the dataset's calibration/wide_camera.yaml)" if sensor == "rgb" else ""
    none = (
        f"add --no-undistort if its dataset had no {camera}-camera calibration ({other} still undistorts the "
        f"{other_camera} images)"
        if given.get("thermal" if sensor == "rgb" else "rgb") is not None
        else "--no-undistort if its dataset had none"
    )
    return (
        "the run's prepared data is not in the cache (HARNESS_CACHE, now "
        f"{os.environ.get('HARNESS_CACHE') or './cache'}), so the {camera}-camera calibration its training "
        f"undistorted the {camera} images with is unknown: give it with {option} FILE{example}, or {none}"
    )


def load_homography(path: str | Path | None, group: str | None) -> dict[str, Any] | None:
    from harness.sensing.registration import load_homography_entries

    if path is None:
        if group is not None:
            raise ConfigError("--group picks an entry of --homography FILE; give the file too")
        return None
    entries = load_homography_entries(path)
    if group is None:
        if len(entries) != 1:
            raise ConfigError(
                f"{path} holds {len(entries)} homographies ({', '.join(sorted(entries))}); pick one with --group NAME"
            )
        group = next(iter(entries))
    if group not in entries:
        raise ConfigError(f"{path}: no group {group!r}; it holds {', '.join(sorted(entries))}")
    e = entries[group]
    return {"H": e.H.tolist(), "method": e.method, "source": str(path), "group": group, "sha1": file_digest(path)}


def screen_key(sm: ScreenModel, settings: FrontEndSettings, backend: str) -> str:
    """What makes two screens of the same files give the same findings."""
    ev = sm.config.get("eval") or {}
    payload = {
        "weights": sm.weights_sha1,
        "detector": sm.detector.name,
        "backend": backend,
        "threshold": sm.threshold,
        "imgsz": sm.imgsz,
        "nms": [ev.get("conf"), ev.get("iou"), ev.get("max_det")],
        "model": sm.config.get("model") or {},
        "frontend": asdict(settings),
        "schema": SCHEMA,
    }
    return hashlib.sha1(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------------ front end in workers
_WORKER: dict[str, Any] = {}


def _init_worker(settings: FrontEndSettings, encoding: Any) -> None:
    import cv2

    cv2.setNumThreads(1)  # one process per core: no threads competing inside each
    _WORKER["frontend"] = FrontEnd(settings, encoding)


def _work(cap: Capture, image_id: int, given: dict[str, Any] | None) -> tuple[Frame | None, str | None, bool]:
    return _run_frontend(_WORKER["frontend"], cap, image_id, given)


def _run_frontend(
    fe: FrontEnd, cap: Capture, image_id: int, given: dict[str, Any] | None = None
) -> tuple[Frame | None, str | None, bool]:
    """(frame, error, rejected): a bad file's error as text, naming the file."""
    try:
        return fe.process(cap, image_id, given), None, False
    except ConfigError:
        raise
    except RegistrationRejected as exc:
        return None, str(exc), True
    except HarnessError as exc:
        return None, str(exc), False
    except Exception as exc:  # noqa: BLE001 - a damaged file can make a decoder library raise anything
        return None, f"{cap.rgb}: {type(exc).__name__}: {exc}", False


class _Now:
    """A future computed when its result is asked for (the one-process path)."""

    def __init__(self, fn: Callable[[], Any]):
        self.fn = fn

    def result(self) -> Any:
        return self.fn()

    def cancel(self) -> bool:
        return True


class FrontEndThread:
    """One thread that runs the front end beside the model (OpenCV's decoding and remaps, NumPy and the model's
    kernels release the GIL), with a clock of the CPU time it has used (``cpu()``; None where the system gives no
    per-thread clock), so the model's CPU time can be told apart from the front end's."""

    def __init__(self) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self._clock: int | None = None
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="screen-frontend", initializer=self._started)
        self.pool.submit(lambda: None).result()

    def _started(self) -> None:
        import threading

        try:
            self._clock = time.pthread_getcpuclockid(threading.get_ident())
        except (AttributeError, OSError):  # not on this system
            self._clock = None

    def cpu(self) -> float | None:
        return time.clock_gettime(self._clock) if self._clock is not None else None

    def submit(self, fn: Callable[..., Any], *args: Any) -> Any:
        return self.pool.submit(fn, *args)

    def shutdown(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


def group_registrations(
    fe: FrontEnd, groups: dict[str, str] | None, done: dict[str, dict[str, Any]]
) -> dict[str, dict[str, Any]]:
    """The group registrations earlier calls made, per group (what a re-run's remaining frames reuse)."""
    out: dict[str, dict[str, Any]] = {}
    for name, rec in done.items():
        reg = rec.get("registered")
        if groups is not None and reg and reg.get("group") is not None and name in groups:
            out.setdefault(groups[name], reg)
    return out


def same_groups(done: dict[str, dict[str, Any]], groups: dict[str, str] | None) -> dict[str, dict[str, Any]]:
    """The frames screened earlier whose inspection group still has the captures its registration was pooled over:
    a capture added to or removed from a group changes the group's registration, so all its frames are screened
    anew (as a fresh screen of the folder would screen them)."""
    if groups is None:
        return done
    members: dict[str, list[str]] = {}
    for name, group in groups.items():
        members.setdefault(group, []).append(name)
    keep, stale = {}, set()
    for name, rec in done.items():
        reg = rec.get("registered") or {}
        group = groups.get(name)
        if reg.get("group") is not None and (reg["group"] != group or reg.get("members") != members.get(group)):
            stale.add(str(group))
            continue
        keep[name] = rec
    if stale:
        log.info(
            "inspection group(s) %s: captures were added or removed since they were screened; their frames are "
            "screened anew with a registration pooled over the captures there now",
            ", ".join(sorted(stale)),
        )
    return keep


def frontend_results(
    fe: FrontEnd,
    caps: Sequence[Capture],
    workers: int,
    groups: dict[str, str] | None = None,
    registered: dict[str, dict[str, Any]] | None = None,
    thread: FrontEndThread | None = None,
    members: Sequence[Capture] | None = None,
) -> Iterator[tuple[Capture, Frame | None, str | None, bool]]:
    """Each capture's front-end result, in order (``workers`` processes, at most two captures queued each; with one
    worker, ``thread`` runs them beside the caller, else each is computed when the caller asks for it).

    With ``groups`` (``{capture: inspection group}``) each group is registered once, pooled over all its captures
    (``FrontEnd.register_group``; ``members``: the whole flight's captures, default ``caps``, in name order), when
    its first capture comes up, and every capture of the group is screened with that registration (``registered``:
    the groups registered already, by an earlier call)."""
    import multiprocessing as mp

    from harness.workers import worker_pool

    registered = dict(registered or {})
    everyone = list(members if members is not None else caps)
    pool = None
    if workers > 1 and len(caps) > 1:
        import pickle

        try:
            pickle.dumps((fe.settings, fe.encoding))
        except Exception as exc:  # noqa: BLE001 - e.g. an encoding function defined as a lambda
            raise ConfigError(
                f"--workers {workers}: encoding {fe.encoding.name!r} cannot be sent to worker "
                f"processes ({type(exc).__name__}: {exc}); use --workers 1"
            ) from None
        # spawned, not forked: a process forked while the model's threads hold a lock can hang for good
        # workers ignore Ctrl-C (``harness.workers``): the parent stops the pool, with one message and no tracebacks
        pool = worker_pool(
            min(workers, len(caps)),
            mp_context=mp.get_context("spawn"),
            initializer=_init_worker,
            initargs=(fe.settings, fe.encoding),
        )

    def submit(cap: Capture, i: int, given: dict[str, Any] | None) -> Any:
        if pool is not None:
            return pool.submit(_work, cap, i, given)
        if thread is not None:
            return thread.submit(_run_frontend, fe, cap, i, given)
        return _Now(lambda: _run_frontend(fe, cap, i, given))

    failed: dict[str, str] = {}  # groups none of whose captures could be read, with the first error

    def group_given(group: str) -> dict[str, Any] | None:
        assert groups is not None
        if group not in registered and group not in failed:
            try:
                registered[group] = fe.register_group([c for c in everyone if groups.get(c.name) == group], group)[0]
            except ConfigError:
                raise
            except HarnessError as exc:
                failed[group] = str(exc)
        return registered.get(group)

    queue: deque = deque()  # (capture, future)
    k = 0
    try:
        while k < len(caps) or queue:
            while k < len(caps) and len(queue) < 2 * max(1, workers):
                cap = caps[k]
                group = groups.get(cap.name) if groups is not None else None
                if group is not None and group not in registered and group not in failed and queue:
                    break  # a group is registered when the captures before it are done, with nothing beside it
                given = group_given(group) if group is not None else None
                queue.append((cap, submit(cap, k, given)))
                k += 1
            cap, fut = queue.popleft()
            frame, error, rejected = fut.result()
            yield cap, frame, error, rejected
    finally:
        for item in queue:
            item[1].cancel()
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)


# ------------------------------------------------------------------------------------------------ the job
class _Bar:
    """The overall progress bar (``harness.progress``: on stderr, only on a terminal, off with ``--no-progress``):
    frames done of the flight, elapsed, ETA, findings and failures."""

    def __init__(self, enabled: bool, total: int, done: int):
        from harness.progress import bar

        self.done = done
        self._bar = bar("screening frames", total, enabled=enabled, eta=True, note=True, transient=False)

    def __enter__(self) -> "_Bar":
        self._bar.__enter__()
        self._bar.update(completed=self.done)
        return self

    def advance(self, n: int, note: str) -> None:
        self._bar.advance(n, note=note)

    def __exit__(self, *exc: Any) -> None:
        self._bar.__exit__(*exc)


def _frame_record(
    frame: Frame,
    findings: list[dict[str, Any]],
    key: str,
    flight: Path,
    overlay: str | None,
    model_s: float,
    model_cpu: float,
) -> dict[str, Any]:
    return {
        "key": key,
        "frame": frame.capture.name,
        "status": "screened",
        "rgb_file": str(frame.capture.rgb.relative_to(flight)),
        "thermal_file": str(frame.capture.thermal.relative_to(flight)),
        "fingerprints": frame.fingerprints,
        "route": frame.route,
        "registration": frame.registration,
        "reduction": frame.reduction,
        "crop_origin": list(frame.origin),
        "aligned_size": [int(frame.image.shape[1]), int(frame.image.shape[0])],
        "rgb_size": list(frame.rgb_size),
        "thermal_size": list(frame.thermal_size),
        "H_rgb_to_aligned": frame.H.tolist(),
        "thermal_decoder": frame.thermal_decoder,
        "temperatures": frame.temperatures,
        "position": frame.position.to_dict(),
        "registered": frame.registered,
        "overlay": overlay,
        "findings": findings,
        "timings": {
            **{k: round(v, 6) for k, v in frame.timings.items()},
            "model": round(model_s, 6),
            "model_cpu": round(model_cpu, 6),
        },
    }


def _done_frames(folder: Path, key: str, caps: Sequence[Capture]) -> dict[str, dict[str, Any]]:
    """Frame records of an earlier call with the same key whose input files are unchanged."""
    from harness.io import read_json
    from harness.screen.frontend import sha1_bytes

    done: dict[str, dict[str, Any]] = {}
    for cap in caps:
        path = folder / "frames" / f"{out.safe_name(cap.name)}.json"
        if not path.exists():
            continue
        try:
            rec = read_json(path)
        except HarnessError:
            continue
        if rec.get("key") != key or rec.get("status") != "screened":
            continue
        fp = rec.get("fingerprints") or {}
        try:
            same = fp.get("rgb") == sha1_bytes(cap.rgb.read_bytes()) and fp.get("thermal") == sha1_bytes(
                cap.thermal.read_bytes()
            )
        except OSError:
            same = False
        if same:
            done[cap.name] = rec
    return done


def _prepare_out(folder: Path, key: str, force: bool) -> None:
    from harness.io import read_json

    manifest = folder / "manifest.json"
    if folder.exists() and any(folder.iterdir()):
        if not manifest.exists() and not (folder / "frames").is_dir():
            raise ConfigError(f"--out {folder}: the folder holds other files; give an empty or new folder")
        old = read_json(manifest).get("key") if manifest.exists() else None
        if old is not None and old != key:
            if not force:
                raise ConfigError(
                    f"--out {folder} holds a screen with another model or other settings (key {old}, "
                    f"now {key}); use another --out, or --force to replace it"
                )
        if force:
            for sub in ("frames", "overlays", "crops"):
                shutil.rmtree(folder / sub, ignore_errors=True)
    folder.mkdir(parents=True, exist_ok=True)


def screen(req: ScreenRequest, on_frame: Callable[[dict[str, Any]], None] | None = None) -> ScreenResult:
    """Screen ``req.flight`` into ``req.out``; see the package docstring. Bad files are listed in the result (and
    with ``fail_fast`` the first one raises a ``DataError`` after the frames before it are written).
    ``on_frame(record)`` is called after each frame is written."""
    import cv2
    import torch

    threads, cv_threads = torch.get_num_threads(), cv2.getNumThreads()
    if req.threads:
        torch.set_num_threads(int(req.threads))
    cv2.setNumThreads(1)  # the front end's OpenCV calls on one thread, beside the model's (as in the workers)
    try:
        return _screen(req, on_frame)
    finally:
        torch.set_num_threads(threads)
        cv2.setNumThreads(cv_threads)


def _screen(req: ScreenRequest, on_frame: Callable[[dict[str, Any]], None] | None) -> ScreenResult:
    from harness import __version__

    t_start = time.perf_counter()
    if req.workers < 1:
        raise ConfigError(f"--workers {req.workers}: give at least 1")
    flight = find_captures(req.flight)
    if req.fail_fast and flight.bad:
        raise DataError(f"{flight.bad[0][0]}: {flight.bad[0][1]}")
    sm = load_model(req)
    rgb_cam, th_cam, cam_source = resolve_cameras(req, sm)
    settings = FrontEndSettings(
        sensing=decode_routes(sm.sensing, req),
        encoding=sm.encoding.name,
        encoding_params=sm.encoding_params,
        rgb_camera=rgb_cam,
        thermal_camera=th_cam,
        homography=load_homography(req.homography, req.group),
        fallback=req.fallback,
        rgb_decode=req.rgb_decode,
        focal_35mm=req.focal_35mm,
        register=req.register,
    )
    fe = FrontEnd(settings, sm.encoding)
    key = screen_key(sm, settings, req.backend)
    folder = Path(req.out)
    _prepare_out(folder, key, req.force)
    predictor = Predictor(sm, req.backend, req.device, folder, req.threads)
    groups = None
    if settings.register == "group" and settings.homography is None and fe.options.registration.method == "auto":
        groups = inspection_groups(flight.captures, fe.options.group_gap_s)
    done = same_groups(_done_frames(folder, key, flight.captures), groups)
    todo = [c for c in flight.captures if c.name not in done]
    if done:
        log.info(
            "%d of %d frames were screened earlier with the same settings: skipped", len(done), len(flight.captures)
        )
    base = {
        "schema": SCHEMA,
        "key": key,
        "harness_version": __version__,
        "flight": str(Path(req.flight).resolve()),
        "model": {**sm.describe(), "backend": req.backend, "device": req.device, "onnx": predictor.onnx or None},
        "frontend": {**asdict(settings), "cameras_from": cam_source},
        "config": sm.config,
    }
    out.write_json(folder / "manifest.json", {**base, "state": "running"})

    failures: list[tuple[str, str]] = list(flight.bad)
    rejected_skipped: list[tuple[str, str]] = []
    records: dict[str, dict[str, Any]] = dict(done)
    batch: list[Frame] = []
    timings = {"decode": 0.0, "align": 0.0, "encode": 0.0, "model": 0.0, "front_cpu": 0.0, "model_cpu": 0.0}
    stop: str | None = None
    thread: FrontEndThread | None = None

    def flush(bar: _Bar) -> None:
        if not batch:
            return
        f0 = thread.cpu() if thread is not None else None
        t0, c0 = time.perf_counter(), time.process_time()
        dets = predictor([f.image for f in batch])
        model_s = (time.perf_counter() - t0) / len(batch)
        model_cpu = time.process_time() - c0
        f1 = thread.cpu() if thread is not None else None
        if f0 is not None and f1 is not None:
            model_cpu -= f1 - f0  # the front end's CPU time beside the model is the front end's
        model_cpu /= len(batch)
        for frame, d in zip(batch, dets):
            found = frame_findings(frame, d, sm.categories, sm.threshold)
            overlay = _write_pictures(folder, frame, found) if (found and req.overlays) else None
            rec = _frame_record(frame, found, key, Path(req.flight), overlay, model_s, model_cpu)
            out.write_json(folder / "frames" / f"{out.safe_name(frame.capture.name)}.json", rec)
            records[frame.capture.name] = rec
            for k in ("decode", "align", "encode"):
                timings[k] += frame.timings[k]
                timings["front_cpu"] += frame.timings.get(f"{k}_cpu", 0.0)
            timings["model"] += model_s
            timings["model_cpu"] += model_cpu
            if on_frame is not None:
                on_frame(rec)
        n = len(batch)
        batch.clear()
        bar.advance(n, _note(records, failures))

    if req.workers == 1 and req.overlap and len(todo) > 1:
        thread = FrontEndThread()
    interrupted = False
    try:
        results = frontend_results(
            fe, todo, req.workers, groups, group_registrations(fe, groups, done), thread, flight.captures
        )
        with _Bar(req.progress, len(flight.captures), len(done)) as bar:
            try:
                for cap, frame, error, rejected in results:
                    if frame is None:
                        (rejected_skipped if rejected else failures).append(_named(cap, error or "unknown error"))
                        bar.advance(1, _note(records, failures))
                        if req.fail_fast and not rejected:
                            stop = error
                            break
                        continue
                    batch.append(frame)
                    if len(batch) >= predictor.batch:
                        flush(bar)
                results.close()  # a stop leaves no worker behind
                flush(bar)
            except KeyboardInterrupt:  # the outputs of the frames done are written below, then it goes on up
                interrupted = True
                results.close()
    finally:
        if thread is not None:
            thread.shutdown()
    screened = len(records) - len(done)
    n_failed = len(failures) - len(flight.bad)
    failures += rejected_skipped
    result = _finish(
        folder,
        base,
        flight,
        records,
        failures,
        sm,
        timings,
        screened,
        len(done),
        req,
        time.perf_counter() - t_start,
        state="interrupted" if interrupted else "stopped" if stop else "finished",
        overlapped=thread is not None,
        failed_captures=n_failed,
        rejected_skipped=len(rejected_skipped),
    )
    if interrupted:
        log.warning(
            "interrupted: the %d frame(s) screened so far are in %s (findings.csv, index.html; a re-run goes on "
            "from there)",
            len(records),
            folder,
        )
        raise KeyboardInterrupt
    if stop is not None:
        raise DataError(f"{stop} (--fail-fast: stopped; the {screened} frame(s) screened before it are in {folder})")
    return result


def _named(cap: Capture, error: str) -> tuple[str, str]:
    """(the bad file, the reason) from an error text that starts with the file's path."""
    for path in (cap.thermal, cap.rgb):
        if error.startswith(f"{path}: "):
            return str(path), error[len(str(path)) + 2 :]
    return str(cap.rgb), error


def _note(records: dict[str, dict[str, Any]], failures: list[tuple[str, str]]) -> str:
    n = sum(len(r.get("findings") or []) for r in records.values())
    return f"{n} findings" + (f", {len(failures)} failed" if failures else "")


def _write_pictures(folder: Path, frame: Frame, findings: list[dict[str, Any]]) -> str:
    name = out.safe_name(frame.capture.name)
    rel = f"overlays/{name}.jpg"
    out.write_jpeg(folder / rel, out.overlay(frame.rgb, frame.thermal, findings))
    for k, f in enumerate(findings):
        crop_rel = f"crops/{name}_{k:03d}.jpg"
        out.write_jpeg(folder / crop_rel, out.crop(frame.rgb, frame.thermal, f["box_aligned"]), quality=85)
        f["crop"] = crop_rel
        f["overlay"] = rel
    return rel


def grouped_failures(failures: Sequence[tuple[str, str]]) -> list[tuple[str, str]]:
    """``failures`` with the wide images of one size that its calibration does not fit as one entry (the first
    file, "and N more"), so that a flight shot in another mode is told once, not file by file."""
    from harness.screen.frontend import SIZE_MISMATCH

    out: list[tuple[str, str]] = []
    same: dict[str, list[str]] = {}
    for path, reason in failures:
        if reason.startswith(SIZE_MISMATCH):
            if reason not in same:
                same[reason] = []
                out.append((path, reason))
            same[reason].append(path)
        else:
            out.append((path, reason))
    return [
        (f"{p} and {len(same[r]) - 1} more wide image(s) of that size" if r in same and len(same[r]) > 1 else p, r)
        for p, r in out
    ]


def count_line(c: dict[str, int]) -> str:
    """The counts of a screen in words, adding up: captures = screened + failed + rejected + not reached."""
    parts = [f"{c['screened']} screened ({c['screened_now']} now, {c['screened_earlier']} earlier)"]
    parts.append(f"{c['failed']} failed")
    if c["rejected_not_screened"]:
        parts.append(f"{c['rejected_not_screened']} not screened (registration rejected, --fallback skip)")
    if c["not_reached"]:
        parts.append(f"{c['not_reached']} not reached")
    text = f"{c['captures']} capture(s): " + ", ".join(parts)
    return text + (
        f"; besides them {c['unpaired_files']} file(s) without a partner, {c['ignored_files']} other file(s) ignored"
    )


def _why_none(c: dict[str, int]) -> str:
    if c["screened"]:
        return ""
    why = []
    if c["failed"]:
        why.append(f"{c['failed']} failed (listed above)")
    if c["rejected_not_screened"]:
        why.append(f"{c['rejected_not_screened']} had their automatic registration rejected (--fallback skip)")
    if c["not_reached"]:
        why.append(f"{c['not_reached']} were not reached")
    return f"of {c['captures']} capture(s), " + ", ".join(why)


def _remove_stale(folder: Path, frames: Sequence[dict[str, Any]]) -> None:
    """Remove the frame records, overlays and thumbnails of captures no longer in the flight (or no longer screened),
    so that the folder holds what its findings.csv and manifest.json list and nothing else."""
    keep = {f"{out.safe_name(r['frame'])}.json" for r in frames}
    pictures = {str(r.get("overlay")) for r in frames if r.get("overlay")}
    pictures |= {str(f.get("crop")) for r in frames for f in r.get("findings") or [] if f.get("crop")}
    for path in sorted((folder / "frames").glob("*.json")):
        if path.name not in keep:
            log.info("removing %s: its capture is no longer screened from this flight", path)
            path.unlink(missing_ok=True)
    for sub in ("overlays", "crops"):
        for path in sorted((folder / sub).glob("*.jpg")):
            if f"{sub}/{path.name}" not in pictures:
                path.unlink(missing_ok=True)


def temperature_counts(frames: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """How the frames' temperatures were decoded: frames per route, and how many are approximate with the largest
    bound (C)."""
    routes: Counter = Counter()
    bounds = []
    for r in frames:
        t = r.get("temperatures") or {}
        routes[str(t.get("thermal_route") or r.get("thermal_decoder") or "unknown")] += 1
        if t.get("thermal_route") == "approximate":
            bounds.append(float(t["temperature_bound_c"]))
    return {"routes": dict(routes), "approximate_frames": len(bounds), "bound_c": max(bounds) if bounds else None}


def approximate_line(t: dict[str, Any]) -> str:
    return (
        f"approximate temperatures in {t['approximate_frames']} frame(s): within {t['bound_c']:g} C of DJI's "
        "correction (--approximate; decode with DJI's own SDK, --converter dji_irp, for exact ones)"
    )


def position_counts(frames: Sequence[dict[str, Any]]) -> dict[str, int]:
    """Frame records by the source of their GPS position (``xmp``, ``exif``, ``none``), with one warning naming the
    frames without one."""
    counts = {"xmp": 0, "exif": 0, "none": 0}
    missing = []
    for r in frames:
        pos = r.get("position") or {}
        source = pos.get("gps_source") if pos.get("lat") is not None and pos.get("lon") is not None else None
        counts[source if source in counts else "none"] += 1
        if source is None:
            missing.append(r["frame"])
    if missing:
        log.warning(
            "%d of %d screened frame(s) carry no GPS position (no DJI XMP drone-dji:GpsLatitude and GpsLongitude, "
            "no EXIF GPS), e.g. %s: their findings have empty lat/lon and a null GeoJSON geometry",
            len(missing),
            len(frames),
            ", ".join(missing[:3]),
        )
    return counts


def _finish(
    folder: Path,
    base: dict[str, Any],
    flight: Flight,
    records: dict[str, dict[str, Any]],
    failures: list[tuple[str, str]],
    sm: ScreenModel,
    timings: dict[str, float],
    screened: int,
    skipped_done: int,
    req: ScreenRequest,
    seconds: float,
    state: str,
    overlapped: bool = False,
    failed_captures: int = 0,
    rejected_skipped: int = 0,
) -> ScreenResult:
    from harness import __version__
    from harness.screen.gallery import render

    frames = [records[c.name] for c in flight.captures if c.name in records]
    findings = []
    for r in frames:
        for f in r.get("findings") or []:
            findings.append({**f, "rgb_file": r["rgb_file"], "thermal_file": r["thermal_file"]})
    out.write_csv(folder / "findings.csv", findings)
    out.write_geojson(folder / "findings.geojson", findings)
    counts = Counter(f["class"] for f in findings)
    routes = Counter(r["route"] for r in frames)
    positions = position_counts(frames)
    temperatures = temperature_counts(frames)
    rejected = [
        (r["frame"], registration_note(r.get("registration") or {}))
        for r in frames
        if str(r["route"]).startswith("prior (")
    ]
    cpu = {k: timings.pop(k) for k in ("front_cpu", "model_cpu")}
    per = {k: (v / screened if screened else None) for k, v in timings.items()}
    front = sum(v for k, v in per.items() if k != "model" and v is not None) if screened else None
    timing = {
        "seconds": round(seconds, 3),
        "frames_per_s": round(screened / seconds, 3) if screened else None,
        "per_frame_s": {k: (round(v, 6) if v is not None else None) for k, v in per.items()},
        "frontend_over_model": round(front / per["model"], 4) if screened and per["model"] else None,
        "frontend_over_model_cpu": round(cpu["front_cpu"] / cpu["model_cpu"], 4) if cpu["model_cpu"] > 0 else None,
        "workers": req.workers,
        "threads": req.threads,
        "overlapped": overlapped,
    }
    _remove_stale(folder, frames)
    frame_counts = {
        "captures": len(flight.captures),
        "screened": len(frames),
        "screened_now": screened,
        "screened_earlier": skipped_done,
        "failed": failed_captures,
        "rejected_not_screened": rejected_skipped,
        "not_reached": len(flight.captures) - len(frames) - failed_captures - rejected_skipped,
        "unpaired_files": len(flight.bad),
        "ignored_files": flight.ignored,
        "with_findings": sum(1 for r in frames if r.get("findings")),
    }
    summary = [
        f"flight {flight.folder}: {count_line(frame_counts)}",
        f"model {sm.detector.name} ({base['model']['backend']}), encoding {sm.encoding.name}, threshold "
        f"{sm.threshold:g} ({sm.threshold_source})",
        "registration routes: " + ", ".join(f"{k} {v}" for k, v in sorted(routes.items())),
    ]
    if temperatures["approximate_frames"]:
        summary.append(approximate_line(temperatures))
    listed = grouped_failures(failures)
    html = render(f"Screen of {flight.folder.name}", frames, findings, sm.categories, listed, summary, __version__)
    from harness.io import atomic_write_text

    atomic_write_text(folder / "index.html", html)
    inputs = [
        {
            "frame": r["frame"],
            "rgb": r["rgb_file"],
            "thermal": r["thermal_file"],
            **{f"{k}_sha1": v for k, v in (r.get("fingerprints") or {}).items()},
        }
        for r in frames
    ]
    manifest = {
        **base,
        "state": state,
        "frames": frame_counts,
        "findings": dict(counts),
        "routes": dict(routes),
        "failures": [list(f) for f in failures],
        "registration_rejected": [list(r) for r in rejected],
        "positions": positions,
        "temperatures": temperatures,
        "inputs": inputs,
        "timings": timing,
    }
    out.write_json(folder / "manifest.json", manifest)
    return ScreenResult(
        folder,
        len(flight.captures),
        screened,
        skipped_done,
        sum(1 for r in frames if r.get("findings")),
        dict(counts),
        failures,
        rejected,
        timing,
        sm.threshold,
        sm.threshold_source,
        positions,
        temperatures,
        frame_counts,
        flight.why_empty() if not flight.captures else _why_none(frame_counts),
    )
