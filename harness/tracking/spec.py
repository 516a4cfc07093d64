"""Old home of the tracker contract, kept so existing imports work: ``RunLogger``, ``TrackingOptions`` and
``LoggerSpec`` live in ``harness.api`` (exported from ``harness``)."""

from harness.api import LoggerSpec, RunLogger, TrackingOptions

__all__ = ["LoggerSpec", "RunLogger", "TrackingOptions"]
