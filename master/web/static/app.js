// The farm's page: jobs (a sequence as one row), one job's image and partition, agents, logs. Plain JavaScript,
// no framework, no build.
// Data arrives by server-sent events (/ui/events); the only timer is a 1 s one that ages "last heartbeat"
// and counts ETAs down locally. Every value from the server is put in the page as text (textContent), never as HTML.
"use strict";

const CSRF = document.querySelector('meta[name="csrf-token"]').content;
const STATE_COLOURS = { pending: "#6b7280", awarded: "#d97706", done: "#15803d", failed: "#b91c1c", cancelled: "#7c3aed" };
// A unit's state in the store's words -> the page's (the legend's).
const STATE_WORDS = { pending: "queued", announced: "queued", awarded: "rendering", done: "done", failed: "failed", cancelled: "cancelled" };
const SEQUENCE_ID = /^seq-[0-9a-f]{8,32}$/;
const VIRIDIS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];

const state = {
  view: "jobs", jobId: null, source: null, jobs: [], agents: [], agentsAt: 0, job: null,
  colour: "status", showGrid: true, selected: null, selectedKey: null, shownPreview: null, reportFor: null,
  armed: new Map(),
};

// ---- small helpers ----------------------------------------------------------------------------------

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs || {})) {
    if (key === "class") node.className = value;
    else if (key === "style") node.style.cssText = value;  // CSSOM: allowed by the page's CSP, a style attribute is not
    else if (key === "dataset") Object.assign(node.dataset, value);
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value);
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

function fill(node, ...children) {
  // replaceChildren would write null as the text "null": leave the empty parts out.
  node.replaceChildren(...children.flat().filter((c) => c !== null && c !== undefined));
}

function fmtTime(epoch) {
  if (!epoch) return "";
  return new Date(epoch * 1000).toLocaleTimeString();
}

function fmtSeconds(s) {
  if (s === null || s === undefined) return "";
  if (s < 60) return `${s.toFixed(1)} s`;
  const m = Math.floor(s / 60);
  return m < 60 ? `${m} min ${Math.round(s % 60)} s` : `${Math.floor(m / 60)} h ${m % 60} min`;
}

function fmtNumber(v, digits = 3) {
  if (v === null || v === undefined) return "";
  if (typeof v !== "number") return String(v);
  return Number.isInteger(v) ? String(v) : Number(v).toPrecision(digits);
}

function eta(job) {
  if (job.status !== "running") return "";
  if (job.eta_s === null || job.eta_s === undefined) return job.passes ? "after the first pass" : "after the first unit";
  // The master sends a job again only when a row of it changes: the ETA counts down here in between
  // (tickEtas), from when it arrived, except while the farm is paused. A noise goal's ETA counts only the
  // passes ordered so far: "at least".
  const prefix = job.eta_at_least ? "at least " : "";
  const dataset = job.paused ? {} : { eta: String(job.eta_s), at: String(job.receivedAt || Date.now() / 1000), prefix };
  return el("span", { class: "eta", dataset }, prefix + fmtSeconds(job.eta_s));
}

function elapsed(job) {
  // Counts up here between the master's sends (tickEtas), like the ETA counts down, until the job ends.
  if (job.finished !== null && job.finished !== undefined) return fmtSeconds(job.elapsed_s);
  const dataset = { elapsed: String(job.elapsed_s), at: String(job.receivedAt || Date.now() / 1000) };
  return el("span", { class: "elapsed", dataset }, fmtSeconds(job.elapsed_s));
}

function tickEtas() {
  const now = Date.now() / 1000;
  for (const span of document.querySelectorAll("span.eta[data-eta]")) {
    span.textContent = (span.dataset.prefix || "") + fmtSeconds(Math.max(0, Number(span.dataset.eta) - (now - Number(span.dataset.at))));
  }
  for (const span of document.querySelectorAll("span.elapsed[data-elapsed]")) {
    span.textContent = fmtSeconds(Number(span.dataset.elapsed) + Math.max(0, now - Number(span.dataset.at)));
  }
}

function badge(text) {
  return el("span", { class: `badge ${text.split(" ")[0]}` }, text);
}

function say(text, isError = false) {
  const box = document.getElementById("message");
  box.textContent = text;
  box.className = isError ? "message error" : "message";
  box.hidden = !text;
}

// To the login form, keeping the view (#/job/ID) to come back to after it (login.js).
function toLogin() { window.location.assign("/ui/login" + window.location.hash); }

async function post(url, body) {
  const headers = { "X-CSRF-Token": CSRF };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const response = await fetch(url, {
    method: "POST", headers, credentials: "same-origin", body: body === undefined ? undefined : JSON.stringify(body),
  });
  const answer = await response.json().catch(() => ({}));
  if (response.status === 401) toLogin();
  if (!response.ok) throw new Error(answer.error || `HTTP ${response.status}`);
  return answer;
}

async function getJSON(url) {
  const response = await fetch(url, { credentials: "same-origin" });
  if (response.status === 401) toLogin();
  const body = await response.json();
  if (!response.ok) throw new Error(body.error || `HTTP ${response.status}`);
  return body;
}

// ---- routing and the event stream ---------------------------------------------------------------------

const JOB_ID = /^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$/;  // the master's own pattern (master/http_guard.py)

function decoded(text) {
  try { return decodeURIComponent(text); } catch { return text; }  // "%zz": shown as typed
}

function route() {
  const hash = window.location.hash || "#/jobs";
  const jobId = hash.startsWith("#/job/") ? decoded(hash.slice("#/job/".length)) : null;
  state.view = jobId !== null ? "job" : hash === "#/agents" ? "agents" : hash === "#/logs" ? "logs" : "jobs";
  if (jobId !== state.jobId || state.source === null) {
    state.jobId = jobId;
    state.job = null;
    state.selected = null;
    state.selectedKey = null;
    state.shownPreview = null;
    state.reportFor = null;
    fill(document.getElementById("unit-details"),
      el("p", { class: "muted" }, "Click a unit of the partition to see its features, the rules that fired, its agent and its attempts."));
    document.getElementById("report").hidden = true;
    // An id the master could never have made is answered here: its stream would be refused, and retried.
    if (jobId !== null && !JOB_ID.test(jobId)) state.job = { error: `no job ${JSON.stringify(jobId)}: not a job id` };
    connect();
  }
  for (const name of ["jobs", "job", "agents", "logs"]) document.getElementById(`${name}-view`).hidden = state.view !== name;
  document.getElementById("nav-jobs").classList.toggle("active", state.view === "jobs" || state.view === "job");
  document.getElementById("nav-agents").classList.toggle("active", state.view === "agents");
  document.getElementById("nav-logs").classList.toggle("active", state.view === "logs");
  if (state.view === "logs") loadLogs();
  render();
}

function connect() {
  if (state.source) state.source.close();
  const live = document.getElementById("live");
  const watched = state.jobId !== null && JOB_ID.test(state.jobId);
  const url = "/ui/events" + (watched ? `?job=${encodeURIComponent(state.jobId)}` : "");
  const source = new EventSource(url);
  source.addEventListener("open", () => { live.textContent = "live"; live.className = "live ok"; });
  source.addEventListener("jobs", (e) => {
    state.jobs = JSON.parse(e.data).jobs.map((j) => ({ ...j, receivedAt: Date.now() / 1000 }));
    renderJobs();
  });
  source.addEventListener("job", (e) => { state.job = { ...JSON.parse(e.data), receivedAt: Date.now() / 1000 }; renderJob(); });
  source.addEventListener("agents", (e) => {
    const data = JSON.parse(e.data);
    state.agents = data.agents;
    state.agentsAt = Date.now() / 1000;
    renderAgents();
  });
  source.addEventListener("error", () => {
    live.textContent = "reconnecting";
    live.className = "live";
    if (source.readyState === EventSource.CLOSED) {
      // A refused stream (session gone) is not retried by the browser: ask once whether we are logged out.
      fetch("/ui/api/agents", { credentials: "same-origin" }).then((r) => {
        if (r.status === 401) toLogin();
        else setTimeout(connect, 3000);
      }).catch(() => setTimeout(connect, 3000));
    }
  });
  state.source = source;
}

function render() {
  if (state.view === "jobs") renderJobs();
  else if (state.view === "job") renderJob();
  else if (state.view === "agents") renderAgents();
}

// ---- jobs ---------------------------------------------------------------------------------------------

// A unit is "failed" in the store only when its job ended without it (cancelled or failed): it was left
// unrendered, not broken (a unit whose render fails is retried elsewhere). A progressive job counts its
// image's units (done: their goal met) and shows its passes apart, their share of the job's work in a
// lighter colour (a noise or time goal meets its units only at the job's end).
function progressBar(job) {
  const total = job.units_total || 0;
  const share = total ? (100 * job.units_done) / total : 0;
  const passes = job.passes;
  const passShare = passes ? 100 * passes.share : 0;  // the work done (a time goal's seconds), not the passes counted
  const left = passes ? "left short of their goal" : "left unrendered";
  return el("div", { class: "progress", dataset: passes ? { passesDone: String(passes.done), passesOrdered: String(passes.ordered) } : {} },
    el("div", { class: "bar" },
      passes ? el("span", { class: "bar-passes", style: `width: ${passShare.toFixed(1)}%` }) : null,
      el("span", { class: "bar-units", style: `width: ${share.toFixed(1)}%` })),
    el("span", { class: "bar-text" }, `${job.units_done}/${total} units`
      + (passes ? `, ${passes.done}/${passes.ordered} passes, ${String(passes.spp_mean)} spp` : "")
      + (job.units_failed ? `, ${job.units_failed} ${left}` : "")));
}

function effectsCell(effects) {
  if (!effects || !effects.variant) return "";
  const head = `${effects.variant} / ${effects.integrator} / depth ${effects.max_depth}`;
  return el("details", {}, el("summary", {}, head), el("ul", {}, (effects.reasons || []).map((r) => el("li", {}, r))));
}

// A button that acts on the second click within 4 s (the first arms it; no browser dialog).
function armedButton(action, id, label, act) {
  const key = `${action}-${id}`;
  const armed = state.armed.has(key);
  return el("button", {
    type: "button", class: armed ? "danger armed" : "danger", "data-action": action, "data-job": id,
    onclick: () => {
      if (!state.armed.has(key)) {
        state.armed.set(key, setTimeout(() => { state.armed.delete(key); render(); }, 4000));
        render();
        return;
      }
      clearTimeout(state.armed.get(key));
      state.armed.delete(key);
      act();
    },
  }, armed ? `Confirm ${label.toLowerCase()}` : label);
}

function actionButtons(job) {
  const buttons = [];
  if (job.status === "running") buttons.push(armedButton("cancel", job.job_id, "Cancel", () => cancelJob(job.job_id)));
  else buttons.push(armedButton("delete", job.job_id, "Delete", () => deleteJob(job.job_id)));
  if (job.status === "failed" || job.status === "cancelled") buttons.push(requeueButton(job.job_id));
  buttons.push(el("button", {
    type: "button", "data-action": "resubmit", "data-job": job.job_id, onclick: () => resubmitJob(job.job_id),
  }, "Re-submit"));
  const denoised = Boolean(job.options && job.options.denoise);
  buttons.push(el("button", {
    type: "button", "data-action": "resubmit-denoise", "data-job": job.job_id, "data-denoise": String(!denoised),
    title: denoised ? "The same job, its raw image only." : "The same job, denoised (the raw image is kept too).",
    onclick: () => resubmitJob(job.job_id, !denoised),
  }, denoised ? "Re-submit without denoising" : "Re-submit denoised"));
  return buttons;
}

// A failed or cancelled job (a sequence: its failed or cancelled frames) runs again, its done units kept.
function requeueButton(id) {
  return el("button", {
    type: "button", "data-action": "requeue", "data-job": id, onclick: () => requeueJob(id),
    title: "Run it again: the units done are kept, the others are rendered.",
  }, "Requeue");
}

function requeueJob(id) {
  post(`/ui/api/jobs/${encodeURIComponent(id)}/requeue`)
    .then((r) => say(r.sequence ? `Sequence ${id}: ${r.requeued.length} frame(s) run again.`
      : `Job ${id} runs again: its units done are kept, the others go back to the auction.`))
    .catch((e) => say(`Requeue failed: ${e.message}`, true));
}

function cancelJob(jobId) {
  post(`/ui/api/jobs/${encodeURIComponent(jobId)}/cancel`)
    .then((r) => say(r.cancelled ? `Job ${jobId} cancelled.` : `Job ${jobId} had already ended.`))
    .catch((e) => say(`Cancel failed: ${e.message}`, true));
}

function deleteJob(jobId) {
  post(`/ui/api/jobs/${encodeURIComponent(jobId)}/delete`)
    .then(() => {
      say(`Job ${jobId} deleted: its image, tiles and records are gone.`);
      if (state.jobId === jobId) window.location.hash = "#/jobs";
    })
    .catch((e) => say(`Delete failed: ${e.message}`, true));
}

function retryUnit(jobId, index) {
  post(`/ui/api/jobs/${encodeURIComponent(jobId)}/units/${index}/retry`)
    .then(() => {
      say(`Unit ${index} of job ${jobId} goes back to the auction, to be rendered again.`);
      if (state.jobId === jobId && state.selected === index) loadUnit(index);
    })
    .catch((e) => say(`Retry failed: ${e.message}`, true));
}

function drainAgent(jid, drain) {
  post("/ui/api/agents/drain", { agent: jid, drain })
    .then(() => say(drain ? `Agent ${jid} drains: no new unit; it finishes those it holds.` : `Agent ${jid} resumed.`))
    .catch((e) => say(`${drain ? "Drain" : "Resume"} failed: ${e.message}`, true));
}

// `denoise` true or false turns the new job's denoising on or off; left out, the job's own options stay.
function resubmitJob(jobId, denoise) {
  say(`Submitting job ${jobId} again (planning its pre-pass)...`);
  post(`/ui/api/jobs/${encodeURIComponent(jobId)}/resubmit`, denoise === undefined ? undefined : { denoise })
    .then((r) => say(`Job ${jobId} submitted again as ${r.job_id}` + (r.denoise ? ", denoised." : ".")))
    .catch((e) => say(`Re-submit failed: ${e.message}`, true));
}

function denoiseText(job) {
  if (!job.options || !job.options.denoise) return "no";
  if (job.result_ready) return "yes: the image is denoised, the raw one is kept beside it";
  return job.aov_pass ? "yes: the preview is denoised" : "yes: the preview is raw until the AOV pass is rendered";
}

function definesText(defines) {
  return Object.entries(defines || {}).map(([k, v]) => `${k}=${v}`).join(" ");
}

function resolutionText(job) {
  const [w, h] = job.resolution || [job.width, job.height];
  return `${w} x ${h}`;
}

// A sequence's status from its frames' (as the master's job API says it).
function sequenceStatus(frames) {
  const statuses = new Set(frames.map((f) => f.status));
  if (statuses.has("running")) return "running";
  if (statuses.has("failed")) return "failed";
  return statuses.size === 1 && statuses.has("done") ? "done" : "cancelled";
}

// The jobs table's rows: a job alone, or a sequence's frames as one row (frames done/total).
function tableRows(jobs) {
  const rows = [], sequences = new Map();
  for (const job of jobs) {
    if (!job.sequence) { rows.push(job); continue; }
    if (!sequences.has(job.sequence)) {
      const row = { sequence: job.sequence, frames: [] };
      sequences.set(job.sequence, row);
      rows.push(row);
    }
    sequences.get(job.sequence).frames.push(job);
  }
  return rows;
}

// A value over a sequence's frames: the one they share, or "first..last" where it varies (the frame's own).
function spanText(frames, value) {
  const values = frames.map(value);
  return values.every((v) => v === values[0]) ? values[0] : `${values[0]}..${values[values.length - 1]}`;
}

// A sequence's -D values: each as its frames share it, or as the span the frames run over.
function sequenceDefines(frames) {
  const names = Object.keys(frames[0].defines || {});
  return Object.fromEntries(names.map((name) => [name, spanText(frames, (f) => (f.defines || {})[name])]));
}

function sequenceRow(seq) {
  const frames = seq.frames.slice().sort((a, b) => a.frame - b.frame);
  const first = frames[0], status = sequenceStatus(frames);
  const done = frames.filter((f) => f.status === "done").length;
  return el("tr", { "data-job": seq.sequence, "data-status": status, "data-sequence": seq.sequence },
    el("td", {}, el("a", { href: `#/job/${seq.sequence}`, class: "job-link" }, first.name || seq.sequence),
      el("div", { class: "muted" }, `sequence ${seq.sequence}`)),
    el("td", {}, first.scene), el("td", {}, badge(status)), el("td", {}, first.level), el("td", {}, spanText(frames, (f) => f.spp)),
    el("td", {}, resolutionText(first)), el("td", {}, definesText(sequenceDefines(frames))),
    el("td", {}, el("span", { class: "frames-done" }, `${done}/${frames.length} frames done`)),
    el("td", {}), el("td", {}, fmtTime(first.created)), el("td", {}), el("td", {}),
    el("td", {}, status === "running" ? armedButton("cancel", seq.sequence, "Cancel", () => cancelJob(seq.sequence)) : null));
}

function renderJobs() {
  if (state.view !== "jobs") return;
  const rows = tableRows(state.jobs).map((job) => job.frames ? sequenceRow(job) : el("tr", { "data-job": job.job_id, "data-status": job.status },
    el("td", {}, el("a", { href: `#/job/${job.job_id}`, class: "job-link" }, job.name || job.job_id),
      job.name ? el("div", { class: "muted" }, job.job_id) : null),
    el("td", {}, job.scene),
    el("td", {}, badge(job.paused ? `${job.status} (paused)` : job.status), job.error ? el("div", { class: "muted" }, job.error) : null),
    el("td", {}, job.level, job.options && job.options.denoise ? el("div", { class: "muted" }, "denoised") : null),
    el("td", {}, job.spp), el("td", {}, resolutionText(job)), el("td", { class: "defines" }, definesText(job.defines)),
    el("td", {}, progressBar(job)),
    el("td", {}, eta(job)),
    el("td", {}, fmtTime(job.created)),
    el("td", {}, elapsed(job), job.finished ? ` (ended ${fmtTime(job.finished)})` : ""),
    el("td", {}, effectsCell(job.effects)),
    el("td", {}, actionButtons(job))));
  fill(document.querySelector("#jobs-table tbody"), ...rows);
  document.getElementById("jobs-empty").hidden = state.jobs.length > 0;
}

// ---- one job ------------------------------------------------------------------------------------------

function renderJob() {
  if (state.view !== "job") return;
  const job = state.job;
  const view = document.getElementById("job-view");
  if (!job) {  // the stream has not sent this job yet: nothing of the job shown before stays
    clearJob();
    document.getElementById("job-title").textContent = `Job ${state.jobId}`;
    fill(document.getElementById("job-summary"), el("div", { class: "muted" }, "waiting for the master"));
    return;
  }
  if (job.error && !job.units && !job.frames) {  // no such job: its title, a sentence, and no image of another
    clearJob();
    document.getElementById("job-title").textContent = `Job ${state.jobId}`;
    fill(document.getElementById("job-summary"), el("div", { id: "no-job" }, `no job ${state.jobId}`),
      el("div", { class: "muted" }, job.error));
    return;
  }
  if (job.frames) { renderSequence(job); return; }
  document.getElementById("frames-table").hidden = true;
  document.getElementById("job-stage-part").hidden = false;
  view.dataset.status = job.status;
  view.dataset.unitsDone = job.units_done;
  view.dataset.unitsTotal = job.units_total;
  view.dataset.passesDone = job.passes ? job.passes.done : "";
  document.getElementById("job-title").textContent = `Job ${job.name ? `${job.name} (${job.job_id})` : job.job_id}: ${job.scene}`
    + (job.sequence ? `, frame ${job.frame}` : "");
  const item = (label, value) => el("div", {}, el("b", {}, label), value);
  fill(document.getElementById("job-summary"),
    item("state", badge(job.status)), job.partial && job.status !== "running" ? item("image so far", badge("partial")) : null, item("level", job.level),
    job.sequence ? item("sequence", el("a", { href: `#/job/${job.sequence}` }, `${job.sequence}, frame ${job.frame}`)) : null,
    item("-D", definesText(job.defines) || "-"),
    item("progress", progressBar(job)),
    item("ETA", eta(job) || "-"),
    item("image", `${job.width} x ${job.height}, spp ${job.spp}, depth ${job.depth} (the job's: each unit's own are on the partition)`),
    item("submitted", fmtTime(job.created)), item("time", elapsed(job)),
    item("effects", effectsCell(job.effects)),
    el("div", { id: "job-denoise", "data-denoise": String(Boolean(job.options && job.options.denoise)) },
      el("b", {}, "denoised"), denoiseText(job)),
    job.adaptive_text ? el("div", { id: "job-adaptive" }, el("b", {}, "adaptive"), " " + job.adaptive_text) : null,
    el("div", {}, actionButtons(job)),
    job.error ? item("error", job.error) : null);
  renderDownloads(job);
  refreshPreview(job);
  drawOverlay();
  refreshSelected(job);
  if (job.status === "done" && job.result_ready && state.reportFor !== job.job_id) loadReport(job.job_id);
  if (job.status !== "done") document.getElementById("report").hidden = true;
}

// Nothing of a job shown before stays: its image, partition, unit, report and downloads.
function clearJob() {
  const img = document.getElementById("preview");
  img.removeAttribute("src");
  delete img.dataset.tiles;
  const canvas = document.getElementById("overlay");
  canvas.getContext("2d").clearRect(0, 0, canvas.width, canvas.height);
  canvas.dataset.units = "0";
  fill(document.getElementById("legend"));
  document.getElementById("report").hidden = true;
  document.getElementById("downloads").hidden = true;
  document.getElementById("frames-table").hidden = true;
  document.getElementById("job-stage-part").hidden = true;
  delete document.getElementById("job-view").dataset.status;
}

// A done job's files to save (named as `quekaro result` names them); a job running or ended without
// finishing offers its partial image.
function renderDownloads(job) {
  const box = document.getElementById("downloads");
  const base = `/ui/api/jobs/${encodeURIComponent(job.job_id)}/download`;
  const link = (kind, text) => el("a", { href: `${base}/${kind}`, download: "", "data-download": kind }, text);
  if (job.status === "done" && job.result_ready) {
    fill(box, el("b", {}, "Download"), link("image", "image (EXR)"), link("png", "PNG"), link("report", "report (JSON)"),
      job.options && job.options.denoise ? link("raw", "raw image (EXR, with AOVs)") : null);
  } else if (job.partial) {
    fill(box, el("b", {}, "Download"), link("image", "partial image (EXR: the tiles done, the rest black)"),
      link("png", "PNG"), link("report", "report (JSON)"));
  } else {
    box.hidden = true;
    return;
  }
  box.hidden = false;
}

// A sequence: one row per frame, each with its progress; a frame is opened, cancelled or deleted as a job.
function renderSequence(seq) {
  clearJob();
  const view = document.getElementById("job-view");
  view.dataset.status = seq.status;
  document.getElementById("job-title").textContent = `Sequence ${seq.name ? `${seq.name} (${seq.sequence})` : seq.sequence}: ${seq.scene}`;
  const first = seq.frames[0] || {};
  const item = (label, value) => el("div", {}, el("b", {}, label), value);
  fill(document.getElementById("job-summary"), item("state", badge(seq.status)),
    item("frames", el("span", { id: "frames-done" }, `${seq.frames_done}/${seq.frames.length} done`)),
    item("level", first.level), item("spp", first.spp), item("resolution", resolutionText(first)),
    seq.status === "running" ? el("div", {}, armedButton("cancel", seq.sequence, "Cancel", () => cancelJob(seq.sequence))) : null,
    seq.frames.some((f) => f.status === "failed" || f.status === "cancelled") ? el("div", {}, requeueButton(seq.sequence)) : null);
  const rows = seq.frames.map((f) => el("tr", { "data-job": f.job_id, "data-frame": String(f.frame), "data-status": f.status },
    el("td", {}, String(f.frame)), el("td", {}, el("a", { href: `#/job/${f.job_id}` }, f.job_id)),
    el("td", {}, badge(f.status), f.error ? el("div", { class: "muted" }, f.error) : null),
    el("td", {}, progressBar(f)), el("td", {}, elapsed(f)), el("td", {}, actionButtons(f))));
  fill(document.querySelector("#frames-table tbody"), ...rows);
  document.getElementById("frames-table").hidden = false;
}

function refreshPreview(job) {
  const version = `${job.tiles}-${job.aov_pass ? 1 : 0}-${job.result_ready ? 1 : 0}`;
  if (state.shownPreview === version) return;
  state.shownPreview = version;
  const img = document.getElementById("preview");
  const next = new Image();
  next.onload = () => {
    img.src = next.src;
    img.dataset.tiles = String(job.tiles);
    img.dataset.final = job.result_ready ? "1" : "0";
    img.dataset.denoised = job.aov_pass ? "1" : "0";
    layoutStage(job);
  };
  next.src = `/ui/api/jobs/${encodeURIComponent(job.job_id)}/preview.png?v=${version}`;
  layoutStage(job);
}

function scaleOf(job) {
  // Small images are shown enlarged (pixelated), large ones fit the window.
  const roomW = Math.max(320, Math.min(window.innerWidth - 480, 1100));
  const roomH = Math.max(320, window.innerHeight - 240);
  const fit = Math.min(roomW / job.width, roomH / job.height);
  return fit >= 1 ? Math.min(16, Math.floor(fit)) : fit;
}

function layoutStage(job) {
  const scale = scaleOf(job);
  const width = Math.round(job.width * scale), height = Math.round(job.height * scale);
  const img = document.getElementById("preview"), canvas = document.getElementById("overlay");
  img.style.width = `${width}px`;
  img.style.height = `${height}px`;
  canvas.style.width = `${width}px`;
  canvas.style.height = `${height}px`;
  const ratio = window.devicePixelRatio || 1;
  if (canvas.width !== Math.round(width * ratio)) canvas.width = Math.round(width * ratio);
  if (canvas.height !== Math.round(height * ratio)) canvas.height = Math.round(height * ratio);
}

function unitValue(unit) {
  const v = unit[state.colour];
  return v === null || v === undefined ? null : Number(v);
}

function viridis(t) {
  const x = Math.min(1, Math.max(0, t)) * (VIRIDIS.length - 1);
  const i = Math.min(VIRIDIS.length - 2, Math.floor(x)), f = x - i;
  const c = VIRIDIS[i].map((a, k) => Math.round(a + f * (VIRIDIS[i + 1][k] - a)));
  return `rgb(${c[0]}, ${c[1]}, ${c[2]})`;
}

function valueRange(units) {
  const values = units.map(unitValue).filter((v) => v !== null && Number.isFinite(v));
  if (!values.length) return null;
  return [Math.min(...values), Math.max(...values)];
}

function unitFill(unit, range) {
  if (state.colour === "status") return { colour: STATE_COLOURS[unit.status] || "#000", alpha: unit.status === "done" ? 0.12 : 0.5 };
  const v = unitValue(unit);
  if (v === null || !range) return { colour: "#9ca3af", alpha: 0.55 };
  const t = range[1] > range[0] ? (v - range[0]) / (range[1] - range[0]) : 0.5;
  return { colour: viridis(t), alpha: 0.7 };
}

function drawOverlay() {
  const job = state.job;
  if (!job || !job.units) return;
  layoutStage(job);
  const canvas = document.getElementById("overlay");
  const ctx = canvas.getContext("2d");
  const k = canvas.width / job.width;
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const range = state.colour === "status" ? null : valueRange(job.units);
  for (const unit of job.units) {
    const [x, y, w, h] = unit.rect;
    const fill = unitFill(unit, range);
    ctx.globalAlpha = fill.alpha;
    ctx.fillStyle = fill.colour;
    ctx.fillRect(x * k, y * k, w * k, h * k);
    ctx.globalAlpha = 1;
    if (state.showGrid) {
      ctx.strokeStyle = state.colour === "status" ? STATE_COLOURS[unit.status] || "#000" : "#ffffffaa";
      ctx.lineWidth = 1;
      ctx.strokeRect(x * k + 0.5, y * k + 0.5, w * k - 1, h * k - 1);
    }
  }
  if (state.selected !== null) {
    const unit = job.units.find((u) => u.index === state.selected);
    if (unit) {
      const [x, y, w, h] = unit.rect;
      ctx.strokeStyle = "#22d3ee";
      ctx.lineWidth = 3;
      ctx.strokeRect(x * k + 1.5, y * k + 1.5, w * k - 3, h * k - 3);
    }
  }
  canvas.dataset.units = String(job.units.length);
  canvas.dataset.done = String(job.units.filter((u) => u.status === "done").length);
  canvas.dataset.colour = state.colour;
  renderLegend(range);
}

function renderLegend(range) {
  const legend = document.getElementById("legend");
  if (state.colour === "status") {
    fill(legend, ...Object.entries(STATE_COLOURS).map(([name, colour]) =>
      el("span", { "data-state": name }, el("span", { class: "swatch", style: `background: ${colour}` }), ` ${STATE_WORDS[name]} `)));
    return;
  }
  const lo = range ? fmtNumber(range[0]) : "-", hi = range ? fmtNumber(range[1]) : "-";
  fill(legend, el("span", { id: "legend-min" }, lo), el("span", { class: "ramp" }),
    el("span", { id: "legend-max" }, hi),
    el("span", {}, el("span", { class: "swatch", style: "background: #9ca3af" }), " no value yet"));
}

function unitAt(event) {
  const job = state.job;
  if (!job || !job.units) return null;
  const canvas = document.getElementById("overlay");
  const box = canvas.getBoundingClientRect();
  const px = ((event.clientX - box.left) / box.width) * job.width;
  const py = ((event.clientY - box.top) / box.height) * job.height;
  return job.units.find((u) => px >= u.rect[0] && px < u.rect[0] + u.rect[2] && py >= u.rect[1] && py < u.rect[1] + u.rect[3]) || null;
}

function refreshSelected(job) {
  if (state.selected === null) return;
  const unit = job.units.find((u) => u.index === state.selected);
  const key = unit ? `${unit.status}-${unit.attempts}-${unit.agent}-${unit.passes}` : null;
  if (key !== state.selectedKey) loadUnit(state.selected);
}

function loadUnit(index) {
  const job = state.job;
  state.selected = index;
  const unit = job.units.find((u) => u.index === index);
  state.selectedKey = unit ? `${unit.status}-${unit.attempts}-${unit.agent}-${unit.passes}` : null;
  drawOverlay();
  getJSON(`/ui/api/jobs/${encodeURIComponent(job.job_id)}/units/${index}`)
    .then(renderUnit)
    .catch((e) => say(`Unit ${index}: ${e.message}`, true));
}

function renderUnit(unit) {
  const rows = [
    ["state", badge(STATE_WORDS[unit.status] || unit.status)], ["rectangle", unit.rect.join(", ")],
    ["C (complexity)", fmtNumber(unit.C, 4)], ["S (size, px)", unit.S], ["Nd (neighbour difference)", fmtNumber(unit.Nd, 4)],
    ["cost", fmtNumber(unit.cost, 4)], ["agent", unit.agent || "-"], ["attempts", unit.attempts],
    ["spp", unit.spp ?? "-"], ["depth", unit.depth ?? "-"], ["band", unit.band ?? "-"],
    ["render seconds", unit.seconds ?? "-"], ...(unit.passes === undefined ? [] : [["passes done", unit.passes]]),
    ["Rl, Ls, Ibs", Object.keys(unit.outputs || {}).length ? Object.entries(unit.outputs).map(([k, v]) => `${k} ${fmtNumber(v, 3)}`).join(", ") : "-"],
  ];
  const table = el("table", { id: "unit-table" }, rows.map(([k, v]) => el("tr", {}, el("th", {}, k), el("td", { "data-field": k }, v))));
  const rules = unit.rules || {};
  let rulesPart;
  if (rules.error) rulesPart = el("p", { class: "error" }, rules.error);
  else if (!rules.fired || !rules.fired.length) rulesPart = el("p", { class: "muted" }, rules.note || "No rule fired.");
  else {
    rulesPart = el("div", {},
      el("p", { class: "muted" }, `${rules.rules_file}, level ${rules.level} (Op ${fmtNumber(rules.inputs.Op, 3)}): ${rules.note}`),
      el("ul", { class: "rules", id: "fired-rules" }, rules.fired.map((r) => el("li", {},
        el("span", { class: "strength", style: `width: ${Math.round(r.strength * 60)}px` }),
        el("b", {}, `${r.name} ${r.strength.toFixed(3)}`), ` IF ${r.if} THEN ${r.then}`))));
  }
  const attempts = el("table", { id: "attempts-table" },
    el("tr", {}, [...(unit.passes === undefined ? [] : ["pass"]), "agent", "started", "finished", "outcome", "seconds",
      "reason"].map((h) => el("th", {}, h))),
    (unit.attempt_list || []).map((a) => el("tr", {}, ...(a.pass === undefined ? [] : [el("td", {}, a.pass)]),
      el("td", {}, a.agent), el("td", {}, fmtTime(a.started)),
      el("td", {}, fmtTime(a.finished)), el("td", {}, a.outcome), el("td", {}, a.seconds ?? ""), el("td", {}, a.reason))));
  const story = el("table", { id: "story-table" },
    el("tr", {}, ["time", "from", "to", "stimulus"].map((h) => el("th", {}, h))),
    (unit.story || []).map((s) => el("tr", {}, el("td", {}, fmtTime(s.at)), el("td", {}, s.start),
      el("td", {}, s.finish), el("td", {}, s.stimulus_id))));
  const job = state.job || {};
  const retry = unit.status === "done" && !job.passes && (job.status === "running" || job.status === "done")
    ? el("button", { type: "button", "data-action": "retry", onclick: () => retryUnit(unit.job_id, unit.index) }, "Render again")
    : null;
  const lines = unit.log || [];
  fill(document.getElementById("unit-details"),
    el("h3", { id: "unit-title", "data-unit": unit.index }, `Unit ${unit.index}`), retry, table,
    el("h3", {}, "Log"), lines.length ? el("pre", { class: "unit-log", id: "unit-log" }, lines.join("\n"))
      : el("p", { class: "muted", id: "unit-log" }, "No line of the master's log names this unit (a farm of separate hosts keeps no log here)."),
    el("h3", {}, "Rules that fired"), rulesPart, el("h3", {}, "Attempts"), attempts,
    el("h3", {}, "Story"), unit.story && unit.story.length ? story
      : el("p", { class: "muted" }, "No change of state since the master started."));
}

function accuracyPart(report) {
  // A report that carries an accuracy comparison shows it; the farm's own reports say why they have none.
  if (!report.accuracy) return el("p", { class: "muted", id: "accuracy-note" }, report.accuracy_note);
  const entries = Object.entries(report.accuracy);
  return el("div", { id: "accuracy" }, el("h3", {}, "Accuracy"),
    el("dl", {}, entries.flatMap(([k, v]) => [el("dt", {}, k),
      el("dd", {}, typeof v === "object" && v !== null ? JSON.stringify(v) : fmtNumber(v, 4))])));
}

function loadReport(jobId) {
  state.reportFor = jobId;
  getJSON(`/ui/api/jobs/${encodeURIComponent(jobId)}/report`).then((report) => {
    const box = document.getElementById("report");
    if (!report.available) { box.hidden = true; state.reportFor = null; return; }
    const totals = report.totals || {}, compose = report.compose || {};
    const pairs = [
      ["units", totals.units], ["render seconds (agents)", fmtNumber(totals.render_seconds, 4)],
      ["samples", totals.samples], ["non-finite pixels", totals.nonfinite],
      ["pre-pass seconds", fmtNumber(totals.prepass_seconds, 3)], ["job seconds (upload to composed image)", fmtNumber(totals.seconds, 3)],
      ["tiles used", compose.tiles_used], ["pixels filled from neighbours (no finite sample)", compose.filled], ["pixels uncovered", compose.uncovered],
    ];
    if (report.passes) pairs.unshift(["job in passes", report.passes]);  // its goal and why it stopped
    fill(box, el("h3", {}, "Report"),
      el("dl", {}, pairs.flatMap(([k, v]) => [el("dt", {}, k), el("dd", {}, v ?? "-")])),
      accuracyPart(report));
    box.hidden = false;
  }).catch((e) => { state.reportFor = null; say(`Report: ${e.message}`, true); });
}

// ---- agents -------------------------------------------------------------------------------------------

function renderAgents() {
  if (state.view !== "agents") return;
  const age = Date.now() / 1000 - state.agentsAt;
  const rows = state.agents.map((a) => el("tr", { "data-agent": a.jid, "data-state": a.state },
    el("td", {}, a.jid, a.shared ? el("div", { class: "warning" }, a.shared) : null),
    el("td", {}, a.host ?? "-"), el("td", {}, a.threads ?? "-"),
    el("td", { class: "agent-state" }, agentState(a),
      a.blocklisted_for && a.blocklisted_for.length ? el("div", { class: "muted" }, `blocklisted for ${a.blocklisted_for.join(", ")}`) : null),
    el("td", {}, `${fmtNumber(a.speed, 3)} x reference`), el("td", {}, a.units_done), el("td", {}, a.units_failed),
    el("td", {}, `${(a.last_seen_s + age).toFixed(0)} s ago`), el("td", {}, a.restarts),
    el("td", {}, a.lost ? null : el("button", {
      type: "button", "data-action": a.draining ? "resume" : "drain", onclick: () => drainAgent(a.jid, !a.draining),
    }, a.draining ? "Resume" : "Drain"))));
  fill(document.querySelector("#agents-table tbody"), ...rows);
  document.getElementById("agents-empty").hidden = state.agents.length > 0;
}

// An agent's state in words: idle, rendering JOB unit N (each unit it holds), draining, lost.
function agentState(a) {
  const holding = (a.holding || []).map((h) => { const [job, unit] = h.split("/"); return `${job} unit ${unit}`; });
  if (a.state === "rendering") return el("span", {}, badge("rendering"), ` ${holding.join(", ")}`);
  if (a.state === "draining") return el("span", {}, badge("draining"), holding.length ? ` finishing ${holding.join(", ")}` : " nothing left to finish");
  return badge(a.state);
}

// ---- logs ---------------------------------------------------------------------------------------------

function loadLogs() {
  getJSON("/ui/api/logs").then((answer) => {
    const select = document.getElementById("log-name");
    const chosen = select.value;
    fill(select, answer.logs.map((l) => el("option", { value: l.name }, `${l.name} (${l.bytes} bytes)`)));
    if (answer.logs.some((l) => l.name === chosen)) select.value = chosen;
    document.getElementById("logs-empty").hidden = answer.logs.length > 0;
    if (answer.logs.length) loadLog(select.value);
    else document.getElementById("log-text").textContent = "";
  }).catch((e) => say(`Logs: ${e.message}`, true));
}

function loadLog(name) {
  getJSON(`/ui/api/logs/${encodeURIComponent(name)}?lines=400`).then((answer) => {
    const text = document.getElementById("log-text");
    text.textContent = answer.lines.join("\n");
    text.dataset.log = answer.name;
    text.scrollTop = text.scrollHeight;
  }).catch((e) => say(`Log ${name}: ${e.message}`, true));
}

// ---- start --------------------------------------------------------------------------------------------

document.getElementById("overlay").addEventListener("click", (event) => {
  const unit = unitAt(event);
  if (unit) loadUnit(unit.index);
});
document.getElementById("colour-by").addEventListener("change", (event) => { state.colour = event.target.value; drawOverlay(); });
document.getElementById("show-grid").addEventListener("change", (event) => { state.showGrid = event.target.checked; drawOverlay(); });
document.getElementById("logout").addEventListener("click", () => {
  post("/ui/logout").finally(() => toLogin());
});
document.getElementById("log-name").addEventListener("change", (event) => loadLog(event.target.value));
document.getElementById("log-refresh").addEventListener("click", () => loadLogs());
window.addEventListener("hashchange", route);
window.addEventListener("resize", () => drawOverlay());
setInterval(() => { if (state.view === "agents") renderAgents(); tickEtas(); }, 1000);  // ages heartbeats and ETAs; no request
route();
