"""The cost/quality frontier as a standalone SVG for a paper (issue 38): one panel per animation, cost (x)
against proportion correct with its interval (y), the criterion as a dashed line, the Pareto set joined, the
cheapest indistinguishable level ringed.  Hand-written SVG (no plotting library in the service); each point is a
``<circle>`` carrying ``data-condition``, ``data-pareto`` and ``data-cheapest`` for tests and tools."""

from __future__ import annotations

from collections.abc import Sequence
from xml.sax.saxutils import escape

from .psychometric import Frontier

PANEL_W, PANEL_H = 360, 260
MARGIN_L, MARGIN_R, MARGIN_T, MARGIN_B = 56, 16, 30, 44
UNITS = {"cost_ms_per_1000": "ms per 1,000 characters per frame", "bytes": "bytes"}


def _fmt(v: float) -> str:
    return f"{v:.4g}"


def _panel(f: Frontier, ox: float) -> list[str]:
    costs = [p.cost for p in f.points]
    lo, hi = min(costs), max(costs)
    pad = (hi - lo) * 0.08 or max(abs(hi), 1.0) * 0.1
    lo, hi = lo - pad, hi + pad
    ylo, yhi = 0.4 if f.criterion < 0.9 else 0.0, 1.0
    w, h = PANEL_W - MARGIN_L - MARGIN_R, PANEL_H - MARGIN_T - MARGIN_B

    def X(c: float) -> float:
        return ox + MARGIN_L + (c - lo) / (hi - lo) * w

    def Y(p: float) -> float:
        return MARGIN_T + (yhi - min(max(p, ylo), yhi)) / (yhi - ylo) * h

    out = [f'<g class="panel" data-animation="{escape(f.animation)}">',
           f'<text x="{ox + MARGIN_L + w / 2:.1f}" y="18" text-anchor="middle" font-weight="bold">'
           f"{escape(f.animation)}</text>",
           f'<rect x="{ox + MARGIN_L}" y="{MARGIN_T}" width="{w}" height="{h}" fill="none" stroke="#444"/>']
    for t in (0.5, 0.6, 0.7, 0.8, 0.9, 1.0) if ylo >= 0.4 else (0.0, 0.25, 0.5, 0.75, 1.0):
        out.append(f'<text x="{ox + MARGIN_L - 6}" y="{Y(t) + 4:.1f}" text-anchor="end" font-size="10">{t:.2f}'
                   "</text>")
    for i in range(5):
        c = lo + (hi - lo) * (i + 0.5) / 5
        out.append(f'<text x="{X(c):.1f}" y="{MARGIN_T + h + 14}" text-anchor="middle" font-size="10">{_fmt(c)}'
                   "</text>")
    out.append(f'<text x="{ox + MARGIN_L + w / 2:.1f}" y="{PANEL_H - 8}" text-anchor="middle" font-size="11">'
               f"cost ({escape(UNITS.get(f.cost_metric, f.cost_metric))})</text>")
    out.append(f'<text transform="translate({ox + 14},{MARGIN_T + h / 2:.1f}) rotate(-90)" text-anchor="middle" '
               'font-size="11">proportion correct</text>')
    out.append(f'<line class="criterion" x1="{ox + MARGIN_L}" x2="{ox + MARGIN_L + w}" y1="{Y(f.criterion):.1f}" '
               f'y2="{Y(f.criterion):.1f}" stroke="#c33" stroke-dasharray="4 3"/>')
    front = sorted((p for p in f.points if p.pareto), key=lambda p: p.cost)
    if len(front) > 1:
        pts = " ".join(f"{X(p.cost):.1f},{Y(p.detection.p):.1f}" for p in front)
        out.append(f'<polyline class="pareto" points="{pts}" fill="none" stroke="#36c" stroke-width="1.5"/>')
    for p in f.points:
        x, d = X(p.cost), p.detection
        out.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{Y(d.low):.1f}" y2="{Y(d.high):.1f}" stroke="#333"/>')
        cheapest = f.cheapest_indistinguishable is not None and p.condition == f.cheapest_indistinguishable.condition
        fill = "#36c" if p.pareto else "#fff"
        out.append(f'<circle cx="{x:.1f}" cy="{Y(d.p):.1f}" r="4" fill="{fill}" stroke="#36c" '
                   f'data-condition="{escape(p.condition)}" data-level="{_fmt(p.level)}" data-cost="{_fmt(p.cost)}" '
                   f'data-p="{d.p:.4f}" data-low="{d.low:.4f}" data-high="{d.high:.4f}" '
                   f'data-pareto="{str(p.pareto).lower()}" data-cheapest="{str(cheapest).lower()}">'
                   f"<title>{escape(p.condition)}: {d.correct}/{d.trials} correct, cost {_fmt(p.cost)}</title>"
                   "</circle>")
        if cheapest:
            out.append(f'<circle class="cheapest" cx="{x:.1f}" cy="{Y(d.p):.1f}" r="8" fill="none" stroke="#2a2" '
                       'stroke-width="2"/>')
        out.append(f'<text x="{x + 6:.1f}" y="{Y(d.p) - 6:.1f}" font-size="9">{escape(p.condition)}</text>')
    out.append("</g>")
    return out


def svg(frontiers: Sequence[Frontier]) -> str:
    """One SVG document with a panel per animation (side by side)."""
    width = PANEL_W * max(1, len(frontiers))
    body = [line for i, f in enumerate(frontiers) for line in _panel(f, i * PANEL_W)]
    return "\n".join([f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{PANEL_H}" '
                      f'viewBox="0 0 {width} {PANEL_H}" font-family="sans-serif">',
                      f'<rect width="{width}" height="{PANEL_H}" fill="#fff"/>', *body, "</svg>", ""])
