"""Scoring predictions made elsewhere (``external``, guarded by ``plausibility``), exporting a run's predictions
(``export``), and moving boxes between the original images and the prepared frame (``frames``)."""
