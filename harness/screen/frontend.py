"""The front end of a screen: one capture through the sensing pipeline and the encoding a run was trained with.

Every step is the one the raw datasets use (``harness.sensing``), driven by the run's stored ``sensing`` section:

1. **decode**: the thermal file by ``read_capture_thermal`` (DJI R-JPEG routes, temperature in C, the preview);
   the wide JPEG by OpenCV, at a reduced scale when the warp would shrink it anyway (below);
2. **undistort and register** through ``SensingContext.align_capture``: undistortion of each sensor, then the
   capture's homography by the first route that applies (recorded per frame):

   * ``file``: the ``--homography`` file (a homographies YAML, e.g. the ``homographies.yaml`` a prepared dataset
     holds: full-frame undistorted wide pixels of the calibration's ``K`` -> thermal pixels);
   * ``auto (group G)``: the inspection group's automatic registration, pooled over its captures
     (``register_group``, ``harness.sensing.registration.pooled``) and handed to each of them (``given``), as the
     datasets register one homography per group; when the group's check rejects it the group's frames are listed
     and, by ``fallback``, screened with the prior (``prior (automatic registration rejected)``, with the error the
     prior is expected to have) or not screened at all;
   * ``auto``: with ``register="frame"``, automatic registration (ECC) of the capture alone from the factory prior,
     with its single-frame check (``sensing.registration``), the prior when that fails;
   * ``prior``: the cameras' factory prior (35-mm focal lengths from the EXIF, centres aligned), when the run's
     ``sensing.registration.method`` is ``focal``;

   then the warp of RGB into the thermal frame and the common-support crop (``align_pair``);
3. **fourth channel**: the run's encoding with its parameters, ``[R, G, B, channel]`` as ``SampleSource`` stacks
   it.

**Reduced decoding.** The warp anti-aliases a wide image it shrinks by ``f >= 2`` with a Gaussian pyramid, one
halving per octave. A JPEG can be decoded straight at 1/2, 1/4 or 1/8 of its size through its DCT
(``cv2.IMREAD_REDUCED_COLOR_*``), which skips most of the inverse DCT and shrinks every later step; only the
entropy decoding of the whole file remains. ``rgb_decode="auto"`` decodes a wide image the warp shrinks by
``f < 2.2`` (``2 REDUCTION_MARGIN``) in full, as shot (the synthetic M3T profiles: 1.7x), and any other at the
smallest ``1 / r``, ``r = 2^k <= 8``, that keeps ``f / r >= MIN_SAMPLING`` (0.85) wide pixels per thermal pixel
(and divides the image size), where ``f`` is the wide pixels per thermal pixel at the thermal centre under the
file's homography or the factory prior: the real M3T (4000x3000 beside 640x512, ``f`` about 3.6) at 1/4, about 0.9
pixel per thermal pixel, which the warp enlarges slightly instead of shrinking. The whole chain then runs on the
reduced image (the calibration through ``CameraModel.scaled``, the homography and the prior, both defined on the
full image, through the change of pixel grid), so only the low-pass filter differs (the DCT's instead of the
pyramid's and the warp's Gaussian): findings agree within the tolerance ``docs/screening.md`` states, which also
gives the measured difference of the model input; ``rgb_decode="full"`` is bit-identical to the training data.

**Speed.** Each file's header is read once (``read_header``: the end marker by the file's end), the wide JPEG is
decoded straight to RGB order, the undistortion maps are built once per calibration
(``harness.sensing.calibration``), and ``job`` runs the front end of the next capture in a thread while the model
works on this one (OpenCV, NumPy and the model release the GIL). The timings in ``Frame.timings`` are the wall
clock and the CPU time of the thread that ran each step.
"""

from __future__ import annotations

import hashlib
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from harness.contracts import encode
from harness.errors import ConfigError, DataError, HarnessError
from harness.screen.flight import Capture
from harness.screen.position import Position, capture_position
from harness.sensing import jpeg

log = logging.getLogger(__name__)

RGB_DECODES = ("auto", "full")
FALLBACKS = ("prior", "skip")
REGISTER = ("group", "frame")
#: the largest DCT reduction OpenCV decodes
MAX_REDUCTION = 8
#: a wide image the warp shrinks by less than twice this is decoded in full: taken as shot, as the training data was
REDUCTION_MARGIN = 1.1
#: any other is decoded at the smallest scale that keeps at least this many pixels per thermal pixel
MIN_SAMPLING = 0.85
_IMREAD_REDUCED = {2: "IMREAD_REDUCED_COLOR_2", 4: "IMREAD_REDUCED_COLOR_4", 8: "IMREAD_REDUCED_COLOR_8"}


#: frames of an inspection group its pooled automatic registration looks at (spread evenly over the group)
POOLED_FRAMES = 24
#: the route of a frame screened with the factory prior after its automatic registration was rejected
REJECTED_ROUTE = "prior (automatic registration rejected)"


class RegistrationRejected(HarnessError):
    """The automatic registration of a capture failed its quality check and ``fallback`` is ``skip``."""


@dataclass(frozen=True)
class FrontEndSettings:
    """What the front end needs, all plain values (it travels to worker processes).

    ``sensing``: the run's ``sensing`` section; ``encoding``/``encoding_params``: the run's encoding;
    ``rgb_camera``/``thermal_camera``: ``CameraModel.to_dict()`` of the calibrations the run's data was undistorted
    with (None: none); ``homography``: ``{"H": 3x3 list, "method", "source"}`` from ``--homography`` (full-frame
    undistorted wide pixels of ``K`` -> thermal pixels), or None; ``focal_35mm``: (wide, thermal) 35-mm-equivalent
    focal lengths when the files' EXIF lacks them.
    """

    sensing: Mapping[str, Any]
    encoding: str
    encoding_params: Mapping[str, Any] = field(default_factory=dict)
    rgb_camera: Mapping[str, Any] | None = None
    thermal_camera: Mapping[str, Any] | None = None
    homography: Mapping[str, Any] | None = None
    fallback: str = "prior"
    rgb_decode: str = "auto"
    focal_35mm: tuple[float, float] | None = None
    register: str = "group"

    def check(self) -> None:
        if self.register not in REGISTER:
            raise ConfigError(f"--register {self.register!r}: use one of {', '.join(REGISTER)}")
        if self.fallback not in FALLBACKS:
            raise ConfigError(f"--fallback {self.fallback!r}: use one of {', '.join(FALLBACKS)}")
        if self.rgb_decode not in RGB_DECODES:
            raise ConfigError(f"--rgb-decode {self.rgb_decode!r}: use one of {', '.join(RGB_DECODES)}")
        from harness.sensing.options import SensingOptions

        method = SensingOptions.from_config(dict(self.sensing)).registration.method
        if method not in ("auto", "focal", "file"):
            raise ConfigError(f"the run's sensing.registration.method is {method!r}; expected auto, focal or file")
        if method == "file" and self.homography is None:
            raise ConfigError(
                "the run registered every group from a homographies file "
                "(sensing.registration.method: file); give the flight's with --homography FILE"
            )


@dataclass
class Frame:
    """One capture after the front end: the model's input and what the findings are computed from."""

    capture: Capture
    image: np.ndarray  # uint8 H x W x (3 + k): [R, G, B, channel] in the aligned (cropped thermal) frame
    thermal: np.ndarray  # float32 H x W temperature in C, the same frame
    origin: tuple[int, int]  # crop origin in the (undistorted) thermal frame
    H: np.ndarray  # decoded (reduced, undistorted) wide pixels -> aligned frame
    cameras: dict[str, Any]  # AlignedPair.cameras: the undistortion applied before H, per sensor
    reduction: int  # the wide image was decoded at 1 / reduction
    rgb_size: tuple[int, int]  # the wide image as shot (w, h)
    thermal_size: tuple[int, int]  # the thermal map as shot (w, h)
    route: str
    registration: dict[str, Any]
    position: Position
    fingerprints: dict[str, str]
    thermal_decoder: str
    #: seconds per step: wall clock (``decode``, ``align``, ``encode``) and CPU time of the thread that ran it
    #: (``*_cpu``; the front end's OpenCV calls run on one thread, ``job`` sees to it)
    timings: dict[str, float] = field(default_factory=dict)
    #: an accepted automatic registration (full-frame undistorted wide pixels of K -> thermal), for the other
    #: captures of its inspection group; None for every other route
    registered: dict[str, Any] | None = None
    #: how the temperatures were decoded (``harness.sensing.radiometry.route_meta``): empty for DJI's exact
    #: correction and for decoded temperature files; ``thermal_route`` otherwise, and for the approximate route
    #: ``temperatures`` ("approximate temperatures"), ``temperature_bound_c`` and ``approximation``
    temperatures: dict[str, Any] = field(default_factory=dict)

    @property
    def approximate_bound_c(self) -> float | None:
        """The measured bound of approximate temperatures (C), None when they are not approximate."""
        if self.temperatures.get("thermal_route") != "approximate":
            return None
        return float(self.temperatures["temperature_bound_c"])

    @property
    def rgb(self) -> np.ndarray:
        return self.image[:, :, :3]


#: how the reason for a wide image of another size than its calibration starts (``job`` lists them once per size)
SIZE_MISMATCH = "RGB size mismatch"


def size_mismatch(image: tuple[int, int], calibration: tuple[int, int]) -> str:
    """The reason a wide image of ``image`` size cannot be undistorted with a calibration of ``calibration`` size
    (the same text for every image of that size)."""
    return (
        f"{SIZE_MISMATCH}: the image is {image[0]}x{image[1]}, the wide-camera calibration is for "
        f"{calibration[0]}x{calibration[1]}; give the calibration of the camera that took these images with "
        "--rgb-camera FILE (sensing calibrate makes one)"
    )


#: advice of the decoder's refusals that names an option ``harness sensing decode`` takes and ``screen`` does not
#: (a screen decodes with the run's ``sensing.radiometry.decoder``: the temperatures its model learnt from)
_DECODE_ONLY_ADVICE = "; uncorrected (blackbody) temperatures only with --decoder blackbody"


def screen_refusal(text: str) -> str:
    """A thermal decoder's refusal as ``screen`` gives it: the routes it names (``--converter``, ``--dji-irp``,
    ``--approximate``) are options of ``screen`` too; advice for ``sensing decode`` alone is left out."""
    return text.replace(_DECODE_ONLY_ADVICE, "")


def sha1_bytes(data: bytes) -> str:
    return hashlib.sha1(data).hexdigest()


def _read(path: Path) -> bytes:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if not data:
        raise DataError(f"{path}: empty file (0 bytes): nothing was copied into it; copy it again from the card")
    return data


#: the bytes of a JPEG the header is first looked for in (DJI's EXIF, XMP and maker segments take well under this)
HEADER_BYTES = 256 * 1024


def read_header(data: bytes, name: Path) -> jpeg.JpegLayout:
    """``jpeg.read_segments(data, name)`` (the header segments and frame size; a cut file is a ``DataError``)
    without its pass over the whole entropy-coded data when the file ends with an EOI marker (``FF D9``).

    Inside entropy-coded data every ``FF`` byte is followed by ``00`` or a restart marker, so a file ending in
    ``FF D9`` has a main picture that was ended by a marker, not cut; its header is then read from the first
    ``HEADER_BYTES`` alone. Otherwise (trailing data after the picture, a header larger than that) the whole file is
    read as before. Only ``segments``, ``width``, ``height`` and ``components`` of the answer are meant to be used:
    ``end`` is that of the first bytes."""
    if not data.startswith(b"\xff\xd8"):
        raise DataError(
            f"{name}: not a JPEG file (starts with {data[:8].hex(' ') or 'nothing'}, expected ff d8); the wide "
            "image of a capture is the JPEG the drone's wide camera wrote"
        )
    if len(data) > HEADER_BYTES and data.endswith(b"\xff\xd9"):
        try:
            return jpeg.read_segments(data[:HEADER_BYTES] + b"\xff\xd9", name)
        except DataError:
            pass
    return jpeg.read_segments(data, name)


def _focal_35mm(layout: jpeg.JpegLayout) -> float | None:
    for payload in layout.payloads(jpeg.APP1):
        exif = jpeg.parse_exif(payload)
        if exif:
            value = exif.get("FocalLengthIn35mmFilm")
            return float(value) if isinstance(value, (int, float)) and value > 0 else None
    return None


def _imread_flag(reduction: int) -> tuple[int, bool]:
    """(OpenCV's imread flag for a decode at ``1 / reduction``, whether it gives RGB order): libjpeg-turbo writes
    R, G, B straight out (OpenCV >= 4.10), the same values as BGR reversed, without the copy."""
    import cv2

    flag = cv2.IMREAD_COLOR if reduction == 1 else getattr(cv2, _IMREAD_REDUCED[reduction])
    rgb = getattr(cv2, "IMREAD_COLOR_RGB", None)
    if rgb is None:
        return flag, False
    return (flag & ~cv2.IMREAD_COLOR) | rgb, True


def decode_rgb(data: bytes, name: Path, reduction: int = 1) -> np.ndarray:
    """The wide JPEG as uint8 RGB, decoded at ``1 / reduction`` (1, 2, 4 or 8) through the JPEG's DCT."""
    import cv2

    flag, rgb_order = _imread_flag(reduction)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flag)
    if img is None:
        raise DataError(f"{name}: RGB unreadable: not a decodable image")
    return img if rgb_order else np.ascontiguousarray(img[:, :, ::-1])


def source_scale(H: np.ndarray, thermal_size: tuple[int, int]) -> float:
    """Wide pixels per thermal pixel at the thermal frame's centre under ``H`` (wide -> thermal)."""
    from harness.sensing.registration import apply_homography

    cx, cy = (thermal_size[0] - 1) / 2.0, (thermal_size[1] - 1) / 2.0
    pts = apply_homography(np.linalg.inv(H), np.array([[cx, cy], [cx + 1.0, cy], [cx, cy + 1.0]]))
    jac = np.stack([pts[1] - pts[0], pts[2] - pts[0]])
    return math.sqrt(abs(float(np.linalg.det(jac))))


def reduction_for(factor: float, rgb_size: tuple[int, int]) -> int:
    """The DCT reduction ``r`` (1, 2, 4, 8) for a warp that shrinks the wide image by ``factor``: 1 below
    ``2 REDUCTION_MARGIN``, else the largest with ``factor / r >= MIN_SAMPLING`` (and the size divisible by it)."""
    r = 1
    if factor / 2 < REDUCTION_MARGIN:
        return r
    while (
        2 * r <= MAX_REDUCTION
        and factor / (2 * r) >= MIN_SAMPLING
        and rgb_size[0] % (2 * r) == 0
        and rgb_size[1] % (2 * r) == 0
    ):
        r *= 2
    return r


def scale_change(reduction: int) -> np.ndarray:
    """Pixels of an image decoded at ``1 / reduction`` -> pixels of the full image (pixel-centre convention:
    ``x_full + 0.5 = r (x_reduced + 0.5)``)."""
    r = float(reduction)
    return np.array([[r, 0.0, (r - 1) / 2], [0.0, r, (r - 1) / 2], [0.0, 0.0, 1.0]])


class FrontEnd:
    """Captures -> ``Frame``s (see the module docstring). Build one per process from ``FrontEndSettings``."""

    def __init__(self, settings: FrontEndSettings, encoding: Any = None):
        from harness.sensing.calibration import CameraModel
        from harness.sensing.options import SensingOptions

        settings.check()
        self.settings = settings
        self.options = SensingOptions.from_config(dict(settings.sensing))
        self.rgb_camera = (
            CameraModel.from_dict(dict(settings.rgb_camera), "rgb camera") if settings.rgb_camera else None
        )
        self.thermal_camera = (
            CameraModel.from_dict(dict(settings.thermal_camera), "thermal camera") if settings.thermal_camera else None
        )
        if encoding is None:
            from harness.plugins import get_host

            encoding = get_host().encoding(settings.encoding)
        self.encoding = encoding
        self.homography = np.asarray(settings.homography["H"], np.float64) if settings.homography else None

    # ------------------------------------------------------------------ pieces
    def _context(self, reduction: int, rgb_size: tuple[int, int]) -> tuple[Any, Any]:
        """A fresh ``SensingContext`` for the wide image decoded at ``1 / reduction`` and its
        ``DatasetRegistration`` (the prior and the frame conversions of the dataset adapters)."""
        from harness.sensing.pipeline import SensingContext
        from harness.sensing.registration.dataset import DatasetRegistration

        cam = self.rgb_camera
        if cam is not None and reduction != 1:
            cam = cam.scaled((rgb_size[0] // reduction, rgb_size[1] // reduction))
        ctx = SensingContext(self.options, cam, self.thermal_camera)
        return ctx, DatasetRegistration(ctx, None, None, "undistorted", {}, (1.0, 1.0))

    @staticmethod
    def _to_frame(H_k: np.ndarray, dreg: Any, reduction: int) -> np.ndarray:
        """A homography on full-frame undistorted wide pixels (camera K, full size) in the frame
        ``align_capture`` registers (the decoded size, ``undistort_image``'s output)."""
        return dreg.to_frame(np.asarray(H_k, np.float64) @ scale_change(reduction))

    @staticmethod
    def _to_k(H_frame: np.ndarray, dreg: Any, reduction: int) -> np.ndarray:
        """The inverse of ``_to_frame``."""
        return dreg.to_k(H_frame) @ np.linalg.inv(scale_change(reduction))

    def _check_rgb_size(self, rgb_size: tuple[int, int], name: Path) -> None:
        cam = self.rgb_camera
        if cam is not None and cam.image_size != rgb_size:
            raise DataError(f"{name}: {size_mismatch(rgb_size, cam.image_size)}")

    def _focal(self, rgb_layout: jpeg.JpegLayout, thermal_layout: jpeg.JpegLayout | None) -> tuple[float, float] | None:
        f_rgb = _focal_35mm(rgb_layout)
        f_th = _focal_35mm(thermal_layout) if thermal_layout is not None else None
        given = self.settings.focal_35mm
        if f_rgb is None and given:
            f_rgb = given[0]
        if f_th is None and given:
            f_th = given[1]
        return (f_rgb, f_th) if f_rgb and f_th else None

    # ------------------------------------------------------------------ an inspection group
    def _registration_input(self, cap: Capture) -> tuple[np.ndarray, np.ndarray, np.ndarray, Any, int, tuple]:
        """(undistorted wide image, undistorted thermal map or preview, the factory prior in their frame, the
        frame conversions, decode reduction, (wide size, thermal size)) of one capture, as ``process`` makes them."""
        from harness.sensing.pipeline import read_capture_thermal

        rgb_data = _read(cap.rgb)
        layout = read_header(rgb_data, cap.rgb)
        rgb_size = (layout.width, layout.height)
        self._check_rgb_size(rgb_size, cap.rgb)
        thermal_data = _read(cap.thermal)
        temp, ir8, _ = read_capture_thermal(cap.thermal, self.options)
        th, tw = temp.shape
        is_jpeg = cap.thermal.suffix.lower() in (".jpg", ".jpeg")
        th_layout = jpeg.read_segments(thermal_data, cap.thermal, require_eoi=False) if is_jpeg else None
        focal = self._focal(layout, th_layout)
        if focal is None:
            raise DataError(
                f"{cap.rgb}: no 35-mm focal length in the EXIF of the wide or thermal image, so no "
                "factory prior; give --focal-35mm WIDE,THERMAL or --homography FILE"
            )
        _, full_reg = self._context(1, rgb_size)
        full_reg.focal_35mm = focal
        prior_full = full_reg.prior(rgb_size, (tw, th))
        reduction = 1
        if self.settings.rgb_decode == "auto":
            reduction = reduction_for(source_scale(prior_full, (tw, th)), rgb_size)
        rgb = decode_rgb(rgb_data, cap.rgb, reduction)
        ctx, dreg = self._context(reduction, rgb_size)
        prior = prior_full
        if reduction != 1:
            prior = self._to_frame(self._to_k(prior_full, full_reg, 1), dreg, reduction)
        rgb_u, _ = ctx.undistort_rgb(rgb)
        th_u, ir8_u, _ = ctx.undistort_thermal(temp, ir8)
        return rgb_u, (th_u if th_u is not None else ir8_u), prior, dreg, reduction, (rgb_size, (tw, th))

    def register_group(self, caps: Sequence[Capture], name: str = "") -> tuple[dict[str, Any], tuple[int, int]]:
        """One automatic registration for the captures of an inspection group, pooled over them
        (``harness.sensing.registration.pooled.register_pooled``, at most ``POOLED_FRAMES`` of them, spread evenly
        in the order given); returns what ``process`` takes as ``given`` for each of them, and the thermal size.

        ``given``: ``H`` (full-frame undistorted wide pixels of K -> thermal), ``prior`` (the same for the factory
        prior), ``route`` (``auto (group NAME)``, or ``prior (automatic registration rejected)`` when the group's
        evidence fails: then ``H`` is the prior), ``registration`` (``ok`` and the pooled quality; on a failure the
        reason and the error the prior is expected to have). A capture that cannot be read gives no evidence (it
        fails on its own later); a group of which none can be read raises its ``DataError``."""
        from harness.sensing.registration.pooled import evenly, register_pooled

        o = self.options.registration
        pairs, first, error = [], None, None
        for i in evenly(len(caps), POOLED_FRAMES):
            try:
                rgb_u, th_u, prior, dreg, reduction, sizes = self._registration_input(caps[i])
            except ConfigError:
                raise
            except HarnessError as exc:
                error = error or exc
                continue
            except Exception as exc:  # noqa: BLE001 - a damaged file can make a decoder library raise anything
                error = error or DataError(f"{caps[i].rgb}: {type(exc).__name__}: {exc}")
                continue
            if first is None:
                first = (prior, dreg, reduction, sizes)
            elif sizes != first[3] or not np.array_equal(prior, first[0]):
                log.warning(
                    "%s: other image sizes or focal lengths than the rest of its inspection group; left out "
                    "of the group's registration",
                    caps[i].rgb,
                )
                continue
            pairs.append((rgb_u, th_u))
        if first is None:
            raise error if error is not None else DataError("an empty inspection group")
        prior, dreg, reduction, sizes = first
        res = register_pooled(
            pairs,
            prior,
            max_frames=POOLED_FRAMES,
            min_correlation=o.min_correlation,
            max_corner_shift=o.max_corner_shift,
        )
        quality = {"ok": res.ok, **res.quality()}
        if res.ok:
            log.info(
                "inspection group %s registered automatically from %d frame(s) (%d agreeing, pooled "
                "correlation %.3f, prior %.3f)",
                name,
                res.frames,
                res.agreeing,
                res.correlation,
                res.prior_correlation,
            )
        else:
            log.warning(
                "inspection group %s: automatic registration rejected (%s); screened with the factory "
                "prior, expected error about %s px",
                name,
                res.reason,
                res.expected_error_px,
            )
        given = {
            "H": self._to_k(res.H, dreg, reduction).tolist(),
            "prior": self._to_k(prior, dreg, reduction).tolist(),
            "registration": quality,
            "route": f"auto (group {name})" if res.ok else REJECTED_ROUTE,
            "group": name,
            "capture": None,
            "members": [c.name for c in caps],  # what it was pooled over: a re-run reuses it for these alone
        }
        return given, sizes[1]

    # ------------------------------------------------------------------ one capture
    def process(self, cap: Capture, image_id: int = 0, given: Mapping[str, Any] | None = None) -> Frame:
        """Decode, undistort, register, warp, crop and encode one capture. Bad files raise a ``HarnessError``
        naming the file; a rejected registration with ``fallback="skip"`` raises ``RegistrationRejected``.

        ``given``: the registration of the capture's inspection group (``register_group``, with a ``route`` label),
        used instead of registering this one."""
        from harness.sensing.pipeline import read_capture_thermal
        from harness.sensing.radiometry import route_meta
        from harness.sensing.registration import HomographyEntry, normalize

        t0, c0 = time.perf_counter(), time.thread_time()
        rgb_data = _read(cap.rgb)
        layout = read_header(rgb_data, cap.rgb)  # a cut file is an error here, not a half-grey image
        rgb_size = (layout.width, layout.height)
        self._check_rgb_size(rgb_size, cap.rgb)
        thermal_data = _read(cap.thermal)
        is_jpeg = cap.thermal.suffix.lower() in (".jpg", ".jpeg")
        try:
            temp, ir8, info = read_capture_thermal(cap.thermal, self.options)
        except ConfigError:
            raise
        except HarnessError as exc:
            text = screen_refusal(str(exc))
            raise DataError(text if str(cap.thermal) in text else f"{cap.thermal}: {text}") from None
        if not np.isfinite(temp).all():
            from harness.sensing.c2 import valid_mask

            valid_mask(temp, str(cap.thermal))  # mostly missing: an error naming the file; a few stay NaN
        th, tw = temp.shape
        # each file's header segments are read once (finding where a 12-megapixel scan ends takes milliseconds)
        th_layout = jpeg.read_segments(thermal_data, cap.thermal, require_eoi=False) if is_jpeg else None
        position = capture_position(
            (rgb_data, str(cap.rgb), layout),
            (thermal_data, str(cap.thermal), th_layout) if th_layout is not None else None,
        )
        focal = self._focal(layout, th_layout)

        # the factory prior, defined on the full image (the frame the training data was registered in)
        _, full_reg = self._context(1, rgb_size)
        prior_full = None
        if focal is not None:
            full_reg.focal_35mm = focal
            prior_full = full_reg.prior(rgb_size, (tw, th))
        # the scale the warp shrinks the wide image by decides the decode
        if given is not None and (given.get("registration") or {}).get("ok") is False:
            if self.settings.fallback == "skip":
                reason = given["registration"].get("reason", "")
                raise RegistrationRejected(f"{cap.rgb}: automatic registration rejected ({reason})")
        fixed = self.homography if given is None else np.asarray(given["H"], np.float64)
        if fixed is not None:
            H_full = self._to_frame(fixed, full_reg, 1)
        elif prior_full is not None:
            H_full = prior_full
        else:
            raise DataError(
                f"{cap.rgb}: no 35-mm focal length in the EXIF of the wide or thermal image, so no "
                "factory prior; give --focal-35mm WIDE,THERMAL or --homography FILE"
            )
        reduction = 1
        if self.settings.rgb_decode == "auto":
            reduction = reduction_for(source_scale(H_full, (tw, th)), rgb_size)
        rgb = decode_rgb(rgb_data, cap.rgb, reduction)
        fingerprints = {"rgb": sha1_bytes(rgb_data), "thermal": sha1_bytes(thermal_data)}
        t1, c1 = time.perf_counter(), time.thread_time()

        ctx, dreg = self._context(reduction, rgb_size)
        prior = prior_full
        if prior_full is not None and reduction != 1:
            prior = self._to_frame(self._to_k(prior_full, full_reg, 1), dreg, reduction)
        group = cap.name
        method = self.options.registration.method
        route, quality = ("auto" if method == "auto" else "prior"), {}
        registered: dict[str, Any] | None = None
        if fixed is not None:
            ctx.entries[group] = HomographyEntry(self._to_frame(fixed, dreg, reduction), "given")
            if given is not None:
                route, quality = str(given.get("route", "given")), dict(given.get("registration") or {})
                if given.get("group") is not None:  # a pooled group registration: kept for a re-run's frames
                    registered = dict(given)
            else:
                route = "file"
        boxes, labels = np.zeros((0, 4), np.float32), np.zeros(0, np.int64)
        try:
            pair = ctx.align_capture(rgb, temp, ir8, boxes, labels, group, boxes_frame="thermal", prior=prior)
            res = ctx.auto_results.get(group)
            if res is not None:
                quality = {"ok": True, **res.quality()}
                registered = {
                    "H": self._to_k(res.H, dreg, reduction).tolist(),
                    "registration": quality,
                    "capture": cap.name,
                }
        except DataError as exc:
            res = ctx.auto_results.get(group)
            if res is None or res.ok:
                raise DataError(f"{cap.rgb}: {exc}") from None
            quality = {"ok": False, "reason": res.reason, **res.quality()}
            if self.settings.fallback == "skip":
                raise RegistrationRejected(f"{cap.rgb}: automatic registration rejected ({res.reason})") from None
            ctx.entries[group] = HomographyEntry(normalize(prior), "focal")  # type: ignore[arg-type]
            pair = ctx.align_capture(rgb, temp, ir8, boxes, labels, group, boxes_frame="thermal", prior=prior)
            route = REJECTED_ROUTE
        t2, c2 = time.perf_counter(), time.thread_time()

        sample = pair.to_sample(image_id, group, {"file_name": cap.rgb.name})
        channel = encode(self.encoding, sample, **dict(self.settings.encoding_params))
        if channel is None:
            image = np.ascontiguousarray(sample.rgb)
        else:
            if channel.dtype != np.uint8 or channel.shape != (sample.height, sample.width):
                raise HarnessError(
                    f"encoding {self.encoding.name!r} returned {channel.dtype} {channel.shape}, "
                    f"expected uint8 {(sample.height, sample.width)}"
                )
            image = np.dstack((sample.rgb, channel))
        t3, c3 = time.perf_counter(), time.thread_time()
        thermal = pair.thermal if pair.thermal is not None else np.full(pair.ir8.shape, np.nan, np.float32)
        return Frame(
            capture=cap,
            image=image,
            thermal=thermal,
            origin=pair.origin,
            H=pair.H,
            cameras=pair.cameras,
            reduction=reduction,
            rgb_size=rgb_size,
            thermal_size=(tw, th),
            route=route,
            registration=quality,
            position=position,
            fingerprints=fingerprints,
            thermal_decoder=str(info.get("decoder") or info.get("format") or ""),
            timings={
                "decode": t1 - t0,
                "align": t2 - t1,
                "encode": t3 - t2,
                "decode_cpu": c1 - c0,
                "align_cpu": c2 - c1,
                "encode_cpu": c3 - c2,
            },
            registered=registered,
            temperatures=route_meta(info),
        )
