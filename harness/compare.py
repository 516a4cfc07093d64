"""Old home of the cross-dataset comparison, kept so existing imports (``from harness.compare import build_table``)
work: it is ``harness.report.compare``, a report of the results store like the others."""

from harness.report.compare import CompareRow, CompareTable, SupportMismatch, build_table, check_matched

__all__ = ["CompareRow", "CompareTable", "SupportMismatch", "build_table", "check_matched"]
