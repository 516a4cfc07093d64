"""Published sizes of the baselines at 640 x 640, batch 1, both inputs, nc = 8, BatchNorm folded.

Models are built on the meta device (no memory, no arithmetic), so the full-width counts take about a second.
GFLOPs come from the harness profiler (``harness.profiling``): the paper convention (thop 0.1.1's module rules on
the BN-folded model, 1 MAC = 2 FLOPs, no attention matmuls) and the exact one (FlopCounterMode, every matmul).
Reachability (parameters that take part in forward) is the profiler's autograd analysis.
"""

from __future__ import annotations

import pytest
import torch

from adapters.detectors import cmadet, eme, icafusion
from harness.profiling.flops import exact_flops, paper_flops
from harness.profiling.params import reachable_parameters

pytestmark = pytest.mark.usefixtures("one_torch_thread")


SEED = {"icafusion": (120.24, 191.68), "eme": (46.15, 109.20), "cmadet": (33.47, 33.67)}
BUILDERS = {"icafusion": icafusion.build, "eme": eme.build, "cmadet": cmadet.build}


@pytest.fixture(scope="module")
def fused_models():
    out = {}
    with torch.device("meta"):
        for name, build in BUILDERS.items():
            out[name] = build(8).eval().fuse()
    return out


def _inputs():
    with torch.device("meta"):
        return torch.zeros(1, 3, 640, 640), torch.zeros(1, 3, 640, 640)


def test_parameter_counts_are_the_published_ones(fused_models):
    counts = {n: sum(p.numel() for p in m.parameters()) for n, m in fused_models.items()}
    assert counts["icafusion"] == 120_240_921  # official yolov5l_Transfusion, BN fused
    assert counts["eme"] == 46_152_885  # YOLOv5l with a 6-channel stem, BN fused
    assert counts["cmadet"] == 33_511_001  # the reconstruction: +0.12 % of 33.47 M
    for name, n in counts.items():
        assert abs(n / 1e6 - SEED[name][0]) / SEED[name][0] < 0.02, name


def test_icafusion_parameters_outside_the_forward_path(fused_models):
    model = fused_models["icafusion"]
    dead = set(model.unused_parameter_names())
    assert sum(p.numel() for n, p in model.named_parameters() if n in dead) == 11_029_760
    report = reachable_parameters(model, _inputs())
    assert report.unreachable_count == 11_029_760
    assert set(report.unreachable) == dead
    assert report.reachable == 120_240_921 - 11_029_760
    for name in ("eme", "cmadet"):
        assert reachable_parameters(fused_models[name], _inputs()).unreachable_count == 0


@pytest.mark.parametrize("name", list(SEED))
def test_gflops_at_640_match_the_seed_within_two_percent(fused_models, name):
    model = fused_models[name]
    paper = paper_flops(model, _inputs()).gflops
    exact = exact_flops(model, _inputs()).gflops
    target = SEED[name][1]
    assert abs(paper - target) / target < 0.02, (name, paper)
    assert abs(exact - target) / target < 0.02, (name, exact)
    expected_paper = {"icafusion": 191.680, "eme": 109.176, "cmadet": 33.622}[name]  # measured, see docs
    assert paper == pytest.approx(expected_paper, abs=0.002)
    if name == "icafusion":
        assert exact - paper > 0.6  # the attention matmuls, which module counters do not see (0.68)
