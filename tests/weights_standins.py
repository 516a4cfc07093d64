"""Checkpoints pickled the way Ultralytics, YOLOv5 and ICAFusion write them, made from stand-in classes.

The model's own classes are swapped for stand-ins registered under the other codebase's module names (for example
``ultralytics.nn.modules.conv.Conv`` and ``ultralytics.nn.tasks.DetectionModel``) while ``torch.save`` runs, then the
fake modules are removed again: the file references classes that no installed package provides, exactly like a
real checkpoint on a machine without that codebase. ``torch.nn`` layers keep their real names.
"""

from __future__ import annotations

import contextlib
import copy
import sys
import types
from pathlib import Path
from typing import Any, Iterator, Mapping

import torch
from torch import nn


@contextlib.contextmanager
def standin_classes(model: nn.Module, module_of: Mapping[str, str], root: tuple[str, str]) -> Iterator[None]:
    """Give every non-``torch.nn`` module of ``model`` a stand-in class named ``<module_of[cls]>.<cls name>`` (the
    root module gets ``root = (module, name)``) for the duration of the block."""
    fake: dict[str, types.ModuleType] = {}
    originals: list[tuple[nn.Module, type]] = []
    made: dict[tuple[str, str, type], type] = {}

    def module(name: str) -> types.ModuleType:
        parts = name.split(".")
        for i in range(1, len(parts) + 1):  # parents too: pickle imports the module to check the class
            sub = ".".join(parts[:i])
            if sub not in fake:
                assert sub not in sys.modules, f"{sub} must not be importable in the tests"
                fake[sub] = types.ModuleType(sub)
                sys.modules[sub] = fake[sub]
        return fake[name]

    try:
        for m in model.modules():
            cls = type(m)
            if cls.__module__.startswith("torch.nn"):
                continue
            modname, clsname = root if m is model else (module_of.get(cls.__name__, module_of["*"]), cls.__name__)
            key = (modname, clsname, cls)
            if key not in made:
                made[key] = type(clsname, (cls,), {"__module__": modname, "__qualname__": clsname})
                setattr(module(modname), clsname, made[key])
            originals.append((m, cls))
            m.__class__ = made[key]
        yield
    finally:
        for m, cls in originals:
            m.__class__ = cls
        for name in fake:
            sys.modules.pop(name, None)


ULTRALYTICS_MODULES = {
    "Conv": "ultralytics.nn.modules.conv",
    "Concat": "ultralytics.nn.modules.conv",
    "Detect": "ultralytics.nn.modules.head",
    "*": "ultralytics.nn.modules.block",
}
YOLOV5_MODULES = {"Detect": "models.yolo", "*": "models.common"}


def half_copy(model: nn.Module) -> nn.Module:
    return copy.deepcopy(model).half()


def reference_float32(model: nn.Module) -> dict[str, torch.Tensor]:
    """What an fp16 checkpoint of ``model`` holds, back in float32 (the weights an import must reproduce)."""
    return {k: (v.half().float() if v.is_floating_point() else v.clone()) for k, v in model.state_dict().items()}


def save_ultralytics(model: nn.Module, path: Path, names: Mapping[int, str], style: str = "trainer") -> Path:
    """An Ultralytics ``.pt``: the trainer's ``{'model': None, 'ema': <model>}`` or ``YOLO.save()``'s final
    ``{'model': <model>, 'ema': None}``; the model in half precision with ``yaml`` and ``names`` attributes."""
    m = half_copy(model)
    m.yaml = {
        "nc": int(model.nc),
        "scale": str(model.scale),
        "backbone": [[-1, 1, "Conv", [64, 3, 2]]],
        "head": [[[15, 18, 21], 1, "Detect", ["nc"]]],
    }
    m.names = dict(names)
    m.args = {"imgsz": 640, "epochs": 3, "save_dir": "runs/detect/train"}
    ckpt: dict[str, Any] = {
        "epoch": 2 if style == "trainer" else -1,
        "best_fitness": 0.25,
        "date": "2024-05-01T12:00:00",
        "version": "8.2.0",
        "license": "AGPL-3.0",
        "train_args": {"imgsz": 640, "data": "facade.yaml", "save_dir": Path("runs/detect/train")},
        "train_metrics": {"metrics/mAP50(B)": 0.5},
        "optimizer": None,
        "updates": 123,
    }
    if style == "trainer":
        ckpt.update(model=None, ema=m)
    else:
        ckpt.update(model=m, ema=None)
    with standin_classes(m, ULTRALYTICS_MODULES, ("ultralytics.nn.tasks", "DetectionModel")):
        torch.save(ckpt, path)
    return path


def save_yolov5_style(model: nn.Module, path: Path, extra: Mapping[str, Any] | None = None) -> Path:
    """A YOLOv5/ICAFusion checkpoint: ``{'epoch', 'best_fitness' (a NumPy array), 'model': <Model> (half),
    'ema': None, 'optimizer': None, 'opt': {...}}`` with ``models.yolo.Model`` as the model class."""
    import numpy as np

    m = half_copy(model)
    m.yaml = {"nc": int(getattr(model, "nc", 0)), "depth_multiple": 0.33, "width_multiple": 0.125}
    m.names = [f"class{i}" for i in range(int(getattr(model, "nc", 0)))]
    ckpt = {
        "epoch": 5,
        "best_fitness": np.array([0.31]),
        "training_results": "0/4 ...",
        "model": m,
        "ema": None,
        "optimizer": None,
        "wandb_id": None,
        "opt": {"weights": "yolov5l.pt", "img_size": [640, 640]},
        **dict(extra or {}),
    }
    with standin_classes(m, YOLOV5_MODULES, ("models.yolo", "Model")):
        torch.save(ckpt, path)
    return path
