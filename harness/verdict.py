"""Whether a rerun of a reference cell reproduces it, and what to compare before it trains.

**The verdict on a difference** (``judge``). A rerun that is not identical to its reference run (metrics, per-category
AP, support and predictions all equal) is judged against the references' own training variance: the seeds of the
same detector, encoding and fold in the reference store (the rerun cell's own seed included: each is one training
run of that cell's recipe). For each of mAP50 and mAP50:95, the seeds' values ``x_1 .. x_n`` give a 95 % prediction
interval for one new training run::

    mean(x) +/- t_{0.975, n-1} * sd(x) * sqrt(1 + 1/n)          sd: the sample SD (n - 1 in the denominator)

A rerun whose value lies inside the interval for both metrics is ``within training variance``: it differs from the
reference no more than training the cell with another seed does, so the difference does not show a failure to
reproduce. A value outside either interval is ``outside training variance``. With the references' three seeds the
interval is wide (t = 4.30 at 2 degrees of freedom): the verdict separates a broken rerun from seed-to-seed noise, it
does not certify digits. The interval is cut to 0..1, the range of an mAP. Fewer than two seeds give no interval, and
no verdict (``not judged``).

**The environment a result depends on** (``environment_differences``): the facts of a run's ``environment`` record
(``harness.provenance.environment_facts`` and ``harness.engine.runtime.environment``) flattened to dotted names
(``cpu.model``, ``torch_build.onednn``, ``packages.opencv``), compared fact by fact; a fact the reference did not
record is listed as unknown, never as a difference.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Iterable, Mapping, Sequence

#: The metrics a verdict judges (``metrics.json`` ``metrics`` keys) and how they are named to a reader.
METRICS = {"mAP50": "mAP50", "mAP50_95": "mAP50:95"}
#: Coverage of the prediction interval.
LEVEL = 0.95
IDENTICAL = "identical"
WITHIN = "within training variance"
OUTSIDE = "outside training variance"
NOT_JUDGED = "not judged"


def t_quantile(p: float, df: int) -> float:
    """The ``p`` quantile of Student's t distribution with ``df`` degrees of freedom."""
    from scipy.stats import t

    return float(t.ppf(p, df))


@dataclass(frozen=True)
class Interval:
    """A prediction interval for one new value drawn like ``n`` observed ones."""

    mean: float
    sd: float
    n: int
    t: float
    low: float
    high: float

    def contains(self, x: float) -> bool:
        return self.low <= x <= self.high


def prediction_interval(
    values: Sequence[float], level: float = LEVEL, low: float = -math.inf, high: float = math.inf
) -> Interval:
    """``mean +/- t_{(1+level)/2, n-1} * sd * sqrt(1 + 1/n)`` of ``values`` (at least two), cut to the range
    ``[low, high]`` the values can take."""
    xs = [float(v) for v in values]
    n = len(xs)
    if n < 2:
        raise ValueError(f"a prediction interval needs at least two values, got {n}")
    mean = sum(xs) / n
    sd = math.sqrt(sum((x - mean) ** 2 for x in xs) / (n - 1))
    t = t_quantile(0.5 + level / 2, n - 1)
    half = t * sd * math.sqrt(1 + 1 / n)
    return Interval(mean, sd, n, t, max(mean - half, low), min(mean + half, high))


@dataclass(frozen=True)
class MetricVerdict:
    metric: str
    reference: float | None
    rerun: float | None
    interval: Interval | None
    inside: bool | None


@dataclass
class Verdict:
    """``result`` is one of ``identical``, ``within training variance``, ``outside training variance``, ``not
    judged``; ``metrics`` holds the numbers behind it, ``seeds`` the reference seeds the intervals come from."""

    result: str
    seeds: list[int] = field(default_factory=list)
    metrics: list[MetricVerdict] = field(default_factory=list)
    why: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def judge(
    reference: Mapping[str, float | None],
    rerun: Mapping[str, float | None],
    seeds: Mapping[int, Mapping[str, float | None]],
    identical: bool,
    level: float = LEVEL,
) -> Verdict:
    """The verdict on a rerun (see the module docstring): ``reference`` and ``rerun`` map ``METRICS`` keys to the
    cell's values, ``seeds`` every reference seed of the cell's detector, encoding and fold to its values."""
    rows: list[MetricVerdict] = []
    used = sorted(seeds)
    missing = []
    for key in METRICS:
        values = [seeds[s].get(key) for s in used]
        ref, new = reference.get(key), rerun.get(key)
        if ref is None or new is None or len([v for v in values if v is not None]) < 2:
            missing.append(METRICS[key])
            rows.append(MetricVerdict(key, ref, new, None, None))
            continue
        iv = prediction_interval([float(v) for v in values if v is not None], level, 0.0, 1.0)  # mAP: 0..1
        rows.append(MetricVerdict(key, ref, new, iv, iv.contains(float(new))))
    if identical:
        return Verdict(IDENTICAL, used, rows)
    if missing:
        return Verdict(
            NOT_JUDGED,
            used,
            rows,
            f"{', '.join(missing)}: needs the values of at least two reference seeds and of the rerun "
            f"(seeds found: {', '.join(map(str, used)) or 'none'})",
        )
    outside = [METRICS[r.metric] for r in rows if not r.inside]
    if outside:
        return Verdict(OUTSIDE, used, rows, f"{', '.join(outside)} outside the seeds' {100 * level:g} % interval")
    return Verdict(WITHIN, used, rows)


def verdict_lines(v: Verdict) -> list[str]:
    """The verdict as text lines (under 100 columns)."""
    lines = [f"verdict: {v.result}" + (f" ({v.why})" if v.why else "")]
    for r in v.metrics:
        line = f"  {METRICS.get(r.metric, r.metric):<8} reference {_num(r.reference)}  rerun {_num(r.rerun)}"
        if r.interval is not None:
            iv = r.interval
            line += f"  {'in' if r.inside else 'OUTSIDE'} [{iv.low:.4f}, {iv.high:.4f}]"
            line += f"  seeds {iv.mean:.4f} SD {iv.sd:.4f}"
        lines.append(line)
    first = next((r.interval for r in v.metrics if r.interval is not None), None)
    if first is not None:
        lines.append(
            f"  interval: mean +/- t({first.n - 1} df) {first.t:.2f} x SD x sqrt(1 + 1/{first.n}) of reference seeds "
            f"{', '.join(map(str, v.seeds))} ({100 * LEVEL:g} % for one run)"
        )
    return lines


def _num(x: float | None) -> str:
    return "?" if x is None else f"{x:.4f}"


# ------------------------------------------------------------------------------------------------- environment
#: Facts of an ``environment`` record that do not change what a run computes (or say only where it ran).
NOT_FACTS = {"device", "cpu_count"}
#: How a flattened fact is named to a reader.
FACT_LABELS = {
    "cpu.vendor": "CPU vendor",
    "cpu.model": "CPU model",
    "cpu.isa": "CPU instruction sets",
    "cpu.machine": "machine",
    "cpu_capability": "torch CPU capability (ISA used)",
    "threads": "torch threads",
    "torch_build.mkl": "MKL build",
    "torch_build.onednn": "oneDNN build",
    "torch_build.blas": "BLAS",
    "torch_build.lapack": "LAPACK",
    "torch_build.parallel": "ATen parallel backend",
    "torch_deterministic": "torch deterministic algorithms",
    "isa_env.ONEDNN_MAX_CPU_ISA": "ONEDNN_MAX_CPU_ISA",
    "isa_env.ATEN_CPU_CAPABILITY": "ATEN_CPU_CAPABILITY",
}


def flatten_environment(env: Mapping[str, Any]) -> dict[str, Any]:
    """``{"cpu": {"cache": {"L2": "1024K"}}}`` -> ``{"cpu.cache.L2": "1024K"}``; package versions recorded both at the
    top level (``torch``) and under ``packages`` are named once, as ``packages.<name>``."""
    out: dict[str, Any] = {}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, Mapping) and value:
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        elif prefix:
            out[prefix] = value

    walk("", env)
    for key in ("torch", "numpy", "opencv", "python"):
        if key in out and key != "python":
            out.setdefault(f"packages.{key}", out[key])
            del out[key]
    return {k: v for k, v in out.items() if k not in NOT_FACTS}


def fact_label(key: str) -> str:
    if key in FACT_LABELS:
        return FACT_LABELS[key]
    if key.startswith("cpu.cache."):
        return f"{key.removeprefix('cpu.cache.')} cache"
    if key.startswith("packages."):
        return key.removeprefix("packages.")
    return key


@dataclass
class EnvironmentComparison:
    differ: list[dict[str, Any]] = field(default_factory=list)  # {"fact", "label", "reference", "here"}
    unknown: list[str] = field(default_factory=list)  # facts recorded here, not by the reference
    same: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def lines(self, width: int = 100) -> list[str]:
        import textwrap

        out = []
        if self.differ:
            out.append("environment differs from the reference run's:")
            for d in self.differ:
                out += textwrap.wrap(
                    f"{d['label']}: reference {_fact(d['reference'])}, here {_fact(d['here'])}",
                    width,
                    initial_indent="  ",
                    subsequent_indent="    ",
                )
        else:
            out.append("environment: every fact the reference run recorded is the same here")
        if self.unknown:
            out += textwrap.wrap(
                "not recorded by the reference run (unknown there, not a difference): "
                + ", ".join(fact_label(k) for k in self.unknown),
                width,
                initial_indent="  ",
                subsequent_indent="    ",
            )
        return out


def _fact(v: Any) -> str:
    return ",".join(map(str, v)) if isinstance(v, (list, tuple)) else str(v)


def environment_differences(
    reference: Mapping[str, Any], here: Mapping[str, Any], ignore: Iterable[str] = ()
) -> EnvironmentComparison:
    """Compare two ``environment`` records fact by fact (``flatten_environment``); ``ignore``: facts left out."""
    a, b = flatten_environment(reference), flatten_environment(here)
    skip = set(ignore)
    out = EnvironmentComparison()
    for key in sorted(a.keys() | b.keys()):
        if key in skip:
            continue
        if key not in a or a[key] is None:
            if b.get(key) is not None:
                out.unknown.append(key)
            continue
        if key not in b:
            continue  # recorded by the reference only: this machine's record has no such fact
        if _norm(a[key]) != _norm(b[key]):
            out.differ.append({"fact": key, "label": fact_label(key), "reference": a[key], "here": b[key]})
        else:
            out.same.append(key)
    return out


def _norm(v: Any) -> Any:
    if isinstance(v, str):
        return v.strip().lower()
    if isinstance(v, (list, tuple)):
        return [_norm(x) for x in v]
    return v


__all__ = [
    "IDENTICAL",
    "METRICS",
    "NOT_JUDGED",
    "OUTSIDE",
    "WITHIN",
    "EnvironmentComparison",
    "Interval",
    "MetricVerdict",
    "Verdict",
    "environment_differences",
    "flatten_environment",
    "judge",
    "prediction_interval",
    "verdict_lines",
]
