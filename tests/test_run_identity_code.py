"""A run's identity holds its detector plugin's code, built-in plugins are keyed by what they import (not their whole
package), and a changed cache key over identical samples is the same run."""

from __future__ import annotations

import importlib
import logging
import sys

import pytest

pytest.importorskip("harness.cache")

from engine_helpers import fast_overrides
from harness.errors import StoreError
from harness.testing import temporary_plugin

FAST = fast_overrides(epochs=1)

DETECTOR_PLUGIN = """
from harness import DetectorSpec, hookimpl
from {pkg}.{kind} import build


@hookimpl
def register_detectors(register):
    register(DetectorSpec(name="{name}", build=build, input_kind="single"))
"""
HELPER = """
def build(num_classes, in_channels=4, **cfg):
    from harness_tinydet.model import TinyDet

    return TinyDet(num_classes, in_channels=in_channels)
"""


def write_package(root, files):
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


@pytest.fixture
def package(tmp_path, monkeypatch):
    """A package folder on ``sys.path`` (``tmp/src``) whose modules are forgotten after the test."""
    src = tmp_path / "src"
    src.mkdir()
    monkeypatch.syspath_prepend(str(src))
    yield src
    for name in [m for m in sys.modules if m.startswith(("codedet_pkg_", "fake_adapters_"))]:
        sys.modules.pop(name, None)


def request(tmp_path, detector, **kw):
    from harness.runner import RunRequest

    base = dict(detector=detector, dataset="shapes", folds="A", seeds=[0], store=tmp_path / "store", overrides=FAST)
    return RunRequest(**{**base, "progress": False, **kw})


def finish(planned, config=None, metrics=None, digest=None):
    """Leave what a finished run leaves behind (no training): config.yaml, metrics.json and status.json."""
    from harness.runner import run_hash

    config = planned.config if config is None else config
    planned.run.path.mkdir(parents=True, exist_ok=True)
    planned.run.write_config(config)
    planned.run.write_metrics(metrics or {"metrics": {}, "support": {}})
    planned.run.set_status("finished", config_hash=digest or run_hash(config))


def first_run(tmp_path, detector, **kw):
    from harness.runner import plan

    return plan(request(tmp_path, detector, **kw)).runs[0]


def test_an_edited_helper_module_of_a_detector_plugin_makes_its_finished_run_a_conflict(
    shapes_run_plugins, package, tmp_path
):
    from harness.config import read_yaml
    from harness.runner import run

    pkg = package / "codedet_pkg_a"
    write_package(
        pkg,
        {
            "__init__.py": "",
            "plugin.py": DETECTOR_PLUGIN.format(pkg="codedet_pkg_a", kind="helper", name="codedet"),
            "helper.py": HELPER,
        },
    )
    module = importlib.import_module("codedet_pkg_a.plugin")
    with temporary_plugin(module, name="codedet-plugin"):
        first = first_run(tmp_path, "codedet")
        finish(first)
        meta = read_yaml(first.run.config_path)["meta"]
        assert len(meta["detector_code"]) == 16 and "codedet_pkg_a/helper.py" in meta["detector_code_files"]
        assert first_run(tmp_path, "codedet").state == "finished"

        (pkg / "helper.py").write_text(HELPER + "\n# a helper edited after the run\n")
        again = first_run(tmp_path, "codedet")
        assert again.state == "conflict"
        (diff,) = [d for d in again.differences() if d.startswith("meta.detector_code:")]
        assert f"{meta['detector_code']} -> {again.config['meta']['detector_code']}" in diff
        assert "the detector plugin's code changed: codedet_pkg_a/helper.py)" in diff
        with pytest.raises(StoreError, match=r"meta\.detector_code: .*helper\.py.*--force"):
            run(request(tmp_path, "codedet"))


FAKE_BUILTINS = {
    "__init__.py": "",
    "detectors/__init__.py": "",
    "detectors/shared.py": "WIDTH = 8\n",
    "detectors/one.py": "from fake_adapters_x.detectors.shared import WIDTH\n"
    + DETECTOR_PLUGIN.format(pkg="fake_adapters_x.detectors", kind="helper", name="fake-one"),
    "detectors/two.py": "from .shared import WIDTH\n"
    + DETECTOR_PLUGIN.format(pkg="fake_adapters_x.detectors", kind="helper", name="fake-two"),
    "detectors/helper.py": HELPER,
    "datasets/__init__.py": "",
    "datasets/_common.py": "SIZE = 4\n",
    "datasets/alpha.py": "def open_alpha():\n    from . import _common\n\n    return _common.SIZE\n",
    "datasets/beta/__init__.py": "from fake_adapters_x.datasets.beta.source import open_beta\n",
    "datasets/beta/source.py": "def open_beta():\n    return 1\n",
    "datasets/beta/extra.py": "UNUSED = 1\n",
}


@pytest.fixture
def fake_builtins(package, monkeypatch):
    """``fake_adapters_x``: a stand-in for the built-in ``adapters`` package (keyed as built-in plugins are)."""
    from harness.cache import key

    write_package(package / "fake_adapters_x", FAKE_BUILTINS)
    monkeypatch.setattr(key, "BUILTIN_PACKAGE", "fake_adapters_x")
    importlib.import_module("fake_adapters_x")
    return package / "fake_adapters_x"


def test_a_built_in_dataset_is_keyed_by_its_own_modules_and_what_it_imports(fake_builtins):
    from harness.cache.key import plugin_code_files

    alpha = importlib.import_module("fake_adapters_x.datasets.alpha")
    beta = importlib.import_module("fake_adapters_x.datasets.beta")
    names = [n for n, _ in plugin_code_files(alpha)]
    assert names == [
        "fake_adapters_x.datasets/__init__.py",
        "fake_adapters_x.datasets/_common.py",
        "fake_adapters_x.datasets/alpha.py",
        "fake_adapters_x/__init__.py",
    ]
    # a dataset in a sub-package brings that whole sub-package (its own code), not its neighbours
    beta_names = [n for n, _ in plugin_code_files(beta)]
    assert "fake_adapters_x.datasets/beta/extra.py" in beta_names
    assert not any(n.endswith(("alpha.py", "_common.py")) for n in beta_names)

    (fake_builtins / "datasets" / "gamma.py").write_text("def open_gamma():\n    return 2\n")
    (fake_builtins / "datasets" / "delta").mkdir()
    (fake_builtins / "datasets" / "delta" / "__init__.py").write_text("")
    assert [n for n, _ in plugin_code_files(alpha)] == names
    assert [n for n, _ in plugin_code_files(beta)] == beta_names


def test_editing_another_built_in_detector_leaves_a_finished_run_alone(shapes_run_plugins, fake_builtins, tmp_path):
    from harness.cache.key import detector_code

    one = importlib.import_module("fake_adapters_x.detectors.one")
    two = importlib.import_module("fake_adapters_x.detectors.two")
    with temporary_plugin(one, name="fake-builtin-one"), temporary_plugin(two, name="fake-builtin-two"):
        digest, files = detector_code("fake-one")
        assert "fake_adapters_x.detectors/shared.py" in files and "fake_adapters_x.detectors/two.py" not in files
        finish(first_run(tmp_path, "fake-one"))

        (fake_builtins / "detectors" / "two.py").write_text(FAKE_BUILTINS["detectors/two.py"] + "# edited\n")
        assert detector_code("fake-one")[0] == digest and detector_code("fake-two")[0] != digest
        assert first_run(tmp_path, "fake-one").state == "finished"

        (fake_builtins / "detectors" / "shared.py").write_text("WIDTH = 16\n")  # what fake-one imports
        again = first_run(tmp_path, "fake-one")
        assert again.state == "conflict"
        assert any("fake_adapters_x.detectors/shared.py" in d for d in again.differences())


def test_a_run_stored_before_the_code_was_recorded_stays_finished(shapes_run_plugins, tmp_path):
    from harness.runner import identity_diff, run

    first = first_run(tmp_path, "tinydet")
    assert first.config["meta"]["detector_code"]
    old = {**first.config, "meta": dict(first.config["meta"])}
    del old["meta"]["detector_code"], old["meta"]["detector_code_files"]
    finish(first, config=old)
    again = first_run(tmp_path, "tinydet")
    assert again.state == "finished"
    assert identity_diff(old, again.config) == [] and identity_diff(again.config, old) == []
    assert run(request(tmp_path, "tinydet")).results[0].state == "skipped"
    # a real difference is still one, and the code is not reported against a run that never recorded it
    changed = first_run(tmp_path, "tinydet", overrides=[*FAST, "train.lr0=0.02"])
    assert changed.state == "conflict"
    assert not any("detector_code" in d for d in changed.differences())


def _moved_cache(planned, samples):
    """``planned``'s config as a finished run stored it under another cache key, and metrics recording ``samples``."""
    meta = {**planned.config["meta"], "prepared_key": "0123456789abcdef", "prepared_fingerprint": "elsewhere"}
    return {**planned.config, "meta": meta}, {"metrics": {}, "support": {}, "samples": samples}


def _samples(p, planned):
    from harness.runner import fold_indices

    train_idx, val_idx = fold_indices(p.prepared, planned.fold)
    enc = p.encoding
    return {
        "encoding": enc.name,
        "train": p.prepared.content_digest(train_idx, enc, {}),
        "held_out": p.prepared.content_digest(val_idx, enc, {}),
    }


def test_a_changed_cache_key_over_identical_samples_is_the_same_run(shapes_run_plugins, tmp_path, caplog):
    from harness.runner import plan

    p = plan(request(tmp_path, "tinydet"))
    planned = p.runs[0]
    config, metrics = _moved_cache(planned, _samples(p, planned))
    finish(planned, config=config, metrics=metrics)
    with caplog.at_level(logging.INFO, logger="harness.runner"):
        again = first_run(tmp_path, "tinydet")
        assert again.state == "finished" and again.state == "finished"
    notes = [r.getMessage() for r in caplog.records if "cache key changed" in r.getMessage()]
    assert len(notes) == 1 and "samples are identical" in notes[0] and "0123456789abcdef" in notes[0]
    # the key alone is forgiven, not another setting beside it
    assert first_run(tmp_path, "tinydet", overrides=[*FAST, "train.lr0=0.02"]).state == "conflict"


def test_a_changed_cache_key_over_other_samples_stays_a_conflict_naming_them(shapes_run_plugins, tmp_path):
    from harness.runner import plan

    p = plan(request(tmp_path, "tinydet"))
    planned = p.runs[0]
    samples = {**_samples(p, planned), "train": "f" * 32}
    config, metrics = _moved_cache(planned, samples)
    finish(planned, config=config, metrics=metrics)
    again = first_run(tmp_path, "tinydet")
    assert again.state == "conflict"
    fingerprint, key, why = again.differences()
    assert key == f"meta.prepared_key: 0123456789abcdef -> {planned.config['meta']['prepared_key']}"
    assert fingerprint.startswith("meta.prepared_fingerprint: elsewhere -> ")
    assert why.startswith("samples: train ffffffffffff..") and "differ from those prepared now" in why
    # recorded image-id identities that differ refuse it without reading a sample
    config["meta"]["prepared_samples"] = "0" * 16
    finish(planned, config=config, metrics=_moved_cache(planned, _samples(p, planned))[1])
    assert first_run(tmp_path, "tinydet").differences()[-1].startswith("meta.prepared_samples: 0000000000000000 ->")
