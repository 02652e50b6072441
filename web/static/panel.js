// The usmswitch panel: a plain client of the daemon's server process (web/panel.py).
// Reads: the live feed (/api/live, a WebSocket: strokes, state, statistics, the queue of runs), the runs
// (/api/runs). Controls: POST /api/control/NAME with the token's cookie (the URL `usmswitchctl web-url`
// prints sets it); without it, read-only (the controls of the queue's entries and a run's notes absent).
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
let runsVersion = -1, runsBusy = false, runsById = new Map();
async function loadRuns(version) {
  if (runsBusy || version === runsVersion) return;
  runsBusy = true;
  try {
    const resp = await fetch("/api/runs");
    const data = await resp.json();
    if (!resp.ok) throw new Error(data.error);
    runsVersion = version;
    runsById = new Map(data.runs.map((r) => [r.run_id, r]));
    const body = $("runs").tBodies[0];
    body.innerHTML = data.runs.slice().reverse().map((r) => {
      const s = r.settings || {}, st = r.stats || {}, on = st.on || {}, off = st.off || {};
      const strokes = r.last_cycle === null ? "running" : r.last_cycle - r.first_cycle + 1;
      const cycles = `${r.first_cycle}..${r.last_cycle ?? ""}`;
      return `<tr data-run="${r.run_id}"><td>${r.run_id}</td><td>${cycles}</td><td>${strokes}</td>` +
        `<td>${wall(r.started_wall_ns)}</td><td>${fmtNs(s.period_ns)}</td><td>${fmtNs(s.target_on_ns)}</td>` +
        `<td>${fmtNs(s.target_off_ns)}</td><td>${fmtNs(on.error_std_ns)} / ${fmtNs(off.error_std_ns)}</td>` +
        `<td>${fmtNs(on.error_max_abs_ns)} / ${fmtNs(off.error_max_abs_ns)}</td>` +
        `<td>${esc(r.end_reason ?? "-")}</td><td class="label">${esc(r.label ?? "")}</td>` +
        `<td class="notes"><span>${esc(r.notes ?? "")}</span>` +
        ` <button type="button" class="op edit-notes" data-run="${r.run_id}">edit</button></td>` +
        `<td><a href="/api/runs/${r.run_id}.csv" download>run-${r.run_id}.csv</a></td></tr>`;
    }).join("");
  } catch (e) {
    notice("runs: " + e.message, true);
  } finally {
    runsBusy = false;
  }
}

// -- the queue of runs ------------------------------------------------------------------------------
// The run going, then what waits in the order it will start (the daemon's `status` and its `queue`
// notifications, kept by the server process). With the token: each entry's priority and cancel.
const who = (owner) => String(owner || "-").split(" pid ")[0];
// Today's times as the time alone (the whole date in the cell's title): the queue fits its column.
function when(ns) {
  const full = wall(ns);
  return `<td title="${full}">${full.slice(0, 10) === wall(Date.now() * 1e6).slice(0, 10) ? full.slice(11) : full}</td>`;
}
function queueRow(e, state, run) {
  const s = (run && run.settings) || {};
  const count = e ? e.count : s.count;
  const period = e ? e.period_ns : s.period_ns;
  const target = e ? e.target_ns : s.target_on_ns;
  const owner = e ? e.owner : s.owner;
  const label = e ? e.label : run.label;
  const prio = e ? e.priority : "-";
  const entry = e ? e.entry : "-";
  const waiting = !run; // the run going has its run; a waiting entry none yet
  const prioCell = waiting
    ? `<span class="ro">${prio}</span><input class="op prio" type="number" min="-1000" max="1000" step="1" ` +
      `value="${prio}" data-entry="${entry}"> <button type="button" class="op prio-set" data-entry="${entry}">set</button>`
    : `${prio}`;
  const act = waiting ? `<button type="button" class="cancel-entry" data-entry="${entry}">cancel</button>` : "";
  return `<tr data-entry="${entry}" class="${waiting ? "waiting" : "running"}"><td>${entry}</td><td>${esc(state)}</td>` +
    `<td class="label">${esc(label ?? "")}</td><td class="owner" title="${esc(owner ?? "")}">${esc(who(owner))}</td>` +
    `<td>${count ? count : "endless"}</td><td>${fmtNs(period)}</td><td>${target ? fmtNs(target) : "as set"}</td>` +
    `<td>${prioCell}</td>${when(e ? e.submitted_wall_ns : run.started_wall_ns)}<td class="op">${act}</td></tr>`;
}
function showQueue(q) {
  if (!q) return;
  const paused = !!q.paused;
  document.body.dataset.queuePaused = paused ? "yes" : "no";
  text("queue-state", paused ? "(paused: nothing starts until it is resumed)" : "(going on)");
  $("queue-resume").hidden = !paused;
  $("queue-pause").hidden = paused;
  const rows = [];
  if (q.run) {
    const cur = q.current && q.current.run_id === q.run.run_id ? q.current : null;
    rows.push(queueRow(cur, `running: run ${q.run.run_id}`, q.run));
  }
  for (const e of q.queued || []) rows.push(queueRow(e, `queued #${e.position}`, null));
  if (!rows.length) rows.push('<tr class="empty"><td colspan="10">nothing going, nothing queued</td></tr>');
  // A priority being typed survives the redraw.
  const typing = document.activeElement;
  const kept = typing && typing.classList.contains("prio") ? [typing.dataset.entry, typing.value] : null;
  $("queue").tBodies[0].innerHTML = rows.join("");
  if (kept) {
    const box = $("queue").querySelector(`input.prio[data-entry="${kept[0]}"]`);
    if (box) { box.value = kept[1]; box.focus(); }
  }
}

// -- the live feed -----------------------------------------------------------------------------------
let feed = null; // the live feed while it is open: the estop goes on it
function connect() {
  const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/api/live");
  ws.onopen = () => { feed = ws; text("link", "live"); $("link").className = "badge ok"; };
  ws.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.estop) { estopAnswered(msg.estop); return; }
    if (msg.type === "hello") {
      for (const k in cols) cols[k].length = 0;
      runErrors = [];
    }
    if (msg.gap) notice("this panel fell behind: some strokes are missing from the plot");
    if (msg.strokes && msg.strokes.length) addStrokes(msg.strokes);
    if (msg.status) showStatus(msg.status);
    if (msg.stats) showStats(msg.stats);
    if (msg.queue) showQueue(msg.queue);
    if (msg.runs_version !== undefined) loadRuns(msg.runs_version);
  };
  ws.onclose = () => {
    if (feed === ws) feed = null;
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

// The estop goes on the live feed the page holds open (no connection to open, no request to parse,
// no wait at a full door); by POST when the feed is down, or when the feed has not answered in 1 s.
let estops = 0;
const estopWaiting = new Map(); // id -> its fallback timer
function estop() {
  const id = ++estops;
  if (feed && feed.readyState === WebSocket.OPEN) {
    estopWaiting.set(id, setTimeout(() => { estopWaiting.delete(id); control("estop"); }, 1000));
    feed.send(JSON.stringify({ estop: id }));
  } else {
    control("estop");
  }
}
function estopAnswered(answer) {
  clearTimeout(estopWaiting.get(answer.id));
  estopWaiting.delete(answer.id);
  notice(answer.error ? `estop: ${answer.error}` : "", Boolean(answer.error));
}
$("estop").addEventListener("click", estop);
// A run going that a client or an experiment started is never ended silently: the start goes without
// take_over, and when the daemon refuses it naming the run, the page says whose run it is and asks
// (in the page, never a blocking dialog: the live feed keeps drawing) before sending it again with
// take_over, as `usmswitchctl cycle` asks for --take-over. The daemon's own start-up run gives way unasked.
const RUN_GOING = /^already cycling: (run \d+ \(.*\) is going)/;
let pending = null; // [what yes does, what no does]
function ask(question, yes, onYes, onNo) {
  pending = [onYes, onNo];
  notice("");
  text("confirm-text", question);
  text("confirm-yes", yes);
  $("confirm").hidden = false;
  $("confirm-yes").focus();
}
function answered() { $("confirm").hidden = true; const p = pending; pending = null; return p; }
$("confirm-yes").addEventListener("click", () => { const p = answered(); if (p) p[0](); });
$("confirm-no").addEventListener("click", () => { const p = answered(); if (p) p[1](); });
const optional = (v) => (v === "" ? undefined : v);
function runBody() {
  return {
    count: Math.round(Number($("run-count").value || 0)),
    period_ns: msToNs($("run-period").value),
    target_ns: msToNs($("run-target").value),
    label: optional($("run-label").value.trim()),
    notes: optional($("run-notes").value),
  };
}
$("run-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  answered();
  const body = runBody();
  await control("start", body, (err) => {
    const going = err.code === STATE_CODE && RUN_GOING.exec(err.error);
    if (!going) return false;
    ask(`${going[1]}. Take it over? That ends it, and its record says "taken over by panel".`, "Take it over",
      () => control("start", { ...body, take_over: true }),
      () => notice("start cancelled: the run going goes on"));
    return true;
  });
});
// Queued, the run waits its turn: it never ends the run going.
$("submit").addEventListener("click", async () => {
  answered();
  const body = { ...runBody(), priority: Math.round(Number($("run-priority").value || 0)) };
  const e = await control("submit", body);
  if (e) notice(`queued as entry ${e.entry}, position ${e.position}` + (e.paused ? " (the queue is paused)" : ""));
});
// Another's entry or run: the daemon refuses naming whose it is; the page asks before acting as an
// operator, as `usmswitchctl queue cancel N` wants --operator.
const OTHERS = /^\w+: ((?:entry|run) \d+ is [^:]+): its (?:submitter|owner)/;
async function asOperator(name, body, verb, done) {
  const result = await control(name, body, (err) => {
    const whose = err.code === STATE_CODE && OTHERS.exec(err.error);
    if (!whose) return false;
    ask(`${whose[1]}. ${verb} as an operator?`, verb,
      async () => { const r = await control(name, { ...body, operator: true }); if (r && done) done(r); },
      () => notice(`${name}: not done`));
    return true;
  });
  if (result && done) done(result);
}
$("queue").addEventListener("click", (ev) => {
  const button = ev.target.closest("button");
  if (!button) return;
  const entry = Number(button.dataset.entry);
  if (button.classList.contains("cancel-entry")) {
    asOperator("queue_cancel", { entry }, `Cancel entry ${entry}`, () => notice(`entry ${entry} cancelled`));
  } else if (button.classList.contains("prio-set")) {
    const box = $("queue").querySelector(`input.prio[data-entry="${entry}"]`);
    const priority = Math.round(Number(box.value));
    asOperator("queue_priority", { entry, priority }, `Give entry ${entry} priority ${priority}`,
      (e) => notice(`entry ${entry}: priority ${e.priority}, position ${e.position}`));
  }
});
$("queue-resume").addEventListener("click", () => control("queue_resume"));
$("queue-pause").addEventListener("click", () => control("queue_pause"));
// A run's notes (and label), edited in a form of its own: the runs list redraws under it.
let editing = null;
$("runs").addEventListener("click", (ev) => {
  const button = ev.target.closest("button.edit-notes");
  if (!button) return;
  const run = runsById.get(Number(button.dataset.run));
  if (!run) return;
  editing = { run: run.run_id, label: run.label ?? "", notes: run.notes ?? "" };
  text("notes-run", `run ${run.run_id}`);
  $("notes-label").value = editing.label;
  $("notes-text").value = editing.notes;
  $("notes-form").hidden = false;
  $("notes-text").focus();
});
$("notes-cancel").addEventListener("click", () => { $("notes-form").hidden = true; editing = null; });
$("notes-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  if (!editing) return;
  const body = { run: editing.run };
  const label = $("notes-label").value.trim(), notes = $("notes-text").value;
  if (label !== editing.label) body.label = label; // "" clears it
  if (notes !== editing.notes) body.notes = notes;
  if (body.label === undefined && body.notes === undefined) { notice("notes: nothing changed"); return; }
  const run = editing.run;
  await asOperator("notes", body, `Edit run ${run}'s notes`, () => {
    $("notes-form").hidden = true;
    editing = null;
    notice(`run ${run}: notes saved`);
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
