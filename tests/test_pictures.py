"""Pictures of prepared samples (``harness show``, the gallery's drawing); ``_fake_run`` also serves the FiftyOne
export's tests (test_fiftyone_export.py)."""

from __future__ import annotations

import base64
import io

import numpy as np
import pytest

from engine_helpers import CATEGORIES, ShapesPlugin
from harness.report import pictures
from harness.sample import AlignedSample
from harness.testing import temporary_plugin


def _sample(radiometric: bool = True) -> AlignedSample:
    h, w = 40, 60
    rgb = np.full((h, w, 3), 100, np.uint8)
    thermal = np.linspace(10.0, 30.0, h * w, dtype=np.float32).reshape(h, w)
    thermal[0, 0] = np.nan  # a missing temperature
    ir8 = np.tile(np.arange(w, dtype=np.uint8) * 4, (h, 1))
    return AlignedSample(
        1,
        rgb,
        thermal if radiometric else None,
        ir8,
        np.array([[10, 10, 30, 20]], np.float32),
        np.array([1], np.int64),
        "g",
        {"file_name": "a.jpg"},
    )


def _panel(img: np.ndarray, k: int, width: int, height: int) -> np.ndarray:
    """Panel ``k`` (0 RGB, 1 thermal, ...) of a picture whose panels are ``width`` wide (4 px gaps), no scale bar."""
    x0 = k * (width + 4)
    return img[pictures.TITLE_H : pictures.TITLE_H + height, x0 : x0 + width]


def test_draw_sample_puts_boxes_on_every_panel_at_the_panel_scale():
    s = _sample(radiometric=False)
    fourth = np.full((40, 60), 200, np.uint8)
    pred = pictures.BoxSet([[40, 25, 55, 35]], [0], [0.87], "det")
    img = pictures.draw_sample(s, fourth=fourth, fourth_name="c2", categories=CATEGORIES, predictions=[pred], height=80)
    assert img.dtype == np.uint8 and img.shape[2] == 3
    assert img.shape[1] == 3 * 120 + 2 * 4  # three panels, twice the sample's size, 4 px apart
    for k in range(3):
        panel = _panel(img, k, 120, 80)
        # the GT box [10, 10, 30, 20] drawn at twice the size: its left edge at x = 20, its top at y = 20
        assert tuple(panel[30, 20]) == pictures.GT_COLOUR and tuple(panel[20, 40]) == pictures.GT_COLOUR
        assert tuple(panel[60, 80]) == pictures.PRED_COLOURS[0]  # the prediction's left edge (x 80, y 50..70)
    thermal = _panel(img, 1, 120, 80)[2:10, 90:118]  # 8-bit thermal (away from boxes): grey, no colour map
    assert (thermal[..., 0] == thermal[..., 1]).all() and (thermal[..., 1] == thermal[..., 2]).all()


def test_radiometric_thermal_is_a_colour_map_with_a_scale_bar():
    s = _sample(radiometric=True)
    assert pictures.thermal_range(s.thermal) == pytest.approx(
        (np.nanpercentile(s.thermal, 1), np.nanpercentile(s.thermal, 99))
    )
    with_bar = pictures.draw_sample(s, gt=None, height=80)
    plain = pictures.draw_sample(_sample(radiometric=False), gt=None, height=80)
    assert with_bar.shape[1] > plain.shape[1]  # the scale bar beside the thermal panel
    panel = with_bar[pictures.TITLE_H : pictures.TITLE_H + 80, 124:244]
    assert not (panel[..., 0] == panel[..., 2]).all()  # colours, not grey levels
    assert tuple(panel[0, 0]) == (128, 128, 128)  # the missing temperature is grey
    # hot (bottom rows) is brighter than cold (top rows) in the inferno colour map
    assert panel[70:, 30:90].astype(int).sum() > panel[5:15, 30:90].astype(int).sum()


def test_coco_boxes_and_thresholds():
    records = [
        {"image_id": 3, "category_id": 2, "bbox": [1, 2, 3, 4], "score": 0.9},
        {"image_id": 3, "category_id": 1, "bbox": [5, 5, 5, 5], "score": 0.2},
        {"image_id": 4, "category_id": 1, "bbox": [0, 0, 1, 1], "score": 0.5},
    ]
    b = pictures.coco_boxes(records, 3, "x")
    assert b.boxes.tolist() == [[1, 2, 4, 6], [5, 5, 10, 10]] and b.labels.tolist() == [1, 0]
    assert len(b.above(0.5)) == 1 and len(b.above(None)) == 2
    assert pictures.coco_boxes([{"image_id": 3, "category_id": 1, "bbox": [0, 0, 1, 1]}], 3).scores is None


def test_pictures_are_compressed_jpeg_or_palette_png(tmp_path):
    from PIL import Image

    img = pictures.draw_sample(_sample(), height=120)
    png8 = pictures.encode_image(img, "png", palette=True)
    full = pictures.encode_image(img, "png")
    jpeg = pictures.encode_image(img, "jpeg", quality=70)
    assert Image.open(io.BytesIO(png8)).mode == "P" and len(png8) < len(full)
    assert jpeg[:2] == b"\xff\xd8"
    path = pictures.save_image(img, tmp_path / "x.jpg")
    assert Image.open(path).size == (img.shape[1], img.shape[0])
    from harness.errors import ConfigError

    with pytest.raises(ConfigError, match="png or .jpg"):
        pictures.save_image(img, tmp_path / "x.gif")


def test_terminal_image_protocols():
    assert pictures.terminal_protocol({"TERM_PROGRAM": "iTerm.app"}) == "iterm2"
    assert pictures.terminal_protocol({"LC_TERMINAL": "iTerm2"}) == "iterm2"
    assert pictures.terminal_protocol({"TERM": "xterm-kitty"}) == "kitty"
    assert pictures.terminal_protocol({"TERM": "xterm-256color"}) is None
    png = pictures.encode_image(np.zeros((4, 4, 3), np.uint8), "png")
    seq = pictures.inline_image(png, "iterm2")
    assert seq.startswith("\033]1337;File=inline=1;size=") and seq.rstrip("\n").endswith("\a")
    assert base64.b64decode(seq.split(":", 1)[1].rstrip("\a\n")) == png
    big = bytes(range(256)) * 30  # 10,240 base64 characters: kitty takes 4,096 at a time, m=1 until the last
    chunks = pictures.inline_image(big, "kitty").rstrip("\n").split("\033\\")[:-1]
    assert len(chunks) == 3 and chunks[0].startswith("\033_Ga=T,f=100,m=1;") and chunks[-1].startswith("\033_Gm=0;")
    assert base64.b64decode("".join(c.split(";", 1)[1] for c in chunks)) == big


# ------------------------------------------------------------------------------------- harness show, FiftyOne
@pytest.fixture
def shapes(host, tmp_path, monkeypatch):
    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    with temporary_plugin(ShapesPlugin(), name="shapes-test"):
        yield host


def _fake_run(store, fold: str = "A", detector: str = "det", seed: int = 0, top: float | None = None):
    """A finished run of the shapes dataset made by hand: its held-out GT, one prediction per GT box (shifted by
    one pixel, score 0.9) and one false positive per image (score 0.1). ``top``: distinct scores instead, the
    boxes' from ``top`` down in steps of 0.001, the false positives' from 0.1 down in steps of 0.0001."""
    from harness.cache import prepare
    from harness.config import load_config
    from harness.evaluation import evaluate
    from harness.io import atomic_write_json
    from harness.plugins import get_host
    from harness.store import RunKey, Store

    spec = get_host().dataset("shapes")
    cfg = load_config(protocol=spec.protocol)
    prepared = prepare("shapes", cfg)
    idx = prepared.indices([fold])
    gt = prepared.coco(idx)
    dets = [
        {
            "image_id": a["image_id"],
            "category_id": a["category_id"],
            "score": 0.9,
            "bbox": [a["bbox"][0] + 1, a["bbox"][1], a["bbox"][2], a["bbox"][3]],
        }
        for a in gt["annotations"]
    ]
    dets += [{"image_id": im["id"], "category_id": 1, "score": 0.1, "bbox": [0, 0, 5, 5]} for im in gt["images"]]
    if top is not None:
        boxes = [d for d in dets if d["score"] == 0.9]
        for k, d in enumerate(boxes):
            d["score"] = round(top - 0.001 * k, 6)
        for k, d in enumerate(dets[len(boxes) :]):
            d["score"] = round(0.1 - 0.0001 * k, 6)
    run = Store(store).run(RunKey("shapes", detector, "test-ir8", fold, seed))
    run.path.mkdir(parents=True)
    if detector.startswith("external/"):  # as `harness score` stores it: no config.yaml, its identity in score.json
        identity = {"prepared_fingerprint": prepared.manifest["fingerprint"]}
        atomic_write_json(run.path / "score.json", {"identity": identity})
    else:
        cfg["meta"] = {"prepared_fingerprint": prepared.manifest["fingerprint"]}
        run.write_config(cfg)
    atomic_write_json(run.gt_path, gt)
    atomic_write_json(run.predictions_path, dets)
    ev = evaluate(gt, dets)
    run.write_metrics({k: ev[k] for k in ("support", "metrics", "per_category")})
    run.set_status("finished")
    return prepared, gt, ev


def test_harness_show_draws_a_prepared_sample_with_predictions(shapes, tmp_path, cli_runner, monkeypatch):
    from PIL import Image

    monkeypatch.chdir(tmp_path)  # the picture without --out lands in the current folder

    prepared, gt, ev = _fake_run(tmp_path / "store")
    iid = gt["images"][0]["id"]
    out = tmp_path / "s.png"
    res = cli_runner(
        [
            "show",
            "--dataset",
            "shapes",
            "--image-id",
            str(iid),
            "--store",
            str(tmp_path / "store"),
            "--detector",
            "det",
            "--height",
            "128",
            "--out",
            str(out),
        ]
    )
    assert res.exit_code == 0, res.output
    assert res.stdout.strip() == str(out)
    pic = np.asarray(Image.open(out).convert("RGB"))
    assert pic.shape[0] > 128 and pic.shape[1] >= 2 * 160  # RGB, thermal (8-bit here), test-ir8 channel
    # the prediction set is drawn in its own colour (its boxes at the operating point: the 0.9 ones)
    assert ev["metrics"]["conf_threshold"] == 0.9
    assert (np.abs(pic.astype(int) - pictures.PRED_COLOURS[0]).sum(axis=2) < 30).any()
    # without --out and without an image-drawing terminal: a file in the current folder, named after the sample
    res = cli_runner(["show", "--dataset", "shapes", "--index", "0", "--encoding", "test-none"])
    assert res.exit_code == 0 and res.stdout.strip() == "show_shapes_1.png"
    assert (tmp_path / "show_shapes_1.png").is_file()
    bad = cli_runner(["show", "--dataset", "shapes", "--image-id", "999"])
    assert bad.exit_code == 2 and "--image-id 999: not a sample of shapes" in bad.output
    none = cli_runner(
        ["show", "--dataset", "shapes", "--index", "0", "--store", str(tmp_path / "store"), "--detector", "other"]
    )
    assert none.exit_code == 2 and "no finished run of other on shapes" in none.output


def test_harness_show_draws_inline_in_a_terminal_that_draws_images(shapes, monkeypatch, capsys):
    from harness.config import load_config
    from harness.plugins import get_host
    from harness.report.show import show

    monkeypatch.delenv("TERM_PROGRAM", raising=False)
    monkeypatch.delenv("LC_TERMINAL", raising=False)
    monkeypatch.setenv("TERM", "xterm-kitty")
    shown = show("shapes", load_config(protocol=get_host().dataset("shapes").protocol), index=1, inline=True)
    assert shown.path is None and shown.protocol == "kitty" and shown.image_id == 2
    out = capsys.readouterr().out
    assert out.startswith("\033_Ga=T,f=100,") and out.rstrip("\n").endswith("\033\\")
