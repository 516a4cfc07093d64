"""Built-in plugins of the harness: detectors (``adapters.detectors``) and datasets (``adapters.datasets``).

Each module here is an ordinary pluggy plugin registered from ``harness.plugins.DEFAULT_PLUGINS``."""
