"""Tiny prepared datasets and plugins for the engine and run tests (made by the tests themselves).

Shapes on a noisy background, in the thermal frame. Category ``window`` is a dark rectangle visible in RGB and
slightly cool in thermal; categories ``warm`` and ``cold`` are the *same* grey square in RGB and differ only in
temperature (+4 C / -4 C), so only a detector that reads the fourth channel can tell them apart.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import pytest

from harness import AlignedSample, DatasetSpec, DetectorSpec, EncodingSpec, Fold, hookimpl
from harness.cache import PreparedDataset, PreparedWriter

REPO = Path(__file__).resolve().parent.parent
PLUGIN_SRC = REPO / "plugins" / "harness-tinydet" / "src"
CATEGORIES = ("window", "warm", "cold")


def tinydet_module():
    """The example plugin's model module, imported from the source tree (no installation needed)."""
    if str(PLUGIN_SRC) not in sys.path:
        sys.path.insert(0, str(PLUGIN_SRC))
    import harness_tinydet.model as m

    return m


def fast_overrides(epochs: int = 1, close_mosaic: int = 0, warmup_epochs: float = 0.5) -> list[str]:
    """``--set`` overrides for a tiny CPU run of TinyDet on the shapes dataset (64 px, batch 8, one thread)."""
    return [
        "protocol.imgsz=64",
        f"protocol.epochs={epochs}",
        "protocol.patience=10",
        "train.batch=8",
        "train.nominal_batch=8",
        f"train.warmup_epochs={warmup_epochs}",
        "train.warmup_min_iters=0",
        f"train.close_mosaic={close_mosaic}",
        "train.threads=1",
        "train.device=cpu",
        "eval.batch=16",
    ]


def set_args(overrides: Sequence[str]) -> list[str]:
    """``--set`` options for the ``key=value`` overrides, in order."""
    return [a for s in overrides for a in ("--set", s)]


def run_args(detector: str, dataset: str, folds: str, store: Path, *extra: str) -> list[str]:
    """The arguments of ``harness run`` for one detector on some folds of a dataset into ``store``, with no progress
    bars; ``extra`` (more options, ``--set`` pairs) comes last."""
    return [
        "run",
        "--detector",
        detector,
        "--dataset",
        dataset,
        "--folds",
        folds,
        "--store",
        str(store),
        "--no-progress",
        *extra,
    ]


class DetectorsPlugin:
    """A plugin that registers the given detectors (for ``temporary_plugin``)."""

    def __init__(self, *specs: DetectorSpec):
        self.specs = specs

    @hookimpl
    def register_detectors(self, register: Any) -> None:
        for spec in self.specs:
            register(spec)


def single_stream(name: str, description: str, model: Any) -> DetectorSpec:
    """A single-stream detector whose build is ``model(num_classes, in_channels)`` (a test's own TinyDet variant)."""
    return DetectorSpec(
        name=name,
        input_kind="single",
        description=description,
        build=lambda num_classes, in_channels=4, **cfg: model(num_classes, in_channels),
    )


def shapes_run_args(store: Path, *extra: str) -> list[str]:
    """The arguments of ``harness run`` for TinyDet on fold A of the shapes dataset (see ``run_args``)."""
    return run_args("tinydet", "shapes", "A", store, *extra)


def one_conv_trainer(folder: Path, **kw: Any) -> Any:
    """A trainer of one 1x1 convolution on two shapes images (one epoch, batch 2) with its checkpoints in
    ``folder / "ckpt"``: for the tests of what resuming makes of a given ``last.pt``; ``kw`` goes to ``Trainer``."""
    import torch

    from harness.engine.data import AugmentSettings, SampleSource, TrainDataset
    from harness.engine.trainer import Trainer, TrainSettings

    prepared = write_dataset(folder / "ds", groups=("A",), per_group=2)
    settings = TrainSettings(imgsz=64, epochs=1, batch=2, nominal_batch=2, threads=1, device="cpu")
    data = TrainDataset(SampleSource(prepared, None, ENCODINGS[0]), 64, AugmentSettings.off())
    return Trainer(torch.nn.Conv2d(4, 1, 1), data, settings, checkpoint_dir=folder / "ckpt", progress=False, **kw)


def train_settings(**kw: Any) -> Any:
    """Trainer settings for a tiny CPU run: 64 px, no warm-up, no mosaic to close, one thread; ``kw`` sets the rest
    (epochs, batch ...) or overrides these."""
    from harness.engine.trainer import TrainSettings

    base: dict[str, Any] = dict(
        imgsz=64, warmup_epochs=0.0, warmup_min_iters=0, close_mosaic=0, threads=1, device="cpu"
    )
    return TrainSettings(**{**base, **kw})


@pytest.fixture
def shapes_run_plugins(host: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """The shapes dataset, the test encodings and the example TinyDet plugin registered for one test, with a cache
    of its own (a fixture of every test module, through ``conftest.py``)."""
    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    with shapes_and_tinydet("run"):
        yield host


@contextlib.contextmanager
def shapes_and_tinydet(tag: str) -> Iterator[None]:
    """The shapes dataset with the test encodings and the example TinyDet plugin, registered for a ``with`` block
    (as ``shapes-<tag>`` and ``tinydet-<tag>``)."""
    from harness.testing import temporary_plugin

    tinydet_module()
    import harness_tinydet.plugin as tinydet_plugin

    with (
        temporary_plugin(ShapesPlugin(), name=f"shapes-{tag}"),
        temporary_plugin(tinydet_plugin, name=f"tinydet-{tag}"),
    ):
        yield


def make_sample(
    image_id: int,
    group: str,
    rng: np.random.Generator,
    size: tuple[int, int] = (64, 80),
    n_objects: tuple[int, int] = (1, 3),
) -> AlignedSample:
    h, w = size
    rgb = np.clip(rng.normal(150, 12, (h, w, 3)), 0, 255).astype(np.uint8)
    temp = (20.0 + rng.normal(0, 0.3, (h, w))).astype(np.float32)
    boxes, labels = [], []
    occupied = np.zeros((h, w), bool)
    for _ in range(int(rng.integers(n_objects[0], n_objects[1] + 1))):
        for _attempt in range(20):
            bw, bh = int(rng.integers(10, 22)), int(rng.integers(10, 22))
            x1, y1 = int(rng.integers(0, w - bw)), int(rng.integers(0, h - bh))
            if not occupied[max(0, y1 - 2) : y1 + bh + 2, max(0, x1 - 2) : x1 + bw + 2].any():
                break
        else:
            continue
        occupied[y1 : y1 + bh, x1 : x1 + bw] = True
        label = int(rng.integers(0, len(CATEGORIES)))
        if label == 0:  # window: dark blue in RGB, a little cooler
            rgb[y1 : y1 + bh, x1 : x1 + bw] = (30, 40, 90)
            temp[y1 : y1 + bh, x1 : x1 + bw] -= 1.0
        else:  # warm / cold: identical grey squares in RGB, opposite temperature
            rgb[y1 : y1 + bh, x1 : x1 + bw] = (225, 225, 225)
            temp[y1 : y1 + bh, x1 : x1 + bw] += 4.0 if label == 1 else -4.0
        boxes.append([x1, y1, x1 + bw, y1 + bh])
        labels.append(label)
    ir8 = np.clip((temp - 14.0) / 12.0 * 255, 0, 255).astype(np.uint8)
    return AlignedSample(
        image_id=image_id,
        rgb=rgb,
        thermal=temp,
        ir8=ir8,
        boxes=np.asarray(boxes, np.float32).reshape(-1, 4),
        labels=np.asarray(labels, np.int64),
        group=group,
        meta={"file_name": f"{group}_{image_id:04d}.jpg"},
    )


def write_dataset(
    folder: Path,
    groups: tuple[str, ...] = ("A", "B"),
    per_group: int = 8,
    seed: int = 0,
    size: tuple[int, int] = (64, 80),
    name: str = "shapes",
) -> PreparedDataset:
    rng = np.random.default_rng(seed)
    with PreparedWriter(folder, name, CATEGORIES, fingerprint=f"shapes-{seed}-{per_group}") as w:
        k = 1
        for g in groups:
            for _ in range(per_group):
                w.add(make_sample(k, g, rng, size))
                k += 1
    return PreparedDataset(folder)


def ir8_channel(sample: AlignedSample, **_: Any) -> np.ndarray:
    return np.ascontiguousarray(sample.ir8)


ENCODINGS = (
    EncodingSpec(name="test-ir8", fn=ir8_channel, channels=1, needs="ir8", description="the 8-bit thermal (tests)"),
    EncodingSpec(name="test-none", fn=lambda s, **_: None, channels=0, needs=None, description="RGB only (tests)"),
)


class ShapesSource:
    """A DatasetSource generating the shapes dataset (for runs through the whole pipeline)."""

    name = "shapes"
    categories = CATEGORIES

    def __init__(
        self, groups: tuple[str, ...] = ("A", "B"), per_group: int = 8, seed: int = 0, size: tuple[int, int] = (64, 80)
    ):
        self._groups, self.per_group, self.seed, self.size = groups, per_group, seed, size

    def groups(self) -> list[str]:
        return list(self._groups)

    def folds(self) -> list[Fold]:
        return [Fold(g, tuple(o for o in self._groups if o != g), (g,)) for g in self._groups]

    def fingerprint(self) -> str:
        return f"shapes-{self._groups}-{self.per_group}-{self.seed}-{self.size}"

    def samples(self, report: Any):
        rng = np.random.default_rng(self.seed)
        k = 1
        for g in self._groups:
            for _ in range(self.per_group):
                yield make_sample(k, g, rng, self.size)
                k += 1


class ContractSource:
    """The smallest dataset source: groups ``a`` (two samples) and ``b`` (one), 8 x 8 at 20 C, one box each."""

    name = "contract-test"
    categories = ("thing", "other")

    def __init__(self, sensing: Any = None):
        self.sensing = sensing

    def groups(self) -> list[str]:
        return ["a", "b"]

    def folds(self) -> list[Fold]:
        return []

    def fingerprint(self) -> str:
        return "fixed"

    def samples(self, report: Any):
        for i, g in enumerate(["a", "a", "b"], start=1):
            t = np.full((8, 8), 20.0, np.float32)
            yield AlignedSample(
                i,
                np.zeros((8, 8, 3), np.uint8),
                t,
                np.zeros((8, 8), np.uint8),
                np.array([[1, 1, 4, 4]], np.float32),
                np.array([1], np.int64),
                g,
                {},
            )


class ShapesPlugin:
    """Registers the test encodings and the ``shapes`` dataset."""

    @hookimpl
    def register_encodings(self, register):
        for e in ENCODINGS:
            register(e)

    @hookimpl
    def register_datasets(self, register):
        register(
            DatasetSpec(
                name="shapes",
                open=lambda root=None, sensing=None, **opts: ShapesSource(**opts),
                categories=CATEGORIES,
                default_encoding="test-ir8",
                description="coloured shapes for engine tests",
            )
        )


PLUGIN_FILE = '''
"""Test plugin loaded through HARNESS_PLUGINS_DIR: the shapes dataset and test encodings."""
import sys
sys.path.insert(0, {tests!r})
from engine_helpers import ShapesPlugin
_p = ShapesPlugin()
register_encodings = _p.register_encodings
register_datasets = _p.register_datasets
'''


def write_plugin_dir(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "shapes_plugin.py").write_text(PLUGIN_FILE.format(tests=str(Path(__file__).resolve().parent)))
    return folder


def install_plugin(folder: str, tmp_path: Path) -> tuple[Path, Path]:
    """``plugins/<folder>`` copied to ``tmp_path/src`` and pip-installed (no dependencies, no index, no build
    isolation) into ``tmp_path/site``: (the copy, the site folder to put on ``PYTHONPATH``)."""
    import shutil
    import subprocess

    src, site = tmp_path / "src", tmp_path / "site"
    shutil.copytree(REPO / "plugins" / folder, src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    pip = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "--target",
            str(site),
            str(src),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert pip.returncode == 0, pip.stderr
    return src, site


def run_plugin_tests(src: Path, env: dict[str, str]) -> Any:
    """The plugin's own ``tests/`` run by pytest in a subprocess, with the fixtures of ``harness.testing``."""
    import subprocess

    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "harness.testing", str(src / "tests")],
        env=env,
        cwd=src,
        capture_output=True,
        text=True,
        timeout=600,
    )
