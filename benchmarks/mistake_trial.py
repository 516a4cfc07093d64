"""A trial of mistakes a new user makes, each run through the CLI as a user runs it, each outcome classified.

Sets up small inputs in a temporary folder (a tiny coco-rgbt folder prepared once, prediction files, checkpoints,
configs, flight folders from the real DJI files beside the repository, plugin files written to disk) and runs every
case of ``CASES``: in-process through click's runner where the plugin host may be shared, as a subprocess
(``nice -n 15 python -m harness``) where the case needs its own plugins or environment. Each case declares what a
good answer names (``says``: the file, field, option or plugin at fault) and, for a harmless variant, how to tell
the right result (``check``). Classes:

- ``refused-clear``: non-zero exit, the message names the fault;
- ``labelled``: exit 0, the output (or the stored result's labels) names the problem;
- ``correct``: the right thing done (a harmless variant accepted with the right result);
- ``silent``: exit 0, wrong or unlabelled; ``unclear``: refused without naming the fault;
- ``traceback``: a Python traceback or exit 70 (a bug); ``runaway``: past the case's time limit.

Usage: ``nice -n 15 python benchmarks/mistake_trial.py [--json OUT] [--only SUBSTRING]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from _common import SHARED_DATA, on_path

on_path("tests")
os.environ["HARNESS_DISABLE_PLUGIN_AUTOLOAD"] = "1"
os.environ.pop("HARNESS_DEBUG", None)
os.environ.pop("HARNESS_PLUGINS_DIR", None)
os.environ.pop("HARNESS_LOAD_PLUGINS", None)

CLASSES = ("refused-clear", "labelled", "correct", "silent", "unclear", "traceback", "runaway")
FOLD = "site-a"


@dataclass
class Case:
    """One mistake: ``args`` for ``harness`` (a callable of the context when it needs files made first); ``says``:
    any of these strings in the output (case and spacing ignored) names the fault; ``check``: for a harmless
    variant, whether exit 0 gave the right result; ``sub``: run as a subprocess with ``env`` added."""

    id: str
    family: str
    args: list[str] | Callable[[Ctx], list[str]]
    says: tuple[str, ...] = ()
    check: Callable[[Ctx, str], bool] | None = None
    sub: bool = False
    env: dict[str, str] = field(default_factory=dict)
    timeout: int = 60


@dataclass
class Ctx:
    tmp: Path
    root: Path
    store: Path
    preds: Path
    coco: dict[str, Any]

    def case_dir(self, name: str) -> Path:
        d = self.tmp / "cases" / name
        d.mkdir(parents=True, exist_ok=True)
        return d


def norm(text: str) -> str:
    return " ".join(text.split()).lower()


# ---------------------------------------------------------------------------------------------------- the world
def build_world(tmp: Path) -> Ctx:
    from coco_rgbt_helpers import make_coco_rgbt, read_json

    root = make_coco_rgbt(tmp / "pairs", n=12)
    os.environ["HARNESS_CACHE"] = str(tmp / "cache")
    ctx = Ctx(tmp, root, tmp / "store", tmp / "preds.json", read_json(root))
    code, out = invoke(["prepare", "--dataset", "coco-rgbt", "--root", str(root), "--no-progress"])
    if code != 0:
        raise SystemExit(f"the known-good coco-rgbt folder did not prepare:\n{out}")
    ctx.preds.write_text(json.dumps(perfect(ctx)))
    code, out = invoke(score_args(ctx, ctx.preds, "good"))
    if code != 0 or "mAP50 100.0" not in out:
        raise SystemExit(f"the known-good predictions did not score 100:\n{out}")
    return ctx


def perfect(ctx: Ctx) -> list[dict[str, Any]]:
    return [
        {"image_id": a["image_id"], "category_id": a["category_id"], "bbox": list(a["bbox"]), "score": 0.9}
        for a in ctx.coco["annotations"]
    ]


def score_args(ctx: Ctx, preds: Path | str, name: str, *more: str) -> list[str]:
    return [
        "score",
        "--dataset",
        "coco-rgbt",
        "--root",
        str(ctx.root),
        "--folds",
        FOLD,
        "--predictions",
        str(preds),
        "--images",
        str(ctx.root / "annotations.json"),
        "--frame",
        "thermal",
        "--name",
        name,
        "--store",
        str(ctx.store),
        "--force",
        *more,
    ]


def mapped(value: float) -> Callable[[Ctx, str], bool]:
    """Exit 0 with mAP50 ``value`` printed."""
    return lambda ctx, out: f"map50 {value:.1f}" in norm(out)


def prepared(n: int) -> Callable[[Ctx, str], bool]:
    return lambda ctx, out: f"coco-rgbt: {n} aligned samples" in norm(out)


# ---------------------------------------------------------------------------------------------------- running
class Runaway(Exception):
    pass


def _alarm(signum: int, frame: Any) -> None:
    raise Runaway


def invoke(args: list[str], timeout: int = 60) -> tuple[int, str]:
    """In-process CLI call: (exit status, stdout + stderr); 70 with the traceback for an exception that escaped."""
    import traceback

    from click.testing import CliRunner

    from harness.cli import get_cli

    signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(timeout)
    try:
        res = CliRunner().invoke(get_cli(), args, catch_exceptions=True)
    finally:
        signal.alarm(0)
    if isinstance(res.exception, Runaway):
        raise Runaway
    out = res.output
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        out += "\nTraceback (most recent call last):\n" + "".join(traceback.format_exception(res.exception))
        return 70, out
    return res.exit_code, out


def invoke_sub(args: list[str], env: dict[str, str], timeout: int) -> tuple[int, str]:
    full = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), **env}
    cmd = ["nice", "-n", "15", sys.executable, "-m", "harness", *args]
    try:
        p = subprocess.run(cmd, env=full, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise Runaway from None
    return p.returncode, p.stdout + p.stderr


def classify(case: Case, code: int, out: str) -> str:
    if code == 70 or "Traceback (most recent call last)" in out:
        return "traceback"
    # the folders the trial made are no evidence: a needle must come from the message, not from a case's folder name
    out = out.replace(str(CTX.tmp / "cases" / case.id), "<case>").replace(str(CTX.tmp), "<tmp>")
    named = any(norm(s) in norm(out) for s in case.says)
    if code != 0:
        return "refused-clear" if named else "unclear"
    if case.check is not None and case.check(CTX, out):
        return "correct"
    return "labelled" if named else "silent"


def first_line(out: str) -> str:
    keep = [ln.strip() for ln in out.splitlines() if ln.strip() and not ln.lstrip().startswith("INFO")]
    for starts in (("error", "bug"), ("warning",)):  # the refusal first, then a warning, else the first line
        found = [ln for ln in keep if ln.lower().startswith(starts)]
        if found:
            return found[0]
    return (keep or [""])[0]


CTX: Ctx


# ---------------------------------------------------------------------------------------------------- case makers
def pred_case(
    name: str,
    says: tuple[str, ...],
    make: Callable[[Ctx], Any],
    *more: str,
    raw: bool = False,
    suffix: str = ".json",
    check: Callable[[Ctx, str], bool] | None = None,
) -> Case:
    """A prediction file made from the perfect predictions by ``make`` (text or bytes when ``raw``)."""

    def args(ctx: Ctx) -> list[str]:
        path = ctx.case_dir(name) / f"preds{suffix}"
        data = make(ctx)
        if raw:
            path.write_bytes(data) if isinstance(data, bytes) else path.write_text(data)
        else:
            path.write_text(json.dumps(data))
        return score_args(ctx, path, name.replace("_", "-"), *more)

    return Case(name, "predictions", args, says, check)


def coco_case(
    name: str,
    says: tuple[str, ...],
    edit: Callable[[Path, dict[str, Any]], Any],
    check: Callable[[Ctx, str], bool] | None = None,
    command: str = "prepare",
) -> Case:
    """A copy of the known-good coco-rgbt folder changed by ``edit(root, coco)`` (which may rewrite the JSON by
    returning a document, or anything else by returning None), prepared into its own cache."""

    def args(ctx: Ctx) -> list[str]:
        root = ctx.case_dir(name) / "pairs"
        shutil.rmtree(root, ignore_errors=True)
        shutil.copytree(ctx.root, root, symlinks=True)
        coco = json.loads(json.dumps(ctx.coco))
        new = edit(root, coco)
        if new is not None:
            (root / "annotations.json").write_text(new if isinstance(new, str) else json.dumps(new))
        cache = ["--cache", str(ctx.case_dir(name) / "cache")] if command == "prepare" else []
        return [command, "--dataset", "coco-rgbt", "--root", str(root), *cache]

    return Case(name, "datasets", args, says, check)


def config_case(name: str, says: tuple[str, ...], text: str, check: Callable[[Ctx, str], bool] | None = None) -> Case:
    """A YAML file given with ``--config`` to ``harness score`` (the cheapest command that loads a configuration)."""

    def args(ctx: Ctx) -> list[str]:
        path = ctx.case_dir(name) / "extra.yaml"
        path.write_text(text)
        return score_args(ctx, ctx.preds, name.replace("_", "-"), "--config", str(path))

    return Case(name, "configs", args, says, check)


def plugin_case(
    name: str,
    says: tuple[str, ...],
    code: str,
    args: list[str] | Callable[[Ctx], list[str]],
    check: Callable[[Ctx, str], bool] | None = None,
    timeout: int = 300,
) -> Case:
    """A plugin file in a folder named by ``HARNESS_PLUGINS_DIR``, and a command run in its own process."""
    case = Case(name, "plugins", args, says, check, sub=True, timeout=timeout)
    case.env = {"HARNESS_PLUGINS_DIR": f"@{name}", "_CODE": code}
    return case


def weights_case(
    name: str,
    says: tuple[str, ...],
    make: Callable[[Path], Path],
    out: str = "o.safetensors",
    check: Callable[[Ctx, str], bool] | None = None,
) -> Case:
    def args(ctx: Ctx) -> list[str]:
        d = ctx.case_dir(name)
        return ["weights", "import", str(make(d)), "--out", str(d / out)]

    return Case(name, "weights", args, says, check)


def _torch_save(obj: Callable[[], Any], fname: str) -> Callable[[Path], Path]:
    def make(d: Path) -> Path:
        import torch

        torch.save(obj(), d / fname)
        return d / fname

    return make


def _bytes(data: bytes, fname: str) -> Callable[[Path], Path]:
    def make(d: Path) -> Path:
        (d / fname).write_bytes(data)
        return d / fname

    return make


def flight_case(
    name: str,
    says: tuple[str, ...],
    files: dict[str, Path | None],
    command: str = "decode",
    check: Callable[[Ctx, str], bool] | None = None,
) -> Case:
    """A flight folder of real DJI files under the names given (None: an empty file of that name); ``decode`` runs
    ``harness sensing decode`` on it, ``screen`` screens it with an untrained ``ours`` checkpoint."""

    def args(ctx: Ctx) -> list[str]:
        d = ctx.case_dir(name)
        flight = d / "flight"
        flight.mkdir(exist_ok=True)
        for fname, src in files.items():
            (flight / fname).write_bytes(src.read_bytes() if src is not None else b"")
        if command == "decode":
            return ["sensing", "decode", str(flight), "--out", str(d / "out")]
        return [
            "screen",
            str(flight),
            "--weights",
            str(ours_weights(ctx)),
            "--detector",
            "ours",
            "--dataset",
            "m3t",
            "--out",
            str(d / "out"),
            "--no-progress",
        ]

    return Case(name, "screening", args, says, check)


def ours_weights(ctx: Ctx) -> Path:
    path = ctx.tmp / "ours_m3t.pt"
    if not path.exists():
        import torch

        from harness.plugins import get_host

        model = get_host().detector("ours").build(8, in_channels=4)
        torch.save(model.state_dict(), path)
    return path


# ---------------------------------------------------------------------------------------------------- the cases
def _s(ctx: Ctx, *more: str) -> list[str]:
    return score_args(ctx, ctx.preds, "opt", *more)


def _drop(key: str) -> Callable[[Ctx], Any]:
    return lambda ctx: [{k: v for k, v in p.items() if k != key} for p in perfect(ctx)]


def _each(fn: Callable[[dict[str, Any]], Any]) -> Callable[[Ctx], Any]:
    def make(ctx: Ctx) -> Any:
        ps = perfect(ctx)
        for p in ps:
            fn(p)
        return ps

    return make


def _png(path: Path, array: Any) -> None:
    import cv2

    cv2.imwrite(str(path), array)


def _thermal_to(fn: Callable[[Any], Any]) -> Callable[[Path, dict[str, Any]], None]:
    def edit(root: Path, coco: dict[str, Any]) -> None:
        import cv2

        for p in sorted((root / "thermal").glob("*.png")):
            _png(p, fn(cv2.imread(str(p), cv2.IMREAD_UNCHANGED)))

    return edit


def _images(fn: Callable[[dict[str, Any]], Any]) -> Callable[[Path, dict[str, Any]], dict[str, Any]]:
    def edit(root: Path, coco: dict[str, Any]) -> dict[str, Any]:
        for im in coco["images"]:
            fn(im)
        return coco

    return edit


def _anns(fn: Callable[[dict[str, Any]], Any]) -> Callable[[Path, dict[str, Any]], dict[str, Any]]:
    def edit(root: Path, coco: dict[str, Any]) -> dict[str, Any]:
        for a in coco["annotations"]:
            fn(a)
        return coco

    return edit


def _yolo_layout(root: Path, coco: dict[str, Any]) -> None:
    (root / "annotations.json").unlink()
    (root / "labels").mkdir()
    for im in coco["images"]:
        stem = Path(im["file_name"]).stem
        (root / "labels" / f"{stem}.txt").write_text("0 0.5 0.5 0.1 0.2\n")


def _voc_layout(root: Path, coco: dict[str, Any]) -> None:
    (root / "annotations.json").unlink()
    (root / "Annotations").mkdir()
    for im in coco["images"]:
        stem = Path(im["file_name"]).stem
        (root / "Annotations" / f"{stem}.xml").write_text(
            "<annotation><object><name>window</name></object></annotation>"
        )


def _rename_ext(upper_json: bool) -> Callable[[Path, dict[str, Any]], dict[str, Any]]:
    def edit(root: Path, coco: dict[str, Any]) -> dict[str, Any]:
        for p in sorted(root.glob("*/*.png")):
            p.rename(p.with_suffix(".PNG"))
        if upper_json:
            for im in coco["images"]:
                im["file_name"] = im["file_name"].replace(".png", ".PNG")
                im["thermal_file_name"] = im["thermal_file_name"].replace(".png", ".PNG")
        return coco

    return edit


def _symlinked(root: Path, coco: dict[str, Any]) -> None:
    real = root.parent / "thermal-real"
    shutil.move(str(root / "thermal"), real)
    (root / "thermal").symlink_to(real)


def _broken_link(root: Path, coco: dict[str, Any]) -> None:
    (root / "thermal" / "001.png").unlink()
    (root / "thermal" / "001.png").symlink_to(root / "nowhere.png")


def _swap(root: Path, coco: dict[str, Any]) -> dict[str, Any]:
    for im in coco["images"]:
        im["file_name"], im["thermal_file_name"] = im["thermal_file_name"], im["file_name"]
    return coco


def _rgb_double(root: Path, coco: dict[str, Any]) -> None:
    import cv2

    for p in sorted((root / "rgb").glob("*.png")):
        img = cv2.imread(str(p))
        _png(p, cv2.resize(img, (img.shape[1] * 2, img.shape[0] * 2)))


def _mismatched_pairs(root: Path, coco: dict[str, Any]) -> dict[str, Any]:
    names = [im["thermal_file_name"] for im in coco["images"]]
    for im, name in zip(coco["images"], names[1:] + names[:1]):
        im["thermal_file_name"] = name
    return coco


def _delete_thermal(root: Path, coco: dict[str, Any]) -> None:
    for k in range(3):
        (root / "thermal" / f"{k:03d}.png").unlink()


def _one_group(im: dict[str, Any]) -> None:
    im["group"] = "site-a"


def _zero_based(root: Path, coco: dict[str, Any]) -> dict[str, Any]:
    for c in coco["categories"]:
        c["id"] -= 1
    for a in coco["annotations"]:
        a["category_id"] -= 1
    return coco


def _bbox_to_segmentation(a: dict[str, Any]) -> None:
    x, y, w, h = a.pop("bbox")
    a["segmentation"] = [[x, y, x + w, y, x + w, y + h, x, y + h]]


def _mmdet(ctx: Ctx) -> Any:
    out = []
    for im in ctx.coco["images"]:
        per_class: list[list[list[float]]] = [[], []]
        for a in ctx.coco["annotations"]:
            if a["image_id"] == im["id"]:
                x, y, w, h = a["bbox"]
                per_class[a["category_id"] - 1].append([x, y, x + w, y + h, 0.9])
        out.append(per_class)
    return out


def _names(ctx: Ctx, p: dict[str, Any]) -> dict[str, Any]:
    return {**p, "category_id": {1: "hot_spot", 2: "window"}[p["category_id"]]}


def _file_names(ctx: Ctx) -> Any:
    names = {im["id"]: im["file_name"] for im in ctx.coco["images"]}
    return [{**p, "image_id": names[p["image_id"]]} for p in perfect(ctx)]


def _other_fold(ctx: Ctx) -> Any:
    fold = {im["id"] for im in ctx.coco["images"] if im["group"] == FOLD}
    return [p for p in perfect(ctx) if p["image_id"] not in fold]


def _state(width: int = 4) -> Callable[[], Any]:
    def make() -> Any:
        import torch

        return {"model.0.conv.weight": torch.randn(width, 3, 3, 3), "model.0.bn.weight": torch.ones(width)}

    return make


def _jit(d: Path) -> Path:
    import torch

    torch.jit.save(torch.jit.script(torch.nn.Linear(2, 2)), d / "model.pt")
    return d / "model.pt"


def _zip_of_text(d: Path) -> Path:
    import zipfile

    with zipfile.ZipFile(d / "weights.pt", "w") as z:
        z.writestr("readme.txt", "not weights")
    return d / "weights.pt"


def _onnx(d: Path) -> Path:
    (d / "yolov8s.onnx").write_bytes(b"\x08\x07\x12\x07pytorch" + bytes(200))
    return d / "yolov8s.onnx"


def _numpy_state() -> Any:
    import numpy as np

    return {"model.0.conv.weight": np.zeros((4, 3, 3, 3), np.float32)}


def _optimizer_only() -> Any:

    return {"optimizer": {"state": {}, "param_groups": [{"lr": 0.01}]}, "epoch": 3}


def _empty_store(ctx: Ctx) -> list[str]:
    d = ctx.case_dir("report-empty-store") / "store"
    d.mkdir(exist_ok=True)
    return ["report", "--store", str(d), "--out", str(ctx.case_dir("report-empty-store") / "rep")]


def _store_of_profile(ctx: Ctx) -> list[str]:
    return ["report", "--profile", "demo", "--store", str(ctx.store), "--print", "--resamples", "0"]


DJI = SHARED_DATA / "dji-m3t-rjpeg"
CAMS = SHARED_DATA / "dji-rjpeg-cameras"
TOY = """
from harness import DetectorSpec, DatasetSpec, hookimpl
import torch
from torch import nn

class Toy(nn.Module):
    def __init__(self, nc, mode):
        super().__init__()
        self.conv = nn.Conv2d(4, 4, 3, padding=1)
        self.nc, self.mode = nc, mode
    def forward(self, x, targets=None):
        x = x[0] if isinstance(x, (tuple, list)) else x
        y = self.conv(x)
        if self.training or self.mode == 'always-loss':
            return {'loss': y.mean() * 0 + y.square().mean()}
        n = x.shape[0]
        box = torch.tensor([[8.0, 8.0, 24.0, 24.0]])
        outs = [{'boxes': box, 'scores': torch.tensor([0.9]), 'labels': torch.tensor([0])} for _ in range(n)]
        if self.mode == 'numpy':
            outs = [{k: v.numpy() for k, v in o.items()} for o in outs]
        if self.mode == 'tuple':
            outs = [(o['boxes'], o['scores'], o['labels']) for o in outs]
        return outs

MODE = '{mode}'

def build(num_classes, in_channels=4, **cfg):
    if MODE == 'raises':
        raise RuntimeError('weights file toy.pt not found')
    if MODE == 'none':
        return None
    return Toy(num_classes, MODE)

@hookimpl
def register_detectors(register):
    register(DetectorSpec(name='toy', build=build, input_kind='{kind}', description='toy'))
"""
RUN_TOY = [
    "run",
    "--detector",
    "toy",
    "--dataset",
    "coco-rgbt",
    "--folds",
    FOLD,
    "--set",
    "protocol.epochs=1",
    "--set",
    "protocol.imgsz=64",
    "--no-progress",
    "--seeds",
    "0",
]


def _run_toy(ctx: Ctx) -> list[str]:
    return [*RUN_TOY, "--root", str(ctx.root), "--store", str(ctx.tmp / "toy-store"), "--force"]


def toy(mode: str, kind: str = "single") -> str:
    return TOY.replace("{mode}", mode).replace("{kind}", kind)


def cases() -> list[Case]:
    c = Case
    o = "cli-options"
    r = lambda ctx: str(ctx.root)  # noqa: E731
    out: list[Case] = [
        # CLI options: typos, units, paths that do not exist, files for folders and back
        c("dataset-underscore", o, ["prepare", "--dataset", "coco_rgbt"], ("coco_rgbt",)),
        c("dataset-uppercase", o, ["prepare", "--dataset", "COCO-RGBT"], ("COCO-RGBT",)),
        c(
            "detector-yolov8",
            o,
            lambda x: ["run", "--detector", "yolov8", "--dataset", "coco-rgbt", "--root", r(x)],
            ("yolov8",),
        ),
        c("fold-unknown", o, lambda x: _s(x)[:6] + ["site-d"] + _s(x)[7:], ("site-d",)),
        c("fold-m3t-name", o, lambda x: _s(x)[:6] + ["P1"] + _s(x)[7:], ("P1",)),
        c("fold-two", o, lambda x: _s(x)[:6] + ["site-a,site-b"] + _s(x)[7:], ("site-a,site-b", "one fold")),
        c(
            "root-missing",
            o,
            ["prepare", "--dataset", "coco-rgbt", "--root", "/nonexistent/pairs"],
            ("/nonexistent/pairs",),
        ),
        c(
            "root-is-json",
            o,
            lambda x: ["prepare", "--dataset", "coco-rgbt", "--root", str(x.root / "annotations.json")],
            ("annotations.json",),
        ),
        c("predictions-is-folder", o, lambda x: score_args(x, x.root, "dir"), (str(Path("pairs")),)),
        c(
            "images-is-folder",
            o,
            lambda x: score_args(x, x.preds, "img")[:10] + [str(x.root)] + score_args(x, x.preds, "img")[11:],
            ("--images",),
        ),
        c("predictions-missing", o, lambda x: score_args(x, x.tmp / "nope.json", "m"), ("nope.json",)),
        c(
            "seeds-range",
            o,
            lambda x: [
                *_run_toy(x)[:1],
                "--detector",
                "ours",
                "--dataset",
                "coco-rgbt",
                "--seeds",
                "0-2",
                "--root",
                r(x),
            ],
            ("0-2",),
        ),
        c(
            "seeds-spaces",
            o,
            lambda x: ["run", "--detector", "ours", "--dataset", "coco-rgbt", "--seeds", "0 1", "--root", r(x)],
            ("0 1",),
        ),
        c("set-epochs-word", o, lambda x: _s(x, "--set", "protocol.epochs=ten"), ("protocol.epochs",)),
        c("set-key-typo", o, lambda x: _s(x, "--set", "protocol.epoch=5"), ("protocol.epoch",)),
        c("set-imgsz-negative", o, lambda x: _s(x, "--set", "protocol.imgsz=-160"), ("imgsz",)),
        c("set-batch-zero", o, lambda x: _s(x, "--set", "train.batch=0"), ("train.batch",)),
        c("set-no-equals", o, lambda x: _s(x, "--set", "protocol.epochs"), ("protocol.epochs",)),
        c("set-lr-percent", o, lambda x: _s(x, "--set", "train.lr0=0.2%"), ("lr0",)),
        c("set-colon", o, lambda x: _s(x, "--set", "protocol.epochs:5"), ("protocol.epochs:5",)),
        c("box-format-yolo", o, lambda x: _s(x, "--box-format", "xywhn"), ("xywhn",)),
        c("frame-ir", o, lambda x: _s(x, "--frame", "ir"), ("'ir'",)),
        c("file-types-pdf", o, lambda x: ["report", "--store", str(x.store), "--file-types", "pdf"], ("pdf",)),
        c(
            "resamples-negative",
            o,
            lambda x: ["report", "--store", str(x.store), "--resamples", "-5"],
            ("--resamples",),
        ),
        c("report-workers-zero", o, lambda x: ["report", "--store", str(x.store), "--workers", "0"], ("--workers",)),
        c(
            "screen-conf-percent",
            o,
            lambda x: ["screen", str(x.tmp), "--run", str(x.store), "--out", str(x.tmp / "s"), "--conf", "25"],
            ("--conf",),
        ),
        c("profile-unknown", o, lambda x: _s(x, "--profile", "fast"), ("fast",)),
        c(
            "profile-as-path",
            o,
            lambda x: _s(x, "--profile", "configs/profiles/smoke.yaml"),
            ("configs/profiles/smoke.yaml",),
            mapped(100.0),
        ),
        c("params-with-unit", o, lambda x: _s(x, "--params", "11.13M"), ("--params",)),
        c("gflops-with-unit", o, lambda x: _s(x, "--gflops", "28.6G"), ("--gflops",)),
        c("category-map-unknown-name", o, lambda x: _s(x, "--category-map", "1=hot_spot,2=windows"), ("windows",)),
        c("category-map-missing-file", o, lambda x: _s(x, "--category-map", str(x.tmp / "map.json")), ("map.json",)),
        c("category-map-arrow", o, lambda x: _s(x, "--category-map", "1->hot_spot"), ("1->hot_spot",)),
        c("name-with-slash", o, lambda x: score_args(x, x.preds, "my/model"), ("my/model",), mapped(100.0)),
        c("name-empty", o, lambda x: score_args(x, x.preds, ""), ("--name",)),
        c(
            "report-dataset-unknown",
            o,
            lambda x: ["report", "--store", str(x.store), "--datasets", "m3t", "--print"],
            ("m3t",),
        ),
        c(
            "report-reference-unknown",
            o,
            lambda x: ["report", "--store", str(x.store), "--reference", "yolov8", "--print", "--resamples", "0"],
            ("yolov8",),
        ),
        c(
            "keep-weights-best",
            o,
            ["run", "--detector", "ours", "--dataset", "coco-rgbt", "--keep-weights", "best"],
            ("best",),
        ),
        c(
            "log-to-wandb",
            o,
            lambda x: [
                "run",
                "--detector",
                "ours",
                "--dataset",
                "coco-rgbt",
                "--root",
                r(x),
                "--log-to",
                "wandb",
                "--folds",
                "site-z",
            ],
            ("wandb",),
        ),
        c(
            "encoding-typo",
            o,
            lambda x: ["run", "--detector", "ours", "--dataset", "coco-rgbt", "--root", r(x), "--encoding", "c3"],
            ("c3",),
        ),
        c("cache-form-zip", o, ["prepare", "--dataset", "coco-rgbt", "--cache-form", "zip"], ("zip",)),
        c("synth-size-medium", o, ["synth", "--size", "medium"], ("medium",)),
        c("synth-family-flir", o, ["synth", "--family", "flir"], ("flir",)),
        c("synth-out-is-file", o, lambda x: ["synth", "--size", "tiny", "--out", str(x.preds)], ("preds.json",)),
        c(
            "synth-workers-zero",
            o,
            lambda x: ["synth", "--size", "tiny", "--workers", "0", "--out", str(x.tmp / "syn")],
            ("--workers",),
            lambda x, out: "8 pairs in" in out,
        ),
        c("config-missing", o, lambda x: _s(x, "--config", "mine.yaml"), ("mine.yaml",)),
        c("store-is-file", o, lambda x: ["report", "--store", str(x.preds), "--print"], ("preds.json",)),
        c("verbose-after", o, lambda x: _s(x, "--verbose"), ("--verbose",), mapped(100.0)),
        c(
            "cache-is-file",
            o,
            lambda x: ["prepare", "--dataset", "coco-rgbt", "--root", r(x), "--cache", str(x.preds)],
            ("preds.json",),
        ),
        c("folds-all-score", o, lambda x: _s(x)[:6] + ["all"] + _s(x)[7:], ("all",)),
    ]
    # datasets: other codebases' layouts and the ways a folder goes wrong
    out += [
        coco_case("yolo-txt-layout", ("annotations.json",), _yolo_layout),
        coco_case("voc-xml-layout", ("annotations.json",), _voc_layout),
        coco_case(
            "empty-folder",
            ("annotations.json",),
            lambda root, coco: [p.unlink() for p in root.rglob("*") if p.is_file()] and None,
        ),
        coco_case("json-empty-list", ("annotations.json",), lambda root, coco: "[]"),
        coco_case("json-trailing-comma", ("annotations.json",), lambda root, coco: json.dumps(coco)[:-1] + ",}"),
        coco_case("zero-based-categories", ("category",), _zero_based, check=prepared(12)),
        coco_case("category-id-unknown", ("category_id", "categor"), _anns(lambda a: a.update(category_id=3))),
        coco_case(
            "rgb-thermal-swapped", ("thermal_file_name", "8-bit", "uint8", "thermal/000.png", "rgb/000.png"), _swap
        ),
        coco_case("pairs-shifted-by-one", ("mismatch", "do not match", "misaligned"), _mismatched_pairs),
        coco_case("thermal-files-deleted", ("thermal/000.png", "missing: 3", "not found: 3"), _delete_thermal),
        coco_case("uppercase-on-disk", ("000.png", "000.PNG"), _rename_ext(False)),
        coco_case("uppercase-everywhere", ("PNG",), _rename_ext(True), check=prepared(12)),
        coco_case("thermal-folder-symlink", ("thermal",), _symlinked, check=prepared(12)),
        coco_case("broken-symlink", ("001.png",), _broken_link),
        coco_case(
            "absolute-paths",
            ("file_name", "is absolute"),
            lambda root, coco: _images(
                lambda im: im.update(
                    file_name=str(root / im["file_name"]), thermal_file_name=str(root / im["thermal_file_name"])
                )
            )(root, coco),
            check=prepared(12),
        ),
        coco_case(
            "windows-backslashes",
            ("\\",),
            _images(lambda im: im.update(file_name=im["file_name"].replace("/", "\\"))),
            check=prepared(12),
        ),
        coco_case(
            "image-ids-as-strings",
            ("image_id", "id"),
            lambda root, coco: {**coco, "images": [{**im, "id": str(im["id"])} for im in coco["images"]]},
            check=prepared(12),
        ),
        coco_case("duplicate-image-ids", ("duplicate", "id 1"), _images(lambda im: im.update(id=1))),
        coco_case(
            "bbox-negative-width",
            ("bbox", "box malformed"),
            _anns(lambda a: a.update(bbox=[a["bbox"][0], a["bbox"][1], -10, 10])),
        ),
        coco_case("bbox-three-numbers", ("bbox", "box malformed"), _anns(lambda a: a.update(bbox=a["bbox"][:3]))),
        coco_case("one-group-only", ("group",), _images(_one_group), command="folds"),
        coco_case("segmentation-only", ("bbox", "box malformed"), _anns(_bbox_to_segmentation)),
        coco_case(
            "no-categories", ("categories",), lambda root, coco: {k: v for k, v in coco.items() if k != "categories"}
        ),
        coco_case(
            "duplicate-category-names",
            ("window",),
            lambda root, coco: {**coco, "categories": [{"id": 1, "name": "window"}, {"id": 2, "name": "window"}]},
        ),
        coco_case(
            "thermal-8bit-grey",
            ("8-bit", "uint8", "thermal/000.png"),
            _thermal_to(lambda t: (t // 256).astype("uint8")),
        ),
        coco_case(
            "thermal-decikelvin",
            ("thermal", "kelvin", "implausible"),
            _thermal_to(lambda t: (t // 10).astype("uint16")),
        ),
        coco_case(
            "rgb-grayscale",
            ("rgb/000.png", "channel"),
            lambda root, coco: (
                [_png(p, __import__("cv2").imread(str(p), 0)) for p in sorted((root / "rgb").glob("*.png"))] and None
            ),
            check=prepared(12),
        ),
        coco_case("rgb-twice-thermal-size", ("size",), _rgb_double),
        coco_case("iscrowd-everywhere", ("iscrowd", "crowd"), _anns(lambda a: a.update(iscrowd=1))),
        coco_case("root-one-level-up", ("annotations.json",), lambda root, coco: None, check=prepared(12)),
        coco_case(
            "annotations-yaml-named",
            ("annotations.json",),
            lambda root, coco: (root / "annotations.json").rename(root / "instances_val.json") and None,
        ),
        coco_case(
            "image-without-annotations",
            ("annotation",),
            lambda root, coco: {**coco, "annotations": [a for a in coco["annotations"] if a["image_id"] > 6]},
            check=prepared(12),
        ),
        coco_case("area-zero", ("area",), _anns(lambda a: a.update(area=0)), check=prepared(12)),
    ]
    (up,) = [k for k in out if k.id == "root-one-level-up"]
    up.args = _up_one_level(up.args)  # type: ignore[arg-type]
    # predictions: other codebases' shapes
    out += [
        pred_case("yolo-txt-as-predictions", ("JSON",), lambda x: "0 0.5 0.5 0.1 0.1 0.9\n", raw=True, suffix=".txt"),
        pred_case("mmdet-per-class-arrays", ("malformed", "expected a COCO results list"), _mmdet),
        pred_case(
            "wrapped-in-annotations", ("annotations",), lambda x: {"annotations": perfect(x)}, check=mapped(100.0)
        ),
        pred_case(
            "json-lines",
            ("JSON",),
            lambda x: "\n".join(json.dumps(p) for p in perfect(x)),
            raw=True,
            suffix=".jsonl",
        ),
        pred_case(
            "scores-as-strings", ("score",), _each(lambda p: p.update(score=str(p["score"]))), check=mapped(100.0)
        ),
        pred_case("bbox-as-dict", ("bbox",), _each(lambda p: p.update(bbox=dict(zip("xywh", p["bbox"]))))),
        pred_case("ground-truth-as-predictions", ("score", "annotations"), lambda x: x.coco),
        pred_case("score-nan", ("score", "nan"), _each(lambda p: p.update(score=float("nan")))),
        pred_case("empty-list", ("no predictions", "empty", "0 predictions"), lambda x: []),
        pred_case(
            "category-names", ("category_id",), lambda x: [_names(x, p) for p in perfect(x)], check=mapped(100.0)
        ),
        pred_case(
            "label-key",
            ("category_id",),
            lambda x: [
                {**{k: v for k, v in p.items() if k != "category_id"}, "label": p["category_id"]} for p in perfect(x)
            ],
        ),
        pred_case("image-id-file-names", ("image_id",), _file_names, check=mapped(100.0)),
        pred_case("csv-file", ("JSON",), lambda x: "image_id,x,y,w,h,score\n1,1,1,2,2,0.9\n", raw=True, suffix=".csv"),
        pred_case(
            "bbox-ints", ("bbox",), _each(lambda p: p.update(bbox=[int(v) for v in p["bbox"]])), check=mapped(100.0)
        ),
        pred_case(
            "extra-fields",
            ("segmentation",),
            _each(lambda p: p.update(segmentation=[], area=1.0, id=7)),
            check=mapped(100.0),
        ),
        pred_case("other-fold-only", ("fold", "site-a"), _other_fold),
        pred_case(
            "utf8-bom",
            ("BOM",),
            lambda x: "\ufeff" + json.dumps(perfect(x)),
            raw=True,
            check=mapped(100.0),
        ),
        pred_case(
            "gzipped",
            ("gzip",),
            lambda x: __import__("gzip").compress(json.dumps(perfect(x)).encode()),
            raw=True,
            suffix=".json.gz",
            check=mapped(100.0),
        ),
        pred_case("missing-score", ("score",), _drop("score")),
        pred_case("missing-bbox", ("bbox",), _drop("bbox")),
        pred_case(
            "score-above-one-few",
            ("score",),
            lambda x: [{**p, "score": 1.5 if i == 0 else 0.9} for i, p in enumerate(perfect(x))],
        ),
        pred_case(
            "zero-based-with-map",
            ("category",),
            _each(lambda p: p.update(category_id=p["category_id"] - 1)),
            "--category-map",
            "0=hot_spot,1=window",
            check=mapped(100.0),
        ),
        pred_case(
            "boxes-negative-size",
            ("bbox", "negative"),
            _each(lambda p: p.update(bbox=[p["bbox"][0] + p["bbox"][2], p["bbox"][1], -p["bbox"][2], p["bbox"][3]])),
        ),
        pred_case(
            "dict-by-image", ("expected a COCO results list",), lambda x: {str(p["image_id"]): p for p in perfect(x)}
        ),
        pred_case("detectron-pth", ("JSON",), lambda x: b"PK\x03\x04" + bytes(64), raw=True, suffix=".pth"),
    ]
    # configs
    out += [
        config_case("yaml-tab", ("extra.yaml",), "protocol:\n\tepochs: 5\n"),
        config_case("yaml-top-list", ("extra.yaml",), "- protocol.epochs: 5\n"),
        config_case("epochs-list", ("protocol.epochs",), "protocol:\n  epochs: [5]\n"),
        config_case("lr-unquoted-exponent", ("lr0",), "train:\n  lr0: 2e-3\n", check=mapped(100.0)),
        config_case("top-key-typo", ("protocl",), "protocl:\n  epochs: 5\n"),
        config_case("config-empty-file", ("extra.yaml",), "", check=mapped(100.0)),
        config_case("duplicate-keys", ("epochs", "duplicate"), "protocol:\n  epochs: 5\n  epochs: 6\n"),
        config_case("dotted-keys", ("protocol.epochs",), "protocol.epochs: 5\n"),
        config_case("yes-as-bool", ("crop",), "sensing:\n  warp:\n    crop: yes\n", check=mapped(100.0)),
        config_case("json-config", ("extra.yaml",), '{"protocol": {"epochs": 5}}', check=mapped(100.0)),
        config_case("string-for-mapping", ("protocol",), "protocol: smoke\n"),
    ]
    out.append(Case("env-var-unset", "configs", _env_config, ("HARNESS_TRIAL_UNSET",)))
    # plugins (each in its own process)
    score = lambda x: ["list"]  # noqa: E731
    out += [
        plugin_case("syntax-error", ("trial_plugin",), "def broken(:\n", ["list"]),
        plugin_case("build-raises", ("toy", "toy.pt"), toy("raises"), _run_toy),
        plugin_case("build-returns-none", ("toy", "None"), toy("none"), _run_toy),
        plugin_case("returns-numpy", ("toy", "numpy", "ndarray"), toy("numpy"), _run_toy),
        plugin_case("returns-tuples", ("toy", "tuple"), toy("tuple"), _run_toy),
        plugin_case("loss-in-eval-mode", ("toy", "loss"), toy("always-loss"), _run_toy),
        plugin_case("input-kind-typo", ("input_kind", "dual-stream"), toy("ok", "dual-stream"), score),
        plugin_case(
            "missing-import", ("trial_plugin", "torchvision_nonexistent"), "import torchvision_nonexistent\n", ["list"]
        ),
        plugin_case(
            "dataset-name-clash",
            ("m3t", "trial_plugin"),
            "from harness import DatasetSpec, hookimpl\n"
            "@hookimpl\ndef register_datasets(register):\n"
            "    register(DatasetSpec(name='m3t', open=print, categories=('a',)))\n",
            ["list"],
        ),
        plugin_case(
            "register-called-with-dict",
            ("trial_plugin", "DetectorSpec"),
            "from harness import hookimpl\n@hookimpl\ndef register_detectors(register):\n    register({'name': 'd'})\n",
            ["list"],
        ),
        Case(
            "entry-point-missing-module",
            "plugins",
            ["list"],
            ("harness_trial_missing", "trial-dist"),
            sub=True,
            env={"HARNESS_LOAD_PLUGINS": "trial-dist", "_DIST": "1"},
        ),
    ]
    # screening: flights without pairs, other DJI cameras
    out += [
        flight_case(
            "decode-h20t",
            ("h20t", "H20T", "dirp"),
            {"DJI_0001_T.JPG": CAMS / "h20t_dirp.jpg"},
            check=decoded_like("decode-h20t", "DJI_0001_T", CAMS / "h20t_dirp_reference.npz"),
        ),
        flight_case("decode-m4t", ("m4t", "M4T", "iirp"), {"DJI_0001_T.JPG": CAMS / "m4t_iirp.jpg"}),
        flight_case(
            "decode-m2ea",
            ("m2ea", "iirp", "Mavic"),
            {"DJI_0001_R.JPG": CAMS / "m2ea_iirp.jpg"},
            check=decoded_like("decode-m2ea", "DJI_0001_R", CAMS / "m2ea_iirp_reference.npz"),
        ),
        flight_case("decode-m3td-hirp", ("hirp",), {"DJI_0001_T.JPG": CAMS / "m3td_hirp_a.jpg"}),
        flight_case("decode-empty-file", ("DJI_0002_T.JPG",), {"DJI_0002_T.JPG": None}),
        flight_case("decode-empty-folder", ("flight", "no"), {}),
        flight_case(
            "screen-thermal-only",
            ("_W", "wide"),
            {"DJI_0001_T.JPG": DJI / "m3t_a.jpg", "DJI_0002_T.JPG": DJI / "m3t_b.jpg"},
            command="screen",
        ),
        flight_case("screen-no-suffixes", ("_T", "_W"), {"img1.jpg": DJI / "m3t_a.jpg"}, command="screen"),
        flight_case(
            "screen-h20t-pair",
            ("h20t", "registration check failed"),
            {"DJI_0001_T.JPG": CAMS / "h20t_dirp.jpg", "DJI_0001_W.JPG": DJI / "m3t_a.jpg"},
            command="screen",
        ),
        flight_case("screen-lowercase-suffix", ("_t", "_T"), {"dji_0001_t.jpg": DJI / "m3t_a.jpg"}, command="screen"),
    ]
    # reports
    out += [
        c("report-empty-store", "reports", _empty_store, ("store",)),
        c("report-store-of-other-profile", "reports", _store_of_profile, ("demo",), lambda x, s: "external/good" in s),
        c(
            "report-store-is-cache",
            "reports",
            lambda x: ["report", "--store", str(x.tmp / "cache"), "--print"],
            ("cache",),
        ),
        c(
            "report-store-run-folder",
            "reports",
            lambda x: ["report", "--store", str(x.store / "coco-rgbt"), "--print"],
            ("coco-rgbt",),
        ),
        c(
            "report-store-missing",
            "reports",
            lambda x: ["report", "--store", str(x.tmp / "resluts"), "--print"],
            ("resluts",),
        ),
        c(
            "report-dataset-underscore",
            "reports",
            lambda x: ["report", "--store", str(x.store), "--datasets", "coco_rgbt", "--print"],
            ("coco_rgbt",),
        ),
        c(
            "report-categories-typo",
            "reports",
            lambda x: [
                "report",
                "--store",
                str(x.store),
                "--print",
                "--ablation-categories",
                "windows",
                "--resamples",
                "0",
            ],
            ("windows",),
        ),
    ]
    # weights import
    out += [
        weights_case("onnx-file", ("onnx",), _onnx),
        weights_case("torchscript", ("torchscript", "TorchScript"), _jit),
        weights_case("zip-without-pickle", ("weights.pt",), _zip_of_text),
        weights_case("weights-empty-file", ("empty", "0 bytes"), _bytes(b"", "empty.pt")),
        weights_case("numpy-arrays", ("numpy", "ndarray", "tensor"), _torch_save(_numpy_state, "weights.pt")),
        weights_case("optimizer-only", ("tensor", "optimizer"), _torch_save(_optimizer_only, "opt.pt")),
        weights_case("out-is-pt", ("--out", ".pt", "safetensors"), _torch_save(_state(), "s.pt"), out="o.pt"),
        weights_case(
            "out-folder-missing",
            ("missing-dir",),
            _torch_save(_state(), "s.pt"),
            out="missing-dir/o.safetensors",
            check=lambda x, s: True,
        ),
        weights_case("yaml-given", ("yolov8s.yaml", "yaml"), _bytes(b"nc: 80\nbackbone: []\n", "yolov8s.yaml")),
        weights_case("directory-given", ("wdir",), lambda d: (d / "wdir").mkdir(exist_ok=True) or d / "wdir"),
        weights_case("src-missing", ("nothere.pt",), lambda d: d / "nothere.pt"),
    ]
    return out


def _env_config(ctx: Ctx) -> list[str]:
    """``prepare`` with the root only in a config file, through an environment variable the shell does not have."""
    d = ctx.case_dir("env-var-unset")
    (d / "extra.yaml").write_text("dataset:\n  root: ${HARNESS_TRIAL_UNSET}/pairs\n")
    return ["prepare", "--dataset", "coco-rgbt", "--config", str(d / "extra.yaml"), "--cache", str(d / "cache")]


def decoded_like(case: str, stem: str, reference: Path) -> Callable[[Ctx, str], bool]:
    """The decoded centi-Kelvin PNG is the reference's corrected temperature within 0.1 C on average."""

    def check(ctx: Ctx, out: str) -> bool:
        import cv2
        import numpy as np

        path = ctx.case_dir(case) / "out" / f"{stem}.png"
        if not path.is_file():
            return False
        t = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64) / 100 - 273.15
        ref = np.load(reference)["temp_c"].astype(np.float64)
        return t.shape == ref.shape and float(np.abs(t - ref).mean()) < 0.1

    return check


def _up_one_level(args: Callable[[Ctx], list[str]]) -> Callable[[Ctx], list[str]]:
    def up(ctx: Ctx) -> list[str]:
        a = args(ctx)
        a[a.index("--root") + 1] = str(Path(a[a.index("--root") + 1]).parent)
        return a

    return up


def _sub_env(case: Case, ctx: Ctx) -> dict[str, str]:
    env = {k: v for k, v in case.env.items() if not k.startswith("_")}
    d = ctx.case_dir(case.id)
    if "_CODE" in case.env:
        (d / "plugins").mkdir(exist_ok=True)
        (d / "plugins" / "trial_plugin.py").write_text(case.env["_CODE"])
        env["HARNESS_PLUGINS_DIR"] = str(d / "plugins")
    if "_DIST" in case.env:  # an installed distribution whose entry point names a module that is not there
        info = d / "site" / "trial_dist-1.0.dist-info"
        info.mkdir(parents=True, exist_ok=True)
        (info / "METADATA").write_text("Metadata-Version: 2.1\nName: trial-dist\nVersion: 1.0\n")
        (info / "entry_points.txt").write_text("[harness]\ntrial = harness_trial_missing.plugin\n")
        env["PYTHONPATH"] = os.pathsep.join([str(d / "site"), *sys.path])
    return env


def run_case(case: Case, ctx: Ctx) -> dict[str, Any]:
    t0 = time.perf_counter()
    try:
        args = case.args(ctx) if callable(case.args) else list(case.args)
        if case.sub:
            code, out = invoke_sub(args, _sub_env(case, ctx), case.timeout)
        else:
            code, out = invoke(args, case.timeout)
        cls = classify(case, code, out)
    except Runaway:
        code, out, cls = -1, f"over {case.timeout} s", "runaway"
    return {
        "id": case.id,
        "family": case.family,
        "class": cls,
        "exit": code,
        "message": first_line(out)[:200],
        "seconds": round(time.perf_counter() - t0, 2),
        "output": out[-3000:],
    }


def main() -> int:
    global CTX
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, help="write every outcome (with its output's tail) as JSON here")
    ap.add_argument("--only", help="run only the cases whose id contains one of these (comma-separated)")
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder (its path goes to stderr)")
    a = ap.parse_args()
    import logging

    import torch

    torch.set_num_threads(1)
    logging.basicConfig(level=logging.WARNING)
    tmp = Path(tempfile.mkdtemp(prefix="mistake-trial-"))
    t0 = time.perf_counter()
    try:
        CTX = build_world(tmp)
        only = [w for w in (a.only or "").split(",") if w]
        todo = [c for c in cases() if not only or any(w in c.id for w in only)]
        ids = [c.id for c in todo]
        dupes = {i for i in ids if ids.count(i) > 1}
        if dupes:
            raise SystemExit(f"duplicate case ids: {sorted(dupes)}")
        rows = []
        for case in todo:
            row = run_case(case, CTX)
            rows.append(row)
            print(f"{row['id'][:30]:30} {row['family'][:11]:11} {row['class']:13} {row['message'][:42]}", flush=True)
    finally:
        if a.keep:
            print(f"kept {tmp}", file=sys.stderr)
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    total = time.perf_counter() - t0
    counts = {k: sum(r["class"] == k for r in rows) for k in CLASSES}
    print(f"\n{len(rows)} cases in {total:.0f} s wall")
    for k, n in counts.items():
        print(f"  {k:14} {n:4}")
    if a.json:
        a.json.write_text(json.dumps({"cases": rows, "counts": counts, "seconds": round(total, 1)}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
