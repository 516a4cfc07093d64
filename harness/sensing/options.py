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


@dataclass(frozen=True)
class SensingOptions:
    decoder: str = "auto"  # R-JPEG route: auto | dji | blackbody (harness.sensing.radiometry.read_rjpeg)
    measurement: dict[str, float] = field(default_factory=dict)  # correction overrides (emissivity, distance, ...)
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
            group_gap_s=float((s.get("groups") or {}).get("gap_s", 300.0)),
            registration=RegistrationOptions(**{k: v for k, v in reg.items() if k in RegistrationOptions.__annotations__}),
            undistort=UndistortOptions(**{k: v for k, v in und.items() if k in UndistortOptions.__annotations__}),
            warp=WarpOptions(**{k: v for k, v in warp.items() if k in WarpOptions.__annotations__}),
            displacement_shifts=tuple(int(v) for v in (s.get("displacement") or {}).get("shifts", (2, 5, 10, 15))),
        )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)
