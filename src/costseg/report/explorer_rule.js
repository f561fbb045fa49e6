// costseg explorer, part 1: decoding the embedded data, the decision rule, SHA-256.
// Decisions follow docs/definitions.md §1 and §14 in float64, as decide_reference computes them:
// the mixed matrix (w0*C0 + w1*C1) + w2*C2, with a defer cost c one more row (c, ..., c) below
// it (with_defer), the column shift C - max over all rows, the sum over the true class k in
// ascending order, argmin with ties to the lowest row (a class wins a tie with deferring); the
// defer row's label is 255.
"use strict";
const COSTSEG = (function () {
  const DATA = JSON.parse(document.getElementById("costseg-data").textContent);
  const N = DATA.classes.length, NN = N * N, DEFERRED = 255;
  const V = Float64Array.from(DATA.vertices);

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
  function halves(raw) {  // little-endian float16 → float64
    const view = new DataView(raw.buffer, raw.byteOffset, raw.byteLength);
    return Float64Array.from({ length: raw.byteLength / 2 },
      (_, i) => HALF[view.getUint16(2 * i, true)]);
  }

  // ---- the rule ----
  function mixed(w) {  // (N, N): the operation order of costs.mix_costs
    const m = new Float64Array(NN);
    for (let i = 0; i < NN; i++) m[i] = (w[0] * V[i] + w[1] * V[NN + i]) + w[2] * V[2 * NN + i];
    return m;
  }
  function withDefer(m, c) {  // (N + 1, N): m and the row (c, ..., c); c null: m itself
    if (c === null) return m;
    const out = new Float64Array(NN + N);
    out.set(m);
    out.fill(c, NN);
    return out;
  }
  function shifted(m) {  // C - max over all rows (defer row included), per true-class column
    const rows = m.length / N, s = new Float64Array(m.length);
    for (let j = 0; j < N; j++) {
      let top = -Infinity;
      for (let i = 0; i < rows; i++) top = Math.max(top, m[i * N + j]);
      for (let i = 0; i < rows; i++) s[i * N + j] = m[i * N + j] - top;
    }
    return s;
  }
  // One pass per pixel, specialised to the matrix: its entries as literals (String() of a
  // float64 is its shortest exact form), the pixel's q in locals, terms with a zero entry left
  // out (adding 0 * q = 0 changes no sum), each term rounded apart (JS never fuses a * b + c).
  // Rows in order, a later row only when strictly cheaper; the defer row (row N) answers 255.
  function compile(s) {
    const lines = ["for (let p = 0, b = 0; p < hw; p++, b += N) {"];
    for (let k = 0; k < N; k++) lines.push(`const q${k} = q[b + ${k}];`);
    lines.push("let acc, low, best = 0;");
    for (let r = 0; r < s.length / N; r++) {
      lines.push("acc = 0;");
      for (let k = 0; k < N; k++) {
        const c = s[r * N + k];
        if (c !== 0) lines.push(`acc += (${String(c)}) * q${k};`);
      }
      const label = r === N ? DEFERRED : r;
      lines.push(r === 0 ? "low = acc;" : `if (acc < low) { low = acc; best = ${label}; }`);
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

  return { DATA, N, DEFERRED, bytes, pixelMajor, halves, mixed, withDefer, shifted, compile,
    argmax, sha256 };
})();
