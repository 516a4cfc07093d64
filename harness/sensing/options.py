"""The ``sensing`` section of the configuration as typed records (defaults and comments: configs/default.yaml)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Mapping

#: ``sensing.radiometry`` keys that override an R-JPEG's measurement parameters in DJI's correction
MEASUREMENT_KEYS = ("emissivity", "distance", "humidity", "reflected")


@dataclass(frozen=True)
class RegistrationOptions:
    homographies: str | None = None
    method: str = "auto"  # auto | focal | file
    min_correlation: float = 0.5
    max_corner_shift: float | None = None
    search_scale: float = 0.06
    search_rotation_deg: float = 4.0

    def search(self) -> dict[str, Any]:
        """The automatic registration's settings, as ``registration.estimate_homography_auto`` takes them."""
        keys = ("min_correlation", "max_corner_shift", "search_scale", "search_rotation_deg")
        return {k: getattr(self, k) for k in keys}


@dataclass(frozen=True)
class UndistortOptions:
    rgb_camera: str | None = None
    thermal_camera: str | None = None
    alpha: float = 0.0


@dataclass(frozen=True)
class WarpOptions:
    crop: bool = True
    min_box_size: float = 1.0
    antialias: bool = True
    interpolation: str = "linear"

    def arguments(self) -> dict[str, Any]:
        """The settings as ``warp.align_pair`` takes them."""
        return asdict(self)


@dataclass(frozen=True)
class SensingOptions:
    decoder: str = "auto"  # R-JPEG route: auto | dji | blackbody (harness.sensing.radiometry.read_rjpeg)
    measurement: dict[str, float] = field(default_factory=dict)  # correction overrides (emissivity, distance, ...)
    approximate: bool = False  # accept the labelled approximate route (harness.sensing.dji_approximate)
    converter: str | None = None  # "dji_irp" or a command template (harness.sensing.dji_converter)
    dji_irp: str | None = None  # where DJI Thermal SDK's dji_irp is (the program or its folder)
    converter_timeout_s: float | None = None
    group_gap_s: float = 300.0
    registration: RegistrationOptions = field(default_factory=RegistrationOptions)
    undistort: UndistortOptions = field(default_factory=UndistortOptions)
    warp: WarpOptions = field(default_factory=WarpOptions)
    displacement_shifts: tuple[int, ...] = (2, 5, 10, 15)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any] | None) -> "SensingOptions":
        """From a resolved config (the whole config or just its ``sensing`` section)."""
        s = dict((cfg or {}).get("sensing", cfg or {}) or {})
        reg = dict(s.get("registration", {}) or {})
        und = dict(s.get("undistort", {}) or {})
        warp = dict(s.get("warp", {}) or {})
        rad = dict(s.get("radiometry", {}) or {})
        return cls(
            decoder=str(rad.get("decoder", "auto")),
            measurement={k: float(rad[k]) for k in MEASUREMENT_KEYS if rad.get(k) is not None},
            approximate=_flag(rad.get("approximate", False)),
            converter=str(rad["converter"]) if rad.get("converter") else None,
            dji_irp=str(rad["dji_irp"]) if rad.get("dji_irp") else None,
            converter_timeout_s=float(rad["converter_timeout_s"]) if rad.get("converter_timeout_s") else None,
            group_gap_s=float((s.get("groups") or {}).get("gap_s", 300.0)),
            registration=RegistrationOptions(
                **{k: v for k, v in reg.items() if k in RegistrationOptions.__annotations__}
            ),
            undistort=UndistortOptions(**{k: v for k, v in und.items() if k in UndistortOptions.__annotations__}),
            warp=WarpOptions(**{k: v for k, v in warp.items() if k in WarpOptions.__annotations__}),
            displacement_shifts=tuple(int(v) for v in (s.get("displacement") or {}).get("shifts", (2, 5, 10, 15))),
        )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def converter_spec(self) -> Any:
        """The ``dji_converter.Converter`` these options name, or ``None``; a wrong setting is a ``ConfigError``."""
        from harness.sensing.dji_converter import resolve

        return resolve(self.converter, self.dji_irp, self.converter_timeout_s)

    def thermal_kwargs(self) -> dict[str, Any]:
        """What ``radiometry.read_thermal`` takes from these options (decoder, overrides, routes)."""
        return {
            "decoder": self.decoder,
            "overrides": self.measurement,
            "approximate": self.approximate,
            "converter": self.converter_spec(),
        }


def _flag(value: Any) -> bool:
    """A yes/no setting: booleans, or the strings true/false/yes/no/1/0 (``--set`` gives strings)."""
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text in ("true", "yes", "1", "on"):
        return True
    if text in ("false", "no", "0", "off", "", "none", "null"):
        return False
    from harness.errors import ConfigError

    raise ConfigError(f"sensing.radiometry.approximate must be true or false, got {value!r}")
