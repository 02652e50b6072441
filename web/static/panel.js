// The usmswitch panel: a plain client of the daemon's server process (web/panel.py).
// Reads: the live feed (/api/live, a WebSocket), the runs (/api/runs). Controls: POST /api/control/NAME
// with the token's cookie (the URL `usmswitchctl web-url` prints sets it); without it, read-only.
"use strict";

const MAX_POINTS = 3000; // strokes kept on the plots (30 s at 100 strokes a second)
const HIST_BINS = 41;

// -- the token: the server trades the URL's token for an HttpOnly, SameSite=Strict cookie and
// redirects to the clean URL before this script runs (Jupyter's way), so the page never sees it and
// it stays out of the history, caches and Referer headers. Same-origin requests carry the cookie.

// -- units for people: 12.000 ms, 95.3 us ------------------------------------------------------------
function fmtNs(ns) {
  if (ns === null || ns === undefined || !isFinite(ns)) return "-";
  const a = Math.abs(ns);
  if (a >= 1e9) return (ns / 1e9).toFixed(3) + " s";
  if (a >= 1e6) return (ns / 1e6).toFixed(3) + " ms";
  if (a >= 1e3) return (ns / 1e3).toFixed(1) + " us";
  return Math.round(ns) + " ns";
}
const $ = (id) => document.getElementById(id);
function text(id, value) { const el = $(id); if (el.textContent !== String(value)) el.textContent = value; }

// -- messages ----------------------------------------------------------------------------------------
function notice(message, isError) {
  const el = $("notice");
  el.hidden = !message;
  el.textContent = message || "";
  el.className = "notice" + (isError ? " error" : "");
}

// -- plots -------------------------------------------------------------------------------------------
// Strokes as columns: x = cycle; on and off apart, as the paper draws them.
const cols = { x: [], opOn: [], opOff: [], errOn: [], errOff: [] };
let strokesSeen = 0;
let runErrors = []; // the current run's errors (us), for the histogram
let currentRun = null;

function plotOpts(title, yLabel, series, height) {
  return {
    width: Math.max(400, $("plot-operating").parentElement.clientWidth - 10),
    height: height,
    legend: { live: false },
    cursor: { drag: { x: false, y: false } },
    scales: { x: { time: false } },
    axes: [{ label: "cycle" }, { label: yLabel, size: 60 }],
    series: [{ label: "cycle" }, ...series],
  };
}
const pointSeries = (label, stroke) => ({ label, stroke, width: 0, points: { show: true, size: 3, fill: stroke } });
const opPlot = new uPlot(
  plotOpts("operating", "t (ms)", [pointSeries("on", "#1f77b4"), pointSeries("off", "#d62728")], 240),
  [[], [], []], $("plot-operating"));
const errPlot = new uPlot(
  plotOpts("error", "error (us)", [pointSeries("on", "#1f77b4"), pointSeries("off", "#d62728")], 200),
  [[], [], []], $("plot-error"));
const histPlot = new uPlot({
  width: Math.max(300, $("plot-hist").parentElement.clientWidth - 10),
  height: 180,
  legend: { show: false },
  cursor: { show: false },
  scales: { x: { time: false } },
  axes: [{ label: "error (us)" }, { label: "strokes", size: 50 }],
  series: [{}, { label: "strokes", stroke: "#555", fill: "rgba(80,80,80,0.35)",
    paths: uPlot.paths.bars({ size: [0.9, 100] }), points: { show: false } }],
}, [[], []], $("plot-hist"));

function addStrokes(rows) {
  for (const r of rows) {
    const [cycle, direction, operating, error, , , , , runId] = r;
    cols.x.push(cycle);
    const op = operating === null ? null : operating / 1e6;
    const err = error === null ? null : error / 1e3;
    cols.opOn.push(direction === 0 ? op : null);
    cols.opOff.push(direction === 1 ? op : null);
    cols.errOn.push(direction === 0 ? err : null);
    cols.errOff.push(direction === 1 ? err : null);
    if (runId !== currentRun) { currentRun = runId; runErrors = []; }
    if (err !== null) { runErrors.push(err); if (runErrors.length > 20000) runErrors.shift(); }
  }
  const extra = cols.x.length - MAX_POINTS;
  if (extra > 0) for (const k in cols) cols[k].splice(0, extra);
  strokesSeen += rows.length;
  document.body.dataset.strokes = String(strokesSeen);
  text("stroke-count", strokesSeen);
  dirty = true;
}

let dirty = false;
function draw() {
  if (dirty) {
    dirty = false;
    opPlot.setData([cols.x, cols.opOn, cols.opOff]);
    errPlot.setData([cols.x, cols.errOn, cols.errOff]);
    drawHistogram();
  }
  requestAnimationFrame(draw);
}
requestAnimationFrame(draw);

function drawHistogram() {
  const n = runErrors.length;
  text("hist-n", n ? `(run ${currentRun ?? "-"}, last ${n} strokes)` : "");
  if (!n) { histPlot.setData([[], []]); return; }
  let lo = Infinity, hi = -Infinity;
  for (const e of runErrors) { if (e < lo) lo = e; if (e > hi) hi = e; }
  const m = Math.max(Math.abs(lo), Math.abs(hi), 1);
  const width = (2 * m) / HIST_BINS;
  const xs = [], counts = new Array(HIST_BINS).fill(0);
  for (let i = 0; i < HIST_BINS; i++) xs.push(-m + (i + 0.5) * width);
  for (const e of runErrors) counts[Math.min(HIST_BINS - 1, Math.floor((e + m) / width))]++;
  histPlot.setData([xs, counts]);
}

// -- state and statistics ----------------------------------------------------------------------------
let status = null;
function showStatus(s) {
  if (!s) return;
  status = s;
  text("rig", s.rig ?? "-");
  text("driver", s.driver + (s.driver_ok === false ? " (not answering)" : ""));
  text("state", s.state);
  text("mode", s.mode + (s.mode === "open" ? ` (delay ${fmtNs(s.open_delay_ns)})` : ""));
  text("model", s.model ? `${s.model}${s.order ? " m=" + s.order : ""}` : "-");
  text("targets", `${fmtNs(s.target_on_ns)} / ${fmtNs(s.target_off_ns)}`);
  text("cycle", s.cycle ?? "-");
  const fault = $("fault");
  fault.hidden = !s.fault;
  fault.textContent = s.fault ? `FAULT latched: ${s.fault} (reset the fault to run again)` : "";
  document.body.dataset.state = s.state;
}

const STAT_ROWS = [
  ["strokes", (d) => d.count ?? "-"],
  ["operating mean", (d) => fmtNs(d.operating_mean_ns)],
  ["operating std", (d) => fmtNs(d.operating_std_ns)],
  ["error mean", (d) => fmtNs(d.error_mean_ns)],
  ["error std", (d) => fmtNs(d.error_std_ns)],
  ["max |error|", (d) => fmtNs(d.error_max_abs_ns)],
  ["max |error| %", (d) => (d.max_abs_error_pct ?? 0).toFixed(2) + " %"],
  ["|error| p95", (d) => fmtNs(d.abs_error_p95_ns)],
  ["start late p99", (d) => fmtNs(d.lateness_p99_ns)],
  ["late / stalls", (d) => `${d.late ?? 0} / ${d.stalls ?? 0}`],
];
function showStats(st) {
  if (!st) return;
  const run = st.run;
  text("run-title", run ? `(run ${run.run_id}, ${run.end_reason ? "ended: " + run.end_reason : "running"})` : "");
  const body = $("stats").tBodies[0];
  const rows = STAT_ROWS.map(([name, f]) => `<tr><td>${name}</td><td>${f(st.on || {})}</td><td>${f(st.off || {})}</td></tr>`);
  body.innerHTML = rows.join("");
}

// -- runs --------------------------------------------------------------------------------------------
// Wall-clock times as usmswitchctl writes them (ISO, local time: 2025-06-01 14:27:03), never the
// browser locale's (11/26/2025, 2:27:03 PM reads differently in every lab).
const pad2 = (n) => String(n).padStart(2, "0");
function wall(ns) {
  if (!ns) return "-";
  const d = new Date(ns / 1e6);
  return `${d.getFullYear()}-${pad2(d.getMonth() + 1)}-${pad2(d.getDate())} ` +
    `${pad2(d.getHours())}:${pad2(d.getMinutes())}:${pad2(d.getSeconds())}`;
}
function esc(s) { return String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" })[c]); }
let runsVersion = -1, runsBusy = false;
async function loadRuns(version) {
  if (runsBusy || version === runsVersion) return;
  runsBusy = true;
  try {
    const resp = await fetch("/api/runs");
    const data = await resp.json();
    if (!resp.ok) throw new Error(data.error);
    runsVersion = version;
    const body = $("runs").tBodies[0];
    body.innerHTML = data.runs.slice().reverse().map((r) => {
      const s = r.settings || {}, st = r.stats || {}, on = st.on || {}, off = st.off || {};
      const strokes = r.last_cycle === null ? "running" : r.last_cycle - r.first_cycle + 1;
      const cycles = `${r.first_cycle}..${r.last_cycle ?? ""}`;
      return `<tr data-run="${r.run_id}"><td>${r.run_id}</td><td>${cycles}</td><td>${strokes}</td>` +
        `<td>${wall(r.started_wall_ns)}</td><td>${fmtNs(s.period_ns)}</td><td>${fmtNs(s.target_on_ns)}</td>` +
        `<td>${fmtNs(s.target_off_ns)}</td><td>${fmtNs(on.error_std_ns)} / ${fmtNs(off.error_std_ns)}</td>` +
        `<td>${fmtNs(on.error_max_abs_ns)} / ${fmtNs(off.error_max_abs_ns)}</td>` +
        `<td>${esc(r.end_reason ?? "-")}</td><td><a href="/api/runs/${r.run_id}.csv" download>run-${r.run_id}.csv</a></td></tr>`;
    }).join("");
  } catch (e) {
    notice("runs: " + e.message, true);
  } finally {
    runsBusy = false;
  }
}

// -- the live feed -----------------------------------------------------------------------------------
function connect() {
  const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/api/live");
  ws.onopen = () => { text("link", "live"); $("link").className = "badge ok"; };
  ws.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.type === "hello") {
      for (const k in cols) cols[k].length = 0;
      runErrors = [];
    }
    if (msg.gap) notice("this panel fell behind: some strokes are missing from the plot");
    if (msg.strokes && msg.strokes.length) addStrokes(msg.strokes);
    if (msg.status) showStatus(msg.status);
    if (msg.stats) showStats(msg.stats);
    if (msg.runs_version !== undefined) loadRuns(msg.runs_version);
  };
  ws.onclose = () => {
    text("link", "disconnected: retrying"); $("link").className = "badge warn";
    setTimeout(connect, 1000);
  };
}

// -- controls ----------------------------------------------------------------------------------------
const STATE_CODE = 4; // protocol/wire.py ErrorCode.STATE: not possible in the current state
// `refused(data)` may take a refusal ({error, code}) in hand (true) instead of it being shown.
async function control(name, body, refused) {
  try {
    const resp = await fetch("/api/control/" + name, {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify(body || {}),
    });
    const data = await resp.json();
    if (!resp.ok) {
      if (!(refused && refused(data))) notice(`${name}: ${data.error}`, true);
      return null;
    }
    const warnings = (data.result && data.result.warnings) || [];
    notice(warnings.length ? warnings.join("; ") : "");
    return data.result;
  } catch (e) {
    notice(`${name}: ${e.message}`, true);
    return null;
  }
}
const msToNs = (v) => (v === "" || v === null ? undefined : Math.round(Number(v) * 1e6));

$("estop").addEventListener("click", () => control("estop"));
// A run going that a client or an experiment started is never ended silently: the start goes without
// take_over, and when the daemon refuses it naming the run, the page says whose run it is and asks
// (in the page, never a blocking dialog: the live feed keeps drawing) before sending it again with
// take_over, as `usmswitchctl cycle` asks for --take-over. The daemon's own start-up run gives way unasked.
const RUN_GOING = /^already cycling: (run \d+ \(.*\) is going)/;
let pendingStart = null;
function ask(question, body) {
  pendingStart = body;
  notice("");
  text("confirm-text", question);
  $("confirm").hidden = false;
  $("confirm-yes").focus();
}
function answered() { $("confirm").hidden = true; const body = pendingStart; pendingStart = null; return body; }
$("confirm-yes").addEventListener("click", () => {
  const body = answered();
  if (body) control("start", { ...body, take_over: true });
});
$("confirm-no").addEventListener("click", () => { if (answered()) notice("start cancelled: the run going goes on"); });
$("run-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  answered();
  const body = {
    count: Math.round(Number($("run-count").value || 0)),
    period_ns: msToNs($("run-period").value),
    target_ns: msToNs($("run-target").value),
  };
  await control("start", body, (err) => {
    const going = err.code === STATE_CODE && RUN_GOING.exec(err.error);
    if (!going) return false;
    ask(`${going[1]}. Take it over? That ends it, and its record says "taken over by panel".`, body);
    return true;
  });
});
$("stop").addEventListener("click", () => control("stop"));
$("target-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const on = msToNs($("target-on").value), off = msToNs($("target-off").value);
  if (on === undefined && off === undefined) { notice("set targets: give T on, T off or both", true); return; }
  if (on !== undefined && on === off) { await control("target", { target_ns: on, direction: "both" }); return; }
  if (on !== undefined && !(await control("target", { target_ns: on, direction: "on" }))) return;
  if (off !== undefined) await control("target", { target_ns: off, direction: "off" });
});
$("mode-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  control("mode", { mode: $("mode-select").value, open_delay_ns: msToNs($("open-delay").value) });
});
$("reset").addEventListener("click", () => control("reset"));

async function session() {
  let data = { control: false, message: "" };
  try {
    const resp = await fetch("/api/session");
    data = await resp.json();
  } catch (e) { /* the live feed's badge says the daemon is gone */ }
  document.body.dataset.control = data.control ? "yes" : "no";
  text("access", data.control ? "control" : "read-only");
  $("access").className = "badge " + (data.control ? "ok" : "warn");
  $("access").title = data.control ? "" : data.message;
}

session();
connect();
