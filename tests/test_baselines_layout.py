"""Official checkpoint layouts of the baselines, and state-dict round trips through ``load_official``.

No official weights can be downloaded here, so the expected key lists are written out independently of the model
code, from three public facts:

1. the layer tables of the official configurations (``yolov5l.yaml`` v6.x for EME's YOLOv5l, the two-stream
   ``yolov5l_Transfusion.yaml`` for ICAFusion): which module sits at which index, with which widths and repeats;
2. the attribute names of the official modules (YOLOv5 ``Conv`` = ``conv`` + ``bn``; ``C3`` = ``cv1``, ``cv2``,
   ``cv3``, ``m.i.cv1``, ``m.i.cv2``; ``SPPF`` = ``cv1``, ``cv2``; ``Detect`` = ``m.i`` plus the ``anchors`` buffer,
   and before YOLOv5 v6.0 (ICAFusion) also the ``anchor_grid`` buffer; ICAFusion's ``TransformerFusionBlock``,
   ``CrossTransformerBlock`` and ``CrossAttention`` attribute names);
3. PyTorch's state-dict naming (``Sequential`` indices, BatchNorm's five entries, parameters and buffers).

The generator below restates those facts as (key, shape) pairs; the models must produce exactly that set.
"""

from __future__ import annotations

import math

import pytest
import torch

from adapters.detectors import cmadet, eme, icafusion

pytestmark = pytest.mark.usefixtures("one_torch_thread")


NC = 8


def _w(c: int, width: float) -> int:
    return int(math.ceil(c * width / 8) * 8)


def _n(n: int, depth: float) -> int:
    return max(round(n * depth), 1) if n > 1 else n


def conv_keys(p: str, c1: int, c2: int, k: int) -> dict[str, tuple]:
    return {
        f"{p}.conv.weight": (c2, c1, k, k),
        f"{p}.bn.weight": (c2,),
        f"{p}.bn.bias": (c2,),
        f"{p}.bn.running_mean": (c2,),
        f"{p}.bn.running_var": (c2,),
        f"{p}.bn.num_batches_tracked": (),
    }


def c3_keys(p: str, c1: int, c2: int, n: int) -> dict[str, tuple]:
    c_ = c2 // 2
    out = {
        **conv_keys(f"{p}.cv1", c1, c_, 1),
        **conv_keys(f"{p}.cv2", c1, c_, 1),
        **conv_keys(f"{p}.cv3", 2 * c_, c2, 1),
    }
    for i in range(n):
        out.update(conv_keys(f"{p}.m.{i}.cv1", c_, c_, 1))
        out.update(conv_keys(f"{p}.m.{i}.cv2", c_, c_, 3))
    return out


def sppf_keys(p: str, c1: int, c2: int) -> dict[str, tuple]:
    return {**conv_keys(f"{p}.cv1", c1, c1 // 2, 1), **conv_keys(f"{p}.cv2", 2 * c1, c2, 1)}


def detect_keys(p: str, nc: int, chs: tuple[int, ...], anchor_grid: bool) -> dict[str, tuple]:
    out: dict[str, tuple] = {f"{p}.anchors": (3, 3, 2)}
    if anchor_grid:
        out[f"{p}.anchor_grid"] = (3, 1, 3, 1, 1, 2)
    for i, c in enumerate(chs):
        out[f"{p}.m.{i}.weight"] = (3 * (nc + 5), c, 1, 1)
        out[f"{p}.m.{i}.bias"] = (3 * (nc + 5),)
    return out


def yaml_layer_keys(index: int, module: str, c1: int, args: tuple, width: float, depth: float) -> tuple[dict, int]:
    """Keys of one yaml row ``[from, n, module, args]`` at a width/depth; returns (keys, output channels)."""
    p = f"model.{index}"
    if module == "Conv":
        c2, k = _w(args[0], width), args[1]
        return conv_keys(p, c1, c2, k), c2
    if module == "C3":
        n, c2 = args[0], _w(args[1], width)
        return c3_keys(p, c1, c2, _n(n, depth)), c2
    if module == "SPPF":
        c2 = _w(args[0], width)
        return sppf_keys(p, c1, c2), c2
    raise AssertionError(module)


# [module, args] of the yolov5l.yaml (v6.x) backbone rows: Conv [c2, k], C3 [n, c2], SPPF [c2]
BACKBONE = [
    ("Conv", (64, 6)),
    ("Conv", (128, 3)),
    ("C3", (3, 128)),
    ("Conv", (256, 3)),
    ("C3", (6, 256)),
    ("Conv", (512, 3)),
    ("C3", (9, 512)),
    ("Conv", (1024, 3)),
    ("C3", (3, 1024)),
    ("SPPF", (1024,)),
]
# PAN rows as (index offset, module, args, index offset of the concatenated input or None)
HEAD = [
    ("Conv", (512, 1), None),
    ("Upsample", (), None),
    ("Concat", (), "P4"),
    ("C3", (3, 512), None),
    ("Conv", (256, 1), None),
    ("Upsample", (), None),
    ("Concat", (), "P3"),
    ("C3", (3, 256), None),
    ("Conv", (256, 3), None),
    ("Concat", (), 4),
    ("C3", (3, 512), None),
    ("Conv", (512, 3), None),
    ("Concat", (), 0),
    ("C3", (3, 1024), None),
]


def backbone_keys(start: int, c_in: int, width: float, depth: float) -> tuple[dict, dict[int, int]]:
    keys: dict = {}
    chans: dict[int, int] = {}
    c = c_in
    for i, (module, args) in enumerate(BACKBONE):
        k, c = yaml_layer_keys(start + i, module, c, args, width, depth)
        keys.update(k)
        chans[i] = c
    return keys, chans


def head_keys(start: int, p3: int, p4: int, p5: int, width: float, depth: float) -> tuple[dict, list[int]]:
    keys: dict = {}
    chans: list[int] = []
    c = p5
    for i, (module, args, cat) in enumerate(HEAD):
        if module == "Upsample":
            chans.append(c)
            continue
        if module == "Concat":
            other = {"P4": p4, "P3": p3}.get(cat) if isinstance(cat, str) else chans[cat]
            c = c + other
            chans.append(c)
            continue
        k, c = yaml_layer_keys(start + i, module, c, args, width, depth)
        keys.update(k)
        chans.append(c)
    return keys, [chans[7], chans[10], chans[13]]


def yolov5_official_layout(c_in: int, nc: int, width: float, depth: float) -> dict[str, tuple]:
    """YOLOv5 (v6.x) ``model.0`` ... ``model.24`` for a ``c_in``-channel input."""
    keys, ch = backbone_keys(0, c_in, width, depth)
    hk, outs = head_keys(10, ch[4], ch[6], ch[9], width, depth)
    return {**keys, **hk, **detect_keys("model.24", nc, tuple(outs), anchor_grid=False)}


def fusion_block_keys(p: str, d: int, tokens: int) -> dict[str, tuple]:
    """ICAFusion TransformerFusionBlock(d, tokens, tokens), one CrossTransformerBlock, expansion 4."""
    out: dict[str, tuple] = {
        f"{p}.pos_emb_vis": (1, tokens * tokens, d),
        f"{p}.pos_emb_ir": (1, tokens * tokens, d),
        f"{p}.vis_coefficient.w1": (1,),
        f"{p}.vis_coefficient.w2": (1,),
        f"{p}.ir_coefficient.w1": (1,),
        f"{p}.ir_coefficient.w2": (1,),
    }
    b = f"{p}.crosstransformer.0"
    ln = lambda q: {f"{q}.weight": (d,), f"{q}.bias": (d,)}  # noqa: E731
    lin = lambda q, i, o: {f"{q}.weight": (o, i), f"{q}.bias": (o,)}  # noqa: E731
    out.update(ln(f"{b}.ln_input"))
    out.update(ln(f"{b}.ln_output"))
    for proj in (
        "que_proj_vis",
        "key_proj_vis",
        "val_proj_vis",
        "que_proj_ir",
        "key_proj_ir",
        "val_proj_ir",
        "out_proj_vis",
        "out_proj_ir",
    ):
        out.update(lin(f"{b}.crossatt.{proj}", d, d))
    out.update(ln(f"{b}.crossatt.LN1"))
    out.update(ln(f"{b}.crossatt.LN2"))
    for mlp in ("mlp_vis", "mlp_ir", "mlp"):
        out.update(lin(f"{b}.{mlp}.0", d, 4 * d))
        out.update(lin(f"{b}.{mlp}.2", 4 * d, d))
    out.update(ln(f"{b}.LN1"))
    out.update(ln(f"{b}.LN2"))
    for i in range(1, 9):
        out[f"{b}.coefficient{i}.bias"] = (1,)
    out.update(conv_keys(f"{p}.conv1x1_out", 2 * d, d, 1))
    return out


def icafusion_official_layout(nc: int, width: float, depth: float, tokens=(20, 16, 10)) -> dict[str, tuple]:
    """``yolov5l_Transfusion``: RGB stream 0-9, thermal stream 10-19 (both 3-channel), fusion 20-22, neck 23-36,
    Detect 37 (with ``anchor_grid``)."""
    rgb, ch = backbone_keys(0, 3, width, depth)
    ir, _ = backbone_keys(10, 3, width, depth)
    fusion: dict = {}
    for i, (tap, t) in enumerate(zip((4, 6, 9), tokens)):
        fusion.update(fusion_block_keys(f"model.{20 + i}", ch[tap], t))
    hk, outs = head_keys(23, ch[4], ch[6], ch[9], width, depth)
    return {**rgb, **ir, **fusion, **hk, **detect_keys("model.37", nc, tuple(outs), anchor_grid=True)}


def shapes(model: torch.nn.Module) -> dict[str, tuple]:
    return {k: tuple(v.shape) for k, v in model.state_dict().items()}


# ------------------------------------------------------------------------------------------------ layouts
def test_icafusion_full_size_has_exactly_the_official_keys_and_shapes():
    with torch.device("meta"):
        model = icafusion.build(NC)
    expected = icafusion_official_layout(NC, 1.0, 1.0)
    got = shapes(model)
    assert set(got) - set(expected) == set(), "keys the official layout does not have"
    assert set(expected) - set(got) == set(), "official keys the model lacks"
    assert got == expected
    # spot checks straight from the official checkpoint naming
    assert got["model.37.m.0.weight"] == (39, 256, 1, 1)
    assert got["model.22.crosstransformer.0.mlp.0.weight"] == (4096, 1024)  # the unused third MLP
    assert got["model.10.conv.weight"] == (64, 3, 6, 6)


def test_eme_full_size_is_the_yolov5l_layout_with_a_6_channel_stem():
    with torch.device("meta"):
        plain = eme.build(NC)
        shaped = eme.build(NC, shape=True)
    assert shapes(plain) == yolov5_official_layout(6, NC, 1.0, 1.0)
    expected = {**yolov5_official_layout(3, NC, 1.0, 1.0), "stem.conv.weight": (3, 6, 7, 7)}
    assert shapes(shaped) == expected
    assert "model.24.anchor_grid" not in shapes(plain)  # v6.x keeps only the anchors buffer


@pytest.mark.parametrize("width,depth", [(0.25, 0.33), (0.125, 0.33)])
def test_reduced_sizes_follow_the_same_scaling_rules(width, depth):
    with torch.device("meta"):
        ica = icafusion.build(NC, width=width, depth=depth)
        e = eme.build(NC, width=width, depth=depth)
    assert shapes(ica) == icafusion_official_layout(NC, width, depth)
    assert shapes(e) == yolov5_official_layout(6, NC, width, depth)


# ------------------------------------------------------------------------------------------------ round trips
def _randomise(model: torch.nn.Module, seed: int) -> None:
    """Random weights and non-trivial BatchNorm statistics, so that a wrong mapping changes the outputs."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, t in model.state_dict().items():
            if t.dtype.is_floating_point and "anchor" not in name:
                if name.endswith("running_var"):
                    t.copy_(torch.rand(t.shape, generator=g) + 0.5)
                else:
                    t.copy_(torch.randn(t.shape, generator=g) * 0.1)


def _inputs(size: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    return torch.rand(1, 3, size, size, generator=g), torch.rand(1, 3, size, size, generator=g)


@pytest.mark.parametrize(
    "spec,kw",
    [
        (icafusion, {"width": 0.125, "depth": 0.33, "tokens": (4, 2, 2)}),
        (eme, {"width": 0.125, "depth": 0.33}),
        (eme, {"width": 0.125, "depth": 0.33, "shape": True}),
    ],
)
def test_save_then_load_official_gives_identical_outputs(tmp_path, spec, kw):
    torch.manual_seed(0)
    src = spec.build(NC, **kw).eval()
    _randomise(src, 1)
    path = tmp_path / "official.pt"
    torch.save(src.state_dict(), path)
    torch.manual_seed(1)
    dst = spec.build(NC, **kw).eval()
    report = spec.load_official(dst, str(path))
    assert report["missing"] == [] and report["unexpected"] == [] and report["mismatched"] == []
    assert len(report["loaded"]) == len(src.state_dict())
    x = _inputs()
    for a, b in zip(src.forward_raw(x), dst.forward_raw(x)):
        assert torch.equal(a, b)
    assert [torch.equal(d["boxes"], e["boxes"]) for d, e in zip(src(x), dst(x))] == [True]


def test_a_state_dict_built_from_the_documented_layout_loads_completely():
    width, depth, tokens = 0.125, 0.33, (4, 2, 2)
    layout = icafusion_official_layout(NC, width, depth, tokens)
    g = torch.Generator().manual_seed(5)
    official = {
        k: (
            torch.zeros(s, dtype=torch.long)
            if k.endswith("num_batches_tracked")
            else torch.randn(s, generator=g).half()
        )
        for k, s in layout.items()
    }  # released files are fp16
    model = icafusion.build(NC, width=width, depth=depth, tokens=tokens)
    report = icafusion.load_official(model, {"model": official, "epoch": 3})  # checkpoint dict with a state dict inside
    assert report["missing"] == [] and report["unexpected"] == [] and report["mismatched"] == []
    sd = model.state_dict()
    for k in (
        "model.20.pos_emb_vis",
        "model.37.anchor_grid",
        "model.22.crosstransformer.0.mlp.2.bias",
        "model.36.m.0.cv2.bn.running_var",
    ):
        assert sd[k].dtype == torch.float32
        torch.testing.assert_close(sd[k], official[k].float())


def test_load_official_reports_unexpected_missing_and_mismatched_keys():
    model = eme.build(NC, width=0.125, depth=0.33)
    sd = {k: v.clone() for k, v in model.state_dict().items()}
    sd.pop("model.0.conv.weight")
    sd["model.99.extra"] = torch.zeros(1)
    sd["model.24.m.0.weight"] = torch.zeros(255, 32, 1, 1)  # a COCO (nc=80) head
    report = eme.load_official(model, sd)
    assert report["missing"] == ["model.0.conv.weight"]
    assert report["unexpected"] == ["model.99.extra"]
    assert report["mismatched"] == [("model.24.m.0.weight", (39, 32, 1, 1), (255, 32, 1, 1))]


def test_single_stream_yolov5_weights_initialise_both_icafusion_streams():
    from adapters.detectors.icafusion_net import yolov5_backbone_to_two_stream

    width, depth = 0.125, 0.33
    single = {
        k: torch.randn(s)
        for k, s in yolov5_official_layout(3, 80, width, depth).items()
        if not k.endswith("num_batches_tracked")
    }
    mapped = yolov5_backbone_to_two_stream(single)
    model = icafusion.build(NC, width=width, depth=depth, tokens=(4, 2, 2))
    report = icafusion.load_official(model, mapped)
    assert report["unexpected"] == [] and report["mismatched"] == []
    assert all(k.startswith(("model.2", "model.3")) or k.endswith("num_batches_tracked") for k in report["missing"])
    sd = model.state_dict()
    torch.testing.assert_close(sd["model.13.conv.weight"], single["model.3.conv.weight"])
    torch.testing.assert_close(sd["model.3.conv.weight"], single["model.3.conv.weight"])


def test_loading_into_a_fused_model_is_refused_with_a_clear_error():
    from harness.errors import HarnessError

    model = eme.build(NC, width=0.125, depth=0.33)
    sd = model.state_dict()
    model.fuse()
    with pytest.raises(HarnessError, match="fuse"):
        eme.load_official(model, sd)


def test_cmadet_has_no_official_checkpoint_but_round_trips_its_own_state_dict(tmp_path):
    spec_kw = {"width": 0.125, "depth": 0.33}
    src = cmadet.build(NC, **spec_kw).eval()
    _randomise(src, 2)
    torch.save(src.state_dict(), tmp_path / "w.pt")
    dst = cmadet.build(NC, weights=str(tmp_path / "w.pt"), **spec_kw).eval()
    assert dst.load_report["missing"] == [] and dst.load_report["unexpected"] == []
    x = _inputs()
    for a, b in zip(src.forward_raw(x), dst.forward_raw(x)):
        assert torch.equal(a, b)
