"""rgbt-harness: a benchmarking harness for RGB-thermal fusion object detectors.

The public surface for plugin authors is re-exported here::

    from harness import hookimpl, DetectorSpec, DatasetSpec, EncodingSpec, AlignedSample
"""

from harness.api import DatasetSource, DatasetSpec, DetectorSpec, EncodingSpec, Fold, PrepareReport, Reference
from harness.errors import HarnessError
from harness.hookspecs import hookimpl
from harness.sample import AlignedSample, validate_sample

__version__ = "0.1.0"

__all__ = [
    "AlignedSample",
    "DatasetSource",
    "DatasetSpec",
    "DetectorSpec",
    "EncodingSpec",
    "Fold",
    "HarnessError",
    "PrepareReport",
    "Reference",
    "__version__",
    "hookimpl",
    "validate_sample",
]
