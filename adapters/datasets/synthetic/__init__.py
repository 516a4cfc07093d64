"""A synthetic M3T-like facade dataset: the data a new user runs first, and the data the tests use.

The generator writes exactly the raw layout of the real M3T release (see ``docs/datasets.md``), so the ``m3t``
adapter reads it with the same code: DJI-named RGB JPEGs (``DJI_<time>_<nnnn>_W.JPG``, with barrel distortion) and
radiometric thermal captures (``..._T.JPG`` R-JPEG, or 16-bit centi-Kelvin files with a sidecar), COCO annotations
in the RGB frame, the wide camera's calibration, and landmark pairs per inspection group. What a real release
cannot contain is kept apart in ``ground_truth/`` (true homographies, true boxes in the thermal frame, true
temperature maps, the sensor offsets of every frame), which no adapter reads.

The model, in the order the generator applies it (all lengths on the facade in metres, converted to thermal pixels
with ``px_per_m = f_T / Z``):

* **Geometry.** One scene is a facade patch seen by the thermal camera: scene coordinates *are* thermal-frame
  coordinates. The wide (RGB) camera views the same plane through the rig homography
  ``H = K_T (R + t n^T / Z) K_W^-1`` (undistorted RGB pixel -> thermal pixel, OpenCV pixel-centre convention), with a
  small boresight rotation ``R``, a lens baseline ``t`` of a few centimetres, the facade normal ``n`` and the
  distance ``Z`` of the inspection group. Focal lengths follow the M3T optics (thermal 40 mm and wide 24 mm
  35-mm-equivalent), so the thermal footprint is the central ~57 % of the RGB frame. The RGB image is then
  distorted with radial ``k1, k2``.
* **Facade.** Five projects with their own material (brick, render, precast concrete, painted plaster, cladding),
  colour, window grid and frames, ambient temperature, sun load and sky temperature. The wall temperature is
  ``T_amb + sun_load * (1 + 0.4 * (a - a_wall) / a_wall)`` with the absorptivity ``a = 1 - 0.7 * luminance`` spread
  laterally by conduction (Gaussian, 8 cm), a vertical gradient, slow blotches and warm floor-slab bridges.
* **Categories** (names and order of ``adapters.datasets.m3t.M3T_CATEGORIES``):
  window (cold sky-reflecting glass, warm frame), ac_unit (hot fan grille, warm housing and plume), vent (louvred
  grille with dark duct gaps, warm exhaust and plume), crack (thin dark polyline, faint in thermal), paint_peeling
  and efflorescence (visible texture, a few tenths of a degree through absorptivity), delamination (a debonded
  render layer: uniform +-0.5..3 C patch whose rim is as wide as the layer is thick, 1-2 % albedo change),
  water_seepage (a damp zone reaching past its faint stain, mottled evaporative cooling of 0.5..2 C, smooth
  drying front).
* **Sensors.** Thermal: the scene rendered on a 2x supersampled canvas and block-averaged to the sensor grid, a
  0.55 px optical blur, a per-frame offset drift (shutter-calibration sawtooth within -0.8..+2.2 C), radial
  vignetting, column fixed-pattern noise and NETD noise, stored at the R-JPEG's 1/16 K resolution. RGB: exposure,
  white balance and vignetting per frame, sensor noise, JPEG compression.
* **Annotations** are what an annotator drawing on the raw RGB image would produce: the envelope of each object's
  outline projected into the distorted RGB frame, rounded to 0.01 px. The true thermal-frame box of each object is
  its extent on the canvas (snapped to the canvas grid, so it is exact).
* **Landmarks** are corners of windows, AC units and vents, spread over the frame, clicked on the undistorted
  wide image (nearly exact) and on the thermal image, where a corner is a soft transition a few pixels wide and a
  person's click lands anywhere across it (``click_landmarks``; the ``tiny`` test profile clicks precisely).

The sources of each modelling choice are listed in ``docs/datasets.md`` (the synthetic generator's section).

Everything is deterministic in ``seed``: each image draws from its own ``SeedSequence((seed, project, index))``.
"""

from __future__ import annotations

from adapters.datasets.synthetic.generation import (
    ENV_DATA,
    GENERATOR_VERSION,
    MARKER,
    THERMAL_FORMATS,
    SynthSummary,
    default_root,
    generate,
)
from adapters.datasets.synthetic.geometry import (
    Canvas,
    Rig,
    Session,
    camera_matrix,
    canvas_for_session,
    distort_points,
    make_session,
    project_box_to_rgb,
    rgb_render_maps,
    rotation_matrix,
    undistort_points_dense,
)
from adapters.datasets.synthetic.painting import PAINTERS, Layers, SceneObject, place_objects, sill_box
from adapters.datasets.synthetic.plugin import open_synthetic, register_datasets
from adapters.datasets.synthetic.profiles import (
    BASE_RATES,
    LOOKS,
    PROFILES,
    PROJECTS,
    Look,
    Profile,
    get_profile,
)
from adapters.datasets.synthetic.rendering import Frame, click_landmarks, pick_landmarks, render_frame

__all__ = [
    "ENV_DATA",
    "GENERATOR_VERSION",
    "MARKER",
    "THERMAL_FORMATS",
    "SynthSummary",
    "default_root",
    "generate",
    "Canvas",
    "Rig",
    "Session",
    "camera_matrix",
    "canvas_for_session",
    "distort_points",
    "make_session",
    "project_box_to_rgb",
    "rgb_render_maps",
    "rotation_matrix",
    "undistort_points_dense",
    "PAINTERS",
    "Layers",
    "SceneObject",
    "place_objects",
    "sill_box",
    "open_synthetic",
    "register_datasets",
    "BASE_RATES",
    "LOOKS",
    "PROFILES",
    "PROJECTS",
    "Look",
    "Profile",
    "get_profile",
    "Frame",
    "click_landmarks",
    "pick_landmarks",
    "render_frame",
]
