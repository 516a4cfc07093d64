"""Scoring predictions made elsewhere (``external``), exporting a run's predictions (``export``), and moving boxes
between the original images and the prepared frame (``frames``)."""
