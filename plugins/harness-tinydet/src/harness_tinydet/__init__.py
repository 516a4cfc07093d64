"""TinyDet: an example third-party detector plugin for rgbt-harness (see README.md).

The model lives in ``harness_tinydet.model``; ``harness_tinydet.plugin`` registers it with the harness. Nothing here
imports torch at import time, so ``harness --help`` and ``harness list`` stay fast with the plugin installed.
"""

__version__ = "0.1.0"
