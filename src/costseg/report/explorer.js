// costseg explorer, part 2: the value-space triangle and the examples' masks at any of its
// points (the rule itself: explorer_rule.js).
"use strict";
(function () {
  const { DATA, N, bytes, pixelMajor, mixed, shifted, compile, argmax, sha256 } = COSTSEG;
  const SQ3 = Math.sqrt(3) / 2;
  const $ = (id) => document.getElementById(id);

  // ---- examples ----
  const examples = DATA.examples.map((ex) => {
    const hw = ex.height * ex.width, q = pixelMajor(bytes(ex.probs), hw);
    return { ...ex, probs: null, hw, q, top: argmax(q, hw), labels: new Uint8Array(hw),
      truth: ex.labels && bytes(ex.labels), rois: ex.roi && bytes(ex.roi) };
  });
  const PALETTE = DATA.palette;
  const RGBA = new Uint32Array(256);  // class → RGBA as one little-endian word; 255: grey
  RGBA.fill(0xffc8c8c8);
  PALETTE.forEach(([r, g, b], c) => { RGBA[c] = 0xff000000 | (b << 16) | (g << 8) | r; });
  function paint(canvas, ex, classes) {
    const ctx = canvas.getContext("2d"), img = ctx.createImageData(ex.width, ex.height);
    const words = new Uint32Array(img.data.buffer);
    for (let p = 0; p < ex.hw; p++) words[p] = RGBA[classes[p]];
    ctx.putImageData(img, 0, 0);
  }
  function buildExamples() {
    const root = $("examples");
    for (const ex of examples) {
      const div = document.createElement("div");
      div.className = "example";
      const title = document.createElement("div");
      title.textContent = `${ex.name} (${ex.height} × ${ex.width} embedded)`
        + (ex.note ? `: ${ex.note}` : "");
      const views = document.createElement("div");
      views.className = "views";
      ex.canvases = ["image", "mask", "diff"].map(() => {
        const c = document.createElement("canvas");
        c.width = ex.width; c.height = ex.height;
        c.addEventListener("mousemove", (ev) => hover(ex, c, ev));
        views.appendChild(c);
        return c;
      });
      const picture = new Image();
      picture.onload = () => ex.canvases[0].getContext("2d").drawImage(picture, 0, 0);
      picture.src = ex.image;
      div.append(title, views);
      root.appendChild(div);
    }
  }
  function drawMasks(ex) {
    paint(ex.canvases[1], ex, ex.labels);
    const differ = ex.differ || (ex.differ = new Uint8Array(ex.hw));
    for (let p = 0; p < ex.hw; p++) differ[p] = ex.labels[p] === ex.top[p] ? 255 : ex.labels[p];
    paint(ex.canvases[2], ex, differ);
  }

  // ---- state ----
  let W = [1, 0, 0], M = mixed(W);
  function parseHash() {
    const m = /(?:^|[#&])w=([^&]+)/.exec(location.hash);
    if (!m) return null;
    const w = m[1].split(",").map(Number);
    const ok = w.length === 3 && w.every((x) => Number.isFinite(x) && x >= 0) && w.some((x) => x > 0);
    return ok ? w : null;
  }
  function recompute(w) {
    const t0 = performance.now();
    W = w; M = mixed(w);
    const decide = compile(shifted(M));
    for (const ex of examples) { decide(ex.q, ex.hw, ex.labels, N); drawMasks(ex); }
    const ms = performance.now() - t0;
    drawTriangle();
    showPoint();
    const state = { w: W, ms, examples: examples.map((ex) => ({ name: ex.name,
      height: ex.height, width: ex.width, labels_sha256: sha256(ex.labels) })) };
    let pre = $("costseg-state");
    if (!pre) {
      pre = document.createElement("pre");
      pre.id = "costseg-state";
      pre.className = "note";
      document.body.appendChild(pre);
    }
    pre.textContent = JSON.stringify(state);
  }

  // ---- the triangle: vertex 0 bottom left, 1 bottom right, 2 top (as report.ternary) ----
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
  function drawTriangle() {
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
    mark(ctx, W, "rgba(255,200,0,0.9)", 7);
  }

  // ---- metrics at the point ----
  function gridIndex(w) {
    if (!sweep) return -1;
    const s = w[0] + w[1] + w[2];
    return sweep.weights.findIndex((g) => g.every((v, i) => Math.abs(v - w[i] / s) < 1e-9));
  }
  function showPoint() {
    $("point").textContent = `point w = (${W.map((x) => +x.toFixed(4)).join(", ")}) on `
      + `(${DATA.vertexNames.join(", ")})`;
    const k = gridIndex(W), cls = $("cls").value || DATA.classes[11], c = DATA.classes.indexOf(cls);
    let html = "";
    if (k >= 0) {
      html = `<b>swept metrics</b> of ${cls} at this grid point<table><tr><th>RoI</th>`;
      const ms = Object.keys(sweep.metrics);
      html += ms.map((m) => `<th>${m}</th>`).join("") + "</tr>";
      for (const r of Object.keys(sweep.metrics[ms[0]][cls] || {})) {
        html += `<tr><td>${DATA.roiNames[+r] || r}</td>` + ms.map((m) => {
          const v = ((sweep.metrics[m][cls] || {})[r] || [])[k];
          return `<td>${v === null || v === undefined ? "–" : v.toFixed(4)}</td>`; }).join("") + "</tr>";
      }
      html += "</table>";
    } else if (examples.some((ex) => ex.truth)) {
      html = exampleMetrics(c, cls);
    } else if (sweep) {
      html = "between grid points: no swept metrics here (click near a grid dot)";
    }
    $("metrics").innerHTML = html;
  }
  function exampleMetrics(c, cls) {
    const rows = [];
    for (let r = 0; r < DATA.roiNames.length; r++) {
      let tp = 0, fp = 0, fn = 0, seen = false;
      for (const ex of examples) {
        if (!ex.truth || (r > 0 && !ex.rois)) continue;
        seen = true;
        for (let p = 0; p < ex.hw; p++) {
          const t = ex.truth[p];
          if (t === 255 || (r > 0 && ex.rois[p] !== r)) continue;
          const d = ex.labels[p];
          if (d === c && t === c) tp++; else if (d === c) fp++; else if (t === c) fn++;
        }
      }
      if (seen) rows.push(`<tr><td>${DATA.roiNames[r]}</td><td>${tp + fp ? (tp / (tp + fp)).toFixed(4) : "–"}`
        + `</td><td>${tp + fn ? (tp / (tp + fn)).toFixed(4) : "–"}</td></tr>`);
    }
    return `<b>precision and recall of ${cls} over the ${examples.length} embedded examples</b>`
      + " (at their embedded resolution; not the swept images)"
      + `<table><tr><th>RoI</th><th>precision</th><th>recall</th></tr>${rows.join("")}</table>`;
  }

  // ---- hover: a pixel's probabilities and expected costs under the chosen matrix ----
  function hover(ex, canvas, ev) {
    const rect = canvas.getBoundingClientRect();
    const x = Math.floor((ev.clientX - rect.left) * ex.width / rect.width);
    const y = Math.floor((ev.clientY - rect.top) * ex.height / rect.height);
    if (x < 0 || y < 0 || x >= ex.width || y >= ex.height) return;
    const p = y * ex.width + x, base = p * N;
    let html = `${ex.name} pixel (${y}, ${x}): expected cost Σ_k C[k̂, k] p(k|x) under the chosen matrix`
      + "<table><tr><th>class</th><th>p</th><th>expected cost</th></tr>";
    for (let r = 0; r < N; r++) {
      let acc = 0;
      for (let k = 0; k < N; k++) acc += M[r * N + k] * ex.q[base + k];
      const cls = (r === ex.labels[p] ? "chosen" : "") + (r === ex.top[p] ? " argmax" : "");
      html += `<tr class="${cls}"><td><span class="swatch" style="background:rgb(${PALETTE[r]})">`
        + `</span>${DATA.classes[r]}</td><td>${ex.q[base + r].toPrecision(4)}</td>`
        + `<td>${acc.toPrecision(5)}</td></tr>`;
    }
    $("hover").innerHTML = html + "</table>";
  }

  // ---- controls ----
  function options(select, values, labels) {
    values.forEach((v, i) => { const o = document.createElement("option");
      o.value = v; o.textContent = labels ? labels[i] : v; select.appendChild(o); });
  }
  function setup() {
    if (sweep) {
      const metrics = Object.keys(sweep.metrics), classes = Object.keys(sweep.metrics[metrics[0]]);
      options($("metric"), metrics);
      options($("cls"), classes);
      const rois = Object.keys(sweep.metrics[metrics[0]][classes[0]]);
      options($("roi"), rois, rois.map((r) => `RoI ${r} (${DATA.roiNames[+r]})`));
    } else {
      $("metric").style.display = $("roi").style.display = "none";
      options($("cls"), DATA.classes);
      $("cls").value = "person";
    }
    for (const id of ["metric", "cls", "roi"]) $(id).addEventListener("change", () => {
      drawHeat($("triangle").getContext("2d")); drawTriangle(); showPoint(); });
    $("triangle").addEventListener("click", (ev) => {
      const rect = ev.target.getBoundingClientRect();
      let w = toWeights(ev.clientX - rect.left, ev.clientY - rect.top);
      const near = snap(ev.clientX - rect.left, ev.clientY - rect.top);
      if (near) w = near;
      history.replaceState(null, "", `#w=${w.join(",")}`);
      recompute(w);
    });
    window.addEventListener("hashchange", () => { const w = parseHash(); if (w) recompute(w); });
    $("notes").innerHTML = DATA.notes.concat(sweep && sweep.note ? [sweep.note] : [])
      .map((n) => `<div>${n.replace(/</g, "&lt;")}</div>`).join("");
    buildExamples();
    drawHeat($("triangle").getContext("2d"));
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
  setup();
  const first = parseHash() || [1, 0, 0];
  recompute(first);
  // "&clicks=n": n more recomputations at the same point, as n clicks would (benchmarks)
  const clicks = /[#&]clicks=(\d+)/.exec(location.hash);
  for (let i = 0; clicks && i < +clicks[1]; i++) recompute(first);
})();
