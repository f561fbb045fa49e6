// costseg explorer, part 3: the examples' masks at any point of the triangle and defer cost,
// the page's state and controls (the rule: explorer_rule.js; the triangle: explorer_triangle.js).
"use strict";
(function () {
  const { DATA, N, DEFERRED, bytes, pixelMajor, halves, mixed, withDefer, shifted, compile,
    argmax, sha256 } = COSTSEG;
  const { toWeights, drawHeat, drawTriangle, snap } = COSTSEG_TRIANGLE;
  const sweep = DATA.sweep;
  const $ = (id) => document.getElementById(id);

  // ---- examples ----
  const examples = DATA.examples.map((ex) => {
    const hw = ex.height * ex.width, q = pixelMajor(bytes(ex.probs), hw);
    return { ...ex, probs: null, hw, q, top: argmax(q, hw), labels: new Uint8Array(hw),
      truth: ex.labels && bytes(ex.labels), rois: ex.roi && bytes(ex.roi),
      uncertainty: Object.entries(ex.uncertainty || {}).map(([k, b]) => [k, halves(bytes(b))]) };
  });
  const PALETTE = DATA.palette;
  const SAME = 254;  // a pixel of the third view where the decision is argmax's: grey
  const RGBA = new Uint32Array(256);  // label → RGBA as one little-endian word
  const word = ([r, g, b]) => (0xff000000 | (b << 16) | (g << 8) | r) >>> 0;
  RGBA.fill(0xffc8c8c8);
  PALETTE.forEach((rgb, c) => { RGBA[c] = word(rgb); });
  RGBA[DEFERRED] = word(DATA.deferredColour);
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
      ex.share = document.createElement("span");
      title.append(" ", ex.share);
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
    let deferred = 0;
    for (let p = 0; p < ex.hw; p++) {
      const d = ex.labels[p];
      differ[p] = d === ex.top[p] ? SAME : d;
      if (d === DEFERRED) deferred++;
    }
    paint(ex.canvases[2], ex, differ);
    ex.deferred = deferred;
    ex.share.textContent = D === null ? "" : `· deferred ${percent(deferred, ex.hw)}`;
  }
  const percent = (part, whole) => `${(100 * part / whole).toFixed(1)} %`;

  // ---- state: the weights W and the defer cost D (null: no defer row) ----
  let W = [1, 0, 0], D = DATA.defer, M = withDefer(mixed(W), D);
  function parseHash() {
    const m = /(?:^|[#&])w=([^&]+)/.exec(location.hash);
    if (!m) return null;
    const w = m[1].split(",").map(Number);
    const ok = w.length === 3 && w.every((x) => Number.isFinite(x) && x >= 0) && w.some((x) => x > 0);
    return ok ? w : null;
  }
  function parseDefer() {  // "&defer=c" (c >= 0) or "&defer=off"; undefined: absent or invalid
    const m = /(?:^|[#&])defer=([^&]+)/.exec(location.hash);
    if (!m) return undefined;
    if (m[1] === "off") return null;
    const c = m[1].trim() === "" ? NaN : Number(m[1]);
    return Number.isFinite(c) && c >= 0 ? c : undefined;
  }
  function hashOf(w, d) {  // "&defer=off" only where the page's default defers
    const defer = d !== null ? `&defer=${d}` : DATA.defer !== null ? "&defer=off" : "";
    return `#w=${w.join(",")}${defer}`;
  }
  function recompute(w, d) {
    const t0 = performance.now();
    W = w; D = d; M = withDefer(mixed(w), d);
    const decide = compile(shifted(M));
    for (const ex of examples) { decide(ex.q, ex.hw, ex.labels, N); drawMasks(ex); }
    const ms = performance.now() - t0;
    drawTriangle(W);
    showPoint();
    showDefer();
    const state = { w: W, defer: D, ms, examples: examples.map((ex) => ({ name: ex.name,
      height: ex.height, width: ex.width, labels_sha256: sha256(ex.labels),
      deferred_pixels: ex.deferred })) };
    let pre = $("costseg-state");
    if (!pre) {  // for scripts and tests, never shown
      pre = document.createElement("pre");
      pre.id = "costseg-state";
      pre.hidden = true;
      document.body.appendChild(pre);
    }
    pre.textContent = JSON.stringify(state);
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
    const k = D === null ? gridIndex(W) : -1;  // the sweep's rules never defer
    const cls = $("cls").value || DATA.classes[11], c = DATA.classes.indexOf(cls);
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
      html = D === null ? "between grid points: no swept metrics here (click near a grid dot)"
        : "the swept metrics are without deferring: set the defer cost off to see them";
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
      + " (at their embedded resolution; not the swept images"
      + (D === null ? ")" : "; a deferred pixel is not predicted as any class)")
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
    if (D !== null) {  // the defer row: D for every true class
      let acc = 0;
      for (let k = 0; k < N; k++) acc += D * ex.q[base + k];
      html += `<tr class="${ex.labels[p] === DEFERRED ? "chosen" : ""}"><td><span class="swatch" `
        + `style="background:rgb(${DATA.deferredColour});outline:1px solid #999"></span>defer`
        + `</td><td></td><td>${acc.toPrecision(5)}</td></tr>`;
    }
    const nats = ex.uncertainty.map(([k, v]) => `${k.replace("_", " ")} ${v[p].toPrecision(3)}`);
    $("hover").innerHTML = html + "</table>"
      + (nats.length ? `<div id="uncertainty">${nats.join(", ")} nats</div>` : "");
  }

  // ---- the defer cost: "off" (no defer row), 0, then STEPS costs spaced evenly in log scale
  // over DECADES decades up to the vertices' largest off-diagonal cost (costs span 0.1 .. 1000)
  const STEPS = 400, DECADES = 4, TOP = DATA.deferMax > 0 ? DATA.deferMax : 1;
  const sliderCost = (i) => (i < 0 ? null : i === 0 ? 0
    : +(TOP * 10 ** (DECADES * (i / STEPS - 1))).toPrecision(3));
  const sliderPosition = (d) => (d === null ? -1 : d <= 0 ? 0
    : Math.max(1, Math.min(STEPS, Math.round(STEPS * (1 + Math.log10(d / TOP) / DECADES)))));
  function showDefer() {
    $("defer").value = String(sliderPosition(D));
    $("defer-cost").value = D === null ? "" : String(D);
    const shown = examples.reduce((n, ex) => n + ex.deferred, 0);
    const pixels = examples.reduce((n, ex) => n + ex.hw, 0);
    $("defer-value").textContent = D === null ? "off (no defer row: every pixel gets a class)"
      : `${D}: deferred ${percent(shown, pixels)} of the embedded pixels (white)`;
  }

  // ---- controls ----
  function options(select, values, labels) {
    values.forEach((v, i) => { const o = document.createElement("option");
      o.value = v; o.textContent = labels ? labels[i] : v; select.appendChild(o); });
  }
  function legend() {  // every class's colour, deferred pixels and the argmax's grey
    const entry = (rgb, name) => `<span class="entry"><span class="swatch" `
      + `style="background:rgb(${rgb})"></span>${name}</span>`;
    $("legend").innerHTML = DATA.classes.map((name, c) => entry(PALETTE[c], name)).join("")
      + entry(DATA.deferredColour, "deferred") + entry([200, 200, 200], "same as argmax");
  }
  function setup() {
    legend();
    if (sweep) {
      const metrics = Object.keys(sweep.metrics), classes = Object.keys(sweep.metrics[metrics[0]]);
      options($("metric"), metrics);
      options($("cls"), classes);
      const rois = Object.keys(sweep.metrics[metrics[0]][classes[0]]);
      options($("roi"), rois, rois.map((r) => `RoI ${r} (${DATA.roiNames[+r]})`));
    } else if (examples.some((ex) => ex.truth)) {  // no heatmap: the class of the metrics
      $("metric").style.display = $("roi").style.display = "none";
      $("choice-label").textContent = "precision and recall of:";
      options($("cls"), DATA.classes);
      $("cls").value = "person";
    } else {  // nothing to choose: no heatmap, no metrics
      $("choice").style.display = "none";
    }
    for (const id of ["metric", "cls", "roi"]) $(id).addEventListener("change", () => {
      drawHeat($("triangle").getContext("2d")); drawTriangle(W); showPoint(); });
    $("triangle").addEventListener("click", (ev) => {
      const rect = ev.target.getBoundingClientRect();
      let w = toWeights(ev.clientX - rect.left, ev.clientY - rect.top);
      const near = snap(ev.clientX - rect.left, ev.clientY - rect.top);
      if (near) w = near;
      history.replaceState(null, "", hashOf(w, D));
      recompute(w, D);
    });
    const slider = $("defer");
    slider.min = "-1"; slider.max = String(STEPS); slider.step = "1";
    slider.addEventListener("input", () => {
      const d = sliderCost(+slider.value);
      history.replaceState(null, "", hashOf(W, d));
      recompute(W, d);
    });
    $("defer-cost").addEventListener("change", (ev) => {
      const text = ev.target.value.trim(), d = text === "" ? null : Number(text);
      if (d !== null && !(Number.isFinite(d) && d >= 0)) { showDefer(); return; }
      history.replaceState(null, "", hashOf(W, d));
      recompute(W, d);
    });
    window.addEventListener("hashchange", () => {
      const w = parseHash(), d = parseDefer();
      if (w || d !== undefined) recompute(w || W, d === undefined ? D : d);
    });
    $("notes").innerHTML = DATA.notes.concat(sweep && sweep.note ? [sweep.note] : [])
      .map((n) => `<div>${n.replace(/</g, "&lt;")}</div>`).join("");
    buildExamples();
    drawHeat($("triangle").getContext("2d"));
  }
  setup();
  const first = parseHash() || [1, 0, 0], firstDefer = parseDefer();
  recompute(first, firstDefer === undefined ? DATA.defer : firstDefer);
  // "&clicks=n": n more recomputations at the same point, as n clicks would (benchmarks)
  const clicks = /[#&]clicks=(\d+)/.exec(location.hash);
  for (let i = 0; clicks && i < +clicks[1]; i++) recompute(first, D);
})();
