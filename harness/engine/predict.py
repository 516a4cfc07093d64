"""Inference over a subset: COCO-format detections in the thermal frame.

The model sees each held-out image letterboxed to the protocol size, exactly as in training; its boxes are mapped
back through the letterbox (``x = (x_input - pad) / ratio``), clipped to the image, and written as COCO results:
``{"image_id", "category_id": label + 1, "bbox": [x, y, w, h], "score"}`` in thermal-frame pixels.
"""

from __future__ import annotations

import logging
from typing import Any

import torch
from torch import nn
from torch.utils.data import Subset

from harness.engine.data import LetterboxDataset, SampleSource, eval_loader, to_inputs
from harness.errors import PluginError

log = logging.getLogger(__name__)


def configure(model: nn.Module, conf: float, iou: float, max_det: int) -> None:
    """Set the model's own NMS settings (the ``conf``, ``iou`` and ``max_det`` attributes of the contract)."""
    model.conf, model.iou, model.max_det = float(conf), float(iou), int(max_det)


def detections_to_coco(det: dict[str, torch.Tensor], image_id: int, letterbox: Any, num_classes: int | None = None,
                       name: str = "model") -> list[dict[str, Any]]:
    """One image's ``{"boxes", "scores", "labels"}`` (input pixels) -> COCO results in the original frame."""
    from harness.contracts import check_detections

    boxes, scores, labels = check_detections(det, name, num_classes)
    if letterbox is not None:
        boxes = letterbox.to_original(boxes)
    out = []
    for (x1, y1, x2, y2), s, lab in zip(boxes.tolist(), scores.tolist(), labels.tolist()):
        w, h = x2 - x1, y2 - y1
        if w <= 0 or h <= 0:
            continue
        out.append({"image_id": int(image_id), "category_id": int(lab) + 1,
                    "bbox": [round(x1, 2), round(y1, 2), round(w, 2), round(h, 2)], "score": round(float(s), 5)})
    return out


@torch.inference_mode()
def predict(model: nn.Module, source: SampleSource, imgsz: int, batch: int = 8, input_kind: str = "single",
            thermal_channels: int = 3, device: torch.device | str = "cpu", conf: float | None = None,
            iou: float | None = None, max_det: int | None = None, num_classes: int | None = None,
            workers: int = 0, progress: bool = False, name: str = "model", distributed: bool = False,
            visited: list[int] | None = None) -> list[dict[str, Any]]:
    """Detections for every image of ``source`` (COCO results, see the module docstring).

    With ``distributed`` (under ``torchrun``) each process predicts one contiguous shard of the images
    (``harness.distributed.inference_shard``: every image exactly once, no padding duplicates) and rank 0 receives
    all detections, in the order a single process would produce them; the other ranks get an empty list. When
    given, ``visited`` receives the ids of the images predicted (on rank 0: by all processes).
    """
    from harness import distributed as hd

    if conf is not None:
        configure(model, conf, iou if iou is not None else getattr(model, "iou", 0.7),
                  max_det if max_det is not None else getattr(model, "max_det", 300))
    d = hd.info() if distributed else hd.DistInfo()
    was_training = model.training
    model.eval()
    device = torch.device(device)
    dataset: Any = LetterboxDataset(source, imgsz)
    if d.active:
        dataset = Subset(dataset, list(hd.inference_shard(len(source), d.rank, d.world_size)))
    loader = eval_loader(dataset, batch, workers)
    results: list[dict[str, Any]] = []
    ids: list[int] = []
    ctx = _bar(progress and d.is_main, len(dataset), f"predict {name}")
    try:
        with ctx as (bar, task):
            for b in loader:
                out = model(to_inputs(b.images, input_kind, thermal_channels, device))
                if not isinstance(out, (list, tuple)) or len(out) != len(b):
                    raise PluginError(f"detector {name!r}: in eval mode model(inputs) must return one dict per image "
                                      f"({len(b)}), got {type(out).__name__}")
                for det, image_id, lb in zip(out, b.image_ids, b.letterboxes):
                    results.extend(detections_to_coco(det, image_id, lb, num_classes, name))
                ids.extend(int(i) for i in b.image_ids)
                if bar is not None:
                    bar.update(task, advance=len(b))
    finally:
        model.train(was_training)
    if d.active:
        parts = hd.gather_to_main((results, ids))
        if parts is None:
            results, ids = [], []
        else:
            results = [r for part, _ in parts for r in part]
            ids = [i for _, part in parts for i in part]
            expected = [source.image_id(k) for k in range(len(source))]
            if ids != expected:  # the shards must partition the images exactly
                raise PluginError(f"distributed prediction visited {len(ids)} images ({len(set(ids))} distinct), "
                                  f"expected each of the {len(expected)} images once")
    if visited is not None:
        visited.extend(ids)
    return results


class _bar:
    def __init__(self, enabled: bool, total: int, description: str):
        self.enabled, self.total, self.description = enabled, total, description
        self.progress: Any = None

    def __enter__(self) -> tuple[Any, Any]:
        if not self.enabled:
            return None, None
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), transient=True)
        self.progress.__enter__()
        return self.progress, self.progress.add_task(self.description, total=self.total)

    def __exit__(self, *exc: Any) -> None:
        if self.progress is not None:
            self.progress.__exit__(*exc)
