"""YOLO building blocks shared by the built-in detectors (and usable by plugins).

Module names and parameter names follow the public YOLOv5/YOLOv8 checkpoint layout (``conv``, ``bn``, ``cv1``,
``m`` ...) so that state dicts in that layout load by key; the code is the harness's own.
"""
