"""Horizontal overflow of the report's HTML tables in headless Chromium at a given window width.

    .venv/bin/python benchmarks/report_html_width.py [--width 1400] [--folds 4] [--old-css]

Builds a report from a synthetic store (the test fixtures: long detector names, ``--folds`` held-out folds, extra
encodings), opens it in ``/usr/bin/chromium --headless --dump-dom`` and prints, per table wrapper, how many pixels
it would scroll horizontally (``scrollWidth - clientWidth``; 0 = fits). ``--old-css`` restores the earlier table
style (no wrapping in headers, wider padding) in the same page, for comparison.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

PROBE = """<script>window.addEventListener('load', () => {
  const w = [...document.querySelectorAll('.table-wrap')].map(e => [
    (e.previousElementSibling || {}).textContent || '', e.scrollWidth - e.clientWidth]);
  document.body.setAttribute('data-overflow', JSON.stringify(w)); });</script></body>"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=1400)
    ap.add_argument("--folds", type=int, default=4)
    ap.add_argument("--old-css", action="store_true")
    args = ap.parse_args()
    from harness.report import build_report
    from report_fixtures import synthetic_store

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        folds = tuple(f"P{i + 1}" for i in range(args.folds - 1)) + (f"P{args.folds}+P{args.folds + 1}",)
        store = synthetic_store(
            root / "s",
            folds=folds,
            per_fold=4,
            detectors={"a-rather-long-detector-name": "strong", "beta": "weak", "gamma": "weak"},
            encodings={"beta": ["ir8", "none"]},
            profiles={"a-rather-long-detector-name": (3_210_000, 8.2), "beta": (1_100_000, 2.5)},
        )
        build_report(store, out=root / "rep", resamples=10)
        html = (root / "rep" / "report.html").read_text()
        if args.old_css:
            html = (
                html.replace("th, td.l { white-space: normal; }", "")
                .replace("padding: 3px 6px", "padding: 4px 8px")
                .replace("th { font-size: 12.5px; }", "")
            )
        page = root / "rep" / "probe.html"
        page.write_text(html.replace("</body>", PROBE))
        out = subprocess.run(
            [
                "/usr/bin/chromium",
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                f"--window-size={args.width},3000",
                "--dump-dom",
                page.as_uri(),
            ],
            capture_output=True,
            text=True,
            timeout=180,
        )
    m = re.search(r'data-overflow="([^"]*)"', out.stdout)
    if not m:
        raise SystemExit(f"chromium gave no measurement: {out.stderr[-400:]}")
    rows = json.loads(m.group(1).replace("&quot;", '"'))
    for title, px in rows:
        print(f"{px:5d} px  {title.strip()[:80]}")
    widest = max((px for _, px in rows), default=0)
    print(f"widest overflow at {args.width} px: {widest} px over {len(rows)} tables")
    print(f"target: no table scrolls horizontally at {args.width} px (0 px) -> {'met' if widest <= 0 else 'NOT met'}")


if __name__ == "__main__":
    main()
