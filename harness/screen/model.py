"""The detector a screen runs: a finished run's model (or a weights file), in PyTorch or through ONNX Runtime.

``from_run(RUN_DIR)`` reads what the run stored: ``config.yaml`` (detector, encoding, model options, input size,
NMS settings and the ``sensing`` section), the categories of its ``gt.json``, the weights it predicted its held-out
fold with (``checkpoints/best.pt`` when ``train.final`` is ``best``, else the EMA weights of ``last.pt``) and the
operating point of its ``metrics.json`` (the confidence that maximised F1 on the held-out fold), the default
screening threshold. ``from_weights`` builds the same record from a checkpoint, a detector name and a dataset (its
categories, protocol and encoding) with the configuration resolved as ``harness run`` resolves it.

Both backends predict through ``harness.engine.predict.predict``: the letterbox, the model's own NMS at the run's
``eval.conf``/``iou``/``max_det``, the mapping back and the rounding of the stored predictions. The ONNX backend
exports the loaded model (``harness.profiling.export.export_onnx``: BatchNorm folded, dynamic batch, checked
against torch) and runs the graph in ONNX Runtime; the model's own decoding and NMS then run on the graph's raw
outputs (its ``forward_raw`` is answered by the session), so only the network itself changes backend.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from harness.errors import ConfigError, PluginError, StoreError
from harness.io import file_digest

log = logging.getLogger(__name__)

BACKENDS = ("torch", "onnx")


@dataclass
class ScreenModel:
    """A loaded detector with everything its run used around it."""

    detector: Any  # DetectorSpec
    model: Any  # torch.nn.Module, eval mode, weights loaded
    categories: list[str]
    encoding: Any  # EncodingSpec
    encoding_params: dict[str, Any] = field(init=False)  # the encoding's section of ``config``
    config: dict[str, Any]
    weights: Path
    weights_sha1: str = field(init=False)  # the digest of ``weights``
    threshold: float
    threshold_source: str
    run: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.encoding_params = dict((self.config.get("encoding") or {}).get(self.encoding.name) or {})
        self.weights_sha1 = file_digest(self.weights)

    @property
    def imgsz(self) -> int:
        return int(self.config["protocol"]["imgsz"])

    @property
    def sensing(self) -> dict[str, Any]:
        return dict(self.config.get("sensing") or {})

    @property
    def in_channels(self) -> int:
        det = self.detector
        return int(det.thermal_channels) if det.input_kind == "dual" else 3 + int(self.encoding.channels)

    def describe(self) -> dict[str, Any]:
        """What the manifest records about the model."""
        ev = self.config.get("eval") or {}
        return {
            "detector": self.detector.name,
            "input_kind": self.detector.input_kind,
            "encoding": self.encoding.name,
            "encoding_params": self.encoding_params,
            "categories": self.categories,
            "imgsz": self.imgsz,
            "model_options": self.config.get("model") or {},
            "nms": {k: ev.get(k) for k in ("conf", "iou", "max_det")},
            "weights": str(self.weights),
            "weights_sha1": self.weights_sha1,
            "threshold": self.threshold,
            "threshold_source": self.threshold_source,
            "run": self.run,
        }


def _build(det: Any, categories: Sequence[str], enc: Any, cfg: dict[str, Any], weights: Path) -> Any:
    from harness.engine import checkpoint as ckpt
    from harness.runner import build_model

    in_channels = det.thermal_channels if det.input_kind == "dual" else 3 + int(enc.channels)
    model = build_model(det, len(categories), in_channels, cfg.get("model") or {})
    state = ckpt.state_dict_of(ckpt.load(weights))
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        what = " ".join(lines[1:2])[:300] or (lines[0] if lines else str(exc))
        raise ConfigError(
            f"{weights}: its weights do not fit detector {det.name!r} with {len(categories)} classes "
            f"and {in_channels} input channels ({what}); is it a checkpoint of this detector, dataset "
            f"and encoding?"
        ) from None
    return model.eval()


def from_run(run_dir: str | Path, threshold: float | None = None) -> ScreenModel:
    """The model of a finished run (see the module docstring)."""
    from harness.config import read_yaml
    from harness.io import read_json
    from harness.plugins import get_host

    path = Path(run_dir)
    cfg_path = path / "config.yaml"
    if not cfg_path.is_file():
        raise StoreError(
            f"{path}: not a run folder (no config.yaml); give a run of the results store, e.g. "
            "results/smoke/m3t/ours/c2/P1/seed0"
        )
    cfg = read_yaml(cfg_path)
    meta = cfg.get("meta") or {}
    status = read_json(path / "status.json") if (path / "status.json").exists() else {}
    if status.get("state") != "finished":
        raise StoreError(
            f"{path}: the run has not finished (state {status.get('state', 'unknown')!r}); screen with "
            "a finished run, or pass its checkpoint with --weights"
        )
    host = get_host()
    det = host.detector(str(meta.get("detector")))
    enc = host.encoding(str(meta.get("encoding")))
    gt_path = path / "gt.json"
    if not gt_path.exists():
        raise StoreError(f"{gt_path}: missing; the run's categories are read from it")
    cats = sorted(read_json(gt_path).get("categories") or [], key=lambda c: int(c["id"]))
    categories = [str(c["name"]) for c in cats]
    if [int(c["id"]) for c in cats] != list(range(1, len(cats) + 1)):
        raise StoreError(f"{gt_path}: category ids {[c['id'] for c in cats]} are not 1..{len(cats)}")
    ckdir = path / "checkpoints"
    final = str((cfg.get("train") or {}).get("final", "best"))
    weights = ckdir / "best.pt" if final == "best" and (ckdir / "best.pt").exists() else ckdir / "last.pt"
    if not weights.exists():
        raise StoreError(f"{path}: no checkpoint (checkpoints/best.pt or last.pt)")
    model = _build(det, categories, enc, cfg, weights)
    metrics = read_json(path / "metrics.json") if (path / "metrics.json").exists() else {}
    op = (metrics.get("metrics") or {}).get("conf_threshold")
    if threshold is not None:
        thr, source = float(threshold), "--conf"
    elif op is not None:
        thr, source = float(op), "the run's operating point (metrics.json conf_threshold: best mean F1, held-out)"
    else:
        thr, source = float(cfg["eval"]["conf"]), "the run's eval.conf"
    run = {
        "path": str(path.resolve()),
        "key": {k: meta.get(k) for k in ("dataset", "detector", "encoding", "fold", "seed")},
        "config_hash": status.get("config_hash"),
        "held_out": meta.get("val_groups"),
    }
    return ScreenModel(det, model, categories, enc, cfg, weights, thr, source, run)


def from_weights(
    weights: str | Path,
    detector: str,
    dataset: str,
    encoding: str | None = None,
    profile: str | None = "smoke",
    config_files: Sequence[str | Path] = (),
    overrides: Sequence[str] = (),
    threshold: float | None = None,
) -> ScreenModel:
    """A checkpoint of ``detector`` trained on ``dataset``'s categories, configured as ``harness run`` would."""
    from harness.plugins import get_host
    from harness.runner import RunRequest, choose_encoding, resolve_config

    path = Path(weights)
    if not path.is_file():
        raise ConfigError(f"--weights {path}: no such file")
    host = get_host()
    det, ds = host.detector(detector), host.dataset(dataset)
    enc = choose_encoding(det, ds, encoding, host)
    request = RunRequest(det.name, ds.name, profile=profile, config_files=config_files, overrides=overrides)
    cfg = resolve_config(request, det, ds)
    categories = list(ds.categories)
    if not categories:
        raise ConfigError(f"dataset {ds.name!r} registers no categories; screen with --run instead")
    model = _build(det, categories, enc, cfg, path)
    thr = float(threshold) if threshold is not None else float(cfg["eval"]["conf"])
    source = "--conf" if threshold is not None else "eval.conf of the configuration (no run: no operating point)"
    return ScreenModel(det, model, categories, enc, cfg, path, thr, source, {"dataset": ds.name})


# ------------------------------------------------------------------------------------------------ prediction
class FrameImages:
    """The ``SampleSource`` view ``predict`` reads: a list of ``[R, G, B, channel]`` images, ids 0..n-1."""

    def __init__(self, images: Sequence[np.ndarray]):
        self.images = list(images)

    def __len__(self) -> int:
        return len(self.images)

    def image(self, k: int) -> np.ndarray:
        return self.images[k]

    def resized(self, k: int, size: int) -> tuple[np.ndarray, float, tuple[int, int]]:
        from harness.engine.data import resized_long_side

        return resized_long_side(self.images[k], size)

    def targets(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros((0, 4), np.float32), np.zeros(0, np.int64)

    def image_id(self, k: int) -> int:
        return k


class Predictor:
    """Detections (COCO results per image) of a ``ScreenModel`` on a batch of front-end images."""

    def __init__(
        self,
        sm: ScreenModel,
        backend: str = "torch",
        device: str = "cpu",
        work_dir: Path | None = None,
        threads: int | None = None,
    ):
        import torch

        from harness.engine.predict import configure

        if backend not in BACKENDS:
            raise ConfigError(f"--backend {backend!r}: use one of {', '.join(BACKENDS)}")
        self.sm, self.backend, self.device = sm, backend, torch.device(device)
        ev = sm.config["eval"]
        configure(sm.model, ev["conf"], ev["iou"], ev["max_det"])
        self.batch = max(1, int(ev.get("batch") or 1))
        self.onnx: dict[str, Any] = {}
        if backend == "torch":
            self.net = sm.model.to(self.device)
        else:
            if self.device.type != "cpu":
                raise ConfigError("--backend onnx runs on the CPU (ONNX Runtime's CPU provider); drop --device")
            self.net = self._onnx_model(work_dir or Path("."), threads)

    def _onnx_model(self, work_dir: Path, threads: int | None) -> Any:
        import torch

        from harness.io import atomic_write_json, read_json
        from harness.profiling.export import export_onnx, ort_session
        from harness.profiling.model_io import example_inputs

        sm = self.sm
        det = sm.detector
        inputs = example_inputs(det.input_kind, sm.imgsz, 2, sm.in_channels, det.thermal_channels)
        path = work_dir / "model.onnx"
        record_path = work_dir / "model.onnx.json"
        want = {"weights_sha1": sm.weights_sha1, "imgsz": sm.imgsz, "detector": det.name, "in_channels": sm.in_channels}
        record = read_json(record_path) if record_path.exists() and path.exists() else {}
        if {k: record.get(k) for k in want} != want:
            log.info("exporting the model to %s (ONNX, BatchNorm folded, dynamic batch)", path)
            rec = export_onnx(sm.model, inputs, path, dynamic_batch=True, check=True)
            record = {
                **want,
                **{k: rec.get(k) for k in ("opset", "exporter", "fused", "max_abs_diff", "atol")},
                "onnx_sha1": file_digest(path),
            }
            atomic_write_json(record_path, record)
        self.onnx = {"path": str(path), **record}
        session = ort_session(path, threads)
        with torch.no_grad():
            raw = sm.model.forward_raw(inputs)
        return ort_model(sm.model, session, det.input_kind == "dual", raw, det.name)

    def __call__(self, images: Sequence[np.ndarray]) -> list[list[dict[str, Any]]]:
        from harness.engine.predict import predict

        sm = self.sm
        dets = predict(
            self.net,
            FrameImages(images),
            sm.imgsz,
            self.batch,
            sm.detector.input_kind,
            sm.detector.thermal_channels,
            self.device,
            num_classes=len(sm.categories),
            name=sm.detector.name,
        )
        out: list[list[dict[str, Any]]] = [[] for _ in images]
        for d in dets:
            out[int(d["image_id"])].append(d)
        return out


def ort_model(model: Any, session: Any, dual: bool, example_raw: Any, name: str) -> Any:
    """``model`` with its raw forward answered by an ONNX Runtime ``session`` (see the module docstring); a
    ``torch.nn.Module`` that ``predict`` drives like the model itself."""
    import torch
    from torch import nn
    from torch.utils import _pytree

    leaves, spec = _pytree.tree_flatten(example_raw)
    if not all(isinstance(t, torch.Tensor) for t in leaves):
        raise PluginError(
            f"detector {name!r}: forward_raw returns non-tensor values; the ONNX backend needs tensors only"
        )
    input_names = [i.name for i in session.get_inputs()]

    class OrtModel(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, inputs: Any) -> Any:
            tensors = tuple(inputs) if dual else (inputs,)
            feeds = {n: t.detach().cpu().numpy() for n, t in zip(input_names, tensors)}
            raw = _pytree.tree_unflatten([torch.from_numpy(o) for o in session.run(None, feeds)], spec)
            called: list[bool] = []

            def forward_raw(_inputs: Any) -> Any:
                called.append(True)
                return raw

            self.model.forward_raw = forward_raw  # the instance attribute answers the model's own call
            try:
                out = self.model(inputs)
            finally:
                del self.model.forward_raw
            if not called:
                raise PluginError(
                    f"detector {name!r}: its eval forward does not call self.forward_raw, so the ONNX "
                    "backend cannot run its decoding and NMS on the graph's outputs; use --backend torch"
                )
            return out

    return OrtModel()
