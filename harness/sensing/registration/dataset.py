"""A raw dataset's registration policy, per inspection group, for the adapters that align captures themselves.

In order, a group's homography is

1. the one in the homographies file named by ``sensing.registration.homographies`` (``SensingContext`` loads it);
2. the dataset's own homographies file;
3. a least-squares fit of the group's landmark pairs (at least 4; ``fit_landmarks``);
4. what ``sensing.registration.method`` says: ``auto`` (ECC on edges from the focal-length prior, checked),
   ``focal`` (the prior itself) or ``file`` (the pair is refused).

Convention: a dataset's homography maps *undistorted* RGB pixels of the calibration's camera matrix ``K`` (full
frame, OpenCV pixel centres) to thermal pixels, whatever ``sensing.undistort.alpha`` crops; without a calibration,
raw RGB pixels. It is converted here to the frame of ``undistort_image``'s output, and back when recorded.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from harness.errors import HarnessError
from harness.sensing.calibration import CameraModel, undistort_points, undistorted_camera
from harness.sensing.pipeline import SensingContext
from harness.sensing.registration.files import HomographyEntry, load_homographies, save_homographies
from harness.sensing.registration.homography import apply_homography, change_camera, focal_prior
from harness.sensing.registration.landmarks import fit_landmarks, read_landmarks

log = logging.getLogger(__name__)

#: The quality fields a dataset records per group (its prepare notes and the prepared homographies file).
RECORDED_QUALITY = ("pairs", "rms_px", "correlation")


class DatasetRegistration:
    """Each inspection group's homography for one dataset, put into ``ctx.entries`` on the group's first pair.

    ``homographies``/``landmarks``: the dataset's files (None when it has none); ``landmarks_rgb``: the frame of
    the landmarks' RGB points, ``"undistorted"`` (camera ``K``) or ``"raw"`` (the image as shot); ``group_of``:
    the group of each landmark's scene (an RGB file name), else the landmark's own group; ``focal_35mm``: the
    RGB and thermal cameras' 35-mm-equivalent focal lengths, for the prior.
    """

    def __init__(
        self,
        ctx: SensingContext,
        homographies: Path | None,
        landmarks: Path | None,
        landmarks_rgb: str,
        group_of: Mapping[str, str],
        focal_35mm: tuple[float, float],
    ):
        self.ctx = ctx
        self.homographies = load_homographies(homographies) if homographies is not None else {}
        self.landmarks = read_landmarks(landmarks) if landmarks is not None else None
        self.landmarks_rgb = landmarks_rgb
        self.group_of = dict(group_of)
        self.focal_35mm = focal_35mm
        self._new_cam: CameraModel | None = None
        self._tried: set[str] = set()

    # ---------------------------------------------------------------- frames
    @property
    def cameras(self) -> tuple[CameraModel, CameraModel] | None:
        """(the RGB calibration's camera ``K``, the camera of ``undistort_image``'s output ``K'``), or None without
        an RGB calibration."""
        cam = self.ctx.rgb_camera
        if cam is None:
            return None
        if self._new_cam is None:
            self._new_cam, _ = undistorted_camera(cam, float(self.ctx.options.undistort.alpha))
        return cam, self._new_cam

    def to_frame(self, h_k: np.ndarray) -> np.ndarray:
        """H on full-frame undistorted pixels (camera K) -> H on ``undistort_image``'s output (``K'``)."""
        cams = self.cameras
        return h_k if cams is None else change_camera(h_k, cams[0].K, cams[1].K)

    def to_k(self, h_new: np.ndarray) -> np.ndarray:
        cams = self.cameras
        return h_new if cams is None else change_camera(h_new, cams[1].K, cams[0].K)

    def _landmark_points(self, idx: list[int]) -> np.ndarray:
        """The landmarks' RGB points in the frame of ``undistort_image``'s output."""
        assert self.landmarks is not None
        pts = self.landmarks.rgb[idx]
        cams = self.cameras
        if cams is None:
            return pts
        if self.landmarks_rgb == "raw":
            return undistort_points(pts, cams[0], cams[1])
        return apply_homography(cams[1].K @ np.linalg.inv(cams[0].K), pts)

    # ---------------------------------------------------------------- per group
    def register_group(self, group: str) -> None:
        """Put the dataset's own registration of ``group`` (file, else landmarks) into the context, once."""
        if group in self._tried or group in self.ctx.entries:
            return
        self._tried.add(group)
        if group in self.homographies:
            self.ctx.entries[group] = HomographyEntry(self.to_frame(self.homographies[group]), "dataset file")
            return
        if self.landmarks is None:
            return
        lm = self.landmarks
        idx = [i for i, (scene, g) in enumerate(zip(lm.scene, lm.group)) if self.group_of.get(scene, g) == group]
        if len(idx) < 4:
            return
        try:
            fit = fit_landmarks(self._landmark_points(idx), lm.thermal[idx], method="lsq")
        except HarnessError as exc:
            log.warning("inspection group %s: landmarks give no homography (%s)", group, exc)
            return
        self.ctx.entries[group] = fit.entry()

    def prior(self, rgb_size: tuple[int, int], thermal_size: tuple[int, int]) -> np.ndarray:
        """Centres aligned, scale = thermal / RGB focal length; ``rgb_size`` is the image's before undistortion
        (the calibrated camera's focal length and frame replace it where there is one)."""
        cams = self.cameras
        if cams is None:
            return focal_prior(rgb_size, thermal_size, self.focal_35mm)
        return focal_prior(cams[1].image_size, thermal_size, self.focal_35mm, f_rgb_px=cams[1].fx)

    # ---------------------------------------------------------------- records
    @property
    def fitted(self) -> dict[str, np.ndarray]:
        """group -> the homography used, on full-frame undistorted pixels (camera K)."""
        return {g: self.to_k(e.H) for g, e in self.ctx.entries.items()}

    def how(self, group: str) -> dict[str, Any]:
        """Where the group's homography came from and its quality (``RECORDED_QUALITY``)."""
        e = self.ctx.entries.get(group)
        if e is None:
            return {}
        return {"source": e.method, **{k: v for k, v in (e.quality or {}).items() if k in RECORDED_QUALITY}}

    def notes(self) -> list[str]:
        """One line per registered group, for the prepare report."""
        return [
            f"registration of {g}: " + ", ".join(f"{k} {v}" for k, v in self.how(g).items())
            for g in sorted(self.ctx.entries)
        ]

    def save(self, path: Path, dataset: str) -> Path | None:
        """The homographies used, one per group (camera K frame), as a homographies file; None when there are none."""
        fitted = self.fitted
        if not fitted:
            return None
        entries = {}
        for g, h in sorted(fitted.items()):
            how = self.how(g)
            entries[g] = HomographyEntry(h, method=str(how.pop("source", "")), quality=how)
        frame = (
            "undistorted wide-camera pixels (calibration K) -> thermal pixels"
            if self.ctx.rgb_camera is not None
            else "RGB pixels -> thermal pixels"
        )
        return save_homographies(path, entries, meta={"frame": frame, "dataset": dataset})


#: how a homographies file's ``method`` names a registration route
ROUTE_NAMES = {
    "landmarks": "landmarks",
    "auto": "automatic",
    "focal": "prior",
    "dataset file": "file",
    "similarity": "similarity",
    "manual": "file",
}


def recorded_routes(folder: Path) -> dict[str, Any]:
    """The registration route a prepared dataset's samples were registered by, per inspection group: read from the
    ``homographies.yaml`` its raw-form adapter wrote beside the samples (``DatasetRegistration.save``).

    Returns ``{"route": one route or "mixed", "groups": {group: route}}``; a route is ``landmarks``, ``automatic``,
    ``prior``, ``file`` or ``similarity``. Without that file the samples came aligned (``route: "none (aligned by
    the dataset)"``, no groups)."""
    from harness.sensing.registration.files import load_homography_entries

    path = Path(folder) / "homographies.yaml"
    if not path.is_file():
        return {"route": "none (aligned by the dataset)", "groups": {}}
    groups = {g: ROUTE_NAMES.get(e.method, e.method) for g, e in sorted(load_homography_entries(path).items())}
    kinds = sorted(set(groups.values()))
    return {"route": kinds[0] if len(kinds) == 1 else "mixed", "groups": groups}
