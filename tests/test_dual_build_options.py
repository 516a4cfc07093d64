"""The dual-stream detectors (ICAFusion, EME, CMA-Det) take the weights and the NMS settings through one shared list
(``adapters.detectors._dual.FINISH_OPTIONS``): every build accepts each of them, sets the NMS settings on the model,
and names any other unknown option."""

from __future__ import annotations

import pytest
import torch

from adapters.detectors import cmadet, eme, icafusion
from adapters.detectors._dual import FINISH_OPTIONS, finish_options
from harness.errors import ConfigError

TINY = {
    "eme": (eme, {"scale": "n"}),
    "icafusion": (icafusion, {"scale": "n", "tokens": (2, 2, 1), "heads": 2}),
    "cmadet": (cmadet, {"width": 0.0625, "depth": 0.33, "align_width": 8, "hidden": 16}),
}


def test_the_shared_options_are_the_weights_and_the_nms_settings():
    assert FINISH_OPTIONS == ("weights", "conf", "iou", "max_det", "multi_label", "max_nms")
    options = {"conf": 0.3, "reduction": 4}
    assert finish_options("cmadet", options, ("reduction",)) == {"conf": 0.3} and options == {"reduction": 4}
    with pytest.raises(ConfigError, match=r"detector 'x': unknown model option\(s\) widht"):
        finish_options("x", {"widht": 1, "iou": 0.5})


@pytest.mark.parametrize("name", sorted(TINY))
def test_every_dual_stream_build_takes_the_nms_settings_and_names_an_unknown_option(name):
    module, options = TINY[name]
    torch.manual_seed(0)
    model = module.build(8, **options, conf=0.3, iou=0.45, max_det=7, multi_label=False, max_nms=99, weights=None)
    assert (model.conf, model.iou, model.max_det) == (0.3, 0.45, 7)
    with pytest.raises(ConfigError, match="unknown model option") as err:
        module.build(8, **options, max_dets=7)
    known = str(err.value).split("known: ")[1].split(" (config section")[0].split(", ")
    assert {"scale", "width", "depth", *FINISH_OPTIONS} <= set(known)  # the error lists what the build takes
    assert {"eme": "shape", "icafusion": "tokens", "cmadet": "align_width"}[name] in known
