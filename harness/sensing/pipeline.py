"""One capture through the whole sensing chain, driven by the ``sensing:`` config section.

What a dataset adapter calls once per RGB/thermal pair::

    ctx = SensingContext.from_config(cfg)                     # cameras and homographies loaded once
    pair = ctx.align_capture(rgb, temperature_c, ir8, boxes, labels, group, boxes_frame="thermal")
    sample = pair.to_sample(image_id, group, meta={"file_name": ...})

Order: undistortion of each sensor (the thermal correction goes to the temperature map and the preview alike;
boxes move with their frame), the group's homography (from the homographies file, else by
``sensing.registration.method``), then ``align_pair`` (warp RGB into the thermal frame, common support, crop, boxes).
Homographies are defined between the *undistorted* images when cameras are configured.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from harness.errors import DataError
from harness.sensing import registration as reg
from harness.sensing.calibration import CameraModel, undistort_boxes, undistort_image
from harness.sensing.options import SensingOptions
from harness.sensing.warp import AlignedPair, align_pair

log = logging.getLogger(__name__)


@dataclass
class SensingContext:
    options: SensingOptions = field(default_factory=SensingOptions)
    rgb_camera: CameraModel | None = None
    thermal_camera: CameraModel | None = None
    entries: dict[str, reg.HomographyEntry] = field(default_factory=dict)
    #: automatic registrations made on the fly, with their quality (for the prepare report)
    auto_results: dict[str, reg.AutoRegistration] = field(default_factory=dict)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any] | None, base: str | Path | None = None) -> "SensingContext":
        """Load the cameras and homographies the config names (relative paths resolved against ``base``)."""
        opts = SensingOptions.from_config(cfg)

        def path(p: str | None) -> Path | None:
            if p is None:
                return None
            q = Path(p).expanduser()
            return q if q.is_absolute() or base is None else Path(base) / q

        rgb_file = path(opts.undistort.rgb_camera) if opts.undistort.rgb_camera else None
        th_file = path(opts.undistort.thermal_camera) if opts.undistort.thermal_camera else None
        rgb_cam = CameraModel.load(rgb_file) if rgb_file else None
        th_cam = CameraModel.load(th_file) if th_file else None
        hfile = path(opts.registration.homographies)
        entries = reg.load_homography_entries(hfile) if hfile else {}
        return cls(opts, rgb_cam, th_cam, entries)

    # ------------------------------------------------------------------ steps
    def undistort_rgb(self, rgb: np.ndarray) -> tuple[np.ndarray, CameraModel | None]:
        if self.rgb_camera is None:
            return rgb, None
        out, new_cam, _ = undistort_image(rgb, self.rgb_camera, self.options.undistort.alpha)
        return out, new_cam

    def undistort_thermal(
        self, thermal: np.ndarray | None, ir8: np.ndarray
    ) -> tuple[np.ndarray | None, np.ndarray, CameraModel | None]:
        """The same geometric correction for the temperature map and the preview."""
        if self.thermal_camera is None:
            return thermal, ir8, None
        a = self.options.undistort.alpha
        ir8_u, new_cam, _ = undistort_image(ir8, self.thermal_camera, a)
        th_u = None if thermal is None else undistort_image(np.asarray(thermal, np.float32), self.thermal_camera, a)[0]
        return th_u, ir8_u, new_cam

    def homography(
        self, group: str, rgb: np.ndarray, thermal: np.ndarray, prior: np.ndarray | None = None
    ) -> np.ndarray:
        """The group's H: from the homographies file; else ``registration.method`` decides: ``auto`` registers
        this pair (from ``prior``, else the default start) and keeps the result for the group's later pairs;
        ``focal`` uses ``prior``; ``file`` is an error. A rejected automatic registration is an error naming the
        group (register it with landmarks or similarity parameters)."""
        if group in self.entries:
            return self.entries[group].H
        method = self.options.registration.method
        if method == "file":
            raise DataError(
                f"group {group!r} has no homography in {self.options.registration.homographies}; add it "
                "with `harness sensing register` or set sensing.registration.method to auto"
            )
        if method == "focal":
            if prior is None:
                raise DataError(f"group {group!r}: registration method 'focal' needs the focal-length prior")
            return reg.normalize(prior)
        if method != "auto":
            raise DataError(f"unknown sensing.registration.method {method!r}; use auto, focal or file")
        res = reg.estimate_homography_auto(rgb, thermal, init=prior, **self.options.registration.search())
        self.auto_results[group] = res
        if not res.ok:
            raise DataError(
                f"group {group!r}: automatic registration rejected ({res.reason}); register the group "
                "with landmarks or similarity parameters (`harness sensing register`)"
            )
        log.info("group %s registered automatically (structure correlation %.3f)", group, res.correlation)
        self.entries[group] = res.entry()
        return res.H

    def align_capture(
        self,
        rgb: np.ndarray,
        thermal: np.ndarray | None,
        ir8: np.ndarray,
        boxes: np.ndarray,
        labels: np.ndarray,
        group: str,
        boxes_frame: str = "thermal",
        prior: np.ndarray | None = None,
    ) -> AlignedPair:
        """Undistort both sensors, get the group's homography, and align (see the module docstring)."""
        rgb_u, rgb_cam = self.undistort_rgb(rgb)
        th_u, ir8_u, th_cam = self.undistort_thermal(thermal, ir8)
        b = np.asarray(boxes, dtype=np.float32).reshape(-1, 4)
        if boxes_frame == "rgb" and rgb_cam is not None:
            b = undistort_boxes(b, self.rgb_camera, rgb_cam)  # type: ignore[arg-type]
        elif boxes_frame == "thermal" and th_cam is not None:
            b = undistort_boxes(b, self.thermal_camera, th_cam)  # type: ignore[arg-type]
        H = self.homography(group, rgb_u, th_u if th_u is not None else ir8_u, prior)
        pair = align_pair(rgb_u, th_u, ir8_u, b, labels, H, boxes_frame=boxes_frame, **self.options.warp.arguments())
        # what maps an original image's pixels into the frame H starts from (for boxes made on the original images)
        for sensor, cam, new in (("rgb", self.rgb_camera, rgb_cam), ("thermal", self.thermal_camera, th_cam)):
            if cam is not None and new is not None:
                pair.cameras[sensor] = {"camera": cam.to_dict(), "undistorted": new.to_dict()}
        return pair


def read_capture_thermal(
    path: str | Path, options: SensingOptions | None = None
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """(temperature C float32, 8-bit preview, info) of a raw capture's thermal file, as the raw datasets and
    ``harness screen`` read it.

    An R-JPEG is decoded by ``options.decoder`` with ``options.measurement`` (``read_rjpeg``, ``rjpeg_temperature``)
    and its own palette picture is the preview, unless that picture is missing, undecodable or of another size (then
    ``ir8_from_temperature``); info: ``format``, ``params`` (the file's measurement parameters), ``decoder`` (the
    route taken), and ``approximate`` / ``converter`` where the file took one of those routes (``options``: its
    ``approximate`` flag and converter, as ``read_thermal`` takes them). Any other thermal file goes through
    ``read_thermal`` and its preview is ``ir8_from_temperature``.
    Errors are ``HarnessError``s naming the file (``ConfigError`` for a bad ``sensing.radiometry`` setting).
    """
    from harness.errors import HarnessError
    from harness.sensing.radiometry import read_rjpeg, read_thermal, rjpeg_temperature

    opts = options or SensingOptions()
    path = Path(path)
    if path.suffix.lower() not in (".jpg", ".jpeg"):
        temp, info = read_thermal(path, **opts.thermal_kwargs())
        return temp, ir8_from_temperature(temp), info
    rj = read_rjpeg(path, opts.decoder, opts.approximate, opts.converter_spec())
    temp, tinfo = rjpeg_temperature(rj, opts.measurement)
    try:
        ir8 = rj.preview(grayscale=True)
        if ir8.shape != temp.shape:
            ir8 = ir8_from_temperature(temp)
    except HarnessError:
        ir8 = ir8_from_temperature(temp)
    return (
        temp,
        ir8,
        {
            "format": "rjpeg",
            "params": dict(rj.params),
            "decoder": tinfo["decoder"],
            **{k: tinfo[k] for k in ("approximate", "converter") if k in tinfo},
        },
    )


def ir8_from_temperature(temp: np.ndarray, low: float = 1.0, high: float = 99.0) -> np.ndarray:
    """An 8-bit rendering of a temperature map: a percentile stretch (``low``..``high``) to 0..255, over the measured
    pixels; a missing one (NaN or inf) shows the median's level, like ``linear16``."""
    finite = np.isfinite(temp)
    if finite.all():
        lo, hi = np.percentile(temp, [low, high])
    else:
        lo, hi = np.percentile(temp[finite], [low, high])
        temp = np.where(finite, temp, np.median(temp[finite]))
    scale = 255.0 / max(float(hi - lo), 1e-3)
    return np.clip(np.rint((temp - lo) * scale), 0, 255).astype(np.uint8)
