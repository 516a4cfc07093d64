"""Built-in detector plugins and their shared YOLO building blocks (``adapters.detectors.yolo``)."""
