"""Synthetic facade scenes for the sensing tests: one material map rendered twice, as a temperature map on the
thermal grid and as an RGB photo through a known homography (colours and temperatures unrelated per material,
as between the two real modalities)."""

from __future__ import annotations

import numpy as np

from harness.sensing.registration import homography_from_focal_lengths, homography_from_similarity, image_center

#: the RGB and thermal frame sizes of the scenes
SCENE_RGB, SCENE_TH = (480, 384), (160, 128)


def scene_truth() -> np.ndarray:
    """The true RGB -> thermal homography of the scenes: a similarity (shifted 3, -2 px, rotated 1.5 degrees, scale
    0.408) with a little perspective."""
    H = homography_from_similarity(3.0, -2.0, 1.5, 0.4 * 1.02, image_center(SCENE_RGB), image_center(SCENE_TH))
    H[2, 0] = 2e-5
    return H / H[2, 2]


def focal_prior() -> np.ndarray:
    """The prior the focal lengths give for the scenes: scale 0.4, centres aligned."""
    return homography_from_focal_lengths(1000.0, 400.0, SCENE_RGB, SCENE_TH)


def facade_labels(seed: int, width: int, height: int, up: int = 4) -> np.ndarray:
    """Material labels (0 wall, 1 floor band, 2-3 window glass, 4-5 round patches) at ``up`` x the thermal grid."""
    import cv2

    rng = np.random.default_rng(seed)
    H, W = height * up, width * up
    lab = np.zeros((H, W), np.int32)
    floors = int(rng.integers(3, 6))
    fh = H // floors
    for f in range(floors):
        lab[f * fh : f * fh + max(2, fh // 10)] = 1
    cols = int(rng.integers(4, 8))
    cw = W // cols
    for f in range(floors):
        for c in range(cols):
            if rng.random() < 0.2:
                continue
            ww, hh = int(cw * rng.uniform(0.35, 0.6)), int(fh * rng.uniform(0.35, 0.6))
            x0 = c * cw + int(rng.integers(2, cw - ww - 1))
            y0 = f * fh + fh // 5 + int(rng.integers(0, max(1, fh - hh - fh // 5 - 1)))
            lab[y0 : y0 + hh, x0 : x0 + ww] = 2 + int(rng.integers(0, 2))
    for _ in range(8):
        cx, cy = int(rng.integers(0, W)), int(rng.integers(0, H))
        cv2.circle(lab, (cx, cy), int(rng.integers(2 * up, 6 * up)), 4 + int(rng.integers(0, 2)), -1)
    return lab


def render_pair(
    seed: int,
    H_true: np.ndarray,
    rgb_size: tuple[int, int] = (480, 384),
    thermal_size: tuple[int, int] = (160, 128),
    up: int = 4,
) -> tuple[np.ndarray, np.ndarray]:
    """(rgb uint8 HxWx3, temperature float32) of one scene; RGB pixel p sees thermal point ``H_true p``."""
    import cv2

    rng = np.random.default_rng(seed + 100)
    tw, th = thermal_size
    lab = facade_labels(seed, tw, th, up)
    colours = rng.integers(0, 255, size=(6, 3)).astype(np.uint8)
    temps = rng.uniform(20, 30, size=6).astype(np.float32)
    thermal = cv2.resize(temps[lab], (tw, th), interpolation=cv2.INTER_AREA)
    thermal = thermal + rng.normal(0, 0.02, (th, tw)).astype(np.float32)
    # thermal pixel centre u sits at u * up + (up - 1) / 2 on the fine grid
    S = np.array([[up, 0, (up - 1) / 2], [0, up, (up - 1) / 2], [0, 0, 1.0]])
    rgb = cv2.warpPerspective(
        colours[lab], S @ H_true, rgb_size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT
    )
    rgb = np.clip(rgb.astype(np.float32) + rng.normal(0, 3, rgb.shape), 0, 255).astype(np.uint8)
    return rgb, thermal.astype(np.float32)
