"""Screening: a benchmarked detector run forward over a new flight, exactly as the drone wrote it.

``screen(ScreenRequest(flight=..., run=RUN_DIR, out=DIR))`` pairs the flight's wide and thermal captures
(``flight``), puts each through the sensing pipeline and the encoding recorded in the run's configuration
(``frontend``: decode to C, undistort, register, warp, crop, fourth channel; nothing re-typed, nothing
re-implemented), runs the run's model in PyTorch or its ONNX export in ONNX Runtime (``model``), and writes what
it found, where, and how warm (``findings``, ``outputs``, ``gallery``): a screened frame and a held-out frame of
the same capture give the same boxes and scores.

===============  ===================================================================================================
module           what it holds
===============  ===================================================================================================
``flight``       ``find_captures``: DJI ``_W``/``_T`` pairs by capture name; zoom, video and other files ignored
``position``     GPS and gimbal attitude from DJI's XMP (``read_position``), and writing it (``add_xmp``)
``frontend``     ``FrontEnd.process``: one capture -> ``Frame`` (the model input, the aligned temperature map, the
                 registration route, reduced JPEG decoding)
``model``        ``from_run``/``from_weights`` -> ``ScreenModel``; ``Predictor`` (torch or ONNX Runtime)
``findings``     boxes in the original images, box temperatures (min, mean, max, P95) and the contrast to a ring
``outputs``      findings.csv, findings.geojson, overlays, crops, manifest
``gallery``      index.html
``job``          ``screen``: progress, workers, re-runs that skip frames done, bad files listed (``ScreenResult``)
===============  ===================================================================================================

The command is ``harness screen`` (``harness/commands/screen.py``); ``docs/screening.md`` is the user's page.
"""

from __future__ import annotations

from harness.screen.flight import Capture, Flight, find_captures
from harness.screen.job import ScreenRequest, ScreenResult, screen
from harness.screen.position import Position, add_xmp, read_position

__all__ = [
    "Capture",
    "Flight",
    "find_captures",
    "ScreenRequest",
    "ScreenResult",
    "screen",
    "Position",
    "add_xmp",
    "read_position",
]
