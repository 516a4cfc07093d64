"""``HARNESS_ONEDNN``: torch's oneDNN kernels on or off for a whole run (``harness.engine.runtime``)."""

from __future__ import annotations

import pytest
import torch
from torch.profiler import profile

from harness.engine.runtime import ENV_ONEDNN, apply_onednn_setting, onednn_setting, seed_everything
from harness.errors import ConfigError


@pytest.fixture(autouse=True)
def _restore_onednn():
    before = torch.backends.mkldnn.enabled
    yield
    torch.backends.mkldnn.enabled = before


def conv_kernels() -> set[str]:
    conv = torch.nn.Conv2d(4, 8, 3, padding=1)
    with torch.no_grad(), profile() as prof:
        conv(torch.rand(2, 4, 16, 16))
    return {e.name for e in prof.events() if "conv" in e.name}


@pytest.mark.parametrize(
    "value, expected",
    [("", None), ("0", False), ("off", False), (" False ", False), ("1", True), ("on", True), ("yes", True)],
)
def test_the_variable_reads_as_on_off_or_unset(value, expected):
    assert onednn_setting({ENV_ONEDNN: value}) is expected
    assert onednn_setting({}) is None


def test_another_value_is_an_error_naming_the_variable():
    with pytest.raises(ConfigError, match=r"HARNESS_ONEDNN='maybe'.*use 1 .* or 0"):
        onednn_setting({ENV_ONEDNN: "maybe"})


def test_unset_leaves_torch_as_it_is():
    torch.backends.mkldnn.enabled = False
    assert apply_onednn_setting({}) is False
    torch.backends.mkldnn.enabled = True
    assert apply_onednn_setting({}) is True


def test_seeding_a_run_under_harness_onednn_0_puts_convolutions_on_atens_kernels(monkeypatch):
    torch.backends.mkldnn.enabled = True
    assert "aten::mkldnn_convolution" in conv_kernels()
    monkeypatch.setenv(ENV_ONEDNN, "0")
    seed_everything(0)
    assert torch.backends.mkldnn.enabled is False
    kernels = conv_kernels()
    assert "aten::mkldnn_convolution" not in kernels
    assert "aten::_slow_conv2d_forward" in kernels
    monkeypatch.setenv(ENV_ONEDNN, "1")
    seed_everything(0)
    assert "aten::mkldnn_convolution" in conv_kernels()
