"""Table cells: a mean with its sample SD (``Stat``), a point estimate with its confidence interval
(``Interval``), and how one cell is written as text (``format_value``). The tables, the paired statistics and the
cross-dataset comparison all build on them; none of those is imported here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping


@dataclass(frozen=True)
class Stat:
    """A mean with its sample SD over ``n`` values (folds, seeds or resamples)."""

    mean: float | None
    sd: float | None = None
    n: int = 1

    @classmethod
    def from_mean_sd(cls, rec: Mapping[str, Any] | None) -> "Stat":
        rec = rec or {}
        return cls(rec.get("mean"), rec.get("sd"), int(rec.get("n") or 0))


@dataclass(frozen=True)
class Interval:
    """A point estimate with a confidence interval (e.g. a bootstrap 95 % CI of a difference)."""

    value: float | None
    low: float | None
    high: float | None

    @property
    def excludes_zero(self) -> bool:
        return self.low is not None and self.high is not None and (self.low > 0 or self.high < 0)


def format_value(v: Any, kind: str, digits: int = 1) -> str:
    """One cell as text; ``None`` and NaN are ``-``."""
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    scale = 100.0 if kind in ("pct", "pp") else 1.0

    def num(x: float | None, signed: bool = False) -> str:
        if x is None or not math.isfinite(float(x)):
            return "-"
        if kind == "int":
            return f"{int(round(x)):,}"
        if kind == "sig":
            return f"{x:.3g}"
        return f"{scale * float(x):{'+' if signed else ''}.{digits}f}"

    if isinstance(v, Stat):
        if v.mean is None:
            return "-"
        return num(v.mean, kind == "pp") + (f" ± {num(v.sd)}" if v.sd is not None else "")
    if isinstance(v, Interval):
        if v.value is None:
            return "-"
        ci = f" [{num(v.low, True)}, {num(v.high, True)}]" if v.low is not None and v.high is not None else ""
        return num(v.value, kind == "pp") + ci
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, float)):
        return num(v, kind == "pp")
    return str(v)
