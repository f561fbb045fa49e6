// costseg explorer: the value-space triangle and the examples' masks at any of its points.
// Decisions follow docs/definitions.md §1 in float64, as decide_reference computes them: the
// mixed matrix (w0*C0 + w1*C1) + w2*C2, the column shift C - max over predicted rows, the sum
// over the true class k in ascending order, argmin with ties to the lowest class.
"use strict";
(function () {
  const DATA = JSON.parse(document.getElementById("costseg-data").textContent);
  const N = DATA.classes.length, NN = N * N;
  const V = Float64Array.from(DATA.vertices);
  const SQ3 = Math.sqrt(3) / 2;
  const $ = (id) => document.getElementById(id);

  // ---- decoding: base64 → bytes; IEEE half → float64 (exact) ----
  function bytes(b64) {
    const bin = atob(b64), out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }
  const HALF = new Float64Array(65536);
  for (let h = 0; h < 65536; h++) {
    const sign = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, f = h & 0x3ff;
    HALF[h] = e === 0 ? sign * f * 2 ** -24
      : e === 31 ? (f ? NaN : sign * Infinity) : sign * (1024 + f) * 2 ** (e - 25);
  }
  function pixelMajor(raw, hw) {  // (N, H*W) little-endian float16 → (H*W, N) float64
    const view = new DataView(raw.buffer, raw.byteOffset, raw.byteLength);
    const q = new Float64Array(hw * N);
    for (let k = 0; k < N; k++) {
      for (let p = 0; p < hw; p++) q[p * N + k] = HALF[view.getUint16(2 * (k * hw + p), true)];
    }
    return q;
  }

  // ---- the rule ----
  function mixed(w) {  // (N, N): the operation order of costs.mix_costs
    const m = new Float64Array(NN);
    for (let i = 0; i < NN; i++) m[i] = (w[0] * V[i] + w[1] * V[NN + i]) + w[2] * V[2 * NN + i];
    return m;
  }
  function shifted(m) {  // C - max over predicted rows, per true-class column
    const s = new Float64Array(NN);
    for (let j = 0; j < N; j++) {
      let top = -Infinity;
      for (let i = 0; i < N; i++) top = Math.max(top, m[i * N + j]);
      for (let i = 0; i < N; i++) s[i * N + j] = m[i * N + j] - top;
    }
    return s;
  }
  // One pass per pixel, specialised to the matrix: its entries as literals (String() of a
  // float64 is its shortest exact form), the pixel's q in locals, terms with a zero entry left
  // out (adding 0 * q = 0 changes no sum), each term rounded apart (JS never fuses a * b + c).
  function compile(s) {
    const lines = ["for (let p = 0, b = 0; p < hw; p++, b += N) {"];
    for (let k = 0; k < N; k++) lines.push(`const q${k} = q[b + ${k}];`);
    lines.push("let acc, low, best = 0;");
    for (let r = 0; r < N; r++) {
      lines.push("acc = 0;");
      for (let k = 0; k < N; k++) {
        const c = s[r * N + k];
        if (c !== 0) lines.push(`acc += (${String(c)}) * q${k};`);
      }
      lines.push(r === 0 ? "low = acc;" : `if (acc < low) { low = acc; best = ${r}; }`);
    }
    lines.push("out[p] = best;", "}");
    return new Function("q", "hw", "out", "N", lines.join("\n"));
  }
  function argmax(q, hw) {
    const out = new Uint8Array(hw);
    for (let p = 0, base = 0; p < hw; p++, base += N) {
      let best = 0;
      for (let k = 1; k < N; k++) if (q[base + k] > q[base + best]) best = k;
      out[p] = best;
    }
    return out;
  }

  // ---- SHA-256 (FIPS 180-4), so the page needs no secure context ----
  const K256 = new Uint32Array([
    0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4,
    0xab1c5ed5, 0xd807aa98, 0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe,
    0x9bdc06a7, 0xc19bf174, 0xe49b69c1, 0xefbe4786, 0x0fc19dc6, 0x240ca1cc, 0x2de92c6f,
    0x4a7484aa, 0x5cb0a9dc, 0x76f988da, 0x983e5152, 0xa831c66d, 0xb00327c8, 0xbf597fc7,
    0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967, 0x27b70a85, 0x2e1b2138, 0x4d2c6dfc,
    0x53380d13, 0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85, 0xa2bfe8a1, 0xa81a664b,
    0xc24b8b70, 0xc76c51a3, 0xd192e819, 0xd6990624, 0xf40e3585, 0x106aa070, 0x19a4c116,
    0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a, 0x5b9cca4f, 0x682e6ff3,
    0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7,
    0xc67178f2]);
  function sha256(msg) {
    const len = msg.length, total = ((len + 9 + 63) >> 6) << 6;
    const buf = new Uint8Array(total);
    buf.set(msg);
    buf[len] = 0x80;
    const bits = len * 8, dv = new DataView(buf.buffer);
    dv.setUint32(total - 8, Math.floor(bits / 2 ** 32));
    dv.setUint32(total - 4, bits >>> 0);
    const h = new Uint32Array([0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a, 0x510e527f,
      0x9b05688c, 0x1f83d9ab, 0x5be0cd19]);
    const w = new Uint32Array(64);
    const rot = (x, n) => (x >>> n) | (x << (32 - n));
    for (let off = 0; off < total; off += 64) {
      for (let i = 0; i < 16; i++) w[i] = dv.getUint32(off + 4 * i);
      for (let i = 16; i < 64; i++) {
        const a = w[i - 15], b = w[i - 2];
        const s0 = rot(a, 7) ^ rot(a, 18) ^ (a >>> 3), s1 = rot(b, 17) ^ rot(b, 19) ^ (b >>> 10);
        w[i] = (w[i - 16] + s0 + w[i - 7] + s1) >>> 0;
      }
      let [a, b, c, d, e, f, g, hh] = h;
      for (let i = 0; i < 64; i++) {
        const t1 = (hh + (rot(e, 6) ^ rot(e, 11) ^ rot(e, 25)) + ((e & f) ^ (~e & g)) + K256[i]
          + w[i]) >>> 0;
        const t2 = ((rot(a, 2) ^ rot(a, 13) ^ rot(a, 22)) + ((a & b) ^ (a & c) ^ (b & c))) >>> 0;
        hh = g; g = f; f = e; e = (d + t1) >>> 0; d = c; c = b; b = a; a = (t1 + t2) >>> 0;
      }
      h[0] += a; h[1] += b; h[2] += c; h[3] += d; h[4] += e; h[5] += f; h[6] += g; h[7] += hh;
    }
    return Array.from(h, (x) => x.toString(16).padStart(8, "0")).join("");
  }

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
