"""ICAFusion, EME and CMA-Det: the model contract, training signal, published sizes and the plugin records."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from adapters.detectors import cmadet, eme, icafusion
from harness.errors import ConfigError, HarnessError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


NC = 8
TINY = {"width": 0.125, "depth": 0.33}
SPECS = {
    "icafusion": (icafusion, {**TINY, "tokens": (4, 2, 2)}),
    "eme": (eme, TINY),
    "eme+shape": (eme, {**TINY, "shape": True}),
    "cmadet": (cmadet, TINY),
}


def tiny(name: str, nc: int = NC, **kw):
    module, options = SPECS[name]
    torch.manual_seed(0)
    return module.build(nc, **{**options, **kw})


def pair(b: int = 2, size: int = 64, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 3, size, size, generator=g), torch.rand(b, 3, size, size, generator=g)


TARGETS = [
    {"boxes": torch.tensor([[8.0, 10.0, 30.0, 40.0]]), "labels": torch.tensor([1])},
    {"boxes": torch.tensor([[30.0, 20.0, 60.0, 50.0], [5.0, 5.0, 20.0, 15.0]]), "labels": torch.tensor([0, 2])},
]


# ------------------------------------------------------------------------------------------------ contract
@pytest.mark.parametrize("name", list(SPECS))
def test_forward_shapes_for_the_pair_and_the_stacked_input(name):
    model = tiny(name).eval()
    rgb, thermal = pair(b=2, size=96)
    raw = model.forward_raw((rgb, thermal))
    assert [tuple(r.shape) for r in raw] == [(2, 3, 12, 12, 13), (2, 3, 6, 6, 13), (2, 3, 3, 3, 13)]
    stacked = model.forward_raw(torch.cat((rgb, thermal), 1))  # [B, 6, H, W] is split into the two streams
    for a, b in zip(raw, stacked):
        assert torch.equal(a, b)
    rect = model.forward_raw((torch.rand(1, 3, 64, 128), torch.rand(1, 3, 64, 128)))  # letterboxed, not square
    assert [tuple(r.shape[2:4]) for r in rect] == [(8, 16), (4, 8), (2, 4)]


@pytest.mark.parametrize("name", list(SPECS))
def test_train_mode_returns_the_loss_dict_and_every_term_has_a_gradient(name):
    model = tiny(name).train()
    losses = model(pair(), TARGETS)
    expected = {"box", "obj", "cls", "osr", "tv"} if name == "cmadet" else {"box", "obj", "cls"}
    assert set(losses) == expected
    for key, value in losses.items():
        assert value.dim() == 0 and torch.isfinite(value), key
    for key in ("box", "obj", "cls") + (("osr",) if name == "cmadet" else ()):
        assert losses[key].item() > 0, key
    sum(losses.values()).backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert sum(g is not None and bool(g.abs().sum() > 0) for g in grads) > 0.9 * len(grads)


@pytest.mark.parametrize("name", ["icafusion", "eme", "cmadet"])
def test_loss_decreases_on_a_tiny_batch(name):
    model = tiny(name, nc=3).train()
    x = pair()
    opt = torch.optim.Adam(model.parameters(), lr=5e-3)
    history = []
    for _ in range(15):
        loss = sum(model(x, TARGETS).values())
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append(loss.item())
    assert sum(history[-3:]) / 3 < 0.8 * history[0], history


@pytest.mark.parametrize("name", list(SPECS))
def test_eval_mode_returns_detections_after_nms_in_the_harness_format(name):
    model = tiny(name).eval()
    model.max_det = 50
    model.conf = 1e-5  # untrained heads with the YOLOv5 bias prior score about 1e-4
    out = model(pair(b=2, size=64))
    assert isinstance(out, list) and len(out) == 2
    for det in out:
        assert set(det) == {"boxes", "scores", "labels"}
        n = len(det["scores"])
        assert 0 < n <= 50
        assert det["boxes"].shape == (n, 4) and det["boxes"].dtype == torch.float32
        assert det["labels"].dtype == torch.int64 and det["labels"].min() >= 0 and det["labels"].max() < NC
        assert (det["scores"] > 1e-5).all() and (det["scores"][:-1] >= det["scores"][1:]).all()
        b = det["boxes"]
        assert (b[:, 0] >= 0).all() and (b[:, 2] <= 64).all() and (b[:, 0] <= b[:, 2]).all()


def test_fuse_folds_batchnorm_and_keeps_the_outputs():
    model = tiny("cmadet").eval()
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.uniform_(-0.3, 0.3)
            m.running_var.uniform_(0.5, 1.5)
    x = pair(b=1)
    ref = model.forward_raw(x)
    model.fuse()
    assert not any(isinstance(m, nn.BatchNorm2d) for m in model.modules())
    for a, b in zip(ref, model.forward_raw(x)):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


# ------------------------------------------------------------------------------------------------ ICAFusion specifics
def test_icafusion_unused_modules_never_take_part_in_forward_or_backward():
    model = tiny("icafusion").train()
    dead = set(model.unused_parameter_names())
    assert len(dead) == 3 * 10  # per block: mlp (2 Linear: 4 tensors), LN1, ln_input, ln_output (2 each)
    touched: set[str] = set()
    names = {id(m): n for n, m in model.named_modules()}
    hooks = [m.register_forward_hook(lambda mod, i, o: touched.add(names[id(mod)])) for m in model.modules()]
    sum(model(pair(), TARGETS).values()).backward()
    for h in hooks:
        h.remove()
    for name, p in model.named_parameters():
        if name in dead:
            assert p.grad is None, name
            assert name.rsplit(".", 1)[0] not in touched, name
        else:
            assert p.grad is not None, name


def test_icafusion_upsamples_tokens_nearest_in_training_and_bilinear_in_eval():
    from adapters.detectors.icafusion_net import TransformerFusionBlock

    torch.manual_seed(0)
    block = TransformerFusionBlock(16, 4, 4, heads=8, attn_pdrop=0.0, resid_pdrop=0.0)
    with torch.no_grad():
        block.pos_emb_vis.normal_()
    v, _ = torch.rand(1, 16, 16, 16), torch.rand(1, 16, 16, 16)
    tokens = block._tokens(v, block.vis_coefficient, block.pos_emb_vis)
    block.train()
    near = block._back(tokens, v)
    block.eval()
    bil = block._back(tokens, v)
    assert torch.equal(near[..., 0:4, 0:4], near[..., 0:1, 0:1].expand(-1, -1, 4, 4))  # 4x4 blocks of one token
    assert not torch.allclose(near, bil)


@pytest.mark.parametrize(
    "size,grid,expected",
    [(80, 20, (4, 4)), (40, 16, (10, 2)), (20, 10, (2, 2)), (32, 20, (13, 1)), (16, 16, None), (8, 10, None)],
)
def test_icafusion_pool_rule(size, grid, expected):
    from adapters.detectors.icafusion_net import pool_geometry, pool_to_grid

    assert pool_geometry(size, grid) == expected
    assert pool_to_grid(torch.rand(1, 2, size, size), (grid, grid), "max").shape[-2:] == (grid, grid)


# ------------------------------------------------------------------------------------------------ EME specifics
def test_shape_stem_pieces_against_hand_values():
    from adapters.detectors.eme_net import gaussian_kernel, sobel_magnitude, ssim_map

    ramp = torch.arange(6.0).view(1, 1, 1, 6).expand(1, 1, 6, 6)  # d/dx = 1 per pixel inside
    g = sobel_magnitude(ramp)
    # Sobel / 8 of a unit ramp: (1 + 2 + 1) * 2 / 8 = 1 inside; at the replicated border the step is 1 over 2 px
    torch.testing.assert_close(g[0, 0, :, 1:5], torch.full((6, 4), (1.0 + 1e-6) ** 0.5))
    torch.testing.assert_close(g[0, 0, :, 0], torch.full((6,), (0.25 + 1e-6) ** 0.5))
    k = gaussian_kernel(7, 1.5)
    assert k.shape == (7, 7) and abs(k.sum().item() - 1) < 1e-6 and k.argmax().item() == 24
    x = torch.rand(1, 1, 12, 12)
    torch.testing.assert_close(ssim_map(x, x), torch.ones(1, 1, 12, 12))
    assert (ssim_map(x, 1 - x) < 0.5).all()


def test_shape_weights_favour_the_modality_that_carries_the_edges_and_are_symmetric():
    from adapters.detectors.eme_net import ShaPE

    stem = ShaPE()
    square = torch.zeros(1, 3, 32, 32)
    square[..., 10:20, 10:20] = 1.0  # a square seen in one modality only
    flat = torch.full((1, 3, 32, 32), 0.5) + 0.01 * torch.rand(1, 3, 32, 32)
    w = stem.fusion_weights(square, flat)
    torch.testing.assert_close(w.sum(1), torch.ones(1, 32, 32))
    assert w[:, 0].mean() > 0.52  # the RGB edges are the union edge map
    swapped = stem.fusion_weights(flat, square)
    torch.testing.assert_close(swapped[:, 1], w[:, 0], atol=1e-5, rtol=0)


# ------------------------------------------------------------------------------------------------ CMA-Det specifics
def test_warp_with_zero_flow_is_identity_and_an_integer_flow_shifts():
    from adapters.detectors.cmadet_net import resize_flow, total_variation, warp

    x = torch.rand(1, 4, 8, 8)
    torch.testing.assert_close(warp(x, torch.zeros(1, 2, 8, 8)), x)
    flow = torch.zeros(1, 2, 8, 8)
    flow[:, 0] = 2.0  # out(x) = in(x + 2)
    out = warp(x, flow)
    torch.testing.assert_close(out[..., :6], x[..., 2:])
    assert out[..., 6:].abs().max() == 0  # sampled outside: zero
    up = resize_flow(flow, (16, 16))
    torch.testing.assert_close(up[:, 0], torch.full((1, 16, 16), 4.0))  # cells are half as wide
    assert total_variation(flow) == 0 and total_variation(torch.rand(1, 2, 4, 4)) > 0


def test_object_search_finds_a_known_shift():
    from adapters.detectors.cmadet_net import osr_offset, osr_search

    torch.manual_seed(0)
    thermal = torch.rand(8, 20, 20)
    visible = torch.roll(thermal, shifts=(1, 2), dims=(1, 2))  # visible(y, x) = thermal(y - 1, x - 2)
    boxes = torch.tensor([[6.0, 6.0, 12.0, 13.0]])
    logits, shifts = osr_search(thermal, visible, boxes, temperature=0.01)
    assert shifts[logits.argmax(1)].tolist() == [[2.0, 1.0]]  # the object sits 2 cells right, 1 down in visible
    torch.testing.assert_close(osr_offset(logits, shifts), torch.tensor([[2.0, 1.0]]), atol=1e-3, rtol=0)
    logits0, _ = osr_search(thermal, thermal, boxes)
    assert logits0.argmax(1).item() == len(shifts) // 2  # aligned: best at zero shift


def test_cmadet_starts_as_the_identity_warp_and_osr_can_be_switched_off():
    model = tiny("cmadet").eval()
    flows = model.flows(pair())
    assert [tuple(f.shape[-2:]) for f in flows] == [(8, 8), (4, 4), (2, 2)]
    assert all(f.abs().max() == 0 for f in flows)
    off = tiny("cmadet", osr=False).train()
    assert off(pair(), TARGETS)["osr"].item() == 0.0


def test_bfcfm_corrects_each_modality_with_the_other():
    from adapters.detectors.cmadet_net import BFCFM

    block = BFCFM(8)
    v, t = torch.rand(2, 8, 5, 5), torch.rand(2, 8, 5, 5)
    assert block(v, t).shape == (2, 8, 5, 5)
    # channel MLP 4C -> 4C -> 2C, spatial 2C -> C -> 2 (biased convs), fuse CBS 2C -> C (conv + BN), C = 8
    assert sum(p.numel() for p in block.parameters()) == (32 * 32 + 32) + (32 * 16 + 16) + (16 * 8 + 8) + (
        8 * 2 + 2
    ) + (16 * 8 + 2 * 8)


# ------------------------------------------------------------------------------------------------ errors, plugin
def test_bad_inputs_and_options_raise_clear_errors():
    model = tiny("icafusion").eval()
    with pytest.raises(HarnessError, match="dual-stream"):
        model.forward_raw([torch.rand(1, 3, 64, 64)] * 3)
    with pytest.raises(HarnessError, match="multiple of 32"):
        model.forward_raw((torch.rand(1, 3, 60, 64), torch.rand(1, 3, 60, 64)))
    with pytest.raises(HarnessError, match="same batch size"):
        model.forward_raw((torch.rand(1, 3, 64, 64), torch.rand(2, 3, 64, 64)))
    with pytest.raises(HarnessError, match="early fusion expects 6"):
        tiny("eme").forward_raw(torch.rand(1, 4, 64, 64))
    with pytest.raises(HarnessError, match="labels"):
        tiny("eme").train()(pair(), [{"boxes": torch.zeros(1, 4)}, {"boxes": torch.zeros(0, 4), "labels": []}])
    with pytest.raises(HarnessError, match="labels must be 0..7"):
        tiny("cmadet").train()(pair(), [{"boxes": torch.ones(1, 4) * torch.tensor([1, 1, 9, 9]), "labels": [8]}] * 2)
    with pytest.raises(ConfigError, match="unknown model option"):
        eme.build(NC, widht=0.5)
    with pytest.raises(ConfigError, match="model.scale"):
        cmadet.build(NC, scale="q")


def test_plugins_register_dual_stream_specs_with_labels_references_and_defaults(host):
    specs = host.detectors()
    ica, e, cma = specs["icafusion"], specs["eme"], specs["cmadet"]
    assert {s.input_kind for s in (ica, e, cma)} == {"dual"}
    assert {s.default_thermal_encoding for s in (ica, e, cma)} == {"ir8"}
    assert (ica.reference.params_m, ica.reference.gflops) == (120.24, 191.68)
    assert (e.reference.params_m, e.reference.gflops) == (46.15, 109.2)
    assert (cma.reference.params_m, cma.reference.gflops) == (33.47, 33.67)
    assert cma.label == "reconstructed from the paper"
    assert "weak supervision and distillation omitted" in e.label
    assert ica.defaults == {"eval": {"iou": 0.5}}
    assert ica.load_official is not None and e.load_official is not None and cma.load_official is None
    model = ica.build(NC, in_channels=3, **SPECS["icafusion"][1])
    assert model.iou == 0.5 and model.conf == 0.001 and model.max_det == 300


def test_harness_list_shows_the_labels(cli_runner):
    result = cli_runner(["list"])
    assert result.exit_code == 0
    assert "cmadet" in result.output and "[reconstructed from the paper]" in result.output
    assert "icafusion" in result.output and "eme" in result.output
