"""Old home of the aligned-sample contract, kept so existing imports work: the record is ``harness.api.AlignedSample``
and its check ``harness.contracts.validate_sample`` (both exported from ``harness``)."""

from harness.api import AlignedSample
from harness.contracts import validate_sample

__all__ = ["AlignedSample", "validate_sample"]
