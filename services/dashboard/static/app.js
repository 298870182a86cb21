// fedrl dashboard: keeps a copy of the run's state, fed by the server's event stream (/events), and draws it.
// No libraries and nothing fetched from elsewhere: the chart is drawn on a <canvas> by drawChart() below.
"use strict";

const COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
  "#bcbd22", "#17becf"];
const MAX_CURVE = 20000;   // points kept per worker in the page
const MAX_ROUNDS = 300;

const state = {
  run: null, workers: new Map(), rounds: [], transfers: [], rigs: new Map(), stats: null, connected: false,
};
// Read by tests and by `python -m services.dashboard.screenshot`.
const probe = window.fedrlDashboard = { loadedAt: Date.now(), snapshotAt: null, firstPointAt: null, points: 0 };

// -- the state -----------------------------------------------------------------------------------------------

function resetState() {
  state.run = null; state.workers.clear(); state.rounds = []; state.transfers = []; state.rigs.clear();
}

function workerEntry(id) {
  let w = state.workers.get(id);
  if (!w) { w = { id: id, curve: [] }; state.workers.set(id, w); }
  return w;
}

function applySnapshot(snap) {
  resetState();
  state.run = snap.run;
  for (const w of snap.workers) Object.assign(workerEntry(w.id), w, { curve: w.curve || [] });
  state.rounds = snap.rounds.slice(-MAX_ROUNDS);
  state.transfers = snap.transfers.slice();
  for (const r of snap.rigs) state.rigs.set(r.id, r);
  state.stats = snap.stats || state.stats;
  probe.snapshotAt = probe.snapshotAt || Date.now();
}

function applyEvent(ev) {
  switch (ev.type) {
    case "run": state.run = ev; break;
    case "worker": { const w = workerEntry(ev.id); const curve = w.curve; Object.assign(w, ev); w.curve = curve; break; }
    case "point": {
      const curve = workerEntry(ev.worker).curve;
      if (curve.length && curve[curve.length - 1][0] === ev.point[0]) curve[curve.length - 1] = ev.point;
      else curve.push(ev.point);
      if (curve.length > MAX_CURVE) curve.splice(0, curve.length - MAX_CURVE);
      break;
    }
    case "round":
      state.rounds.push(ev);
      if (state.rounds.length > MAX_ROUNDS) state.rounds.shift();
      if (ev.kind === "transfer") state.transfers.push(ev);
      break;
    case "rig": state.rigs.set(ev.id, ev); break;
    case "reset": resetState(); break;
    default: break;  // a newer server's event: nothing to show
  }
}

// -- the event stream ------------------------------------------------------------------------------------------

let renderTimer = null;
function scheduleRender() {
  if (renderTimer === null) renderTimer = setTimeout(() => { renderTimer = null; render(); }, 100);
}

function connect() {
  const source = new EventSource("/events");
  source.addEventListener("open", () => { state.connected = true; scheduleRender(); });
  source.addEventListener("error", () => { state.connected = false; scheduleRender(); });
  source.addEventListener("snapshot", (e) => { applySnapshot(JSON.parse(e.data)); scheduleRender(); });
  source.addEventListener("delta", (e) => { for (const ev of JSON.parse(e.data)) applyEvent(ev); scheduleRender(); });
  source.addEventListener("stats", (e) => { state.stats = JSON.parse(e.data); scheduleRender(); });
}

// -- small DOM helpers -------------------------------------------------------------------------------------------

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined) continue;
    if (k === "class") node.className = v;
    else if (k === "style") node.style.cssText = v;  // CSSOM: allowed by the page's content security policy
    else if (k.startsWith("data-")) node.setAttribute(k, String(v));
    else node[k] = v;
  }
  for (const c of children) if (c !== null && c !== undefined) node.append(c instanceof Node ? c : String(c));
  return node;
}
const $ = (id) => document.getElementById(id);
function fmt(x, digits = 1) { return x === null || x === undefined ? "–" : Number(x).toFixed(digits); }
function setText(id, text) { const n = $(id); if (n.textContent !== text) n.textContent = text; }
function badge(text) { return el("span", { class: "badge " + text }, text); }
function ago(t) {
  if (!t || !state.stats) return "–";
  const s = Math.max(0, state.stats.t - t);
  return s < 60 ? s.toFixed(0) + " s" : (s / 60).toFixed(0) + " min";
}
function colorOf(id) {
  const ids = workerIds();
  const i = ids.indexOf(id);
  return COLORS[(i < 0 ? ids.length : i) % COLORS.length];
}
function workerIds() {
  const ids = new Set(state.run && state.run.workers ? state.run.workers : []);
  for (const id of state.workers.keys()) ids.add(id);
  return Array.from(ids).sort();
}
function progress(pi) {
  const run = state.run;
  if (!run || run.tc === null || pi === null || pi === undefined) return null;
  const p = (pi - run.r_floor) / (run.tc - run.r_floor);
  return Math.max(0, Math.min(1, p));
}
function replaceRows(tbody, rows) { tbody.replaceChildren(...rows); }

// -- rendering ---------------------------------------------------------------------------------------------------

function render() {
  renderHeader();
  renderWorkers();
  renderRounds();
  renderRigs();
  renderStats();
  drawChart();
}

function renderHeader() {
  const run = state.run;
  setText("run-id", run ? run.run_id : "…");
  const phase = run ? run.phase : "waiting";
  const ph = $("run-phase");
  ph.textContent = phase; ph.className = "badge " + phase;
  const conn = $("conn");
  const over = run && run.phase === "stopped";
  conn.textContent = state.connected ? "live" : over ? "offline (the run is over)" : "reconnecting…";
  conn.className = "conn " + (state.connected ? "on" : "off");
  if (!run) return;
  setText("run-env", run.env || "–");
  $("run-env").title = run.env || "";
  setText("run-policy", run.policy || "–");
  setText("run-tc", run.tc === null ? "–" : fmt(run.tc, 0));
  setText("run-workers", String(workerIds().length));
  const openRound = run.rounds_per_episode > 1 ? `${run.round} (episode ${run.episode})` : String(run.round);
  setText("run-round-label", run.round_label || "open round");
  setText("run-round", run.stop ? String(run.rounds) : run.round === null ? "–" : openRound);
  setText("transfers-empty", run.no_transfer || "No worker has finished yet.");
  setText("run-solved", `${run.solved.length} / ${workerIds().length}`);
  $("run-last-rig-card").hidden = !run.last_rig;
  if (run.last_rig) setText("run-last-rig", `${run.last_rig.id}: ${rigText(run.last_rig)}`);
  setText("run-transfers", String(run.transfers));
  let status = "waiting for the chief to start the run";
  if (run.stop) {
    status = `ended after ${run.stop.episodes} episodes (${run.rounds} rounds): ${run.stop.reason}`;
  } else if (run.phase === "running") {
    const solved = run.solved.map((s) => `${s.worker}@${s.episode}`).join(", ");
    status = `running, seed ${run.seed}, at most ${run.max_episodes} episodes` + (solved ? `; solved: ${solved}` : "");
  }
  setText("run-status", status);
  const now = state.stats ? state.stats.t : null;
  const end = run.stopped_at || now;
  const verb = run.stopped_at ? "ran for" : "running for";
  setText("run-clock", run.started_at && end ? `${verb} ${fmt(Math.max(0, end - run.started_at), 0)} s` : "");
}

function rigText(rig) {
  if (!rig) return "–";
  const idle = `idle ${fmt(rig.idle_s, 1)}${rig.idle === "modelled" ? " (modelled)" : ""}`;
  return `${fmt(rig.rig_s, 1)} (${fmt(rig.balance_s, 1)} + ${fmt(rig.reset_s, 1)}) · ${idle}`;
}

function renderWorkers() {
  const rows = [];
  let total = 0;
  for (const id of workerIds()) {
    const w = state.workers.get(id) || { id: id, state: "waiting", curve: [] };
    total += w.curve.length;
    const p = progress(w.pi);
    const piCell = el("td", {}, fmt(w.pi),
      p === null ? null : el("span", { class: "bar", title: `${(100 * p).toFixed(0)} % of the way to TC` },
        el("span", { style: `width:${(100 * p).toFixed(1)}%` })));
    rows.push(el("tr", { "data-worker": id, "data-state": w.state, "data-points": w.curve.length },
      el("td", {}, el("span", { class: "swatch", style: `background:${colorOf(id)}` }), id),
      el("td", {}, badge(w.state || "waiting")),
      el("td", { class: "num" }, w.episode || 0),
      piCell,
      el("td", { class: "num" }, fmt(w.ret)),
      el("td", { class: "num" }, fmt(w.weight, 3)),
      el("td", { class: "num" }, fmt(w.keep, 3)),
      el("td", { class: "num" }, w.solved_episode || "–"),
      el("td", { class: "num", "data-rig": w.rig ? w.rig.rig_s : "" }, rigText(w.rig)),
      el("td", { class: "num" }, ago(w.last_seen)),
      el("td", { class: "muted" }, w.detail || "")));
  }
  replaceRows(document.querySelector("#workers tbody"), rows);
  $("workers-empty").hidden = rows.length > 0;
  probe.points = total;
  if (total > 0 && probe.firstPointAt === null) probe.firstPointAt = Date.now();
}

function weightChips(weights) {
  return Object.keys(weights).sort().map((id) => el("span", { class: "chip" },
    el("span", { class: "swatch", style: `background:${colorOf(id)}` }), `${id} ${fmt(weights[id], 2)}`,
    el("span", { class: "bar" }, el("span", { style: `width:${(100 * weights[id]).toFixed(1)}%` }))));
}

function sourceLabel(r) {
  return [el("span", { class: "swatch", style: `background:${colorOf(r.source)}` }), `${r.source} (PI ${fmt(r.source_pi)})`];
}

function keepChips(r) {
  const ids = Object.keys(r.keep_weights).sort();
  if (!ids.length) return ["nobody left to receive it"];
  return ids.map((id) => el("span", { class: "chip" },
    el("span", { class: "swatch", style: `background:${colorOf(id)}` }), `${id} ${fmt(r.keep_weights[id], 2)}`));
}

function renderRounds() {
  const rows = state.rounds.slice(-12).reverse().map((r) => {
    let detail;
    if (r.kind === "transfer") {
      detail = el("td", {}, "actor of ", ...sourceLabel(r), " \u2192 ", ...keepChips(r));
    } else if (!r.shared) {
      detail = el("td", { class: "muted" }, `no gradient shared (${r.contributors.length} submitted)`);
    } else {
      detail = el("td", {}, ...weightChips(r.weights));
    }
    return el("tr", { "data-round": r.round, "data-kind": r.kind },
      el("td", { class: "num", title: `episode ${r.episode}, step ${r.step}` }, r.round),
      el("td", {}, badge(r.kind)), detail);
  });
  replaceRows(document.querySelector("#rounds tbody"), rows);
  $("rounds-empty").hidden = rows.length > 0;
  setText("rounds-count", state.run ? `${state.run.rounds} closed, newest first` : "");
  const transfers = state.transfers.slice().reverse().map((r) => el("tr", { "data-round": r.round },
    el("td", { class: "num" }, r.round), el("td", {}, ...sourceLabel(r)), el("td", {}, ...keepChips(r))));
  replaceRows(document.querySelector("#transfers tbody"), transfers);
  $("transfers-empty").hidden = transfers.length > 0;
}

function renderRigs() {
  const rows = Array.from(state.rigs.values()).sort((a, b) => a.id.localeCompare(b.id)).map((r) => {
    const lat = r.latency_ms || {};
    return el("tr", { "data-rig": r.id },
      el("td", {}, r.id), el("td", {}, badge(r.phase)), el("td", { class: "num" }, r.telemetry ? r.ticks : "–"),
      el("td", { class: "num" }, `${fmt(lat.p50, 2)} / ${fmt(lat.p99, 2)} / ${fmt(lat.max, 2)}`),
      el("td", { class: "num" }, fmt((r.jitter_ms || {}).p99, 2)),
      el("td", { class: "num" }, r.deadline_misses), el("td", { class: "num" }, r.late_actions),
      el("td", { class: "num" }, r.faults), el("td", { class: "num" }, ago(r.last_seen)),
      el("td", { class: "muted" }, [r.detail, r.note].filter(Boolean).join("; ")));
  });
  replaceRows(document.querySelector("#rigs tbody"), rows);
  $("rigs-empty").hidden = rows.length > 0;
}

function renderStats() {
  const s = state.stats;
  if (!s) return;
  const rejected = Object.entries(s.rejected || {});
  const nRejected = rejected.reduce((a, [, n]) => a + n, 0);
  const unknown = Object.values(s.unknown || {}).reduce((a, n) => a + n, 0);
  const ignored = Object.values(s.ignored || {}).reduce((a, n) => a + n, 0);
  const refused = Object.entries(s.refused || {});
  const nRefused = refused.reduce((a, [, n]) => a + n, 0);
  const parts = [
    `${s.received} messages`,
    `${nRejected} rejected` + (rejected.length ? ` (${rejected.map(([k, n]) => `${k} ${n}`).join(", ")})` : ""),
    `${nRefused} refused as not the chief's` + (refused.length ? ` (${refused.map(([k, n]) => `${k} ${n}`).join(", ")})` : ""),
    `${unknown} of unknown kinds`, `${ignored} not shown`, `${s.dropped} dropped`,
    s.connected ? "broker connected" : "broker disconnected", `${s.pages} page(s) open`,
  ];
  setText("stats", parts.join(" · "));
}

// -- the chart -------------------------------------------------------------------------------------------------

function niceStep(span, count) {
  const raw = span / Math.max(1, count);
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const norm = raw / mag;
  return (norm < 1.5 ? 1 : norm < 3 ? 2 : norm < 7 ? 5 : 10) * mag;
}

function ticks(lo, hi, count) {
  const step = niceStep(hi - lo, count);
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(Math.round(v / step) * step);
  return out;
}

function drawChart() {
  const canvas = $("curves");
  const ratio = window.devicePixelRatio || 1;
  const cssW = canvas.clientWidth, cssH = canvas.clientHeight;
  if (canvas.width !== Math.round(cssW * ratio) || canvas.height !== Math.round(cssH * ratio)) {
    canvas.width = Math.round(cssW * ratio); canvas.height = Math.round(cssH * ratio);
  }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
  ctx.clearRect(0, 0, cssW, cssH);
  const showReturns = $("show-returns").checked;
  const run = state.run;
  const ids = workerIds();
  const pad = { l: 56, r: 16, t: 30, b: 34 };
  const w = cssW - pad.l - pad.r, h = cssH - pad.t - pad.b;

  let xMax = 10, yMin = Infinity, yMax = -Infinity, drawn = 0;
  for (const id of ids) {
    const wk = state.workers.get(id);
    if (!wk) continue;
    for (const [ep, pi, ret] of wk.curve) {
      xMax = Math.max(xMax, ep);
      yMin = Math.min(yMin, pi, showReturns ? ret : pi);
      yMax = Math.max(yMax, pi, showReturns ? ret : pi);
    }
  }
  if (run && run.tc !== null) { yMin = Math.min(yMin, run.tc); yMax = Math.max(yMax, run.tc); }
  if (!isFinite(yMin)) { yMin = 0; yMax = 1; }
  if (yMax - yMin < 1e-9) { yMax += 1; yMin -= 1; }
  const span = yMax - yMin;
  yMin -= span * 0.04; yMax += span * 0.06;
  const X = (ep) => pad.l + (ep - 1) / Math.max(1, xMax - 1) * w;
  const Y = (v) => pad.t + (1 - (v - yMin) / (yMax - yMin)) * h;

  // grid and axes
  ctx.font = "11px system-ui, sans-serif";
  ctx.fillStyle = "#6b7280"; ctx.strokeStyle = "#eceef1"; ctx.lineWidth = 1;
  ctx.textAlign = "right"; ctx.textBaseline = "middle";
  for (const v of ticks(yMin, yMax, 6)) {
    const y = Math.round(Y(v)) + 0.5;
    ctx.beginPath(); ctx.moveTo(pad.l, y); ctx.lineTo(pad.l + w, y); ctx.stroke();
    ctx.fillText(String(+v.toFixed(6)), pad.l - 6, y);
  }
  ctx.textAlign = "center"; ctx.textBaseline = "top";
  for (const v of ticks(1, xMax, 10)) {
    if (v < 1) continue;
    const x = Math.round(X(v)) + 0.5;
    ctx.beginPath(); ctx.moveTo(x, pad.t); ctx.lineTo(x, pad.t + h); ctx.stroke();
    ctx.fillText(String(v), x, pad.t + h + 5);
  }
  ctx.strokeStyle = "#9aa1ab";
  ctx.strokeRect(pad.l + 0.5, pad.t + 0.5, w, h);
  ctx.fillText("episode", pad.l + w / 2, pad.t + h + 19);
  ctx.save(); ctx.translate(14, pad.t + h / 2); ctx.rotate(-Math.PI / 2);
  ctx.textBaseline = "middle"; ctx.fillText("return", 0, 0); ctx.restore();

  // transfers: a dotted vertical line at the round's episode
  ctx.setLineDash([2, 3]); ctx.lineWidth = 1;
  for (const t of state.transfers) {
    const x = X(t.episode);
    ctx.strokeStyle = colorOf(t.source);
    ctx.beginPath(); ctx.moveTo(x, pad.t); ctx.lineTo(x, pad.t + h); ctx.stroke();
  }
  // TC
  if (run && run.tc !== null) {
    ctx.setLineDash([6, 4]); ctx.strokeStyle = "#1d2330"; ctx.lineWidth = 1.2;
    const y = Y(run.tc);
    ctx.beginPath(); ctx.moveTo(pad.l, y); ctx.lineTo(pad.l + w, y); ctx.stroke();
    ctx.fillStyle = "#1d2330"; ctx.textAlign = "right"; ctx.textBaseline = "top";
    ctx.fillText(`TC ${fmt(run.tc, 0)}`, pad.l + w - 4, y + 3);
  }
  ctx.setLineDash([]);

  const line = (points, index, color, width, alpha) => {
    if (!points.length) return;
    ctx.globalAlpha = alpha; ctx.strokeStyle = color; ctx.lineWidth = width; ctx.lineJoin = "round";
    ctx.beginPath();
    points.forEach((p, i) => { const x = X(p[0]), y = Y(p[index]); if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y); });
    ctx.stroke();
    ctx.globalAlpha = 1;
  };
  for (const id of ids) {
    const wk = state.workers.get(id);
    if (!wk || !wk.curve.length) continue;
    const color = colorOf(id);
    if (showReturns) line(wk.curve, 2, color, 1, 0.3);
    line(wk.curve, 1, color, 2.4, 1);
    drawn += wk.curve.length;
    const last = wk.curve[wk.curve.length - 1];
    ctx.fillStyle = color;
    ctx.beginPath(); ctx.arc(X(last[0]), Y(last[1]), wk.state === "finished" ? 4.5 : 3, 0, 2 * Math.PI); ctx.fill();
  }
  // legend
  ctx.textAlign = "left"; ctx.textBaseline = "middle"; ctx.font = "12px system-ui, sans-serif";
  let lx = pad.l;
  const ly = pad.t - 14;
  for (const id of ids) {
    ctx.fillStyle = colorOf(id); ctx.fillRect(lx, ly - 5, 14, 10);
    ctx.fillStyle = "#1d2330"; ctx.fillText(id, lx + 18, ly);
    lx += 28 + ctx.measureText(id).width;
  }
  canvas.dataset.points = String(drawn);
  canvas.dataset.workers = String(ids.length);
}

$("show-returns").addEventListener("change", scheduleRender);
window.addEventListener("resize", scheduleRender);
setInterval(scheduleRender, 1000);  // "seen ... ago" and the clock move on even when nothing arrives
connect();
render();
