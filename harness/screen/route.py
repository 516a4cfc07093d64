"""A run's held-out fold scored under the registration route a new flight gets: what registration costs.

The run's samples were registered by the route its dataset offers (landmarks, for the M3T layout; recorded in
``config.yaml`` ``meta.registration``). A new flight has no landmarks: ``harness screen`` registers each inspection
group automatically, pooled over its captures, and falls back to the factory prior where the group's evidence fails.
``score_screening_route`` runs the held-out fold's raw captures through exactly that path (the screen's front end,
``frontend_results``, and its ``Predictor``, with ``harness screen``'s default options) twice:

* ``automatic``: the screening route itself (pooled automatic registration, the prior where it is rejected);
* ``prior``: every group registered by the factory prior alone;

and scores each against the run's ground truth (``gt.json``), the boxes taken into the frame of the run's own
samples (the crop origins of both routes differ where the common support does). ``landmarks`` is the run's own
score (``metrics.json``). The result is stored beside the run's metrics as ``screening_route.json``: the three
scores, the registration of every group, and the predictions of both routes in the form ``predictions.json`` has
(image ids of the dataset, boxes in the aligned frame the model saw), which are exactly what ``harness screen`` of
the same captures with default options finds (``findings.csv`` ``bbox`` and ``score``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Sequence

from harness.errors import ConfigError, StoreError

log = logging.getLogger(__name__)

FILE = "screening_route.json"
SCHEMA = 1
#: the routes scored, in the order a report shows them
ROUTES = ("landmarks", "automatic", "prior")


def held_out_captures(cfg: dict[str, Any]) -> list[tuple[int, Any]]:
    """``(image id, Capture)`` of the raw captures of a run's held-out groups, sorted by capture name as a flight
    folder lists them; the dataset must offer its raw captures (``source.raw_captures(groups)``)."""
    from harness.cache.preparation import open_source
    from harness.screen.flight import Capture

    meta = cfg.get("meta") or {}
    _, source = open_source(str(meta.get("dataset")), cfg)
    if not hasattr(source, "raw_captures"):
        raise ConfigError(
            f"dataset {meta.get('dataset')!r} offers no raw captures (wide and thermal files before alignment), so "
            "its runs cannot be scored under the screening route"
        )
    items = [
        (int(i), Capture(name, Path(rgb), Path(th)))
        for i, name, rgb, th in source.raw_captures(list(meta.get("val_groups") or []))
    ]
    return sorted(items, key=lambda it: it[1].name)


def route_predictions(
    sm: Any, run: Path, captures: Sequence[tuple[int, Any]], route: str, work_dir: Path
) -> tuple[list[dict[str, Any]], dict[int, dict[str, Any]], list[tuple[str, str]]]:
    """The run's detections on ``captures`` through the screen's front end under ``route`` (``automatic`` or
    ``prior``), with ``harness screen``'s defaults: (COCO results with the dataset's image ids, per image its
    route, registration and crop origin, failures)."""
    import cv2

    from harness.screen.flight import inspection_groups
    from harness.screen.frontend import FrontEnd, FrontEndSettings
    from harness.screen.job import ScreenRequest, frontend_results, resolve_cameras
    from harness.screen.model import Predictor

    sensing = dict(sm.sensing)
    if route == "prior":
        sensing["registration"] = {**dict(sensing.get("registration") or {}), "method": "focal"}
    elif route != "automatic":
        raise ConfigError(f"unknown screening route {route!r}; use automatic or prior")
    req = ScreenRequest(flight=work_dir, out=work_dir, run=run)
    rgb_cam, th_cam, _ = resolve_cameras(req, sm)
    settings = FrontEndSettings(
        sensing=sensing,
        encoding=sm.encoding.name,
        encoding_params=sm.encoding_params,
        rgb_camera=rgb_cam,
        thermal_camera=th_cam,
    )
    fe = FrontEnd(settings, sm.encoding)
    caps = [c for _, c in captures]
    image_id = {c.name: i for i, c in captures}
    groups = inspection_groups(caps, fe.options.group_gap_s) if fe.options.registration.method == "auto" else None
    predictor = Predictor(sm, "torch", "cpu", work_dir)
    dets: list[dict[str, Any]] = []
    frames: dict[int, dict[str, Any]] = {}
    failures: list[tuple[str, str]] = []
    batch: list[Any] = []

    def flush() -> None:
        for frame, found in zip(batch, predictor([f.image for f in batch])):
            iid = image_id[frame.capture.name]
            dets.extend({**d, "image_id": iid} for d in found)
            frames[iid] = {
                "frame": frame.capture.name,
                "route": frame.route,
                "registration": frame.registration,
                "crop_origin": list(frame.origin),
            }
        batch.clear()

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # as ``screen`` runs the front end
    try:
        for cap, frame, error, _ in frontend_results(fe, caps, 1, groups, None, None, caps):
            if frame is None:
                failures.append((cap.name, error or "unknown error"))
                continue
            batch.append(frame)
            if len(batch) >= predictor.batch:
                flush()
        flush()
    finally:
        cv2.setNumThreads(threads)
    return dets, frames, failures


def _origins(cfg: dict[str, Any]) -> dict[int, tuple[float, float]]:
    """The crop origin of each of the run's prepared samples (the frame its ground truth is in)."""
    from harness.runner import prepare_dataset

    prepared = prepare_dataset(str((cfg.get("meta") or {}).get("dataset")), cfg)
    out = {}
    for rec in prepared.records:
        o = (rec.get("meta") or {}).get("crop_origin") or [0, 0]
        out[int(rec["image_id"])] = (float(o[0]), float(o[1]))
    return out


def _scored(
    gt: dict[str, Any],
    dets: list[dict[str, Any]],
    frames: dict[int, dict[str, Any]],
    origins: dict[int, tuple[float, float]],
    cfg: dict[str, Any],
) -> dict[str, Any]:
    """COCO scores of ``dets`` against the run's ground truth, each box moved into its sample's frame."""
    from harness.evaluation import evaluate_with_config

    keep = {int(im["id"]) for im in gt.get("images") or []}
    moved = []
    for d in dets:
        iid = int(d["image_id"])
        if iid not in keep:
            continue
        o = frames[iid]["crop_origin"]
        base = origins.get(iid, (0.0, 0.0))
        x, y, w, h = d["bbox"]
        moved.append({**d, "bbox": [x + o[0] - base[0], y + o[1] - base[1], w, h]})
    missing = sorted(keep - set(frames))
    if missing:  # a held-out image the route could not screen keeps its ground truth and gets no detection
        log.warning("%d held-out image(s) were not screened under the route: scored without detections", len(missing))
    res = evaluate_with_config(gt, moved, cfg)
    m = res["metrics"]
    return {
        "mAP50_95": m.get("mAP50_95"),
        "mAP50": m.get("mAP50"),
        "images": len(keep),
        "screened": len(frames),
        "detections": len(moved),
    }


def score_screening_route(run_dir: str | Path, routes: Sequence[str] = ("automatic", "prior")) -> dict[str, Any]:
    """Score the run in ``run_dir`` under the screening route and the prior, write ``screening_route.json`` beside
    its ``metrics.json`` and return what it holds (see the module docstring)."""
    import json

    from harness.io import atomic_write_json, read_json
    from harness.screen.model import from_run

    run = Path(run_dir)
    sm = from_run(run)
    cfg = sm.config
    metrics_path = run / "metrics.json"
    if not metrics_path.is_file():
        raise StoreError(f"{metrics_path}: missing; score a finished run")
    metrics = read_json(metrics_path)
    gt = read_json(run / "gt.json")
    captures = held_out_captures(cfg)
    ids = {int(im["id"]) for im in gt.get("images") or []}
    captures = [(i, c) for i, c in captures if i in ids]
    if not captures:
        raise ConfigError(f"{run}: none of the run's held-out images is among its dataset's raw captures")
    origins = _origins(cfg)
    m = metrics.get("metrics") or {}
    meta = cfg.get("meta") or {}
    out: dict[str, Any] = {
        "schema": SCHEMA,
        "run": {k: meta.get(k) for k in ("dataset", "detector", "encoding", "fold", "seed")},
        "recorded_route": meta.get("registration"),
        "routes": {
            "landmarks": {
                "mAP50_95": m.get("mAP50_95"),
                "mAP50": m.get("mAP50"),
                "images": len(ids),
                "source": "metrics.json (the run's own samples)",
            }
        },
        "predictions": {},
        "frames": {},
    }
    work = run  # the torch backend writes nothing there
    for route in routes:
        dets, frames, failures = route_predictions(sm, run, captures, route, work)
        scored = _scored(gt, dets, frames, origins, cfg)
        registered = sum(1 for f in frames.values() if str(f["route"]).startswith("auto"))
        groups: dict[str, Any] = {}
        for f in frames.values():
            reg = f["registration"] or {}
            name = str(f["route"]).removeprefix("auto (group ").rstrip(")") if reg.get("ok") else None
            groups.setdefault(
                name or f["route"],
                {
                    k: reg.get(k)
                    for k in (
                        "ok",
                        "frames",
                        "agreeing",
                        "correlation",
                        "prior_correlation",
                        "reason",
                        "expected_error_px",
                    )
                    if k in reg
                },
            )
        out["routes"][route] = {
            **scored,
            "registered_automatically": registered,
            "failures": failures,
            "groups": groups if route == "automatic" else {},
        }
        out["predictions"][route] = dets
        out["frames"][route] = {str(k): v for k, v in sorted(frames.items())}
    atomic_write_json(run / FILE, json.loads(json.dumps(out, default=float)))
    return out


def summary_lines(result: dict[str, Any]) -> list[str]:
    """What ``harness score-route`` prints: mAP per route and the share registered automatically."""
    lines = []
    for route in ROUTES:
        r = (result.get("routes") or {}).get(route)
        if r is None:
            continue
        extra = ""
        if route == "automatic":
            extra = f", {r['registered_automatically']} of {r['screened']} frames registered automatically"
        lines.append(f"{route:<10} mAP50-95 {_f(r.get('mAP50_95'))}  mAP50 {_f(r.get('mAP50'))}{extra}")
    return lines


def _f(v: Any) -> str:
    return "-" if v is None else f"{100 * float(v):.1f} %"
