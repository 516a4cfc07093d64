"""rgbt-harness: a benchmarking harness for RGB-thermal fusion object detectors.

The public surface for plugin authors is re-exported here: the hook marker, every record of the plugin contracts
(``harness.api``) and the sample check (``harness.contracts``)::

    from harness import hookimpl, DetectorSpec, DatasetSpec, EncodingSpec, LoggerSpec, AlignedSample

Fixtures for a plugin's own tests are in ``harness.testing`` (a pytest plugin).
"""

from harness.api import (
    AlignedSample,
    CommandGroup,
    DatasetSource,
    DatasetSpec,
    DetectorSpec,
    EncodingSpec,
    Fold,
    InputKind,
    LoggerSpec,
    PrepareReport,
    Reference,
    RunLogger,
    TrackingOptions,
)
from harness.contracts import validate_sample
from harness.errors import HarnessError, PluginError
from harness.hookspecs import hookimpl

__version__ = "0.1.0"

__all__ = [
    "AlignedSample",
    "CommandGroup",
    "DatasetSource",
    "DatasetSpec",
    "DetectorSpec",
    "EncodingSpec",
    "Fold",
    "HarnessError",
    "InputKind",
    "LoggerSpec",
    "PluginError",
    "PrepareReport",
    "Reference",
    "RunLogger",
    "TrackingOptions",
    "__version__",
    "hookimpl",
    "validate_sample",
]
