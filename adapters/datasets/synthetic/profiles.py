"""What the generator makes: the size profiles, and each project's building and weather (see the package docstring)."""

from __future__ import annotations

from dataclasses import dataclass, field

from harness.errors import DataError

PROJECTS = ("P1", "P2", "P3", "P4", "P5")


@dataclass(frozen=True)
class Profile:
    """How much to generate: images per project, frame sizes, inspection groups per project."""

    name: str
    images: tuple[int, int, int, int, int]
    thermal_size: tuple[int, int]  # (width, height)
    rgb_size: tuple[int, int]
    sessions: tuple[int, int, int, int, int]
    jpeg_quality: int = 92
    description: str = ""
    clicks: str = "human"  # landmark clicking: "human" (a few thermal px off) or "precise" (sub-pixel, for tests)

    @property
    def total(self) -> int:
        return sum(self.images)


#: The sizes, a row each: name, images per project, thermal (width, height), RGB (width, height), inspection groups
#: per project, landmark clicking.
_SIZES = (
    ("tiny", (2, 2, 2, 1, 1), (160, 128), (480, 360), (1, 1, 1, 1, 1), "precise"),
    ("small", (32, 20, 28, 16, 16), (320, 256), (960, 720), (2, 2, 2, 1, 1), "human"),
    ("full", (256, 87, 201, 70, 60), (640, 512), (2000, 1500), (4, 2, 3, 2, 2), "human"),
)
_DESCRIPTIONS = {
    "tiny": "8 pairs, for tests (precise landmark clicks: the geometry is checked to < 1 px)",
    "small": "112 pairs, thermal 320x256, RGB 960x720: the demo and CPU runs",
    "full": "674 pairs with the seed's fold sizes, thermal 640x512, RGB 2000x1500",
}
PROFILES: dict[str, Profile] = {
    name: Profile(name, images, thermal, rgb, sessions, description=_DESCRIPTIONS[name], clicks=clicks)
    for name, images, thermal, rgb, sessions, clicks in _SIZES
}


def get_profile(name: str) -> Profile:
    if name not in PROFILES:
        raise DataError(f"unknown synthetic profile {name!r}; available: {', '.join(PROFILES)}")
    return PROFILES[name]


# ----------------------------------------------------------------------------------------------- looks
@dataclass(frozen=True)
class Look:
    """What a project's building looks like, and the weather on the day it was flown."""

    title: str
    material: str  # brick | render | concrete | paint | cladding
    wall_rgb: tuple[float, float, float]
    ambient_c: float
    sun_load_c: float
    sky_delta_c: float  # glass reflects the sky: this much colder than the ambient air
    window_m: tuple[float, float]  # width, height
    pitch_m: tuple[float, float]  # horizontal pitch, storey height
    frame_rgb: tuple[float, float, float]
    mullion: bool
    distance_m: tuple[float, float]
    drift_c: tuple[float, float]
    vignette_c: float  # corners read this much warmer (negative: cooler)
    delamination_sign: float  # +1: sun-heated (warmer), -1: morning (cooler)
    slab_bridge_c: float
    rates: dict[str, float] = field(default_factory=dict)  # mean instances per frame
    date: str = "2024-05-12 09:00:00"


BASE_RATES = {
    "ac_unit": 0.55,
    "vent": 0.75,
    "crack": 0.9,
    "paint_peeling": 0.7,
    "efflorescence": 0.65,
    "delamination": 1.1,
    "water_seepage": 0.65,
}

LOOKS: dict[str, Look] = {
    "P1": Look(
        "red-brick apartment block, mild spring day",
        "brick",
        (0.56, 0.28, 0.21),
        16.0,
        5.0,
        -7.0,
        (1.2, 1.5),
        (2.8, 3.0),
        (0.92, 0.92, 0.90),
        True,
        (5.0, 7.5),
        (-0.8, 1.6),
        -0.8,
        1.0,
        0.3,
        dict(BASE_RATES),
        "2024-05-12 09:40:00",
    ),
    "P2": Look(
        "white render, cold clear morning",
        "render",
        (0.88, 0.86, 0.81),
        5.0,
        1.5,
        -9.0,
        (1.0, 1.3),
        (2.4, 2.9),
        (0.32, 0.23, 0.17),
        False,
        (5.0, 7.0),
        (-0.6, 1.8),
        -1.1,
        -1.0,
        0.7,
        {**BASE_RATES, "efflorescence": 1.1, "water_seepage": 1.0},
        "2024-03-08 07:55:00",
    ),
    "P3": Look(
        "grey precast concrete, sunny",
        "concrete",
        (0.60, 0.60, 0.58),
        24.0,
        10.0,
        -12.0,
        (1.4, 1.6),
        (3.2, 3.2),
        (0.70, 0.72, 0.75),
        True,
        (5.5, 8.0),
        (-0.5, 2.2),
        -0.6,
        1.0,
        0.2,
        {**BASE_RATES, "crack": 1.4},
        "2024-07-21 13:10:00",
    ),
    "P4": Look(
        "ochre painted plaster, overcast",
        "paint",
        (0.80, 0.62, 0.33),
        13.0,
        3.0,
        -4.0,
        (1.1, 1.4),
        (2.6, 3.0),
        (0.94, 0.94, 0.92),
        False,
        (5.0, 7.0),
        (-0.8, 1.2),
        -0.9,
        1.0,
        0.5,
        {**BASE_RATES, "paint_peeling": 1.3},
        "2024-10-02 11:20:00",
    ),
    "P5": Look(
        "dark fibre-cement cladding, hot afternoon",
        "cladding",
        (0.27, 0.31, 0.36),
        29.0,
        12.0,
        -10.0,
        (0.9, 1.8),
        (2.5, 3.1),
        (0.13, 0.13, 0.13),
        False,
        (5.5, 8.0),
        (-0.4, 2.0),
        -0.7,
        1.0,
        0.2,
        {**BASE_RATES, "ac_unit": 0.85, "vent": 1.0},
        "2024-08-14 15:30:00",
    ),
}

#: Object sizes on the facade in metres: (min, max) of width and height (cracks: length and angle below).
SIZES_M = {
    "ac_unit": ((0.75, 0.95), (0.50, 0.62)),
    "vent": ((0.25, 0.45), None),  # square or round: height = width (wall grilles and exhaust outlets)
    "paint_peeling": ((0.25, 0.75), (0.22, 0.70)),
    "efflorescence": ((0.30, 0.85), (0.40, 1.05)),
    "delamination": ((0.40, 1.00), (0.36, 0.95)),
    "water_seepage": ((0.70, 1.50), (0.60, 1.10)),
}
CRACK_LENGTH_M = (0.35, 1.10)
#: A seepage's damp zone reaches this far past its visible stain (its fringe and drying front): nothing else is
#: placed in it, and it keeps this far from the windows beside it (60 % of it from those below).
DAMP_FRINGE_M = 0.45
