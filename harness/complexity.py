"""The complexity of the exact model a run trained, measured once per run and stored with its results.

``measure(model, input_kind, in_channels, thermal_channels, imgsz, num_classes, model_options)`` returns the record
``harness run`` writes under ``complexity`` in the run's ``metrics.json``::

    {"schema": 1, "model_options": {...}, "num_classes": int, "input_kind": "single" | "dual",
     "in_channels": int, "params": int, "params_fused": int, "bn_folded": bool, "trainable": int,
     "unused_params": int, "gflops": {"<imgsz>": {"paper": float, "exact": float}, "640": {...}},
     "imgsz": int}

Parameters and the reachability analysis come from the model as built; FLOPs from its BN-folded copy (when the
model declares a fold, see ``harness.profiling.model_io.fused_copy``), both on the meta device (no memory, no
compute). Reports, ``compare`` and the accuracy-versus-GFLOPs figure read this record and nothing else, so every
Params/GFLOPs figure belongs to the model that produced the accuracy next to it.
"""

from __future__ import annotations

import logging
from typing import Any, Mapping

log = logging.getLogger(__name__)

SCHEMA = 1
#: The reference input size of the published tables; every run is measured there as well as at its own size.
REFERENCE_IMGSZ = 640


def measure(
    model: Any,
    input_kind: str,
    in_channels: int,
    thermal_channels: int,
    imgsz: int,
    num_classes: int,
    model_options: Mapping[str, Any] | None = None,
    label: str = "the model",
) -> dict[str, Any]:
    """The complexity record of ``model`` (see the module docstring); a failure is recorded, never raised.
    ``label`` names the detector in the warning."""
    from harness.profiling.flops import exact_flops, paper_flops
    from harness.profiling.model_io import example_inputs, fused_copy, require_forward_raw
    from harness.profiling.params import count_parameters, reachable_parameters

    rec: dict[str, Any] = {
        "schema": SCHEMA,
        "model_options": dict(model_options or {}),
        "num_classes": int(num_classes),
        "input_kind": input_kind,
        "in_channels": int(in_channels),
        "imgsz": int(imgsz),
    }
    try:
        require_forward_raw(model, label)
        small = example_inputs(input_kind, int(imgsz), 1, in_channels, thermal_channels, device="meta")
        params = reachable_parameters(model, small)
        fused, did_fuse = fused_copy(model)
        fused_total, _, _ = count_parameters(fused)
        rec.update(
            params=params.total,
            trainable=params.trainable,
            params_fused=int(fused_total),
            bn_folded=bool(did_fuse),
            unused_params=int(params.unreachable_count - params.frozen_unreachable_count),
        )
        gflops: dict[str, dict[str, float]] = {}
        for size in dict.fromkeys((int(imgsz), REFERENCE_IMGSZ)):
            inputs = example_inputs(input_kind, size, 1, in_channels, thermal_channels, device="meta")
            gflops[str(size)] = {
                "paper": round(paper_flops(fused, inputs).gflops, 4),
                "exact": round(exact_flops(fused, inputs).gflops, 4),
            }
        rec["gflops"] = gflops
    except Exception as exc:  # noqa: BLE001 - the run goes on; the record says why its complexity is missing
        said = str(exc) or repr(exc)  # an exception without a message still says what it was
        log.warning("complexity of the trained model could not be measured: %s: %s", type(exc).__name__, said)
        rec["error"] = f"{type(exc).__name__}: {said}"
    return rec


def given(params_m: float | None, gflops: float | None, imgsz: int = REFERENCE_IMGSZ) -> dict[str, Any] | None:
    """The record of a model the harness did not build (scored from a predictions file): the figures its user gave.

    ``None`` when none was given. ``source: "given"`` marks it; the report shows such figures like measured ones,
    and the run's ``external`` block says where they came from."""
    if params_m is None and gflops is None:
        return None
    return {
        "schema": SCHEMA,
        "source": "given",
        "model_options": {},
        "num_classes": None,
        "input_kind": "external",
        "params": None if params_m is None else int(round(float(params_m) * 1e6)),
        "bn_folded": False,
        "gflops": {} if gflops is None else {str(imgsz): {"paper": float(gflops), "exact": None}},
        "imgsz": int(imgsz),
    }


def numbers(rec: Mapping[str, Any] | None, imgsz: int = REFERENCE_IMGSZ) -> dict[str, Any]:
    """Params (M, BN-folded when folded), GFLOPs (paper, exact) at ``imgsz`` and the conditions of one record."""
    if not rec or rec.get("error") or not (rec.get("gflops") or rec.get("source") == "given"):
        return {}
    g = (rec.get("gflops") or {}).get(str(imgsz)) or {}
    count = rec.get("params_fused") if rec.get("bn_folded") else rec.get("params")
    return {
        "params_m": None if count is None else float(count) / 1e6,
        "gflops": g.get("paper"),
        "gflops_exact": g.get("exact"),
        "imgsz": imgsz,
        "bn_folded": bool(rec.get("bn_folded")),
        "num_classes": rec.get("num_classes"),
        "input_kind": rec.get("input_kind"),
        "model_options": dict(rec.get("model_options") or {}),
        "unused_params": rec.get("unused_params"),
        "source": rec.get("source", "measured"),
    }


def options_label(options: Mapping[str, Any]) -> str:
    """``scale=n, width=0.5``: the model options a run was built with (empty for the detector's defaults)."""
    return ", ".join(f"{k}={v}" for k, v in sorted(options.items()))
