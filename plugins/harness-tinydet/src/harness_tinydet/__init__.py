"""TinyDet: an example third-party detector plugin for rgbt-harness (see README.md)."""

from harness_tinydet.model import TinyDet, build_tinydet

__all__ = ["TinyDet", "build_tinydet"]
__version__ = "0.1.0"
