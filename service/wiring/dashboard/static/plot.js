// fluxcal dashboard plots: time series and the coverage sphere on <canvas>, no library, no network.
(function () {
"use strict";

const COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf",
                "#7f7f7f", "#bcbd22"];

function niceTicks(lo, hi, n) {
  if (!(hi > lo)) { hi = lo + 1; }
  const span = hi - lo, raw = span / Math.max(1, n);
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 2.5, 5, 10].map(m => m * mag).find(s => s >= raw) || raw;
  // k * step, not a running sum: a sum of 0.2 steps from -1 gives -5.6e-17 where 0 belongs (printed "-5.6")
  const out = [];
  for (let k = Math.ceil(lo / step - 1e-9); k * step <= hi + step * 1e-9; k++) { out.push(Number((k * step).toPrecision(12))); }
  return out;
}

// Ticks of a log10 axis (lo, hi in decades): 1, 2 and 5 times the powers of ten inside it, or 1 alone where
// those are too many; round values of the quantity where fewer than two of those fall inside.
function logTicks(lo, hi, n) {
  for (const mults of [[1, 2, 5], [1]]) {
    const out = [];
    for (let d = Math.floor(lo); d <= Math.ceil(hi); d++) {
      for (const m of mults) {
        const v = d + Math.log10(m);
        if (v >= lo - 1e-9 && v <= hi + 1e-9) { out.push(v); }
      }
    }
    if (out.length >= 2 && out.length <= 2 * n) { return out; }
  }
  // a narrow range: round values of the quantity itself, placed on the log axis
  return niceTicks(Math.pow(10, lo), Math.pow(10, hi), n).filter(v => v > 0).map(v => Math.log10(v));
}

function fmt(v) {
  const a = Math.abs(v);
  if (a === 0) { return "0"; }
  if (a >= 1e5 || a < 1e-3) { return v.toExponential(1); }
  return Number(v.toPrecision(4)).toString();
}

// A time-series chart: chart.draw(t, [{name, values}], {floor: [{name, value}], window_s}).
class Chart {
  constructor(canvas, opts) {
    this.canvas = canvas;
    this.title = opts.title || "";
    this.unit = opts.unit || "";
    this.log = !!opts.log;
  }

  draw(t, series, extra) {
    extra = extra || {};
    const c = this.canvas, dpr = window.devicePixelRatio || 1;
    const w = c.clientWidth || 600, h = c.clientHeight || 180;
    if (c.width !== Math.round(w * dpr)) { c.width = Math.round(w * dpr); c.height = Math.round(h * dpr); }
    const g = c.getContext("2d");
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    g.clearRect(0, 0, w, h);
    const L = 64, R = 8, T = 20, B = 22, pw = w - L - R, ph = h - T - B;
    g.font = "12px sans-serif";
    g.fillStyle = "#222";
    g.fillText(this.title + (this.unit ? " (" + this.unit + ")" : ""), L, 13);
    const tx = (v) => this.log ? Math.log10(Math.max(v, 1e-12)) : v;
    let t0 = Infinity, t1 = -Infinity, y0 = Infinity, y1 = -Infinity;
    for (const v of t) { if (v !== null) { t0 = Math.min(t0, v); t1 = Math.max(t1, v); } }
    if (extra.window_s && t1 > -Infinity) { t0 = Math.max(t0, t1 - extra.window_s); }
    const visible = t.map(v => v !== null && v >= t0);
    for (const s of series) {
      s.values.forEach((v, i) => { if (v !== null && visible[i]) { const y = tx(v); y0 = Math.min(y0, y); y1 = Math.max(y1, y); } });
    }
    for (const f of (extra.floor || [])) {
      if (f.value !== null && f.value !== undefined) { y0 = Math.min(y0, tx(f.value)); y1 = Math.max(y1, tx(f.value)); }
    }
    if (!(t1 > -Infinity) || !(y1 > -Infinity)) {
      g.fillStyle = "#888"; g.fillText(extra.empty || "no data yet", L + 10, T + ph / 2); return;
    }
    if (y1 - y0 < 1e-9) { y0 -= 0.5; y1 += 0.5; }
    const pad = (y1 - y0) * 0.06; y0 -= pad; y1 += pad;
    if (t1 - t0 < 1e-9) { t0 -= 0.5; t1 += 0.5; }          // one instant: it in the middle of a 1-s axis
    const X = (v) => L + (v - t0) / (t1 - t0) * pw, Y = (v) => T + (1 - (tx(v) - y0) / (y1 - y0)) * ph;
    g.strokeStyle = "#ddd"; g.fillStyle = "#555"; g.lineWidth = 1;
    const yt = this.log ? logTicks(y0, y1, 4) : niceTicks(y0, y1, 4), step = yt.length > 1 ? yt[1] - yt[0] : 1;
    const digits = Math.max(0, Math.min(6, -Math.floor(Math.log10(step) + 1e-9)));
    for (const v of yt) {
      const y = T + (1 - (v - y0) / (y1 - y0)) * ph;
      g.beginPath(); g.moveTo(L, y); g.lineTo(L + pw, y); g.stroke();
      g.fillText(this.log ? fmt(Number(Math.pow(10, v).toPrecision(3))) : v.toFixed(digits), 2, y + 4);
    }
    for (const v of niceTicks(t0, t1, 6)) {
      const x = X(v);
      g.beginPath(); g.moveTo(x, T); g.lineTo(x, T + ph); g.stroke();
      g.fillText(fmt(v) + " s", x - 12, h - 6);
    }
    g.strokeStyle = "#999"; g.strokeRect(L, T, pw, ph);
    series.forEach((s, k) => {
      g.strokeStyle = s.color || COLORS[k % COLORS.length]; g.lineWidth = 1.2; g.beginPath();
      let pen = false;
      const drawn = (i) => i >= 0 && i < s.values.length && s.values[i] !== null && visible[i] && t[i] !== null;
      s.values.forEach((v, i) => {
        if (!drawn(i)) { pen = false; return; }
        const x = X(t[i]), y = Y(v);
        if (pen) { g.lineTo(x, y); } else { g.moveTo(x, y); pen = true; }
      });
      g.stroke();
      // a value with no drawn neighbour makes no line: a dot shows it (one calibration so far, a lone interval)
      g.fillStyle = s.color || COLORS[k % COLORS.length];
      s.values.forEach((v, i) => {
        if (drawn(i) && !drawn(i - 1) && !drawn(i + 1)) { g.fillRect(X(t[i]) - 2, Y(v) - 2, 4, 4); }
      });
    });
    (extra.floor || []).forEach((f, k) => {
      if (f.value === null || f.value === undefined) { return; }
      g.setLineDash([5, 4]); g.strokeStyle = f.color || COLORS[k % COLORS.length];
      g.beginPath(); g.moveTo(L, Y(f.value)); g.lineTo(L + pw, Y(f.value)); g.stroke(); g.setLineDash([]);
    });
    let lx = L + 6;
    series.forEach((s, k) => {
      g.fillStyle = s.color || COLORS[k % COLORS.length];
      g.fillRect(lx, T + 4, 10, 3); g.fillStyle = "#222"; g.fillText(s.name, lx + 13, T + 10);
      lx += g.measureText(s.name).width + 26;
    });
  }
}

// Coverage sphere: the 26 direction bins seen from +z (upper hemisphere) and from -z (lower), coloured by
// how often the field pointed there; red rings where no sample came; the recent directions as a trail.
function drawSphere(canvas, cov, probe) {
  const c = canvas, dpr = window.devicePixelRatio || 1;
  const w = c.clientWidth || 360, h = c.clientHeight || 190;
  if (c.width !== Math.round(w * dpr)) { c.width = Math.round(w * dpr); c.height = Math.round(h * dpr); }
  const g = c.getContext("2d");
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, w, h);
  g.font = "11px sans-serif";
  const r = Math.min(w / 4 - 8, h / 2 - 18);
  const centres = [[w / 4, h / 2 + 6, 1, "+z side (looking down)"], [3 * w / 4, h / 2 + 6, -1, "-z side (looking up)"]];
  const maxCount = Math.max(1, ...probe.counts);
  for (const [cx, cy, side, label] of centres) {
    g.strokeStyle = "#999"; g.beginPath(); g.arc(cx, cy, r, 0, 2 * Math.PI); g.stroke();
    g.fillStyle = "#333"; g.fillText(label, cx - r, cy - r - 4);
    const ys = side > 0 ? -1 : 1;           // seen from below, +y points down the screen
    g.fillText("+x", cx + r + 2, cy + 4); g.fillText("+y", cx - 6, cy + ys * (r - 12) + 4);
    cov.bins.forEach((b, i) => {
      if (b[2] * side < -1e-9) { return; }
      const x = cx + b[0] * r, y = cy + ys * b[1] * r;
      const n = probe.counts[i], seen = n >= probe.min_count;
      g.beginPath(); g.arc(x, y, 7, 0, 2 * Math.PI);
      if (seen) {
        const a = 0.25 + 0.75 * Math.min(1, Math.log1p(n) / Math.log1p(maxCount));
        g.fillStyle = "rgba(44,160,44," + a.toFixed(2) + ")"; g.fill();
      } else {
        g.strokeStyle = "#d62728"; g.lineWidth = 2; g.stroke(); g.lineWidth = 1;
      }
    });
    g.fillStyle = "rgba(31,119,180,0.7)";
    for (const d of probe.trail) {
      if (d[2] * side < 0) { continue; }
      g.fillRect(cx + d[0] * r - 1, cy + ys * d[1] * r - 1, 2, 2);
    }
  }
}

// A shape discovery found: per probe, the partial residual in bins of the observable (points with their standard
// errors) and the law's field along its direction with a band of two standard errors.
function drawShape(canvas, shape) {
  const dpr = window.devicePixelRatio || 1, w = canvas.clientWidth || 600, h = canvas.clientHeight || 220;
  canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
  const g = canvas.getContext("2d");
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, w, h);
  const L = 64, R = 8, T = 20, B = 26, pw = w - L - R, ph = h - T - B;
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  for (const p of shape.partial) {
    p.grid.forEach((x, i) => { x0 = Math.min(x0, x); x1 = Math.max(x1, x);
      y0 = Math.min(y0, p.law_nT[i] - p.band_nT[i]); y1 = Math.max(y1, p.law_nT[i] + p.band_nT[i]); });
    p.x.forEach((x, i) => { y0 = Math.min(y0, p.mean_nT[i] - p.stderr_nT[i]); y1 = Math.max(y1, p.mean_nT[i] + p.stderr_nT[i]); });
  }
  if (!(x1 > x0) || !(y1 > y0)) { return; }
  const pad = (y1 - y0) * 0.06; y0 -= pad; y1 += pad;
  const X = (v) => L + (v - x0) / (x1 - x0) * pw, Y = (v) => T + (1 - (v - y0) / (y1 - y0)) * ph;
  g.font = "12px sans-serif"; g.fillStyle = "#222";
  g.fillText(`${shape.observable}: ${shape.law} (field along its direction, nT; band: 2 standard errors)`, L, 13);
  g.strokeStyle = "#ddd"; g.fillStyle = "#555"; g.lineWidth = 1;
  for (const v of niceTicks(y0, y1, 4)) { g.beginPath(); g.moveTo(L, Y(v)); g.lineTo(L + pw, Y(v)); g.stroke(); g.fillText(fmt(v), 2, Y(v) + 4); }
  for (const v of niceTicks(x0, x1, 6)) { g.beginPath(); g.moveTo(X(v), T); g.lineTo(X(v), T + ph); g.stroke(); g.fillText(fmt(v), X(v) - 10, h - 8); }
  g.strokeStyle = "#999"; g.strokeRect(L, T, pw, ph);
  shape.partial.forEach((p, k) => {
    const colour = COLORS[k % COLORS.length];
    g.fillStyle = colour; g.globalAlpha = 0.2; g.beginPath();
    p.grid.forEach((x, i) => { const y = Y(p.law_nT[i] + p.band_nT[i]); if (i) { g.lineTo(X(x), y); } else { g.moveTo(X(x), y); } });
    for (let i = p.grid.length - 1; i >= 0; i--) { g.lineTo(X(p.grid[i]), Y(p.law_nT[i] - p.band_nT[i])); }
    g.fill(); g.globalAlpha = 1;
    g.strokeStyle = colour; g.lineWidth = 1.5; g.beginPath();
    p.grid.forEach((x, i) => { if (i) { g.lineTo(X(x), Y(p.law_nT[i])); } else { g.moveTo(X(x), Y(p.law_nT[i])); } });
    g.stroke(); g.lineWidth = 1;
    p.x.forEach((x, i) => {
      g.beginPath(); g.moveTo(X(x), Y(p.mean_nT[i] - p.stderr_nT[i])); g.lineTo(X(x), Y(p.mean_nT[i] + p.stderr_nT[i])); g.stroke();
      g.fillRect(X(x) - 2, Y(p.mean_nT[i]) - 2, 4, 4);
    });
    g.fillText(p.probe, L + 8 + 40 * k, T + 14);
  });
}

window.fluxplot = { Chart, drawSphere, drawShape, COLORS };
})();
