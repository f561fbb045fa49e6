// costseg explorer, part 2: the value-space triangle (vertex 0 bottom left, 1 bottom right, 2
// top, as report.ternary): where a point lies, the heatmap of a swept metric, the marked points.
"use strict";
const COSTSEG_TRIANGLE = (function () {
  const { DATA } = COSTSEG;
  const SQ3 = Math.sqrt(3) / 2;
  const $ = (id) => document.getElementById(id);
  const TRI = { x0: 55, y0: 370, side: 330 };
  const toXY = (w) => { const s = w[0] + w[1] + w[2];
    return [TRI.x0 + TRI.side * (w[1] + 0.5 * w[2]) / s, TRI.y0 - TRI.side * SQ3 * w[2] / s]; };
  function toWeights(x, y) {
    const c = Math.max(0, (TRI.y0 - y) / (TRI.side * SQ3));
    const b = Math.max(0, (x - TRI.x0) / TRI.side - c / 2);
    const a = Math.max(0, 1 - b - c), s = a + b + c;
    const ai = Math.round(1000 * a / s), bi = Math.round(1000 * b / s);
    return [ai / 1000, bi / 1000, Math.max(0, 1000 - ai - bi) / 1000];
  }
  const sweep = DATA.sweep;
  function selected() {
    if (!sweep) return null;
    const m = $("metric").value, c = $("cls").value, r = $("roi").value;
    return ((sweep.metrics[m] || {})[c] || {})[r] || null;
  }
  function viridis(t) {
    const stops = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];
    const x = Math.min(1, Math.max(0, t)) * 4, i = Math.min(3, Math.floor(x)), f = x - i;
    return stops[i].map((v, j) => Math.round(v + f * (stops[i + 1][j] - v)));
  }
  let HEAT = null;  // the heatmap image, redrawn when the selection changes
  function drawHeat(ctx) {
    const values = selected();
    if (!values) { HEAT = null; return; }
    const finite = values.filter((v) => v !== null);
    const lo = Math.min(...finite), hi = Math.max(...finite), n = Math.round(1 / sweepStep());
    const index = new Map(sweep.weights.map((w, k) => [`${Math.round(w[1] * n)},${Math.round(w[2] * n)}`, k]));
    HEAT = ctx.createImageData(ctx.canvas.width, ctx.canvas.height);
    for (let y = 0; y < ctx.canvas.height; y++) {
      for (let x = 0; x < ctx.canvas.width; x++) {
        const c = (TRI.y0 - y) / (TRI.side * SQ3), b = (x - TRI.x0) / TRI.side - c / 2;
        if (c < 0 || b < 0 || b + c > 1) continue;
        const k = index.get(`${Math.round(b * n)},${Math.round(c * n)}`);
        const v = k === undefined ? null : values[k];
        const rgb = v === null ? [190, 190, 190] : viridis(hi > lo ? (v - lo) / (hi - lo) : 0.5);
        const o = 4 * (y * ctx.canvas.width + x);
        HEAT.data.set([...rgb, 255], o);
      }
    }
    drawColorbar(lo, hi);
  }
  function sweepStep() {
    let step = 1;
    for (const w of sweep.weights) for (const v of w) if (v > 0 && v < step) step = v;
    return step;
  }
  function drawColorbar(lo, hi) {
    const ctx = $("colorbar").getContext("2d");
    ctx.clearRect(0, 0, 440, 28);
    for (let x = 0; x < 300; x++) { ctx.fillStyle = `rgb(${viridis(x / 299)})`; ctx.fillRect(70 + x, 2, 1, 12); }
    ctx.fillStyle = "#222";
    ctx.fillText(lo.toFixed(3), 30, 12); ctx.fillText(hi.toFixed(3), 374, 12);
    ctx.fillText(`${$("metric").value} of ${$("cls").value}, RoI ${$("roi").value} (swept)`, 70, 26);
  }
  function mark(ctx, w, style, size, label) {
    const [x, y] = toXY(w);
    ctx.fillStyle = style; ctx.strokeStyle = "#000";
    ctx.beginPath(); ctx.arc(x, y, size, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
    if (label) { ctx.fillStyle = "#000"; ctx.fillText(label, x + size + 2, y - size - 1); }
  }
  function drawTriangle(w) {  // the chosen point: w
    const ctx = $("triangle").getContext("2d");
    ctx.clearRect(0, 0, 440, 400);
    ctx.fillStyle = "#f4f4f4";
    const corners = [[1, 0, 0], [0, 1, 0], [0, 0, 1]].map(toXY);
    ctx.beginPath(); corners.forEach(([x, y]) => ctx.lineTo(x, y)); ctx.closePath(); ctx.fill();
    if (HEAT) { const tmp = document.createElement("canvas"); tmp.width = 440; tmp.height = 400;
      tmp.getContext("2d").putImageData(HEAT, 0, 0); ctx.drawImage(tmp, 0, 0); }
    ctx.strokeStyle = "#333"; ctx.stroke();
    ctx.font = "12px sans-serif"; ctx.fillStyle = "#000";
    DATA.vertexNames.forEach((name, i) => { const [x, y] = corners[i];
      ctx.fillText(name, x - (i === 1 ? 60 : i === 2 ? 25 : 10), y + (i === 2 ? -6 : 16)); });
    if (sweep) for (const w of sweep.weights) mark(ctx, w, "rgba(0,0,0,0.25)", 1.2);
    for (const p of DATA.named) {
      const vertex = p.w.findIndex((v) => v === 1);
      mark(ctx, p.w, "#fff", 5, DATA.vertexNames[vertex] === p.label ? "" : p.label);
    }
    for (const p of DATA.targets) mark(ctx, p.w, "#2a7", 4);
    for (const p of DATA.certified) mark(ctx, p.w, "#d22", 6, p.label);
    mark(ctx, w, "rgba(255,200,0,0.9)", 7);
  }
  function snap(x, y) {  // a grid point within 6 pixels, or a marked point
    const points = [...(sweep ? sweep.weights : []), ...DATA.named.map((p) => p.w),
      ...DATA.certified.map((p) => p.w), ...DATA.targets.map((p) => p.w)];
    let best = null, dist = 6;
    for (const w of points) {
      const [px, py] = toXY(w), d = Math.hypot(px - x, py - y);
      if (d <= dist) { dist = d; best = w; }
    }
    return best && best.slice();
  }

  return { toWeights, drawHeat, drawTriangle, snap };
})();
