// Small SVG chart helpers for the dashboard (no library, nothing fetched from elsewhere).
"use strict";

const Charts = (() => {
  const NS = "http://www.w3.org/2000/svg";

  function el(tag, attrs = {}, text) {
    const node = document.createElementNS(NS, tag);
    for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
    if (text !== undefined) node.textContent = text;
    return node;
  }

  // The size is set once the legend's height is known (see legend).
  function svg(title) {
    const root = el("svg", { role: "img" });
    root.appendChild(el("title", {}, title));
    return root;
  }

  const size = (root, width, height) => root.setAttribute("viewBox", `0 0 ${width} ${height}`);

  // Label widths measured with the font of `.chart text` (dashboard.css; SVG text is in viewBox units), not
  // guessed from the number of characters, so that neighbouring labels never overlap.
  const measure = (() => {
    const ctx = document.createElement("canvas").getContext("2d");
    ctx.font = "12px system-ui, sans-serif";
    return (text) => ctx.measureText(text).width;
  })();
  const LEGEND_ROW = 18;

  // Swatch and label per item from (x, 16), wrapped into as many rows as the width up to maxX needs; returns
  // the height the rows beyond the first take, by which the chart below moves down.
  function legend(root, items, x, maxX) {
    let cx = x, y = 16;
    for (const item of items) {
      const w = 16 + measure(item.label);
      if (cx > x && cx + w > maxX) { cx = x; y += LEGEND_ROW; }
      root.appendChild(el("rect", { x: cx, y: y - 9, width: 12, height: 12, fill: item.color, rx: 2 }));
      root.appendChild(el("text", { x: cx + 16, y: y + 1 }, item.label));
      cx += w + 12;
    }
    return y - 16;
  }

  const pct = (x) => `${Math.round(100 * x)} %`;

  // Likert answers as diverging stacked bars: what favours the keyframe clip goes left of the centre line,
  // what favours the hybrid right, "equal" straddles it.
  function diverging(rows, categories, title) {
    const W = 1100, left = 150, right = 20, rowH = 30;
    const root = svg(title);
    const top = 30 + legend(root, categories, left, W - right);
    const H = top + rows.length * rowH + 30;
    size(root, W, H);
    const mid = left + (W - left - right) / 2;
    const scale = (W - left - right) / 2; // 100 % on each side
    rows.forEach((row, i) => {
      const y = top + i * rowH + 6;
      const total = categories.reduce((s, c) => s + (row.counts[c.key] || 0), 0) || 1;
      const share = categories.map((c) => (row.counts[c.key] || 0) / total);
      const neutral = share[2];
      let x = mid - (share[0] + share[1] + neutral / 2) * scale;
      root.appendChild(el("text", { x: left - 8, y: y + 13, "text-anchor": "end" }, row.label));
      share.forEach((s, k) => {
        const w = s * scale;
        if (w > 0) {
          const bar = el("rect", { x, y, width: w, height: rowH - 10, fill: categories[k].color });
          bar.appendChild(el("title", {}, `${categories[k].label}: ${row.counts[categories[k].key] || 0} (${pct(s)})`));
          root.appendChild(bar);
          if (w > 30) root.appendChild(el("text", { x: x + w / 2, y: y + 14, "text-anchor": "middle" }, pct(s)));
        }
        x += w;
      });
    });
    root.appendChild(el("line", { x1: mid, x2: mid, y1: top, y2: H - 24, class: "axis" }));
    for (const f of [-1, -0.5, 0.5, 1]) {
      const gx = mid + f * scale;
      root.appendChild(el("text", { x: gx, y: H - 8, "text-anchor": "middle", class: "muted" }, pct(Math.abs(f))));
    }
    return root;
  }

  // 100 % stacked horizontal bars.
  function stacked(rows, segments, title) {
    const W = 560, left = 140, right = 10, rowH = 28;
    const root = svg(title);
    const top = 30 + legend(root, segments, left, W - right);
    const H = top + rows.length * rowH + 10;
    size(root, W, H);
    const width = W - left - right;
    rows.forEach((row, i) => {
      const y = top + i * rowH + 4;
      const total = segments.reduce((s, seg) => s + (row[seg.key] || 0), 0) || 1;
      root.appendChild(el("text", { x: left - 8, y: y + 13, "text-anchor": "end" }, row.label));
      let x = left;
      for (const seg of segments) {
        const s = (row[seg.key] || 0) / total;
        const w = s * width;
        if (w > 0) {
          const bar = el("rect", { x, y, width: w, height: rowH - 8, fill: seg.color });
          bar.appendChild(el("title", {}, `${seg.label}: ${row[seg.key] || 0} (${pct(s)})`));
          root.appendChild(bar);
          if (w > 30) root.appendChild(el("text", { x: x + w / 2, y: y + 14, "text-anchor": "middle" }, pct(s)));
        }
        x += w;
      }
    });
    return root;
  }

  // Point estimates with intervals on a fixed axis (e.g. -2..2), one row each.
  function forest(rows, lo, hi, title) {
    const W = 1100, left = 150, right = 30, rowH = 26, top = 10;
    const H = top + rows.length * rowH + 30;
    const root = svg(title);
    size(root, W, H);
    const x = (v) => left + ((v - lo) / (hi - lo)) * (W - left - right);
    for (let t = lo; t <= hi; t += 0.5) {
      root.appendChild(el("line", { x1: x(t), x2: x(t), y1: top, y2: H - 24, class: t === 0 ? "axis" : "grid" }));
      root.appendChild(el("text", { x: x(t), y: H - 8, "text-anchor": "middle", class: "muted" }, String(t)));
    }
    rows.forEach((row, i) => {
      const y = top + i * rowH + rowH / 2;
      root.appendChild(el("text", { x: left - 8, y: y + 4, "text-anchor": "end" }, row.label));
      if (row.value === null || row.value === undefined) {
        root.appendChild(el("text", { x: x(0) + 6, y: y + 4, class: "muted" }, row.missing || "no data"));
        return;
      }
      if (row.ci) {
        root.appendChild(el("line", { x1: x(Math.max(lo, row.ci[0])), x2: x(Math.min(hi, row.ci[1])), y1: y, y2: y,
                                       stroke: "#1f5fbf", "stroke-width": 2 }));
      }
      const dot = el("circle", { cx: x(row.value), cy: y, r: 5, fill: "#1f5fbf" });
      dot.appendChild(el("title", {}, `${row.label}: ${row.value.toFixed(2)}${row.ci ? ` [${row.ci[0].toFixed(2)}, ${row.ci[1].toFixed(2)}]` : ""}`));
      root.appendChild(dot);
    });
    return root;
  }

  // Grouped horizontal bars of signed values (e.g. mean score per group), centred on 0.
  function groupedSigned(rows, groups, lo, hi, title) {
    const W = 560, left = 140, right = 10;
    const barH = 8, rowH = Math.max(24, groups.length * (barH + 2) + 8);
    const root = svg(title);
    const top = 30 + legend(root, groups, left, W - right);
    const H = top + rows.length * rowH + 24;
    size(root, W, H);
    const x = (v) => left + ((v - lo) / (hi - lo)) * (W - left - right);
    root.appendChild(el("line", { x1: x(0), x2: x(0), y1: top, y2: H - 20, class: "axis" }));
    for (const t of [lo, hi]) root.appendChild(el("text", { x: x(t), y: H - 6, "text-anchor": t === lo ? "start" : "end", class: "muted" }, String(t)));
    rows.forEach((row, i) => {
      const y0 = top + i * rowH + 4;
      root.appendChild(el("text", { x: left - 8, y: y0 + rowH / 2, "text-anchor": "end" }, row.label));
      groups.forEach((g, k) => {
        const v = row.values[g.key];
        if (v === undefined || v === null) return;
        const y = y0 + k * (barH + 2);
        const bar = el("rect", { x: Math.min(x(0), x(v)), y, width: Math.abs(x(v) - x(0)) || 1, height: barH, fill: g.color });
        bar.appendChild(el("title", {}, `${g.label}: ${v.toFixed(2)}`));
        root.appendChild(bar);
      });
    });
    return root;
  }

  // Vertical grouped bars of non-negative values (e.g. a metric per clip), groups along x.
  function columns(groups, series, title, format) {
    const W = 1100, left = 50, right = 10, bottom = 30;
    const root = svg(title);
    const top = 30 + legend(root, series, left, W - right);
    const H = top + 190;
    size(root, W, H);
    const max = Math.max(1e-9, ...groups.flatMap((g) => series.map((s) => g.values[s.key] || 0)));
    const groupW = (W - left - right) / groups.length;
    const barW = Math.min(40, (groupW - 20) / series.length);
    const y = (v) => H - bottom - (v / max) * (H - top - bottom - 10);
    root.appendChild(el("line", { x1: left, x2: W - right, y1: H - bottom, y2: H - bottom, class: "axis" }));
    root.appendChild(el("text", { x: left - 6, y: y(max) + 4, "text-anchor": "end", class: "muted" }, format(max)));
    groups.forEach((g, i) => {
      const gx = left + i * groupW + (groupW - barW * series.length) / 2;
      series.forEach((s, k) => {
        const v = g.values[s.key];
        if (v === undefined || v === null) return;
        const bar = el("rect", { x: gx + k * barW, y: y(v), width: barW - 3, height: H - bottom - y(v), fill: s.color });
        bar.appendChild(el("title", {}, `${g.label} ${s.label}: ${format(v)}`));
        root.appendChild(bar);
      });
      root.appendChild(el("text", { x: left + (i + 0.5) * groupW, y: H - 10, "text-anchor": "middle" }, g.label));
    });
    return root;
  }

  // Lines on log-log axes (e.g. milliseconds per frame against the number of characters).
  function lines(series, title, xLabel, yLabel) {
    const W = 1100, left = 60, right = 20, bottom = 40;
    const root = svg(title);
    const top = 30 + legend(root, series, left, W - right);
    const H = top + 270;
    size(root, W, H);
    const xs = series.flatMap((s) => s.points.map((p) => p[0]));
    const ys = series.flatMap((s) => s.points.map((p) => p[1])).filter((v) => v > 0);
    const x0 = Math.log10(Math.min(...xs)), x1 = Math.max(Math.log10(Math.max(...xs)), x0 + 1);
    const y0 = Math.floor(Math.log10(Math.min(...ys))), y1 = Math.max(Math.ceil(Math.log10(Math.max(...ys))), y0 + 1);
    const x = (v) => left + ((Math.log10(v) - x0) / (x1 - x0)) * (W - left - right);
    const y = (v) => H - bottom - ((Math.log10(v) - y0) / (y1 - y0)) * (H - top - bottom);
    for (let e = y0; e <= y1; e++) {
      root.appendChild(el("line", { x1: left, x2: W - right, y1: y(10 ** e), y2: y(10 ** e), class: "grid" }));
      root.appendChild(el("text", { x: left - 6, y: y(10 ** e) + 4, "text-anchor": "end", class: "muted" }, String(10 ** e)));
    }
    root.appendChild(el("line", { x1: left, x2: W - right, y1: H - bottom, y2: H - bottom, class: "axis" }));
    for (const v of [...new Set(xs)]) root.appendChild(el("text", { x: x(v), y: H - bottom + 14, "text-anchor": "middle", class: "muted" }, String(v)));
    root.appendChild(el("text", { x: left + (W - left - right) / 2, y: H - 6, "text-anchor": "middle", class: "muted" }, xLabel));
    root.appendChild(el("text", { x: left, y: top - 2, class: "muted" }, yLabel));
    for (const s of series) {
      const pts = s.points.filter((p) => p[1] > 0);
      const d = pts.map((p, i) => `${i ? "L" : "M"}${x(p[0])},${y(p[1])}`).join(" ");
      root.appendChild(el("path", { d, fill: "none", stroke: s.color, "stroke-width": 2 }));
      for (const p of pts) {
        const dot = el("circle", { cx: x(p[0]), cy: y(p[1]), r: 3, fill: s.color });
        dot.appendChild(el("title", {}, `${s.label}: ${p[0]} characters, ${p[1].toPrecision(3)}`));
        root.appendChild(dot);
      }
    }
    return root;
  }

  return { diverging, stacked, forest, groupedSigned, columns, lines };
})();
