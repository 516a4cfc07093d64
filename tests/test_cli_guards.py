"""What a user can get wrong on the command line, and a detector plugin's model beside its contract, each stopped
with a clear usage error instead of a silent result or a traceback: repeated or empty folds and seeds, seeds numpy
cannot take, a reference detector that is not in the store, a full disk, the deprecated ``--fold``; a detector
without ``forward_raw``, one built for another channel count, and thresholds set where the host ignores them."""

from __future__ import annotations

import errno

import pytest

pytest.importorskip("harness.cache")

from engine_helpers import DetectorsPlugin, shapes_and_tinydet, single_stream, tinydet_module
from harness.errors import ConfigError, PluginError
from harness.testing import temporary_plugin

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def shapes(tmp_path, monkeypatch):
    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    with shapes_and_tinydet("cli-guards"):
        yield tmp_path


def _run(cli_runner, tmp, *args):
    return cli_runner(
        ["run", "--detector", "tinydet", "--dataset", "shapes", "--store", str(tmp / "store"), "--no-progress", *args]
    )


@pytest.mark.parametrize(
    "args, said",
    [
        (["--folds", "A,A"], "'A' given more than once"),
        (["--seeds", "0,0"], "seed 0 given more than once"),
        (["--folds", ""], "names no fold"),
        (["--seeds", "-1"], "seed -1 is outside 0..4294967295"),
    ],
)
def test_repeated_empty_or_impossible_folds_and_seeds_are_usage_errors(shapes, cli_runner, args, said):
    res = _run(cli_runner, shapes, *args)
    assert res.exit_code == 2, res.output
    assert said in res.stderr and "Traceback" not in res.output
    assert not (shapes / "store" / "shapes").exists()  # nothing was trained


def test_the_deprecated_fold_spelling_works_for_run(shapes, cli_runner):
    res = _run(cli_runner, shapes, "--fold", "A", "--seeds", "-1")  # stops at the seeds, after --fold was read
    assert res.exit_code == 2 and "deprecated: --fold, use --folds" in res.stderr
    assert "No such option" not in res.stderr and "seed -1" in res.stderr


def test_thresholds_set_as_model_options_are_refused_naming_eval(shapes, cli_runner):
    res = _run(cli_runner, shapes, "--set", "model.conf=0.9")
    assert res.exit_code == 2
    assert "model.conf" in res.stderr and "--set eval.conf=" in res.stderr


def test_a_reference_detector_not_in_the_store_is_a_usage_error(tmp_path, cli_runner):
    (tmp_path / "store").mkdir()
    res = cli_runner(["report", "--store", str(tmp_path / "store"), "--reference", "nosuch", "--print"])
    assert res.exit_code == 2 and "'nosuch' has no runs" in res.stderr


def test_a_full_disk_names_the_file_being_written(tmp_path, cli_runner):
    from harness.io import atomic_write

    def full(_f):
        raise OSError(errno.ENOSPC, "No space left on device")

    target = tmp_path / "store" / "metrics.json"
    with pytest.raises(OSError) as err:
        atomic_write(target, full)
    assert err.value.errno == errno.ENOSPC and str(target) in str(err.value)
    assert list((tmp_path / "store").iterdir()) == []  # the temporary file is gone


# ------------------------------------------------------------------------------------------------ detector plugins
def _plugin():
    m = tinydet_module()

    def no_raw(self):
        raise AttributeError("forward_raw")

    class NoRaw(m.TinyDet):
        """A detector whose raw head is private: forward decodes and runs NMS, and there is no forward_raw."""

        _raw_head = m.TinyDet.forward_raw
        forward_raw = property(no_raw)

        def forward(self, inputs, targets=None):
            h, w = inputs.shape[-2:]
            raw = self._raw_head(inputs)
            pts, strides = self.points(h, w, raw.device)
            boxes, logits = self.decode(raw, pts, strides)
            if self.training:
                return self.loss(boxes, logits, pts, strides, targets)
            return self.postprocess(boxes, logits)

    class ThreeChannels(m.TinyDet):
        """A build that ignores ``in_channels``."""

        def __init__(self, num_classes, in_channels=4, **kw):
            super().__init__(num_classes, 3, **kw)

    plugin = DetectorsPlugin(
        single_stream("noraw", "no forward_raw", NoRaw),
        single_stream("threech", "ignores in_channels", ThreeChannels),
    )
    return plugin, NoRaw


@pytest.fixture
def faulty():
    plugin, no_raw = _plugin()
    with temporary_plugin(plugin, name="faulty-detectors"):
        yield no_raw


def test_export_of_a_detector_without_forward_raw_stops_instead_of_tracing_nms(faulty, cli_runner, tmp_path):
    res = cli_runner(["export", "--detector", "noraw", "--onnx", str(tmp_path / "m.onnx"), "--imgsz", "64"])
    assert res.exit_code == 2, res.output
    assert "detector 'noraw'" in res.stderr and "no forward_raw" in res.stderr
    assert not (tmp_path / "m.onnx").exists() and "matches torch" not in res.output


def test_profile_and_a_runs_complexity_say_forward_raw_is_missing(faulty, cli_runner):
    from harness.complexity import measure

    res = cli_runner(["profile", "--detector", "noraw", "--imgsz", "64"])
    assert res.exit_code == 2 and "no forward_raw" in res.stderr and "meta device" not in res.stderr
    rec = measure(faulty(2, 4), "single", 4, 3, 64, 2, label="detector 'noraw'")
    assert "detector 'noraw'" in rec["error"] and "no forward_raw" in rec["error"]


def test_a_build_that_ignores_in_channels_is_named_with_the_contract(faulty, cli_runner, shapes):
    from harness.config import load_config
    from harness.plugins import get_host
    from harness.runner import check_settings

    res = cli_runner(["profile", "--detector", "threech", "--imgsz", "64"])
    assert res.exit_code == 2 and "detector 'threech'" in res.stderr and "in_channels=4" in res.stderr
    host = get_host()
    cfg = load_config("smoke", protocol=host.dataset("shapes").protocol)
    enc = host.encoding("test-ir8")
    with pytest.raises(PluginError, match=r"detector 'threech'.*in_channels=4.*detector contract"):
        check_settings(host.detector("threech"), host.dataset("shapes"), enc, cfg)
    check_settings(host.detector("tinydet"), host.dataset("shapes"), enc, cfg)  # a good build passes
    with pytest.raises(ConfigError, match=r"model\.iou.*eval\.iou"):
        check_settings(host.detector("tinydet"), host.dataset("shapes"), enc, {**cfg, "model": {"iou": 0.5}})
