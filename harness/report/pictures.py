"""Pictures of prepared samples: the channels side by side with ground truth and predictions drawn on each.

``draw_sample(sample, fourth=..., gt=..., predictions=[...])`` returns one RGB ``uint8`` image: the RGB, the
thermal image (temperature in °C as a colour map with a scale bar; grey levels for 8-bit thermal) and the fourth
channel (the encoding's, in grey), each under a title, the boxes of every box set drawn on every panel, and a
legend below. ``harness show`` calls it for one sample; a gallery calls it for many thumbnails (``height`` small,
saved with ``save_image`` as JPEG or 8-bit palette PNG, so that a report folder stays small).

Boxes are ``BoxSet``s in the sample's (prepared, thermal) frame, xyxy pixels; ``coco_boxes`` makes one from COCO
records (``gt.json`` annotations or ``predictions.json`` detections, ``category_id = label + 1``).

``inline_image`` shows a PNG in terminals that draw images (iTerm2's and kitty's inline image protocols);
``terminal_protocol`` says which one the current terminal speaks, if any.
"""

from __future__ import annotations

import base64
import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

#: colours (RGB): ground truth first, then one per prediction set
GT_COLOUR = (40, 220, 60)
PRED_COLOURS = ((255, 64, 64), (64, 160, 255), (255, 200, 0), (230, 80, 230), (0, 220, 220), (255, 140, 0))
NAN_COLOUR = (128, 128, 128)
THERMAL_PERCENTILES = (1.0, 99.0)  # the colour map's range: robust to a few hot or dead pixels
TITLE_H = 18
LABEL_LIMIT = 30  # boxes of a set above which no per-box labels are written (they would hide the image)


@dataclass
class BoxSet:
    """Boxes to draw: ``boxes`` [N, 4] xyxy in the sample's frame, 0-based ``labels``, optional ``scores``."""

    boxes: np.ndarray
    labels: np.ndarray
    scores: np.ndarray | None = None
    name: str = ""
    colour: tuple[int, int, int] | None = None

    def __post_init__(self) -> None:
        self.boxes = np.asarray(self.boxes, dtype=np.float64).reshape(-1, 4)
        self.labels = np.asarray(self.labels, dtype=np.int64).reshape(-1)
        if self.scores is not None:
            self.scores = np.asarray(self.scores, dtype=np.float64).reshape(-1)

    def __len__(self) -> int:
        return len(self.boxes)

    def above(self, threshold: float | None) -> "BoxSet":
        """Only the boxes scored at least ``threshold`` (all when None or unscored)."""
        if threshold is None or self.scores is None:
            return self
        keep = self.scores >= threshold
        return BoxSet(self.boxes[keep], self.labels[keep], self.scores[keep], self.name, self.colour)


def coco_boxes(
    records: Iterable[Mapping[str, Any]], image_id: Any, name: str = "", colour: tuple[int, int, int] | None = None
) -> BoxSet:
    """The COCO records (``bbox`` xywh, ``category_id`` = label + 1, optional ``score``) of one image as a BoxSet."""
    rows = [r for r in records if r.get("image_id") == image_id and not r.get("iscrowd")]
    boxes = np.array([[x, y, x + w, y + h] for x, y, w, h in (r["bbox"] for r in rows)], dtype=np.float64)
    labels = np.array([int(r["category_id"]) - 1 for r in rows], dtype=np.int64)
    scored = bool(rows) and all("score" in r for r in rows)
    scores = np.array([float(r["score"]) for r in rows]) if scored else None
    return BoxSet(boxes.reshape(-1, 4), labels, scores, name, colour)


# --------------------------------------------------------------------------------------------- panels
def _font(size: int) -> Any:
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def grey_panel(channel: np.ndarray) -> np.ndarray:
    """An 8-bit channel as an RGB image in grey levels."""
    c = np.asarray(channel, dtype=np.uint8)
    return np.repeat(c[:, :, None], 3, axis=2)


def thermal_range(thermal: np.ndarray) -> tuple[float, float] | None:
    """The colour map's range in °C: the 1st and 99th percentiles of the measured (finite) pixels."""
    t = np.asarray(thermal, dtype=np.float32)
    valid = t[np.isfinite(t)]
    if valid.size == 0:
        return None
    lo, hi = (float(v) for v in np.percentile(valid, THERMAL_PERCENTILES))
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    return lo, hi


def colour_map(values: np.ndarray) -> np.ndarray:
    """0..255 values -> RGB through the inferno colour map (OpenCV's)."""
    import cv2

    return cv2.applyColorMap(np.asarray(values, dtype=np.uint8), cv2.COLORMAP_INFERNO)[..., ::-1]


def thermal_panel(
    thermal: np.ndarray, span: tuple[float, float] | None = None
) -> tuple[np.ndarray, tuple[float, float]]:
    """Temperature in °C as an RGB colour-mapped image (missing pixels grey) and the range it maps."""
    t = np.asarray(thermal, dtype=np.float32)
    span = span or thermal_range(t) or (0.0, 1.0)
    lo, hi = span
    finite = np.isfinite(t)
    scaled = np.clip((np.where(finite, t, lo) - lo) / (hi - lo), 0.0, 1.0)
    img = colour_map(np.round(255.0 * scaled).astype(np.uint8)).copy()
    img[~finite] = NAN_COLOUR
    return img, span


def _resize(img: np.ndarray, height: int) -> np.ndarray:
    import cv2

    h, w = img.shape[:2]
    if h == height:
        return img
    width = max(1, int(round(w * height / h)))
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA if height < h else cv2.INTER_LINEAR)


def _scale_bar(height: int, span: tuple[float, float], font_size: int) -> np.ndarray:
    """A vertical colour bar (hot at the top) with its temperatures in °C."""
    from PIL import Image, ImageDraw

    bar_w, pad = max(8, height // 30), 4
    font = _font(font_size)
    labels = [f"{v:.1f} °C" for v in (span[1], (span[0] + span[1]) / 2, span[0])]
    text_w = max(int(font.getlength(s)) for s in labels)
    out = Image.new("RGB", (bar_w + text_w + 3 * pad, height), (255, 255, 255))
    ramp = np.linspace(255, 0, height).round().astype(np.uint8)[:, None].repeat(bar_w, axis=1)
    out.paste(Image.fromarray(np.ascontiguousarray(colour_map(ramp))), (pad, 0))
    draw = ImageDraw.Draw(out)
    for frac, text in zip((0.0, 0.5, 1.0), labels):
        y = int(round(frac * (height - font_size - 2)))
        draw.text((bar_w + 2 * pad, y), text, fill=(0, 0, 0), font=font)
    return np.asarray(out)


def _draw_boxes(
    panel: np.ndarray, sets: Sequence[BoxSet], scale: float, categories: Sequence[str], font_size: int
) -> np.ndarray:
    from PIL import Image, ImageDraw

    img = Image.fromarray(np.ascontiguousarray(panel))
    draw = ImageDraw.Draw(img)
    font = _font(font_size)
    line = 1 if panel.shape[0] < 200 else 2
    for s in sets:
        colour = s.colour or GT_COLOUR
        labelled = len(s) <= LABEL_LIMIT
        for k in range(len(s)):
            x1, y1, x2, y2 = (float(v) * scale for v in s.boxes[k])
            draw.rectangle([x1, y1, max(x2, x1 + 1), max(y2, y1 + 1)], outline=colour, width=line)
            if not labelled:
                continue
            lab = int(s.labels[k])
            text = categories[lab] if 0 <= lab < len(categories) else str(lab)
            if s.scores is not None:
                text = f"{text} {s.scores[k]:.2f}"
            if panel.shape[0] < 200:  # thumbnails: the score alone, or nothing for ground truth
                if s.scores is None:
                    continue
                text = f"{s.scores[k]:.2f}"
            tw = font.getlength(text)
            ty = y1 - font_size - 2 if y1 >= font_size + 2 else y2 + 1
            draw.rectangle([x1, ty, x1 + tw + 2, ty + font_size + 1], fill=colour)
            draw.text((x1 + 1, ty), text, fill=(0, 0, 0), font=font)
    return np.asarray(img)


def _titled(panel: np.ndarray, title: str, font_size: int) -> np.ndarray:
    from PIL import Image, ImageDraw

    h, w = panel.shape[:2]
    out = Image.new("RGB", (w, h + TITLE_H), (255, 255, 255))
    out.paste(Image.fromarray(np.ascontiguousarray(panel)), (0, TITLE_H))
    ImageDraw.Draw(out).text((3, 2), title, fill=(0, 0, 0), font=_font(font_size))
    return np.asarray(out)


def _legend(width: int, sets: Sequence[BoxSet], title: str, font_size: int) -> np.ndarray:
    from PIL import Image, ImageDraw

    out = Image.new("RGB", (width, font_size + 8), (255, 255, 255))
    draw = ImageDraw.Draw(out)
    font = _font(font_size)
    x = 4
    if title:
        draw.text((x, 3), title, fill=(0, 0, 0), font=font)
        x += int(font.getlength(title)) + 12
    for s in sets:
        text = f"{s.name or 'boxes'} ({len(s)})"
        draw.rectangle([x, 4, x + font_size, 4 + font_size], outline=s.colour or GT_COLOUR, width=2)
        draw.text((x + font_size + 4, 3), text, fill=(0, 0, 0), font=font)
        x += font_size + 16 + int(font.getlength(text))
    return np.asarray(out)


def _hstack(parts: Sequence[np.ndarray], gap: int = 4) -> np.ndarray:
    h = max(p.shape[0] for p in parts)
    cols = []
    for i, p in enumerate(parts):
        if p.shape[0] < h:
            p = np.concatenate([p, np.full((h - p.shape[0], p.shape[1], 3), 255, np.uint8)])
        cols.append(p)
        if i < len(parts) - 1:
            cols.append(np.full((h, gap, 3), 255, np.uint8))
    return np.concatenate(cols, axis=1)


def draw_sample(
    sample: Any,
    *,
    fourth: np.ndarray | None = None,
    fourth_name: str = "fourth channel",
    categories: Sequence[str] = (),
    gt: BoxSet | None | bool = True,
    predictions: Sequence[BoxSet] = (),
    height: int = 360,
    title: str = "",
    thermal_span: tuple[float, float] | None = None,
) -> np.ndarray:
    """One picture of an aligned sample (module docstring): RGB | thermal | fourth channel, boxes on each.

    ``gt=True`` draws the sample's own boxes, a ``BoxSet`` draws those instead, ``None``/``False`` none.
    ``predictions`` are drawn in order, each in its own colour unless it sets one. ``height`` is each panel's
    height in pixels; ``thermal_span`` fixes the colour map's range in °C (default: the sample's 1st-99th
    percentiles).
    """
    sets: list[BoxSet] = []
    if gt is True:
        gt = BoxSet(sample.boxes, sample.labels, None, "ground truth", GT_COLOUR)
    if isinstance(gt, BoxSet):
        sets.append(gt if gt.colour else BoxSet(gt.boxes, gt.labels, gt.scores, gt.name or "ground truth", GT_COLOUR))
    for k, p in enumerate(predictions):
        sets.append(
            p
            if p.colour
            else BoxSet(
                p.boxes, p.labels, p.scores, p.name or f"predictions {k + 1}", PRED_COLOURS[k % len(PRED_COLOURS)]
            )
        )
    h0 = int(sample.ir8.shape[0])
    scale = height / h0
    font_size = 11 if height < 200 else 13
    panels: list[tuple[np.ndarray, str, np.ndarray | None]] = [(np.asarray(sample.rgb), "RGB", None)]
    if sample.thermal is not None:
        img, span = thermal_panel(sample.thermal, thermal_span)
        panels.append((img, "thermal (°C)", _scale_bar(height, span, font_size)))
    else:
        panels.append((grey_panel(sample.ir8), "thermal (8-bit)", None))
    if fourth is not None:
        panels.append((grey_panel(fourth), fourth_name, None))
    parts = []
    for img, name, bar in panels:
        drawn = _draw_boxes(_resize(img, height), sets, scale, categories, font_size)
        if bar is not None:
            drawn = _hstack([drawn, bar], gap=2)
        parts.append(_titled(drawn, name, font_size))
    body = _hstack(parts)
    legend = _legend(body.shape[1], sets, title, font_size)
    return np.concatenate([body, legend], axis=0)


# --------------------------------------------------------------------------------------------- files
def encode_image(img: np.ndarray, fmt: str = "png", quality: int = 82, palette: bool = False) -> bytes:
    """``img`` (RGB uint8) as compressed bytes: ``jpeg`` (``quality``), or ``png``; ``palette=True`` makes the PNG
    an 8-bit palette image (PNG-8: about a third of the size, with visible banding in smooth gradients)."""
    from PIL import Image

    pil = Image.fromarray(np.ascontiguousarray(img))
    buf = io.BytesIO()
    fmt = fmt.lower()
    if fmt in ("jpg", "jpeg"):
        pil.save(buf, format="JPEG", quality=quality, optimize=True)
    elif fmt == "png":
        if palette:
            pil = pil.quantize(colors=256, method=Image.Quantize.MEDIANCUT)
        pil.save(buf, format="PNG", optimize=True)
    else:
        raise ValueError(f"unknown picture format {fmt!r}; use png or jpeg")
    return buf.getvalue()


def save_image(img: np.ndarray, path: str | Path, quality: int = 82, palette: bool = False) -> Path:
    """Write ``img`` to ``path`` atomically: JPEG for ``.jpg``/``.jpeg``, PNG for ``.png`` (PNG-8 with
    ``palette``)."""
    from harness.errors import ConfigError
    from harness.io import atomic_write_bytes

    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in ("png", "jpg", "jpeg"):
        raise ConfigError(f"{path}: write pictures as .png or .jpg")
    return atomic_write_bytes(path, encode_image(img, fmt, quality, palette))


# --------------------------------------------------------------------------------------------- terminals
def terminal_protocol(env: Mapping[str, str] | None = None) -> str | None:
    """``"iterm2"``, ``"kitty"`` or None: the inline image protocol the terminal running us speaks."""
    env = os.environ if env is None else env
    if env.get("TERM") == "xterm-kitty" or "KITTY_WINDOW_ID" in env or env.get("TERM_PROGRAM") == "ghostty":
        return "kitty"
    if env.get("TERM_PROGRAM") in ("iTerm.app", "WezTerm") or env.get("LC_TERMINAL") == "iTerm2":
        return "iterm2"
    return None


def inline_image(png: bytes, protocol: str) -> str:
    """The escape sequence that draws ``png`` inline: iTerm2's ``OSC 1337 File`` or kitty's graphics protocol."""
    data = base64.standard_b64encode(png).decode("ascii")
    if protocol == "iterm2":
        return f"\033]1337;File=inline=1;size={len(png)};preserveAspectRatio=1:{data}\a\n"
    if protocol == "kitty":
        chunks = [data[i : i + 4096] for i in range(0, len(data), 4096)] or [""]
        out = []
        for i, chunk in enumerate(chunks):
            more = int(i < len(chunks) - 1)
            head = f"a=T,f=100,m={more}" if i == 0 else f"m={more}"
            out.append(f"\033_G{head};{chunk}\033\\")
        return "".join(out) + "\n"
    raise ValueError(f"unknown inline image protocol {protocol!r}")
