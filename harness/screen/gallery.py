"""``index.html``: one self-contained page per screen (inline CSS and SVG, pictures beside it, no script).

The counts per class, the flight's capture positions as a plot (longitude east, latitude north, equal metres per
pixel both ways; frames with findings in red, sized by their count), the frames listed as failed or registered
only by the prior, then one gallery per class (classes by their count), its findings sorted by score, each with
its thumbnail, frame (linked to the frame's overlay), score, contrast and box temperatures.
"""

from __future__ import annotations

import math
from collections import Counter
from html import escape
from typing import Any, Sequence

from harness.screen.findings import registration_note
from harness.screen.outputs import score_digits

#: findings shown per class (all are in findings.csv)
MAX_CARDS = 400

CSS = """
:root { --fg: #1d2329; --muted: #5b6670; --line: #d5dbe1; --head: #eef2f6; --warn: #b00020; }
* { box-sizing: border-box; }
body { font: 14px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif; color: var(--fg);
       margin: 0 auto; padding: 24px 32px 48px; max-width: 1400px; }
h1 { font-size: 24px; margin: 0 0 4px; }
h2 { font-size: 20px; margin: 28px 0 8px; border-bottom: 2px solid var(--line); }
.meta { color: var(--muted); margin: 0 0 12px; }
table { border-collapse: collapse; font-variant-numeric: tabular-nums; }
th, td { border: 1px solid var(--line); padding: 3px 8px; text-align: left; } th { background: var(--head); }
td.r { text-align: right; }
.cards { display: flex; flex-wrap: wrap; gap: 10px; }
.card { border: 1px solid var(--line); border-radius: 6px; padding: 6px; width: 260px; font-size: 12.5px; }
.card img { width: 100%; height: auto; display: block; margin-bottom: 4px; }
.card .score { font-weight: 700; }
.warn { color: var(--warn); }
svg.map { border: 1px solid var(--line); background: #fafbfc; max-width: 100%; height: auto; }
footer { margin-top: 40px; color: var(--muted); font-size: 12px; border-top: 1px solid var(--line); padding-top: 8px; }
"""


def _num(v: Any, digits: int = 1, sign: bool = False) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:+.{digits}f}" if sign else f"{v:.{digits}f}"


def map_svg(frames: Sequence[dict[str, Any]], width: int = 640, height: int = 420) -> str:
    """The capture positions (equirectangular, metres) in capture order, findings per frame as red dots."""
    pts = [
        (f["position"]["lon"], f["position"]["lat"], len(f.get("findings") or []), f["frame"])
        for f in frames
        if (f.get("position") or {}).get("lat") is not None and (f.get("position") or {}).get("lon") is not None
    ]
    if not pts:
        return "<p class='meta'>No capture carries a GPS position (DJI XMP GpsLatitude/GpsLongitude).</p>"
    lat0 = sum(p[1] for p in pts) / len(pts)
    kx = 111_320.0 * math.cos(math.radians(lat0))
    xs = [p[0] * kx for p in pts]
    ys = [p[1] * 110_540.0 for p in pts]
    span = max(max(xs) - min(xs), max(ys) - min(ys), 1.0)
    pad = 30
    s = min(width - 2 * pad, height - 2 * pad) / span
    cx, cy = (max(xs) + min(xs)) / 2, (max(ys) + min(ys)) / 2

    def at(x: float, y: float) -> tuple[float, float]:
        return width / 2 + (x - cx) * s, height / 2 - (y - cy) * s

    xy = [at(x, y) for x, y in zip(xs, ys)]
    path = " ".join(f"{x:.1f},{y:.1f}" for x, y in xy)
    dots = []
    for (x, y), (_, _, n, name) in zip(xy, pts):
        r = 3.0 if n == 0 else 4.0 + min(8.0, 2.0 * math.sqrt(n))
        colour = "#7a8691" if n == 0 else "#c62828"
        dots.append(
            f"<circle cx='{x:.1f}' cy='{y:.1f}' r='{r:.1f}' fill='{colour}' fill-opacity='0.8'>"
            f"<title>{escape(name)}: {n} finding(s)</title></circle>"
        )
    unit = 10 ** math.floor(math.log10(max(span / 4, 1e-3)))
    bar_m = max(k * unit for k in (1, 2, 5) if k * unit <= max(span / 4, 1e-3))
    bar = (
        f"<line x1='{pad}' y1='{height - 12}' x2='{pad + bar_m * s:.1f}' y2='{height - 12}' stroke='#1d2329' "
        f"stroke-width='2'/><text x='{pad}' y='{height - 16}' font-size='11'>{bar_m:g} m</text>"
    )
    return (
        f"<svg class='map' viewBox='0 0 {width} {height}' width='{width}' height='{height}' "
        f"xmlns='http://www.w3.org/2000/svg'><polyline points='{path}' fill='none' stroke='#b0bac4' "
        f"stroke-width='1'/>{''.join(dots)}{bar}<text x='{width - pad}' y='18' font-size='11' "
        f"text-anchor='end'>N up, {len(pts)} captures with GPS</text></svg>"
    )


def render(
    title: str,
    frames: Sequence[dict[str, Any]],
    findings: Sequence[dict[str, Any]],
    categories: Sequence[str],
    failures: Sequence[tuple[str, str]],
    summary: Sequence[str],
    version: str,
) -> str:
    counts = Counter(f["class"] for f in findings)
    order = sorted(categories, key=lambda c: (-counts.get(c, 0), list(categories).index(c)))
    rows = "".join(f"<tr><td>{escape(c)}</td><td class='r'>{counts.get(c, 0)}</td></tr>" for c in order)
    out = [
        f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>{escape(title)}</title>"
        f"<style>{CSS}</style></head><body><h1>{escape(title)}</h1>"
    ]
    out += [f"<p class='meta'>{escape(line)}</p>" for line in summary]
    out.append(
        f"<h2>Findings per class</h2><table><tr><th>class</th><th>findings</th></tr>{rows}"
        f"<tr><td><b>total</b></td><td class='r'><b>{len(findings)}</b></td></tr></table>"
    )
    out.append(f"<h2>Flight</h2>{map_svg(frames)}")
    prior = [f for f in frames if str(f.get("route", "")).startswith("prior (")]
    if failures or prior:
        out.append("<h2>Frames to check</h2><ul>")
        out += [f"<li class='warn'>{escape(p)}: {escape(r)}</li>" for p, r in failures]
        out += [
            f"<li>{escape(f['frame'])}: {escape(f['route'])} "
            f"({escape(registration_note(f.get('registration') or {}))})</li>"
            for f in prior
        ]
        out.append("</ul>")
    for c in order:
        mine = sorted((f for f in findings if f["class"] == c), key=lambda f: -f["score"])
        if not mine:
            continue
        out.append(f"<h2 id='{escape(c)}'>{escape(c)} ({len(mine)})</h2><div class='cards'>")
        digits = max(3, score_digits([f["score"] for f in mine[:MAX_CARDS]]))
        for f in mine[:MAX_CARDS]:
            tip = f"box {', '.join(f'{v:.0f}' for v in f['box_thermal'])} (thermal px)"
            where = f"{_num(f.get('lat'), 6)}, {_num(f.get('lon'), 6)}" if f.get("lat") is not None else "no GPS"
            if f.get("lat") is not None and f.get("gps_source") == "exif":
                where += " (EXIF GPS)"
            link = escape(f.get("overlay") or "")
            approx = ""
            if f.get("temperature_route") == "approximate":
                approx = f" <span class='warn'>(approximate, &plusmn;{_num(f.get('t_bound_c'), 3)} &deg;C)</span>"
            out.append(
                f"<div class='card'><a href='{link}'><img loading='lazy' src='{escape(f.get('crop') or '')}' "
                f"alt='{escape(c)}'></a><span class='score'>{f['score']:.{digits}f}</span> "
                f"&Delta;T {_num(f.get('delta_t'), 1, True)} &deg;C &middot; max {_num(f.get('t_max'))} &deg;C"
                f"{approx}<br>"
                f"<a href='{link}' title='{escape(tip)}'>{escape(f['frame'])}</a><br>"
                f"<span class='meta'>{escape(where)}</span></div>"
            )
        if len(mine) > MAX_CARDS:
            out.append(f"<p class='meta'>{len(mine) - MAX_CARDS} more in findings.csv</p>")
        out.append("</div>")
    out.append(f"<footer>rgbt-harness {escape(version)} &middot; harness screen</footer></body></html>")
    return "\n".join(out)
