"""Radiometric decoding: DJI M3T R-JPEGs and decoded temperature maps, to temperature in degrees C.

Other DJI cameras: ``dji_formats`` tells the layouts apart; H20T (dirp) files are decoded by ``dji_dirp``.

DJI M3T R-JPEG ("iirp" family: M3T, M30T, M3TD, H20N, H30T, M4T, Mavic 2 Enterprise Advanced), as laid out in the
file (see ``docs/sensing.md``)::

    SOI  APP1 Exif  APP2 MPF  APP3 x N  APP4 (256 B)  APP5 (tau table)  APP7 ...  APP0 JFIF ...
    SOS <palette preview> EOI

* APP3: the payloads concatenated in file order are W*H little-endian uint16 words; each word is a 14-bit count
  shifted left by 2, so ``raw14 = word >> 2`` (the two low bits are always zero).
* APP4: a 32-byte header (``FF D2 D1 FF`` + ``iirp``), then five little-endian float32 measurement parameters at
  table offset 0: ambient temperature (C), object distance (m), emissivity (0-1), relative humidity (fraction
  0-1), reflected temperature (C). Further fields: gain-mode byte (0x80), sensor name (0x85), format version
  (uint32, 0x99), width and height (uint16, 0x9D / 0x9F), all offsets from the payload start.

Blackbody (uncorrected, emissivity 1, no atmosphere) temperature::

    T0 [C] = raw14 / 16 - 273.15          (resolution 1/16 K)

* APP5: a 0x100-byte header and the camera's atmospheric-transmission (tau) table. With it, the temperature is
  DJI Thermal SDK's corrected one (emissivity, reflected/atmospheric temperature, transmission over distance
  and humidity; ``harness.sensing.dji_correction``), bit-identical to ``dirp_measure_ex`` on the reference M3T
  files. Routes (``read_rjpeg(path, decoder=..., approximate=..., converter=...)``; ``RJpeg.decoder`` says which
  one a file took):

  ``dji``          DJI's correction, computed here (iirp with its table; dirp)
  ``converter``    DJI's own SDK (``dji_irp``) or the user's converter, run per file (``dji_converter``), for the
                   formats and tables this module cannot correct, when a converter is given
  ``approximate``  opt-in (``approximate=True``) for iirp files whose table is DJI's own: a named approximation
                   with its measured bound (``dji_approximate``); every output says "approximate temperatures"
  ``blackbody``    ``T0``, uncorrected: only when asked for (``decoder="blackbody"``), or for files ``write_rjpeg``
                   wrote (APP5 header only: their raw counts are the temperatures written)

  A file that cannot be corrected and has no route chosen for it is refused, naming the camera, the format and
  both options; uncorrected temperatures are never the default for a camera's file.

Decoded thermal is read from uint16 centi-Kelvin PNG/TIFF, int16 deci-Celsius TIFF, float32 TIFF or ``.npy``; a
JSON sidecar ``<file>.json`` (e.g. ``frame.png.json``) states the unit (``read_thermal``/``write_thermal``).

Kept in one module: the R-JPEG reader and writer and the decoded-file reader share one temperature convention
(raw14 <-> degrees C, APP4 parameters, sidecar routes) that a reader checks side by side.
"""

from __future__ import annotations

import json
import logging
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from harness.errors import ConfigError, DataError
from harness.sensing import dji_approximate, dji_converter, dji_correction, dji_dirp, dji_formats, jpeg, plausible
from harness.sensing.plausible import PLAUSIBLE_C, implausible_to_missing  # noqa: F401  (their old home)

log = logging.getLogger(__name__)

KELVIN = 273.15
#: raw14 counts per kelvin of the iirp blackbody scale.
COUNTS_PER_K = 16.0
IIRP_TAG = b"iirp"
APP4_MAGIC = b"\xff\xd2\xd1\xff"
#: EXIF models whose R-JPEGs use the iirp layout (used when APP4 carries no format tag).
IIRP_MODELS = dji_formats.IIRP_MODELS
PARAM_KEYS = ("ambient", "distance", "emissivity", "humidity", "reflected")
#: Measurement parameters of the public M3T samples; used by ``write_rjpeg`` when none are given.
DEFAULT_PARAMS: dict[str, float] = {
    "ambient": 25.0,
    "distance": 5.0,
    "emissivity": 0.95,
    "humidity": 50.0,
    "reflected": 25.0,
}
PARAM_UNITS = {"ambient": "C", "distance": "m", "emissivity": "0-1", "humidity": "%", "reflected": "C"}
#: the parameters a converter is handed (DJI's ``dji_irp`` takes these four)
CONVERTER_KEYS = ("emissivity", "distance", "humidity", "reflected")
#: the measurement overrides ``RJpeg.corrected_c`` takes, in the order they are checked
OVERRIDE_KEYS = (*CONVERTER_KEYS, "ambient")
#: ``read_rjpeg`` decoders: auto (corrected, or the chosen route, else refused), dji (corrected or error), blackbody.
DECODERS = ("auto", "dji", "blackbody")
#: the APP5 ``write_rjpeg`` writes: the header alone, no table (its files read back by the blackbody route)
WRITTEN_APP5 = b"\x00\x00\x00\x00" + b"\xff" * (dji_correction.HEADER_BYTES - 4)


# ---------------------------------------------------------------------------------------------- maths
def raw14_to_celsius(raw14: np.ndarray) -> np.ndarray:
    """Blackbody temperature ``T0 = raw14 / 16 - 273.15`` in C, float32 (computed in float64, then rounded)."""
    return (np.asarray(raw14, dtype=np.float64) / COUNTS_PER_K - KELVIN).astype(np.float32)


def celsius_to_raw14(temperature_c: np.ndarray) -> np.ndarray:
    """Inverse of ``raw14_to_celsius``: ``round((T + 273.15) * 16)`` as uint16; exact to 1/16 K.

    Raises ``DataError`` for temperatures outside the 14-bit range (below -273.15 C or above 750.7 C) or NaN.
    """
    t = np.asarray(temperature_c, dtype=np.float64)
    if not np.isfinite(t).all():
        raise DataError("temperature map has NaN or infinite values; cannot encode raw counts")
    raw = np.rint((t + KELVIN) * COUNTS_PER_K)
    if raw.min() < 0 or raw.max() > 0x3FFF:
        raise DataError(
            f"temperatures {t.min():.2f}..{t.max():.2f} C are outside the 14-bit range "
            f"({-KELVIN:.2f}..{0x3FFF / COUNTS_PER_K - KELVIN:.2f} C)"
        )
    return raw.astype(np.uint16)


# ---------------------------------------------------------------------------------------------- R-JPEG
@dataclass
class RJpeg:
    """A decoded DJI R-JPEG.

    ``raw14`` uint16 HxW counts; ``params`` the APP4 measurement parameters (``ambient`` C, ``distance`` m,
    ``emissivity`` 0-1, ``humidity`` %, ``reflected`` C); ``exif`` the EXIF tags; ``header`` the other APP4
    fields (format tag, version, gain mode, sensor, width, height); ``tau_table`` the APP5 transmission table
    (``None`` when not read or absent); ``decoder`` the route ``temperature_c`` takes (``dji``, ``approximate``,
    ``converter`` or ``blackbody``, module docstring) and ``decoder_note`` why the file's own correction does not
    apply (for the other routes than ``dji``); ``approximation`` the approximation of the ``approximate`` route;
    ``converter`` the converter of the ``converter`` route. For the formats only a converter decodes (hirp, girp,
    XT S), ``raw14`` holds the stored words (``dirp_get_original_raw``) and ``params`` what the file states.
    """

    path: Path
    raw14: np.ndarray
    params: dict[str, float]
    exif: dict[str, Any] = field(default_factory=dict)
    header: dict[str, Any] = field(default_factory=dict)
    tau_table: dji_correction.TauTable | None = None
    decoder: str = "blackbody"
    decoder_note: str = ""
    fmt: str = "iirp"  # the DJI layout (``dji_formats``): iirp, or dirp (then ``dirp`` holds its calibration)
    dirp: dji_dirp.DirpCalibration | None = None
    approximation: dji_approximate.Approximation | None = None
    converter: dji_converter.Converter | None = None

    @property
    def temperature_c(self) -> np.ndarray:
        """Temperature in C (float32 HxW) by the file's route: ``corrected_c()`` for ``dji`` and ``approximate``,
        ``converted_c()`` for ``converter``, else ``blackbody_c()``."""
        if self.decoder in ("dji", "approximate"):
            return self.corrected_c()
        if self.decoder == "converter":
            return self.converted_c()[0]
        return self.blackbody_c()

    @property
    def model(self) -> str:
        return str(self.exif.get("Model") or "").strip()

    def blackbody_c(self) -> np.ndarray:
        """Blackbody temperature ``raw14 / 16 - 273.15`` in C (float32 HxW): emissivity 1, no atmosphere."""
        if self.fmt != "iirp":
            raise DataError(
                f"{self.path}: {self.exif.get('Model', 'this camera')} ({self.fmt}) raw counts are "
                "not blackbody counts; only the corrected temperature (decoder 'auto' or 'dji') exists"
            )
        return raw14_to_celsius(self.raw14)

    @property
    def pre_v0300(self) -> bool:
        """APP4 format before v0300 (M3T: 0x200): the SDK then takes the air temperature from the reflected one
        whenever measurement parameters are set."""
        version = self.header.get("version")
        if self.header.get("format") != "iirp" or version is None:
            return True
        return (version & 0xFFFEFFFF) == 0x200 or version == 0x20200

    def correction_params(self, **overrides: float | None) -> dict[str, float]:
        """The parameters ``corrected_c`` uses: the file's, with the given overrides (``OVERRIDE_KEYS``, checked
        against the ranges DJI's SDK accepts), plus ``atmosphere`` (C): the file's ambient temperature without
        overrides; with overrides, the reflected temperature for pre-v0300 files (M3T), else the ambient one."""
        table = self.tau_table
        given = {**dict.fromkeys(OVERRIDE_KEYS), **overrides}
        if self.fmt == "dirp":
            return dji_dirp.measurement_params(given)
        over = dji_correction.check_overrides(given, table.max_distance if table else 25.0)
        if "ambient" in over and self.pre_v0300:
            raise ConfigError(
                f"{self.path}: this file's format (APP4 version {self.header.get('version', 0x100):#x}) "
                "takes the air temperature from the reflected temperature; set 'reflected' instead of "
                "'ambient'"
            )
        p = {k: float(self.params[k]) for k in PARAM_KEYS if k in self.params}
        if over:
            p.update(over)
            if self.pre_v0300:
                p["ambient"] = p["reflected"]
        dji_correction.check_file_params(p, self.path)
        p["atmosphere"] = p["ambient"]
        return p

    def corrected_c(
        self,
        emissivity: float | None = None,
        distance: float | None = None,
        humidity: float | None = None,
        reflected: float | None = None,
        ambient: float | None = None,
    ) -> np.ndarray:
        """DJI Thermal SDK's corrected temperature in C (float32 HxW), at the file's measurement parameters or
        the given overrides (emissivity 0.1-1, distance m, humidity %, reflected C; ``ambient`` C only for v0300
        formats). Equations: ``harness.sensing.dji_correction``. A ``DataError`` when the file has no usable
        transmission table (``decoder_note`` says why). ``correction_params`` and ``approximate_c`` take the same
        overrides by keyword."""
        overrides = dict(
            emissivity=emissivity, distance=distance, humidity=humidity, reflected=reflected, ambient=ambient
        )
        if self.dirp is not None:
            return dji_dirp.measure(self.raw14, self.dirp, self.correction_params(**overrides), self.path)
        if self.tau_table is None:
            raise DataError(
                f"{self.path}: no atmospheric-transmission table to correct with"
                f"{' (' + self.decoder_note + ')' if self.decoder_note else ''}; "
                "use the blackbody temperature (decoder 'blackbody')"
            )
        if self.approximation is not None:
            return self.approximate_c(**overrides)[0]
        return self._correct_raw14(self.tau_table, self.correction_params(**overrides))

    def approximate_c(self, **overrides: float | None) -> tuple[np.ndarray, dict[str, Any]]:
        """(temperature C, record) of the ``approximate`` route: DJI's correction with the file's stand-in table
        (``dji_approximate``); temperatures above the measured range are missing (NaN); the record names the
        approximation and its measured bound for this frame. An emissivity outside the measured range is a
        ``DataError``."""
        approx, table = self.approximation, self.tau_table
        if approx is None or table is None:
            raise DataError(f"{self.path}: this file was not read by the approximate route")
        p = self.correction_params(**overrides)
        dji_approximate.check_emissivity(approx, p["emissivity"], self.path)
        return dji_approximate.apply(self._correct_raw14(table, p), approx, p["emissivity"])

    def _correct_raw14(self, table: dji_correction.TauTable, p: Mapping[str, float]) -> np.ndarray:
        """DJI's correction of this file's raw counts by ``table`` at the measurement parameters ``p``."""
        return dji_correction.correct_raw14(
            self.raw14, table, p["emissivity"], p["distance"], p["humidity"], p["reflected"], p["atmosphere"]
        )

    def converter_params(self, overrides: Mapping[str, float | None] | None = None) -> dict[str, float]:
        """The measurement parameters handed to the converter: the file's (as this module reads them) with the
        given overrides (checked against DJI's ranges). A pre-v0300 iirp file whose ambient and reflected
        temperatures differ is passed none of its own (DJI's SDK then reads them itself, as setting them would
        make it take the air temperature from the reflected one); a file emissivity of about 0 is a ``DataError``."""
        over = dji_correction.check_overrides(
            {k: v for k, v in dict(overrides or {}).items() if k in CONVERTER_KEYS}, 25.0
        )
        own = {k: float(self.params[k]) for k in CONVERTER_KEYS if k in self.params}
        if (
            not over
            and self.fmt == "iirp"
            and self.pre_v0300
            and self.params.get("ambient") != self.params.get("reflected")
        ):
            own = {}
        p = {**own, **over}
        e = p.get("emissivity")
        if e is not None and not e >= dji_correction.MIN_EMISSIVITY:
            raise DataError(
                f"{self.path}: measurement parameter emissivity={e:g} is physically impossible (a "
                "surface that emits nothing cannot be measured); give --emissivity"
            )
        return p

    def converted_c(self, **overrides: float | None) -> tuple[np.ndarray, dict[str, Any]]:
        """(temperature C, record) of the ``converter`` route: the converter run on the file
        (``dji_converter.convert``) with ``converter_params(overrides)``."""
        if self.converter is None:
            raise DataError(f"{self.path}: no converter was given for this file")
        h, w = self.raw14.shape
        temp, record = dji_converter.convert(self.converter, self.path, w, h, self.converter_params(overrides))
        if self.fmt == "iirp" and np.isfinite(temp).any():  # the file's own counts say roughly where the scene is
            seen_c = float(np.nanmedian(temp))
            gap = seen_c - float(np.median(self.blackbody_c()))
            if abs(gap - KELVIN) < KELVIN_GAP_C:
                raise DataError(
                    f"{self.path}: the converter ({self.converter.name}) wrote temperatures "
                    f"{gap:.1f} C above the file's own blackbody reading: Kelvin, not C; make it write C "
                    "(float32 degrees Celsius)"
                )
            own = self._own_reading(overrides)
            own_c = float(np.nanmedian(own)) if np.isfinite(own).any() else float("nan")
            if _reads_as_fahrenheit(temp, own, seen_c, own_c):
                raise DataError(
                    f"{self.path}: the converter ({self.converter.name}) wrote a median of {seen_c:.1f}, "
                    f"{seen_c - own_c:+.1f} from the file's own reading ({own_c:.1f} C: its counts corrected for "
                    f"emissivity and the reflected temperature) and {seen_c - (1.8 * own_c + 32):+.1f} from that "
                    f"reading in Fahrenheit ({1.8 * own_c + 32:.1f} F): Fahrenheit, not C; make it write C "
                    "(float32 degrees Celsius)"
                )
        seen = plausible.classify(temp, units=("kelvin",))  # any format: a scene's median of 223..373 in C
        if seen.kind == "kelvin":
            raise DataError(
                f"{self.path}: the converter ({self.converter.name}) wrote {seen.detail}; make it write C "
                "(float32 degrees Celsius)"
            )
        return temp, record

    def _own_reading(self, overrides: Mapping[str, float | None]) -> np.ndarray:
        """The file's own reading of the scene, to check a converter's unit against: its counts corrected for
        emissivity and the reflected temperature at the converter's parameters with the transmission taken as 1
        (``dji_approximate.unity_table``; within 0.8 C of DJI's SDK up to 30 C and 4.4 C up to 63 C on the Mavic 2
        Enterprise Advanced, whose table only a converter applies), or the blackbody reading when the file's
        parameters cannot be read."""
        try:
            p = self.correction_params(**overrides)
            return dji_correction.correct_raw14(
                self.raw14,
                dji_approximate.unity_table(),
                p["emissivity"],
                p["distance"],
                p["humidity"],
                p["reflected"],
                p["atmosphere"],
            )
        except (DataError, ConfigError, KeyError):
            return self.blackbody_c()

    def deci_celsius(self, **overrides: float | None) -> np.ndarray:
        """``dirp_measure``'s int16 deci-C: ``trunc(10 * T)`` of ``corrected_c(**overrides)`` (toward zero)."""
        return dji_correction.deci_celsius(self.corrected_c(**overrides))

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.raw14.shape)  # type: ignore[return-value]

    def preview(self, grayscale: bool = False) -> np.ndarray:
        """The palette rendering stored as the file's picture: uint8 HxWx3 RGB (or HxW with ``grayscale``).

        Never use it for radiometry; it is the 8-bit preview (``ir8``) only.
        """
        import cv2

        data = np.frombuffer(jpeg._read_bytes(self.path), np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR)
        if img is None:
            raise DataError(f"{self.path}: the preview picture cannot be decoded")
        return img if grayscale else img[:, :, ::-1].copy()


def read_rjpeg(
    path: str | Path, decoder: str = "auto", approximate: bool = False, converter: dji_converter.Converter | None = None
) -> RJpeg:
    """Decode a DJI R-JPEG: ``raw14`` from APP3, measurement parameters from APP4, EXIF from APP1, the
    transmission table from APP5, and choose its route (module docstring). A dirp (H20T) file is read by
    ``dji_dirp`` (``fmt == "dirp"``, corrected route only).

    A file this module cannot correct takes the ``converter`` route when a ``converter`` is given (any layout,
    hirp, girp and the XT S included), else the ``approximate`` route when ``approximate`` and the file has one
    (``decoder`` ``auto`` only), else it is refused with the camera model, the format and both options named
    (``dji_formats.UnsupportedFormat`` or ``dji_correction.UnsupportedCorrection``).

    ``raw14 = (APP3 words, little-endian uint16) >> 2``. A file that is not a JPEG, has no radiometric payload
    (a plain JPEG), is cut short, or whose payload size does not match the frame is a ``DataError`` naming it;
    so is a damaged APP5 table (with ``auto`` and ``dji``), and with ``dji`` a file without a usable table.
    """
    if decoder not in DECODERS:
        raise ConfigError(f"unknown R-JPEG decoder {decoder!r}; use one of {', '.join(DECODERS)}")
    if approximate and decoder != "auto":
        raise ConfigError(f"the approximate route applies to decoder 'auto' only, not {decoder!r}")
    path = Path(path)
    data = jpeg._read_bytes(path)
    layout = jpeg.read_segments(data, path, require_eoi=False)  # the format first: a refusal names it
    exif: dict[str, Any] = {}
    for payload in layout.payloads(jpeg.APP1):
        exif = jpeg.parse_exif(payload)
        if exif:
            break
    app4 = layout.payloads(jpeg.APP4)
    model = str(exif.get("Model") or "").strip()
    fmt = dji_formats.detect(app4[0] if app4 else None, model)
    if fmt not in dji_formats.DECODED:
        if converter is not None and decoder != "blackbody":
            return _read_for_converter(path, layout, exif, model, fmt, converter)
        raise dji_formats.refusal(path, fmt, model)
    layout.check_complete(path)
    if fmt == "dirp":
        return _read_dirp(path, layout, exif, model, decoder)
    header, params = parse_app4(app4[0], path) if app4 else ({}, {})
    if app4 and "format" not in header:  # no tag (M2EA): the SDK reads the table as format version 0x100
        header["version"] = 0x100
    chunks = layout.payloads(jpeg.APP3)
    if not chunks:
        raise DataError(
            f"{path}: no radiometric payload (APP3 segments): this is a plain JPEG, not a DJI R-JPEG; "
            "export the original R-JPEG from the drone, or give a decoded temperature file"
        )
    raw = b"".join(chunks)
    w, h = layout.width, layout.height
    if header.get("width") and header.get("height") and (header["width"], header["height"]) != (w, h):
        log.debug("%s: APP4 says %dx%d, frame is %dx%d; using APP4", path, header["width"], header["height"], w, h)
        w, h = header["width"], header["height"]
    if len(raw) != w * h * 2:
        raise DataError(
            f"{path}: radiometric payload holds {len(raw)} bytes, expected {w * h * 2} for {w}x{h} "
            "16-bit words; the file is damaged or of an unsupported layout"
        )
    words = np.frombuffer(raw, dtype="<u2").reshape(h, w)
    if np.any(words & 3):
        raise DataError(
            f"{path}: radiometric words have their two low bits set; not the iirp layout "
            "(14-bit counts shifted left by 2)"
        )
    raw14 = (words >> 2).astype(np.uint16)
    rj = RJpeg(path=path, raw14=raw14, params=params, exif=exif, header=header)
    if decoder != "blackbody":
        _attach_tau_table(rj, layout.payloads(jpeg.APP5), decoder, approximate, converter)
    return rj


def _read_for_converter(
    path: Path, layout: jpeg.JpegLayout, exif: dict[str, Any], model: str, fmt: str, converter: dji_converter.Converter
) -> RJpeg:
    """A file only a converter decodes: its stored words (for the frame size) and the parameters it states."""
    words = dji_formats.frame_words(layout, fmt, model, path)
    app4 = layout.payloads(jpeg.APP4)
    params: dict[str, float] = {}
    header: dict[str, Any] = {"format": fmt or "unknown", "width": int(words.shape[1]), "height": int(words.shape[0])}
    if fmt == "hirp" and app4:
        params = dji_formats.hirp_params(app4[0])
    note = str(dji_formats.refusal(path, fmt, model)).removeprefix(f"{path}: ").split("; ")[0]
    return RJpeg(
        path=path,
        raw14=dji_formats.original_raw(words, fmt),
        params=params,
        exif=exif,
        header=header,
        decoder="converter",
        decoder_note=note,
        fmt=fmt or "unknown",
        converter=converter,
    )


def _read_dirp(path: Path, layout: jpeg.JpegLayout, exif: dict[str, Any], model: str, decoder: str) -> RJpeg:
    """A dirp (class D, H20T) file: raw words from APP3, calibration from APP4, curve from APP5."""
    if decoder == "blackbody":
        raise DataError(
            f"{path}: camera {model or 'unknown'!r} writes DJI's dirp format, whose raw counts are not "
            "blackbody counts; use decoder 'auto' or 'dji'"
        )
    app5 = layout.payloads(jpeg.APP5)
    cal = dji_dirp.parse(layout.payloads(jpeg.APP4)[0], app5[0] if app5 else None, path)
    raw = b"".join(layout.payloads(jpeg.APP3))
    w, h = layout.width, layout.height
    if len(raw) != w * h * 2:
        raise DataError(
            f"{path}: radiometric payload holds {len(raw)} bytes, expected {w * h * 2} for {w}x{h} "
            "16-bit words; the file is damaged"
        )
    words = np.frombuffer(raw, dtype="<u2").reshape(h, w)
    header = {"format": "dirp", "version": cal.header_version, "width": w, "height": h}
    return RJpeg(
        path=path,
        raw14=dji_formats.original_raw(words, "dirp"),
        params=dict(cal.stored_params),
        exif=exif,
        header=header,
        decoder="dji",
        fmt="dirp",
        dirp=cal,
    )


def _attach_tau_table(
    rj: RJpeg,
    app5: list[bytes],
    decoder: str,
    approximate: bool = False,
    converter: dji_converter.Converter | None = None,
) -> None:
    """Set ``rj.tau_table`` and ``rj.decoder`` from the file's first APP5 payload (``decoder`` auto or dji): DJI's
    correction when the file carries its table; the blackbody route for the files ``write_rjpeg`` writes; else
    the converter, the approximate route or a refusal (``read_rjpeg``)."""
    version = rj.header.get("version", 0x100)
    what = f"{dji_formats.camera_text(rj.model)}, DJI R-JPEG format 'iirp' (APP4 format version {version:#x})"
    kind, note = "missing", ""
    if not app5:
        note = "the file has no APP5 calibration segment, so no transmission table"
    elif app5[0] == WRITTEN_APP5:
        note = "APP5 holds only its header, no transmission table (as write_rjpeg writes)"
        if decoder == "dji":
            raise DataError(f"{rj.path}: cannot apply DJI's correction: {note}; use decoder 'blackbody'")
        log.debug("%s: blackbody temperature (%s)", rj.path, note)
        rj.decoder, rj.decoder_note = "blackbody", note
        return
    elif len(app5[0]) == dji_correction.HEADER_BYTES:
        note = "APP5 holds only its header, no transmission table"
    else:
        try:
            rj.tau_table = dji_correction.parse_app5(app5[0], version, rj.path)
            rj.decoder = "dji"
            return
        except dji_correction.UnsupportedCorrection as exc:
            kind, note = exc.kind, str(exc).removeprefix(f"{rj.path}: ")
    rj.decoder_note = f"{rj.model or 'unnamed camera'} (iirp, APP4 format version {version:#x}): {note}"
    if converter is not None:
        rj.decoder, rj.converter = "converter", converter
        return
    approx = dji_approximate.for_kind(kind)
    if approximate and decoder == "auto":
        if approx is None:
            raise dji_correction.UnsupportedCorrection(
                f"{rj.path}: {what}: {note}; there is no approximate route for it (no measured stand-in); "
                f"{dji_formats.CONVERTER_HINT}",
                kind=kind,
            )
        if kind == "emissivity-remap":
            rj.tau_table = dji_correction.parse_app5(app5[0], version, rj.path, skip_emissivity_remap=True)
        else:
            rj.tau_table = dji_approximate.unity_table()
        rj.decoder, rj.approximation = "approximate", approx
        return
    if decoder == "dji":
        raise dji_correction.UnsupportedCorrection(
            f"{rj.path}: {what}: cannot apply DJI's correction: {note}; {dji_formats.CONVERTER_HINT}", kind=kind
        )
    raise dji_correction.UnsupportedCorrection(
        f"{rj.path}: {what}: temperatures are not decoded by default: {note}; "
        f"{dji_formats.options_text(approx, 'nothing measured stands in for it')}; uncorrected (blackbody) "
        "temperatures only with --decoder blackbody",
        kind=kind,
    )


def parse_app4(payload: bytes, name: str | Path = "<APP4>") -> tuple[dict[str, Any], dict[str, float]]:
    """(header fields, measurement params) of an iirp APP4 payload; see the module docstring for offsets."""
    header: dict[str, Any] = {}
    base = 0
    if payload.startswith(APP4_MAGIC):
        header["format"] = payload[4:8].split(b"\x00", 1)[0].decode("ascii", "replace")
        base = 32
    if header.get("format", "iirp") != "iirp":
        return header, {}
    if len(payload) < base + 20:
        raise DataError(f"{name}: APP4 parameter block is {len(payload)} bytes, too short for the five parameters")
    ambient, distance, emissivity, humidity, reflected = struct.unpack("<5f", payload[base : base + 20])
    params = {
        "ambient": round(float(ambient), 6),
        "distance": round(float(distance), 6),
        "emissivity": round(float(emissivity), 6),
        "humidity": round(float(humidity) * 100.0, 4),  # stored as a fraction, reported in %
        "reflected": round(float(reflected), 6),
    }
    if len(payload) >= 0xA1:
        header["gain_mode"] = payload[0x80]
        header["sensor"] = payload[0x85:0x95].split(b"\x00", 1)[0].decode("ascii", "replace")
        header["version"] = struct.unpack("<I", payload[0x99:0x9D])[0]
        header["width"], header["height"] = struct.unpack("<HH", payload[0x9D:0xA1])
    return header, params


def _checked_params(params: Mapping[str, Any] | None) -> dict[str, float]:
    out = dict(DEFAULT_PARAMS)
    for key, value in (params or {}).items():
        if key not in PARAM_KEYS:
            raise DataError(f"unknown measurement parameter {key!r}; known: {', '.join(PARAM_KEYS)}")
        out[key] = float(value)
    if out["humidity"] <= 1.0:  # given as a fraction
        out["humidity"] *= 100.0
    return out


def build_app4(params: Mapping[str, Any] | None, width: int, height: int) -> bytes:
    """A 256-byte iirp APP4 payload with the five parameters and the header fields the reader checks."""
    p = _checked_params(params)
    buf = bytearray(256)
    buf[0:8] = APP4_MAGIC + IIRP_TAG
    struct.pack_into(
        "<5f", buf, 32, p["ambient"], p["distance"], p["emissivity"], p["humidity"] / 100.0, p["reflected"]
    )
    buf[64:68] = b"\x2c\x01\x20\x00"  # marks the table at offset 32 (as in camera files)
    buf[0x80] = 1  # gain mode
    buf[0x85 : 0x85 + 9] = b"synthetic"
    struct.pack_into("<I", buf, 0x99, 0x200)
    struct.pack_into("<HH", buf, 0x9D, width, height)
    return bytes(buf)


def write_rjpeg(
    path: str | Path,
    temperature_c: np.ndarray,
    params: Mapping[str, Any] | None = None,
    preview: np.ndarray | None = None,
    exif: Mapping[str, Any] | None = None,
    quality: int = 95,
) -> Path:
    """Write a DJI-layout iirp R-JPEG whose blackbody temperature is ``temperature_c`` (exact to 1/16 K).

    Layout: SOI, APP1 Exif (Make ``DJI``, Model ``M3T``, size, focal length 9.1 mm, plus ``exif``), APP3 chunks of
    ``raw14 << 2`` little-endian words, APP4 (iirp header + ``params``), APP5 (its 0x100-byte header only: no
    transmission table, so DJI's own SDK will not open the file), then the ``preview`` (uint8 HxW or HxWx3 RGB; a
    white-hot min-max rendering when ``None``) as a baseline JPEG. ``read_rjpeg`` returns
    ``raw14 = round((T+273.15)*16)``, and because there is no table the file reads back by the blackbody route
    (``decoder`` ``auto``): ``temperature_c`` is ``temperature_c`` as written, to 1/16 K, whatever ``params`` say
    (they are carried for provenance; a camera's table cannot be synthesised).
    """
    import cv2

    path = Path(path)
    t = np.asarray(temperature_c)
    if t.ndim != 2:
        raise DataError(f"{path}: temperature map must be 2-D (HxW), got shape {t.shape}")
    h, w = t.shape
    raw14 = celsius_to_raw14(t)
    if preview is None:
        lo, hi = float(t.min()), float(t.max())
        preview = np.rint((t - lo) / max(hi - lo, 1e-6) * 255).astype(np.uint8)
    preview = np.asarray(preview)
    if preview.shape[:2] != (h, w) or preview.dtype != np.uint8:
        raise DataError(f"{path}: preview must be uint8 {h}x{w}[x3], got {preview.dtype} {preview.shape}")
    if preview.ndim == 2:
        preview = np.repeat(preview[:, :, None], 3, axis=2)
    ok, encoded = cv2.imencode(".jpg", np.ascontiguousarray(preview[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # pragma: no cover
        raise DataError(f"{path}: could not encode the preview")
    picture = encoded.tobytes()
    tags: dict[str, Any] = {
        "Make": "DJI",
        "Model": "M3T",
        "ImageDescription": "WhiteHot",
        "Software": "rgbt-harness",
        "FocalLength": 9.1,
        "FocalLengthIn35mmFilm": 40,
        "ExifImageWidth": w,
        "ExifImageHeight": h,
    }
    tags.update(exif or {})
    words = (raw14.astype("<u2") << 2).tobytes()
    chunk = 65532  # what the camera uses; even, so no word is split across segments
    app3 = b"".join(jpeg.segment(jpeg.APP3, words[i : i + chunk]) for i in range(0, len(words), chunk))
    app5 = jpeg.segment(jpeg.APP5, b"\x00\x00\x00\x00" + b"\xff" * (dji_correction.HEADER_BYTES - 4))
    out = (
        b"\xff\xd8"
        + jpeg.segment(jpeg.APP1, jpeg.build_exif(tags))
        + app3
        + jpeg.segment(jpeg.APP4, build_app4(params, w, h))
        + app5
        + picture[2:]
    )
    from harness.io import atomic_write_bytes

    return atomic_write_bytes(path, out)


# ---------------------------------------------------------------------------------------------- decoded files
#: unit -> (scale, offset) with ``C = value * scale + offset``
UNITS: dict[str, tuple[float, float]] = {
    "celsius": (1.0, 0.0),
    "kelvin": (1.0, -KELVIN),
    "fahrenheit": (1.0 / 1.8, -32.0 / 1.8),
    "centikelvin": (0.01, -KELVIN),
    "decicelsius": (0.1, 0.0),
    "centicelsius": (0.01, 0.0),
    "raw14": (1.0 / COUNTS_PER_K, -KELVIN),
}
#: what a file's unit is assumed to be when it has no sidecar, by dtype
DEFAULT_UNIT = {"uint16": "centikelvin", "int16": "decicelsius", "float32": "celsius", "float64": "celsius"}
#: how each unit is stored
UNIT_DTYPE = {
    "celsius": np.float32,
    "kelvin": np.float32,
    "fahrenheit": np.float32,
    "centikelvin": np.uint16,
    "decicelsius": np.int16,
    "centicelsius": np.int16,
    "raw14": np.uint16,
}
#: the value an integer unit stores for a missing pixel (``write_thermal``; float units store NaN)
NODATA = {"centikelvin": 0, "raw14": 0, "decicelsius": -32768, "centicelsius": -32768}
THERMAL_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".npy")
#: a converter's median this close to 273.15 C above the file's blackbody median wrote Kelvin (a correction for
#: emissivity and atmosphere moves a scene by tens of degrees at most, never by 273)
KELVIN_GAP_C = 60.0


#: A converter's median this far (C) from the file's own reading (``RJpeg._own_reading``: within a few C of DJI's
#: SDK, the transmission left out) ...
FAHRENHEIT_GAP_C = 15.0
#: ... and this many times closer to that reading written in Fahrenheit (1.8 x C + 32) wrote Fahrenheit; where the
#: reading has a spread (IQR above 1 C), the converter's must be 1.5-2.2 times it (Fahrenheit: 1.8; a correct
#: converter: about 1). Below -40 C the two scales cross (-40 C = -40 F) and the medians cannot tell them apart.
FAHRENHEIT_CLOSER = 3.0
FAHRENHEIT_SPREAD = (1.5, 2.2)


def _reads_as_fahrenheit(temp: np.ndarray, own: np.ndarray, seen_c: float, own_c: float) -> bool:
    """Whether a converter's map ``temp`` (median ``seen_c``) is the file's own reading ``own`` (median ``own_c``)
    written in Fahrenheit rather than C (``FAHRENHEIT_GAP_C``, ``FAHRENHEIT_CLOSER``, ``FAHRENHEIT_SPREAD``);
    missing values are left out, and a reading without a valid value decides nothing."""
    if not (np.isfinite(seen_c) and np.isfinite(own_c)):
        return False
    as_c, as_f = abs(seen_c - own_c), abs(seen_c - (1.8 * own_c + 32.0))
    if as_c < FAHRENHEIT_GAP_C or as_f * FAHRENHEIT_CLOSER > as_c:
        return False
    q_own = np.nanpercentile(own, [25, 75])
    if q_own[1] - q_own[0] > 1.0:
        q = np.nanpercentile(temp, [25, 75])
        ratio = float(q[1] - q[0]) / float(q_own[1] - q_own[0])
        return FAHRENHEIT_SPREAD[0] <= ratio <= FAHRENHEIT_SPREAD[1]
    return True


def sidecar_path(path: str | Path) -> Path:
    """The sidecar of ``frame.png`` is ``frame.png.json``."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def read_sidecar(path: str | Path) -> dict[str, Any] | None:
    """The sidecar of ``path`` (``frame.png.json``, else ``frame.json``) or ``None`` when there is none."""
    path = Path(path)
    for candidate in (sidecar_path(path), path.with_suffix(".json")):
        if candidate.exists() and candidate != path:
            try:
                data = json.loads(candidate.read_text(encoding="utf-8"))
            except (OSError, json.JSONDecodeError) as exc:
                raise DataError(f"{candidate}: unreadable sidecar ({exc})") from None
            if not isinstance(data, dict) or not ({"unit", "scale", "offset"} & set(data)):
                if candidate == sidecar_path(path):
                    raise DataError(f"{candidate}: sidecar must be a JSON object with a 'unit' key")
                continue  # frame.json that is not a thermal sidecar (e.g. annotations)
            data["_path"] = str(candidate)
            return data
    return None


def load_thermal_array(path: Path) -> np.ndarray:
    """The pixel array of a thermal PNG/TIFF/NPY as stored (single channel, no unit applied); a missing, damaged or
    multi-channel file is a ``DataError`` naming it."""
    suffix = path.suffix.lower()
    if not path.exists():
        raise DataError(f"{path}: file not found")
    try:
        if suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif suffix in (".tif", ".tiff"):
            import tifffile

            arr = tifffile.imread(path)
        else:
            import cv2

            arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if arr is None:
                raise DataError(f"{path}: not a decodable image (truncated or wrong format)")
    except DataError:
        raise
    except Exception as exc:  # tifffile / numpy raise many types for damaged files
        raise DataError(f"{path}: cannot read the {suffix} file ({type(exc).__name__}: {exc})") from None
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim != 2:
        raise DataError(f"{path}: expected a single-channel temperature map, got shape {arr.shape}")
    return arr


def route_label(info: Mapping[str, Any]) -> str:
    """One line naming the route of a decoded R-JPEG (from ``rjpeg_temperature``'s info), for tables and sidecars."""
    decoder = info.get("decoder")
    if decoder == "dji":
        return (
            "dji: dirp curve, corrected (emissivity, reflected)"
            if info.get("format_dji") == "dirp"
            else "dji: corrected (emissivity, reflected, atmosphere)"
        )
    if decoder == "approximate":
        return "approximate: " + dji_approximate.describe(info["approximate"])
    if decoder == "converter":
        conv = info.get("converter", {})
        return (
            "converter: DJI Thermal SDK dji_irp"
            if conv.get("converter") == dji_converter.DJI_IRP
            else "converter: user command"
        )
    note = info.get("decoder_note")
    return f"blackbody raw14/16-273.15, uncorrected{' (' + note + ')' if note else ''}"


def sidecar_route(side: Mapping[str, Any] | None) -> dict[str, Any]:
    """The route a decoded file's sidecar records (``harness sensing decode``): ``decoder`` and, for the approximate
    route, its ``approximate`` record; empty for DJI's correction and files written otherwise. Files decoded with
    approximate temperatures stay labelled when a dataset reads them back."""
    route = (side or {}).get("decoder_route")
    if route in (None, "dji"):
        return {}
    out: dict[str, Any] = {"decoder": route}
    if isinstance((side or {}).get("approximate"), dict):
        out["approximate"] = dict(side["approximate"])  # type: ignore[index]
    return out


#: the keys ``route_meta`` may set in a sample's ``meta``
ROUTE_META_KEYS = ("thermal_route", "temperatures", "temperature_bound_c", "approximation")


def route_meta(info: Mapping[str, Any]) -> dict[str, Any]:
    """What a prepared sample's ``meta`` records of its thermal route: nothing for DJI's own correction and for
    non-R-JPEG files; ``thermal_route`` otherwise, and for the approximate route ``temperatures`` ("approximate
    temperatures"), ``temperature_bound_c`` and ``approximation`` (read back by ``harness.cache``)."""
    decoder = info.get("decoder")
    if decoder in (None, "dji"):
        return {}
    out: dict[str, Any] = {"thermal_route": decoder}
    if decoder == "approximate":
        rec = info["approximate"]
        out.update(temperatures=rec["label"], temperature_bound_c=rec["bound_c"], approximation=rec["approximation"])
    return out


def rjpeg_temperature(
    rj: RJpeg, overrides: Mapping[str, float | None] | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """(temperature C float32, info) of a read R-JPEG by its route (``rj.decoder``), with measurement
    ``overrides`` for the corrected, approximate and converter routes; overrides on a blackbody-route file are a
    ``DataError``. ``info`` as ``read_thermal`` documents it, plus ``route`` (``route_label``)."""
    over = {k: v for k, v in dict(overrides or {}).items() if v is not None}
    info: dict[str, Any] = {
        "format": "rjpeg",
        "format_dji": rj.fmt,
        "decoder": rj.decoder,
        "params": dict(rj.params),
        "exif": rj.exif,
        "header": rj.header,
        "nodata": 0,
    }
    if rj.decoder == "dji":
        temp = rj.corrected_c(**over)
        table = rj.dirp if rj.dirp is not None else rj.tau_table
        info.update(
            unit="celsius",
            scale=1.0,
            offset=0.0,
            dtype="float32",
            correction={**rj.correction_params(**over), **table.summary()},  # type: ignore[union-attr]
        )
    elif rj.decoder == "approximate":
        temp, record = rj.approximate_c(**over)
        info.update(
            unit="celsius",
            scale=1.0,
            offset=0.0,
            dtype="float32",
            decoder_note=rj.decoder_note,
            approximate=record,
            correction={**rj.correction_params(**over), **rj.tau_table.summary()},  # type: ignore[union-attr]
        )
    elif rj.decoder == "converter":
        temp, record = rj.converted_c(**over)
        info.update(
            unit="celsius", scale=1.0, offset=0.0, dtype="float32", decoder_note=rj.decoder_note, converter=record
        )
    else:
        if over:
            raise DataError(
                f"{rj.path}: measurement parameters {', '.join(sorted(over))} were given, but the file "
                f"is read by the blackbody route ({rj.decoder_note or 'decoder blackbody'}), which uses "
                "none"
            )
        info.update(
            unit="raw14", scale=1.0 / COUNTS_PER_K, offset=-KELVIN, dtype="uint16", decoder_note=rj.decoder_note
        )
        temp = rj.blackbody_c()
    if rj.decoder != "converter":  # a converter's output is checked where it is read (dji_converter.convert)
        temp = np.array(temp, np.float32)
        implausible = implausible_to_missing(temp, str(rj.path), f"the {rj.decoder} route")
        if implausible:
            info["implausible"] = implausible
    missing = ~np.isfinite(temp)
    if missing.any():  # the converter's "not measured", or temperatures above an approximation's measured range
        from harness.sensing.c2 import valid_mask

        info["missing"] = int(missing.sum())
        valid_mask(temp, str(rj.path))
    info["route"] = route_label(info)
    return temp, info


def read_thermal(
    path: str | Path,
    decoder: str = "auto",
    overrides: Mapping[str, float | None] | None = None,
    approximate: bool = False,
    converter: dji_converter.Converter | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Temperature in C (float32 HxW) and an info dict, from any supported thermal file.

    * ``.jpg``/``.jpeg``: a DJI R-JPEG (``read_rjpeg(path, decoder, approximate, converter)``): DJI's corrected
      temperature when the file carries its transmission table (``decoder`` ``auto``/``dji``), optionally at
      measurement ``overrides`` (emissivity, distance, humidity, reflected; ``RJpeg.corrected_c``); else the
      route chosen for files that cannot be corrected here (converter, approximate), else an error;
    * ``.png``/``.tif``/``.tiff``/``.npy``: ``C = value * scale + offset`` with the unit taken from the sidecar
      ``<file>.json`` (``{"unit": "centikelvin"}`` or explicit ``scale``/``offset``); without a sidecar the dtype
      decides (uint16 centi-Kelvin, int16 deci-Celsius, float Celsius) and implausible values are refused.

    ``info``: ``unit``, ``scale``, ``offset``, ``dtype``, ``format``, ``params`` (measurement parameters when
    known), ``nodata`` (pixels equal to the sidecar's ``nodata`` value), ``missing`` (pixels returned as NaN: the
    nodata ones and any NaN or infinite value; more than ``c2.MAX_INVALID_FRACTION`` of them is an error naming the
    file, fewer are treated as missing by C2 and every analysis); for R-JPEGs also
    ``decoder`` (the route taken: ``dji``, ``approximate``, ``converter`` or ``blackbody``), ``route`` (one line
    naming it), ``decoder_note`` (why the file's own correction does not apply), for ``dji`` and ``approximate``
    ``correction`` (the parameters applied and the table's summary), for ``approximate`` ``approximate`` (label,
    approximation, measured bound ``bound_c``), for ``converter`` ``converter`` (what ran, with which parameters).
    ``unit``/``scale``/``offset`` describe the raw counts for the blackbody route (``C = raw14 / 16 - 273.15``)
    and plain Celsius for the others.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in THERMAL_SUFFIXES:
        raise DataError(f"{path}: unsupported thermal file type {suffix!r}; use one of {', '.join(THERMAL_SUFFIXES)}")
    if suffix in (".jpg", ".jpeg"):
        return rjpeg_temperature(read_rjpeg(path, decoder, approximate, converter), overrides)
    arr = load_thermal_array(path)
    side = read_sidecar(path)
    dtype = arr.dtype.name
    if side is not None:
        unit = side.get("unit", "custom")
        if "scale" in side or "offset" in side:
            scale, offset = float(side.get("scale", 1.0)), float(side.get("offset", 0.0))
        elif unit in UNITS:
            scale, offset = UNITS[unit]
        else:
            raise DataError(
                f"{side['_path']}: unknown unit {unit!r}; use one of {', '.join(UNITS)} "
                "or give 'scale' and 'offset' (C = value * scale + offset)"
            )
    else:
        if dtype not in DEFAULT_UNIT:
            raise DataError(
                f"{path}: {dtype} image without a sidecar: an 8-bit or colour image carries no "
                f"temperatures; write {sidecar_path(path).name} with its 'unit' if it does"
            )
        unit = DEFAULT_UNIT[dtype]
        scale, offset = UNITS[unit]
    temp = (arr.astype(np.float64) * scale + offset).astype(np.float32)
    nodata_value = side.get("nodata") if side else None
    masked = arr == nodata_value if nodata_value is not None else np.zeros(arr.shape, bool)
    nodata = int(masked.sum())
    # masked pixels (the sidecar's nodata value, NaN or inf in a float file) are missing: NaN, never a temperature
    missing = masked | ~np.isfinite(temp)
    if missing.any():
        from harness.sensing.c2 import valid_mask

        temp[missing] = np.nan
        valid_mask(temp, str(path))  # no valid pixel, or too many missing: an error naming the file
    implausible = 0
    if side is not None:  # the stated unit: values outside the plausible range are missing, mostly so an error;
        # a unit mix-up (Kelvin, Fahrenheit, 8-bit counts) is a console warning, the unit having been stated
        implausible = plausible.check(
            temp, str(path), f"the unit of {Path(side['_path']).name} ({unit})", units=True, declared=True
        )
        if implausible:
            from harness.sensing.c2 import valid_mask

            missing = missing | ~np.isfinite(temp)
            valid_mask(temp, str(path))
    else:
        lo, hi = float(np.nanmin(temp)), float(np.nanmax(temp))
        if lo < PLAUSIBLE_C[0] or hi > PLAUSIBLE_C[1]:
            raise DataError(
                f"{path}: read as {unit} ({dtype}, no sidecar) the values span {lo:.1f}..{hi:.1f} C, "
                f"which is not plausible; write {sidecar_path(path).name} with the right 'unit'"
            )
        plausible.check(  # Kelvin, Fahrenheit or 8-bit counts in a file read as C: refused with the fix
            temp, str(path), f"read as {unit} ({dtype}, no sidecar; write {sidecar_path(path).name} with its 'unit')"
        )
    info = {
        "format": suffix.lstrip("."),
        "unit": unit,
        "scale": scale,
        "offset": offset,
        "dtype": dtype,
        "params": dict(side.get("params", {})) if side else {},
        "nodata": nodata,
        "missing": int(missing.sum()),
        **({"implausible": implausible} if implausible else {}),
        "sidecar": side.get("_path") if side else None,
        **sidecar_route(side),
    }
    return temp, info


def write_thermal(
    path: str | Path,
    temperature_c: np.ndarray,
    unit: str = "centikelvin",
    params: Mapping[str, Any] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Write a temperature map (C) as ``path`` (.png, .tif/.tiff or .npy) in ``unit``, plus its sidecar.

    ``centikelvin``: uint16 ``round((T + 273.15) * 100)``; ``decicelsius``: int16 ``round(T * 10)`` (TIFF or
    npy only: PNG cannot hold int16); ``celsius``: float32 (TIFF or npy). The sidecar ``<file>.json`` records
    unit, scale, offset, dtype, shape and ``params`` (strict JSON: a non-finite number is ``null``). Missing pixels
    (NaN, inf) stay missing: stored as the unit's ``NODATA`` value (NaN in a float file), with ``nodata`` and the
    count ``missing`` in the sidecar; a map with none valid, or more than ``c2.MAX_INVALID_FRACTION`` missing, is a
    ``DataError``. Returns the data file's path.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if unit not in UNITS:
        raise DataError(f"unknown unit {unit!r}; use one of {', '.join(UNITS)}")
    if suffix not in (".png", ".tif", ".tiff", ".npy"):
        raise DataError(f"{path}: write thermal maps as .png, .tif/.tiff or .npy")
    t = np.asarray(temperature_c, dtype=np.float64)
    if t.ndim != 2:
        raise DataError(f"{path}: temperature map must be a 2-D array, got shape {t.shape}")
    missing = ~np.isfinite(t)
    n_missing = int(missing.sum())
    if n_missing:  # missing pixels stay missing: the unit's nodata value (NaN in a float file), never a temperature
        from harness.sensing.c2 import valid_mask

        valid_mask(t, str(path))  # none valid, or more missing than a map may miss: an error naming the file
    scale, offset = UNITS[unit]
    dtype = np.dtype(UNIT_DTYPE[unit])
    values = (t - offset) / scale
    nodata: int | None = None
    if dtype.kind in "iu":
        values = np.rint(values)
        info = np.iinfo(dtype)  # type: ignore[type-var]
        nodata = NODATA[unit]
        lowest = info.min + 1 if nodata == info.min else info.min  # the nodata value is never a temperature
        valid = values[~missing]
        if valid.min() < lowest or valid.max() > info.max:
            tv = t[~missing]
            raise DataError(f"{path}: temperatures {tv.min():.2f}..{tv.max():.2f} C do not fit {unit} ({dtype.name})")
        values[missing] = nodata
    arr = values.astype(dtype)
    if suffix == ".png" and dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: PNG cannot store {dtype.name} ({unit}); use .tif or unit='centikelvin'")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".npy":
        np.save(path, arr)
    elif suffix in (".tif", ".tiff"):
        import tifffile

        tifffile.imwrite(path, arr)
    else:
        import cv2

        if not cv2.imwrite(str(path), arr):  # pragma: no cover
            raise DataError(f"{path}: could not write PNG")
    from harness import __version__
    from harness.io import atomic_write_json, nan_to_none

    sidecar = {
        "unit": unit,
        "scale": scale,
        "offset": offset,
        "dtype": dtype.name,
        "shape": list(arr.shape),
        "formula": "C = value * scale + offset",
        "params": dict(params or {}),
        "writer": f"rgbt-harness {__version__}",
        **dict(extra or {}),
    }
    if n_missing:
        sidecar.update({"nodata": nodata, "missing": n_missing} if nodata is not None else {"missing": n_missing})
    atomic_write_json(sidecar_path(path), nan_to_none(sidecar))  # strict JSON: a non-finite number is null
    return path
