"""The sample-matched guard: numbers are compared only when they were measured on the same samples.

Two results of the same dataset and fold are sample-matched when their supports agree: the hash of the
evaluated image ids, the image count, the instance count and the instances per category. ``check_sample_matched``
refuses a comparison that breaks this with a message naming every difference, or, when the caller allows it
explicitly, returns a short label to print in every table that shows those numbers.
"""

from __future__ import annotations

from typing import Any, Iterable, Mapping

from harness.errors import HarnessError


class SampleMismatchError(HarnessError):
    """Results compared side by side were evaluated on different samples."""


def _as_items(results: Any) -> list[tuple[str, Mapping[str, Any]]]:
    """(label, metrics dict) pairs from a mapping, a list of metrics dicts, or results-store ``Run`` objects."""
    if isinstance(results, Mapping) and "support" in results:
        results = [results]
    pairs: Iterable[tuple[Any, Any]]
    if isinstance(results, Mapping):
        pairs = results.items()
    else:
        pairs = ((None, r) for r in results)
    out = []
    for i, (label, item) in enumerate(pairs):
        if hasattr(item, "read_metrics") and hasattr(item, "key"):
            metrics = item.read_metrics()
            label = label or str(item.key)
        elif isinstance(item, Mapping):
            metrics = item
        else:
            raise SampleMismatchError(
                f"cannot check item {i} ({type(item).__name__}): give metrics dicts or results-store runs"
            )
        if label is None:
            run = metrics.get("run") or {}
            label = (
                "/".join(str(run[k]) for k in ("dataset", "detector", "encoding", "fold", "seed") if k in run)
                or f"result {i}"
            )
        out.append((str(label), metrics))
    return out


def _group_key(metrics: Mapping[str, Any]) -> tuple[str, str]:
    run = metrics.get("run") or {}
    return (str(run.get("dataset", "")), str(run.get("fold", "")))


def _differences(items: list[tuple[str, Mapping[str, Any]]]) -> tuple[list[str], list[str]]:
    """(short kinds, detailed sentences) of what differs between the supports of ``items``."""
    ref_label, ref = items[0]
    ref_s = ref.get("support") or {}
    kinds: list[str] = []
    details: list[str] = []
    checks = (("image_ids_sha1", "image-id hash"), ("images", "image count"), ("instances", "instance count"))
    for label, m in items[1:]:
        s = m.get("support") or {}
        for key, what in checks:
            a, b = ref_s.get(key), s.get(key)
            if a is None or b is None:
                if "support unknown" not in kinds:
                    kinds.append("support unknown")
                details.append(f"{what}: not recorded for {ref_label if a is None else label}")
            elif a != b:
                if what not in kinds:
                    kinds.append(what)
                shown_a, shown_b = (a[:12], b[:12]) if key == "image_ids_sha1" else (a, b)
                details.append(f"{what}: {shown_a} ({ref_label}) vs {shown_b} ({label})")
        ca, cb = ref_s.get("categories") or {}, s.get("categories") or {}
        cat_diff = [n for n in sorted(set(ca) | set(cb)) if ca.get(n, 0) != cb.get(n, 0)]
        if cat_diff and ca and cb:
            if "per-category instances" not in kinds:
                kinds.append("per-category instances")
            shown = ", ".join(f"{n} {ca.get(n, 0)} vs {cb.get(n, 0)}" for n in cat_diff[:5])
            details.append(f"per-category instances ({ref_label} vs {label}): {shown}")
    return kinds, details


#: What the refusal suggests when the caller names no other way (the Python API's own option).
API_HINT = (
    "Re-evaluate every detector on the same prepared split, or allow the comparison explicitly "
    "(allow=True) so that every table showing these numbers is labelled as not sample-matched."
)


def check_sample_matched(results: Any, allow: bool = False, hint: str | None = None) -> str | None:
    """Refuse (``SampleMismatchError``) to compare results measured on different samples.

    ``results``: a list of metrics dicts (``evaluate`` output or metrics.json contents), a ``{label: metrics}``
    mapping, or results-store ``Run`` objects. Results are compared within each (dataset, fold) of their ``run``
    section. Returns ``None`` when everything matches; with ``allow=True`` a mismatch returns a label such as
    ``"NOT sample-matched: image count, instance count differ"`` instead of raising. ``hint`` replaces the
    refusal's last sentence (what to do), so that a command can name its own option instead of ``allow=True``.
    """
    items = _as_items(results)
    groups: dict[tuple[str, str], list[tuple[str, Mapping[str, Any]]]] = {}
    for label, m in items:
        groups.setdefault(_group_key(m), []).append((label, m))
    all_kinds: list[str] = []
    lines: list[str] = []
    for (dataset, fold), members in groups.items():
        if len(members) < 2:
            continue
        kinds, details = _differences(members)
        if not details:
            continue
        where = " ".join(x for x in (f"dataset {dataset!r}" if dataset else "", f"fold {fold!r}" if fold else "") if x)
        lines.append(f"{where or 'results'}: " + "; ".join(details))
        all_kinds.extend(k for k in kinds if k not in all_kinds)
    if not lines:
        return None
    if allow:
        return "NOT sample-matched: " + ", ".join(all_kinds) + " differ"
    raise SampleMismatchError(
        "refusing to compare results evaluated on different samples:\n  "
        + "\n  ".join(lines)
        + "\n"
        + (hint or API_HINT)
    )
