// fluxcal dashboard page: polls /api/units and /api/view, keeps ten minutes of history, draws it.
"use strict";

const WINDOW_S = 600, KEEP = 6000, VIEW_EVERY_MS = 500, UNITS_EVERY_MS = 2000;
const $ = (id) => document.getElementById(id);
// this server's session token: only a page served from it can read it; every POST must carry it
const TOKEN = (document.querySelector('meta[name="fluxcal-token"]') || {}).content || "";
const { Chart, drawSphere, COLORS } = window.fluxplot;
const charts = {
  total: new Chart($("chart-total"), { title: "|B| per probe", unit: "nT" }),
  vectors: new Chart($("chart-vectors"), { title: "components", unit: "nT" }),
  diff: new Chart($("chart-diff"), { title: "differences probe k - probe 1", unit: "nT" }),
  tensor: new Chart($("chart-tensor"), { title: "gradient tensor G[i,j] = dBj/dxi", unit: "nT/m" }),
  error: new Chart($("chart-error"), { title: "model-vs-measurement error", unit: "nT RMS", log: true }),
  offsets: new Chart($("chart-offsets"), { title: "offsets by calibration (x: s since this page's first)", unit: "nT" }),
};
let unit = null, hist = null, updates = 0, readOnly = false, readOnlyReason = "", units = null;

function newHist() { return { series: null, raw: null, error: null }; }

// merge rows {columns, id, t, v} into a columnar history {columns, id, t: [], cols: [[]...]}
function merge(h, rows) {
  if (!rows) { return h; }
  if (!h || h.columns.join() !== rows.columns.join() || rows.id < h.id) {
    h = { columns: rows.columns, id: 0, t: [], cols: rows.columns.slice(1).map(() => []) };
  }
  rows.t.forEach((t, i) => { h.t.push(t); rows.v[i].forEach((x, k) => h.cols[k].push(x)); });
  if (h.t.length > KEEP) { const cut = h.t.length - KEEP; h.t.splice(0, cut); h.cols.forEach(c => c.splice(0, cut)); }
  h.id = rows.id;
  return h;
}

function col(h, name) { const k = h ? h.columns.indexOf(name) : -1; return k > 0 ? h.cols[k - 1] : null; }
function last(a) { for (let i = a.length - 1; i >= 0; i--) { if (a[i] !== null) { return a[i]; } } return null; }
function num(x, d) { return x === null || x === undefined ? "–" : Number(x).toFixed(d === undefined ? 2 : d); }
// text from the network shown, never interpreted: HTML's specials escaped, control characters as escapes (\n, \x1b)
function esc(s) {
  return String(s).replace(/[&<>"]/g, c => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c]))
    .replace(/[\x00-\x1f\x7f-\x9f\u061c\u200b-\u200f\u2028-\u202e\u2060-\u2069\ufeff]/g,
      c => ({ "\n": "\\n", "\r": "\\r", "\t": "\\t" }[c] ||
        (c.charCodeAt(0) < 256 ? "\\x" : "\\u") + c.charCodeAt(0).toString(16).padStart(c.charCodeAt(0) < 256 ? 2 : 4, "0")));
}

async function getJSON(url, init) {
  const r = await fetch(url, init);
  const body = await r.json();
  if (!r.ok && !("ok" in body)) { throw new Error(body.error || r.statusText); }
  return body;
}

// a state-changing request: JSON, with the page's token (the server refuses any other)
function postJSON(url, obj) {
  return getJSON(url, { method: "POST", headers: { "Content-Type": "application/json", "X-Fluxcal-Token": TOKEN },
                        body: JSON.stringify(obj) });
}

// a read-only dashboard greys what it refuses and says why beside it
function showReadOnly() {
  const why = readOnly ? (readOnlyReason || "read-only: started with --read-only") : "";
  document.querySelectorAll("button[data-cmd], #diagnose, [data-needs-write]").forEach(b => {
    b.disabled = readOnly; b.title = why || b.dataset.title || "";
  });
  for (const id of ["read-only-note", "diagnose-note"]) {
    if (readOnly) { $(id).hidden = false; $(id).textContent = "Greyed: " + why + "."; $(id).dataset.readOnly = "1"; }
    else if ($(id).dataset.readOnly) { $(id).hidden = true; $(id).textContent = ""; delete $(id).dataset.readOnly; }
  }
}

async function pollUnits() {
  try {
    const u = await getJSON("/api/units");
    units = u;
    readOnly = u.read_only;
    readOnlyReason = u.read_only_reason || "";
    const nav = $("units");
    nav.innerHTML = "";
    for (const x of u.units) {
      const b = document.createElement("button");
      b.innerHTML = `<span class="dot ${x.status}"></span>${esc(x.unit)}`;
      b.title = x.status_text; b.dataset.unit = x.unit;
      if (x.unit === unit) { b.classList.add("selected"); }
      b.onclick = () => { unit = x.unit; hist = newHist(); pollUnits(); };
      nav.appendChild(b);
    }
    if (!unit && u.units.length) { unit = u.units[0].unit; hist = newHist(); }
    if (u.message && (!unit || !u.connected)) { banner(u.connected ? "waiting" : "unreachable", u.message); }
    showReadOnly();
  } catch (e) {
    banner("unreachable", "the dashboard server does not answer: " + e.message);
  }
}

function banner(state, text) { const b = $("banner"); b.dataset.state = state; b.textContent = text; }

async function pollView() {
  if (!unit) { return; }
  try {
    const q = new URLSearchParams({ unit, series: hist.series ? hist.series.id : 0, raw: hist.raw ? hist.raw.id : 0,
                                    error: hist.error ? hist.error.id : 0 });
    const v = await getJSON("/api/view?" + q);
    hist.series = merge(hist.series, v.series);
    hist.raw = merge(hist.raw, v.raw);
    hist.error = merge(hist.error, v.error);
    const reachable = !units || units.connected;
    banner(reachable ? v.status : "unreachable", reachable ? v.status_text : units.message);
    render(v);
    updates += 1;
    document.body.dataset.updates = updates;
    document.body.dataset.status = reachable ? v.status : "unreachable";
  } catch (e) {
    banner("unreachable", "the dashboard server does not answer: " + e.message);
  }
}

function probeNames(v) {
  const h = hist.series || hist.raw;
  if (!h) { return v.probe_names || []; }
  const names = [];
  for (const c of h.columns) { const m = /^([^.-]+)\.x$/.exec(c); if (m && m[1] !== "centre") { names.push(m[1]); } }
  return names;
}

function render(v) {
  $("clock").textContent = new Date().toLocaleTimeString();
  const names = probeNames(v);
  const h = hist.series && hist.series.t.length ? hist.series : null;
  const src = h || hist.raw;
  $("field-note").textContent = h ? "(corrected, 0.1-s means)" : hist.raw ? "(raw: no usable calibration yet)" : "";
  let rows = "<tr><th>probe</th><th>Bx</th><th>By</th><th>Bz</th><th>|B|</th></tr>";
  for (const p of names.concat(h && col(h, "centre.x") ? ["centre"] : [])) {
    const xyz = ["x", "y", "z"].map(a => last(col(src, `${p}.${a}`) || []));
    const tot = h ? last(col(h, `${p}.total`) || []) : Math.hypot(...xyz.map(x => x || 0));
    rows += `<tr><th>${esc(p)}</th>${xyz.map(x => `<td>${num(x, 1)}</td>`).join("")}` +
            `<td data-col="${esc(p)}.total">${num(tot, 1)}</td></tr>`;
  }
  $("latest").innerHTML = rows;
  if (src) {
    const series = h ? names.map(p => ({ name: p, values: col(h, `${p}.total`) })) : [];
    if (h && col(h, "centre.total")) { series.push({ name: "centre", values: col(h, "centre.total") }); }
    charts.total.draw(src.t, series, { window_s: WINDOW_S });
    const p0 = names[0];
    charts.vectors.title = `components of ${p0 || "?"}` + (h ? "" : " (raw)");
    charts.vectors.draw(src.t, ["x", "y", "z"].map(a => ({ name: `${p0}.${a}`, values: col(src, `${p0}.${a}`) || [] })),
                        { window_s: WINDOW_S });
  }
  if (h) {
    // |d|: the norm of the components' mean over the window, not a mean of |d| (the noise would bias it upward)
    const diffs = h.columns.filter(c => /-.*\.norm$/.test(c)), win = (v.windows || {}).window_s || 10;
    charts.diff.title = `differences probe k - probe 1: components (0.1-s means); |d|: norm of the ${num(win, 0)}-s mean components`;
    charts.diff.draw(h.t, diffs.map(c => ({ name: `|${c.replace(".norm", "")}| (${num(win, 0)}-s mean)`, values: col(h, c) }))
      .concat(diffs.length ? ["x", "y", "z"].map(a => { const c = diffs[0].replace("norm", a); return { name: c, values: col(h, c) }; }) : []),
      { window_s: WINDOW_S });
    const g = h.columns.filter(c => c.startsWith("G."));
    charts.tensor.draw(h.t, g.map(c => ({ name: c.slice(2), values: col(h, c) })),
                       { window_s: WINDOW_S, empty: "no tensor: it needs at least four probes, not all in one plane" });
    $("tensor").innerHTML = g.length ? "<tr><th></th><th>Bx</th><th>By</th><th>Bz</th></tr>" + ["x", "y", "z"].map(i =>
      `<tr><th>d/d${i}</th>${["x", "y", "z"].map(j => `<td>${num(last(col(h, `G.${i}${j}`)), 2)}</td>`).join("")}</tr>`).join("")
      + `<tr><th>trace</th><td colspan="3">${num(last(col(h, "G.trace")), 3)} nT/m</td></tr>` : "";
  }
  renderError(v);
  renderCoverage(v.coverage);
  renderCalibration(v);
  renderCommands(v);
  renderDiagnosis(v.diagnosis, v.raw_kept);
  renderHealth(v);
  renderFaults(v.faults);
}

function renderError(v) {
  const e = hist.error;
  if (!e || !e.t.length) { return; }
  const chans = e.columns.slice(1);
  const floors = v.floors || {}, w = v.windows || {}, rms = w.error_rms_nT || {};
  $("error-window").textContent = num(w.window_s, 0);
  charts.error.draw(e.t, chans.map((c, k) => ({ name: c, values: col(e, c), color: COLORS[k % COLORS.length] })),
    { window_s: WINDOW_S, floor: chans.map((c, k) => ({ name: c, value: floors[c], color: COLORS[k % COLORS.length] })) });
  const span = w.error_span_s !== undefined && w.error_span_s < w.window_s - 0.05 ? ` (${num(w.error_span_s, 1)} s so far)` : "";
  let rows = `<tr><th>channel</th><th>error nT, RMS over the last ${num(w.window_s, 0)} s${span}</th><th>floor nT</th><th>ratio</th></tr>`;
  for (const c of chans) {
    const x = rms[c] ?? null, f = floors[c], r = x !== null && f ? x / f : null;
    rows += `<tr><th>${esc(c)}</th><td>${num(x, 3)}</td><td>${num(f, 3)}</td>` +
            `<td class="${r !== null && r > 1.5 ? "bad" : "good"}">${num(r, 2)}</td></tr>`;
  }
  $("error-table").innerHTML = rows;
}

function renderCoverage(cov) {
  const div = $("coverage");
  if (!cov) { div.textContent = "no field directions yet"; return; }
  $("coverage-note").textContent = `(${cov.frame}; ${cov.n_directions} directions)`;
  if (div.children.length !== cov.probes.length) {
    div.innerHTML = cov.probes.map((p, k) => `<div><b>${esc(p.name)}</b> <span id="cov-text-${k}"></span>` +
                                              `<canvas class="sphere" id="cov-${k}"></canvas></div>`).join("");
  }
  cov.probes.forEach((p, k) => {
    drawSphere($(`cov-${k}`), cov, p);
    $(`cov-text-${k}`).innerHTML = `${num(100 * p.fraction, 0)} % of directions seen` +
      (p.missing.length ? ` <span class="bad">missing ${esc(p.missing.join(", "))}</span>: ${esc(p.advice)}` : "");
  });
}

function renderCalibration(v) {
  const st = v.state || {};
  const probes = st.probes || [];
  let html = `<p>${st.usable ? '<span class="good">usable</span>' : '<span class="bad">not usable yet</span>'}` +
    ` · cal_id <span id="cal-id">${esc(st.cal_id ?? "–")}</span> · ${esc(st.method || "")}` +
    (st.frozen ? ' · <b id="frozen">FROZEN</b>' : "") + (st.held ? ' · <b id="held">APPLIED: held until reset</b>' : "") + ` · effects: ${esc((st.effects || []).join(", ") || "none")}` +
    ` · ${esc(st.samples_seen ?? "–")} samples seen</p>`;
  if (probes.length) {
    html += "<table class='numbers'><tr><th>probe</th><th>offset x</th><th>offset y</th><th>offset z</th>" +
            "<th>sensor scale x</th><th>sensor scale y</th><th>sensor scale z</th></tr>";
    const scales = v.sensor_scales || [], sources = new Set();
    probes.forEach((p, k) => {
      const off = p.offset_nT || [], se = p.offset_se_nT || [], sc = scales[k] || {}, c = sc.scale || [];
      if (sc.source) { sources.add(sc.source); }
      html += `<tr><th>${esc(p.name)}</th>` + [0, 1, 2].map(i => `<td>${num(off[i], 1)} ± ${se[i] >= 0 ? num(se[i], 2) : "?"}</td>`).join("")
        + [0, 1, 2].map(i => `<td data-col="${esc(p.name)}.scale">${num(c[i], 5)}</td>`).join("") + "</tr>";
    });
    html += "</table><p class='muted'>offsets in nT ± standard error (? : not determined); sensor scale: the " +
            "sensor's scale factor per axis as <code>fluxcal fit</code> prints it (1.021: the axis reads 2.1 % high; " +
            "the correction divides it out), " + esc([...sources].join(", ") || "–") + "</p>";
  }
  $("calibration").innerHTML = html;
  const gate = st.gate;
  $("gate").innerHTML = gate ? `<p>quality gate, latest online candidate: ${gate.usable ? '<span class="good">passed</span>' : '<span class="bad">refused</span>'}` +
    (st.usable && !gate.usable ? " (the calibration in use stays)" : "") +
    (gate.coverage === null || gate.coverage === undefined ? "" :
     ` · its window's coverage ${num(100 * gate.coverage, 0)} % · condition ${num(gate.condition, 1)}`) + "</p>" +
    (gate.reasons && gate.reasons.length ? "<ul id='gate-reasons'>" + gate.reasons.map(r => `<li>${esc(r)}</li>`).join("") + "</ul>" : "")
    : "<p class='muted'>no quality-gate verdict yet</p>";
  const ch = v.cal_history || [];
  if (ch.length) {
    const t0 = ch[0].time_unix_s, t = ch.map(c => c.time_unix_s - t0), series = [];
    (ch[ch.length - 1].offset_nT || []).forEach((_, k) => ["x", "y", "z"].forEach((a, i) =>
      series.push({ name: `${probes[k] ? probes[k].name : "s" + (k + 1)}.${a}`, values: ch.map(c => (c.offset_nT[k] || [])[i] ?? null) })));
    charts.offsets.draw(t, series, { empty: "no calibration yet" });
    $("offsets-note").textContent = ch.length < 2 ? "one calibration so far: a point per offset; a line once it changes" : "";
  }
}

function renderCommands(v) {
  $("save-calibration").href = "/api/calibration?unit=" + encodeURIComponent(unit);
  $("command-log").innerHTML = (v.commands || []).slice().reverse().map(c =>
    `<li class="${c.ok ? "good" : "bad"}" data-command="${esc(c.command)}" data-ok="${c.ok}">` +
    `${new Date(c.time_unix_s * 1000).toLocaleTimeString()} ${esc(c.command)} ${esc(c.payload || "")}: ` +
    `${c.ok ? "ok" : "refused: " + esc(c.error || "")} (${num(1000 * c.round_trip_s, 0)} ms)` +
    `${c.warning ? " — WARNING: " + esc(c.warning) : ""}</li>`).join("");
}

function renderDiagnosis(d, kept) {
  $("kept").textContent = kept ? `${kept.samples} raw samples kept` : "";
  const div = $("diagnosis");
  div.dataset.status = d.status;
  if (d.status === "running") { div.textContent = `running… ${num(100 * (d.fraction || 0), 0)} %`; return; }
  if (d.status === "failed") { div.innerHTML = `<p class="bad">${esc(d.error)}</p>`; return; }
  if (d.status !== "done") { div.textContent = ""; return; }
  const rows = (d.candidates || []).map(c => `<tr><th>${esc(c.effect)}</th><td>${num(100 * (c.heldout_gain ?? NaN), 1)} %</td>` +
    `<td>${c.significant ? '<b class="good">yes</b>' : "no"}</td><td class="muted">${esc(c.reason || "")}</td></tr>`).join("");
  const verdict = d.verdict || {};
  const what = verdict.effect ? ` by ${verdict.effect}` : "";
  div.innerHTML = `<p id="verdict"><b>${esc((verdict.kind || "") + what)}</b>: residual ${num(verdict.rms_nT, 3)} nT ` +
    `against a floor of ${num(verdict.floor_nT, 3)} nT. ${esc(verdict.left || "")} ${esc(verdict.advice || "")}</p>` +
    `<table class="numbers"><tr><th>effect</th><th>held-out gain</th><th>significant</th><th></th></tr>${rows}</table>` +
    (d.discovery ? `<p id="discovery">beyond the catalogue: ${esc(d.discovery.sentence || "")}` +
      (d.effect_module ? ` <a id="effect-download" href="/api/effect?unit=${encodeURIComponent(unit)}" ` +
        `download>write it as an effect of your own (.py)</a>` : "") + `</p>` : "") +
    ((d.discovery && d.discovery.shapes) || []).map((s, i) =>
      `<canvas class="shape" id="shape-${i}" data-observable="${esc(s.observable)}"></canvas>`).join("") +
    `<p class="muted" id="diagnosis-given">${esc(d.given || "")}</p>` +
    `<details><summary>full text (${d.n_samples} samples, ${num(d.duration_s, 0)} s)</summary><pre>${esc(d.text)}</pre></details>`;
  ((d.discovery && d.discovery.shapes) || []).forEach((s, i) => window.fluxplot.drawShape($("shape-" + i), s));
}

// a counter of what arrived or was sent (bytes_received, frames_accepted, published_*) is not a fault: never red.
// The source's own counters say so themselves (state.source.counters: its kind's declaration, docs/sources.md);
// the rule on names serves the service's counters and a service that does not say.
function counterIsThroughput(k, about) {
  if (about && about[k]) { return Boolean(about[k].flow); }
  return /(^|_)(received|accepted)$/.test(k) || k.startsWith("published_") || k.startsWith("received");
}

function renderHealth(v) {
  const counters = (v.health && v.health.counters) || {};
  const bus = (v.health && v.health.bus) || {};
  const source = (v.state && v.state.source) || {};
  const about = source.counters || {};
  const good = k => counterIsThroughput(k, about);
  const title = k => (about[k] && about[k].doc) ? ` title="${esc(about[k].doc)}"` : "";
  const head = source.kind ? `counter (${esc(source.kind)}${source.protocol ? ", " + esc(source.protocol) : ""})` : "counter";
  $("health").innerHTML = `<tr><th>${head}</th><th>value</th></tr>` + Object.entries(counters).concat(
    Object.entries(bus).filter(([k]) => /errors|dropped|refused|expired/.test(k)).map(([k, x]) => ["bus." + k, x])).map(([k, x]) =>
    `<tr><th${title(k)}>${esc(k)}</th><td class="${x && !good(k) ? "bad" : ""}">${esc(x)}</td></tr>`).join("");
  $("events").innerHTML = (v.events || []).slice().reverse().map(e => `<li>${esc(e.kind)} at seq ${esc(e.seq ?? "–")}` +
    (e.reasons && e.reasons.length ? ": " + esc(e.reasons.join("; ")) : "") + (e.command ? " " + esc(e.command) : "") + "</li>").join("");
}

// losses and faults the service said (health.faults), as events with their counts; the panel is made here
function renderFaults(f) {
  if (!f) { return; }
  let panel = $("faults-panel");
  if (!panel) {
    panel = document.createElement("div");
    panel.id = "faults-panel";
    panel.innerHTML = "<h3>Losses and faults</h3><p id='faults-active'></p><ol id='faults' reversed></ol>";
    $("health").after(panel);
  }
  const totals = Object.entries(f.totals || {}).filter(([, n]) => n);
  const now = f.active.length ? `<span class="bad">now: ${esc(f.active.join(", "))}</span> · ` : "";
  const sums = totals.map(([k, n]) => `${esc(k)} ${esc(n)}`).join(", ");
  $("faults-active").innerHTML = now + (totals.length ? "totals: " + sums : '<span class="good">none so far</span>');
  const item = e => `<li class="${e.phase === "end" ? "good" : "bad"}" data-kind="${esc(e.kind)}" ` +
    `data-count="${esc(e.count)}">${new Date(e.time_unix_s * 1000).toLocaleTimeString()} ${esc(e.text)}</li>`;
  $("faults").innerHTML = (f.summary || []).map(x => `<li class="summary">${esc(x)}</li>`).join("") +
    f.events.slice().reverse().map(item).join("");
}

async function sendCommand(name) {
  // apply sends the calibration's content (chosen here or pasted), never a path: the unit reads no file for us
  const payload = name === "add-effect" ? $("effect-name").value : name === "apply" ? $("apply-payload").value : "";
  const li = document.createElement("li");
  li.textContent = `${name}: sending…`;
  $("command-log").prepend(li);
  const answer = await postJSON("/api/command", { unit, command: name, payload }).catch(e => ({ ok: false, error: e.message }));
  if (answer && answer.ok === false && !answer.command) {     // refused here, before it reached the unit
    li.className = "bad"; li.textContent = `${name}: refused by the dashboard: ${answer.error}`;
  }
  pollView();
}

$("apply-file").onchange = async () => {
  const f = $("apply-file").files[0];
  if (f) { $("apply-payload").value = await f.text(); }
};

document.querySelectorAll("button[data-cmd]").forEach(b => { b.onclick = () => sendCommand(b.dataset.cmd); });
$("diagnose").onclick = async () => {
  const answer = await postJSON("/api/diagnose", { unit }).catch(e => ({ ok: false, error: e.message }));
  if (answer && answer.ok === false) {
    $("diagnose-note").hidden = false; $("diagnose-note").textContent = "refused: " + answer.error;
  } else { pollView(); }
};
hist = newHist();
pollUnits();
setInterval(pollUnits, UNITS_EVERY_MS);
setInterval(pollView, VIEW_EVERY_MS);
