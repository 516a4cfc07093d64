"""TinyDet's own tests, written with the fixtures the harness ships for plugin authors (``harness.testing``: a
pytest plugin that installing the harness enables). Run them with ``pytest`` in this folder."""

from __future__ import annotations

import json

import harness_tinydet.plugin as plugin
import torch

from harness.contracts import check_detections, check_losses


def test_both_detectors_are_registered(harness_plugin, harness_host):
    name = harness_plugin(plugin, name="tinydet-under-test")  # or the entry point's name, when it is installed
    assert harness_host.owner("detector", "tinydet") == name
    assert harness_host.detector("tinydet").input_kind == "single"
    assert harness_host.detector("tinydet-dual").input_kind == "dual"


def test_the_model_keeps_the_detector_contract(harness_plugin, harness_host):
    harness_plugin(plugin)
    spec = harness_host.detector("tinydet")
    torch.manual_seed(0)
    model = spec.build(2, in_channels=spec.model_channels(4))
    images = torch.rand(2, 4, 64, 64)
    targets = [{"boxes": torch.tensor([[8.0, 8.0, 40.0, 30.0]]), "labels": torch.tensor([1])} for _ in range(2)]
    check_losses(model.train()(images, targets), spec.name)  # a dict of scalar losses
    with torch.no_grad():
        for detections in model.eval()(images):  # one {"boxes", "scores", "labels"} per image
            check_detections(detections, spec.name, num_classes=2)


def test_the_cli_lists_them(harness_plugin, harness_cli):
    harness_plugin(plugin)
    listed = json.loads(harness_cli(["list", "--format", "json"]).stdout)
    assert {"tinydet", "tinydet-dual"} <= {d["name"] for d in listed["detectors"]}
