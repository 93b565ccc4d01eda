// rigcal dashboard: one more client of the JSON API (see src/dashboard/mod.rs for why).
// Plain JavaScript, no framework. Every text from the API goes through textContent; the
// only markup inserted is the SVG figures the API draws itself.
"use strict";

const KEY = "rigcal.api_key";
const PAGE_SIZE = 25;
const TERMINAL = ["succeeded", "degraded", "failed", "cancelled"];
const STAGE_COLOURS = ["#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000"];

const state = {
  key: sessionStorage.getItem(KEY),
  noAuth: false,
  tenant: null,
  view: null, // {name, ...}: what the live stream updates
  stream: null,
};

// ---- DOM helpers -----------------------------------------------------------------

function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined || v === false) continue;
    if (k === "class") el.className = v;
    else if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else if (k === "dataset") Object.assign(el.dataset, v);
    else el.setAttribute(k, v === true ? "" : String(v));
  }
  for (const c of children.flat()) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

const main = () => document.getElementById("main");

function show(title, ...nodes) {
  document.title = `${title} · rigcal`;
  const m = main();
  m.replaceChildren(...nodes);
  m.focus({ preventScroll: true });
}

function announce(text) {
  document.getElementById("announce").textContent = text;
}

function fmt(v, digits) {
  return v === null || v === undefined || Number.isNaN(v) ? "–" : Number(v).toFixed(digits);
}

function when(iso) {
  if (!iso) return "–";
  const d = new Date(iso);
  return d.toLocaleString(undefined, { dateStyle: "medium", timeStyle: "medium" });
}

function duration(job) {
  const s = job.running_seconds;
  if (s === null || s === undefined) return `queued ${fmt(job.queued_seconds, 1)} s`;
  if (s < 120) return `${fmt(s, 1)} s`;
  return `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`;
}

function badge(status) {
  return h("span", { class: `badge ${status}`, dataset: { status } }, status);
}

function acceptanceMark(job) {
  const a = job.acceptance;
  if (!a || a.pass === null || a.pass === undefined) return h("span", { class: "muted" }, "–");
  const title = a.pass ? "within the acceptance thresholds" : a.reasons.join("; ");
  return h("span", { class: `badge ${a.pass ? "pass" : "fail"}`, title, dataset: { acceptance: a.pass ? "pass" : "fail" } },
    a.pass ? "✓ pass" : "✗ fail");
}

function progressCell(job) {
  if (job.status === "running" || job.status === "queued") {
    const pct = Math.round((job.progress || 0) * 100);
    return h("span", {},
      h("progress", { max: 100, value: pct, "aria-label": `progress ${pct}%` }),
      h("span", { class: "stage" }, job.stage ? `${job.stage} · ${pct}%` : `${pct}%`));
  }
  return h("span", { class: "muted" }, job.status === "succeeded" || job.status === "degraded" ? "done" : "–");
}

// ---- API -------------------------------------------------------------------------

class ApiError extends Error {
  constructor(status, problem) {
    super(problem.detail || problem.title || `HTTP ${status}`);
    this.status = status;
    this.problem = problem;
  }
}

function authHeaders(extra) {
  const headers = Object.assign({}, extra || {});
  if (state.key) headers.Authorization = `Bearer ${state.key}`;
  return headers;
}

async function api(path, opts = {}) {
  const resp = await fetch(path, Object.assign({}, opts, { headers: authHeaders(opts.headers) }));
  const type = resp.headers.get("content-type") || "";
  if (!resp.ok) {
    let problem = {};
    try { problem = await resp.json(); } catch (_) { problem = { detail: `HTTP ${resp.status}` }; }
    if (resp.status === 401 && state.key) forgetKey("The API key was refused: " + (problem.detail || ""));
    throw new ApiError(resp.status, problem);
  }
  if (opts.raw) return resp;
  if (type.includes("json")) return resp.json();
  return resp.text();
}

function problemBox(err) {
  const p = err.problem || {};
  return h("div", { class: "box bad", role: "alert" },
    h("strong", {}, err.status ? `Error ${err.status}: ` : "Error: "), err.message,
    p.field ? h("div", {}, "Field: ", h("code", {}, p.field)) : null);
}

// ---- API key ----------------------------------------------------------------------

function forgetKey(reason) {
  sessionStorage.removeItem(KEY);
  state.key = null;
  state.tenant = null;
  stopStream();
  renderKeyForm(reason);
}

// Ask the server who `key` is, without touching the stored key: the sign-in form uses
// it to try a key, boot to confirm the stored one.
async function fetchTenant(key) {
  const headers = key ? { Authorization: `Bearer ${key}` } : {};
  const resp = await fetch("/v1/tenant", { headers });
  if (!resp.ok) {
    let problem = {};
    try { problem = await resp.json(); } catch (_) { problem = { detail: `HTTP ${resp.status}` }; }
    throw new ApiError(resp.status, problem);
  }
  return resp.json();
}

function signedIn(tenant) {
  state.tenant = tenant;
  document.getElementById("who").textContent = `Tenant: ${tenant.name}`;
  document.getElementById("forget").hidden = state.noAuth;
}

function renderKeyForm(message) {
  document.getElementById("who").textContent = "";
  document.getElementById("forget").hidden = true;
  const input = h("input", { id: "api-key", type: "password", autocomplete: "off", required: true, size: 40 });
  const err = h("p", { class: "error", role: "alert" }, message || "");
  const form = h("form", {
    class: "box", onsubmit: async (e) => {
      e.preventDefault();
      const key = input.value.trim();
      try {
        signedIn(await fetchTenant(key));
        state.key = key;
        sessionStorage.setItem(KEY, key);
        route();
      } catch (x) {
        err.textContent = `That key was not accepted: ${x.message}`;
        input.focus();
      }
    }
  },
  h("label", { for: "api-key" }, "API key"),
  h("p", { class: "muted", id: "api-key-help" }, "Kept in this browser tab's session only; closing the tab forgets it."),
  input, " ", h("button", { type: "submit" }, "Sign in"), err);
  input.setAttribute("aria-describedby", "api-key-help");
  show("API key", h("h1", {}, "rigcal dashboard"), form);
  input.focus();
}

// ---- Live updates: one server-sent event stream for the tenant ---------------------

function stopStream() {
  if (state.stream) state.stream.abort();
  state.stream = null;
}

// EventSource cannot send an Authorization header, so the stream is read with fetch.
// Read a server-sent event stream to its end, calling onEvent({event, id, data}) for
// each event (keep-alive comments skipped).
async function readEvents(resp, onEvent) {
  const reader = resp.body.pipeThrough(new TextDecoderStream()).getReader();
  let buf = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buf += value;
    let cut;
    while ((cut = buf.indexOf("\n\n")) >= 0) {
      const raw = buf.slice(0, cut);
      buf = buf.slice(cut + 2);
      const ev = { event: "message", data: "" };
      for (const line of raw.split("\n")) {
        const i = line.indexOf(":");
        if (i <= 0) continue;
        const k = line.slice(0, i);
        const v = line.slice(i + 1).replace(/^ /, "");
        if (k === "event") ev.event = v;
        else if (k === "data") ev.data += v;
        else if (k === "id") ev.id = v;
      }
      if (ev.data) onEvent(ev);
    }
  }
}

async function startStream() {
  stopStream();
  const ctrl = new AbortController();
  state.stream = ctrl;
  let last = null;
  let delay = 500;
  const conn = document.getElementById("conn");
  while (!ctrl.signal.aborted) {
    try {
      const headers = authHeaders({ Accept: "text/event-stream" });
      if (last !== null) headers["Last-Event-ID"] = last;
      const resp = await fetch("/v1/events", { headers, signal: ctrl.signal });
      if (!resp.ok) throw new Error(`HTTP ${resp.status}`);
      conn.textContent = "● live";
      delay = 500;
      await readEvents(resp, (ev) => {
        if (ev.id !== undefined) last = ev.id;
        if (ev.event === "job") onJobEvent(JSON.parse(ev.data));
      });
    } catch (e) {
      if (ctrl.signal.aborted) return;
    }
    conn.textContent = "○ reconnecting…";
    await new Promise((r) => setTimeout(r, delay));
    delay = Math.min(delay * 2, 10000);
  }
}

let reloadTimer = null;

function onJobEvent(ev) {
  const v = state.view;
  if (!v) return;
  if (v.name === "jobs") {
    const row = document.querySelector(`tr[data-job="${CSS.escape(ev.job_id)}"]`);
    if (row) {
      if (Number(row.dataset.eventId || 0) >= ev.id) return;
      row.dataset.eventId = ev.id;
      if (TERMINAL.includes(ev.status)) {
        // The finished row needs the job's RMS, duration and verdict.
        api(`/v1/jobs/${encodeURIComponent(ev.job_id)}`).then((job) => {
          const fresh = jobRow(job);
          fresh.dataset.eventId = ev.id;
          row.replaceWith(fresh);
          announce(`Job ${job.id.slice(0, 8)} ${job.status}`);
        }).catch(() => {});
      } else {
        const job = Object.assign({}, JSON.parse(row.dataset.snapshot), {
          status: ev.status, stage: ev.stage, progress: ev.progress,
        });
        row.querySelector(".c-status").replaceChildren(badge(job.status));
        row.querySelector(".c-progress").replaceChildren(progressCell(job));
        row.dataset.snapshot = JSON.stringify(job);
      }
    } else if (ev.kind === "status" && ev.status === "queued" && v.page === 0) {
      // A new job: show it if it belongs on this page (the server filters).
      clearTimeout(reloadTimer);
      reloadTimer = setTimeout(() => loadJobs(v, false), 300);
    }
  } else if (v.name === "job" && v.id === ev.job_id) {
    if (TERMINAL.includes(ev.status)) {
      renderJob(v.id, false);
    } else {
      const el = document.getElementById("job-progress");
      if (el) el.replaceChildren(badge(ev.status), " ", progressCell(ev));
    }
  }
}

// ---- Jobs list -------------------------------------------------------------------

function jobRow(job) {
  const short = job.id.slice(0, 8);
  return h("tr", { dataset: { job: job.id, snapshot: JSON.stringify(job) } },
    h("td", {}, h("a", { href: `#/jobs/${job.id}`, "aria-label": `job ${short}` }, h("code", {}, short))),
    h("td", {}, job.vehicle_id ? h("a", { href: `#/vehicles/${encodeURIComponent(job.vehicle_id)}` }, job.vehicle_id) : h("span", { class: "muted" }, "–")),
    h("td", { class: "hide-narrow" }, job.method),
    h("td", { class: "c-status" }, badge(job.status)),
    h("td", { class: "c-progress" }, progressCell(job)),
    h("td", { class: "hide-narrow" }, when(job.created_at)),
    h("td", { class: "num" }, duration(job)),
    h("td", { class: "num" }, fmt(job.residual_rms_px, 3)),
    h("td", {}, acceptanceMark(job)));
}

function parseHashQuery(q) {
  const p = new URLSearchParams(q || "");
  return {
    status: p.get("status") || "", vehicle: p.get("vehicle") || "", method: p.get("method") || "",
    from: p.get("from") || "", to: p.get("to") || "", page: Math.max(0, parseInt(p.get("page") || "0", 10) || 0),
  };
}

function hashFor(f) {
  const p = new URLSearchParams();
  for (const k of ["status", "vehicle", "method", "from", "to"]) if (f[k]) p.set(k, f[k]);
  if (f.page) p.set("page", f.page);
  const s = p.toString();
  return `#/jobs${s ? "?" + s : ""}`;
}

function select(id, label, value, options) {
  return h("div", {}, h("label", { for: id }, label),
    h("select", { id, name: id }, options.map(([v, t]) => h("option", { value: v, selected: v === value }, t))));
}

function renderJobs(query) {
  const f = parseHashQuery(query);
  const view = Object.assign({ name: "jobs" }, f);
  state.view = view;
  const form = h("form", {
    class: "filters", role: "search", "aria-label": "Filter jobs", onsubmit: (e) => {
      e.preventDefault();
      const d = new FormData(e.target);
      location.hash = hashFor({
        status: d.get("status"), vehicle: String(d.get("vehicle") || "").trim(), method: d.get("method"),
        from: d.get("from"), to: d.get("to"), page: 0,
      });
    }
  },
  select("status", "Status", f.status, [["", "any"], ["queued", "queued"], ["running", "running"], ["succeeded", "succeeded"], ["degraded", "degraded"], ["failed", "failed"], ["cancelled", "cancelled"]]),
  h("div", {}, h("label", { for: "vehicle" }, "Vehicle"), h("input", { id: "vehicle", name: "vehicle", value: f.vehicle, size: 14 })),
  select("method", "Method", f.method, [["", "any"], ["motion", "motion"], ["vanishing", "vanishing"]]),
  h("div", {}, h("label", { for: "from" }, "Created from"), h("input", { id: "from", name: "from", type: "date", value: f.from })),
  h("div", {}, h("label", { for: "to" }, "Created up to"), h("input", { id: "to", name: "to", type: "date", value: f.to })),
  h("button", { type: "submit" }, "Apply"),
  h("a", { class: "button secondary", href: "#/jobs" }, "Clear"));
  const body = h("tbody", { id: "jobs-body", "aria-busy": "true" });
  const table = h("div", { class: "table-wrap" }, h("table", { "aria-describedby": "jobs-summary" },
    h("caption", { class: "visually-hidden" }, "Calibration jobs, newest first"),
    h("thead", {}, h("tr", {},
      h("th", { scope: "col" }, "Job"), h("th", { scope: "col" }, "Vehicle"), h("th", { scope: "col", class: "hide-narrow" }, "Method"),
      h("th", { scope: "col" }, "Status"), h("th", { scope: "col" }, "Progress"), h("th", { scope: "col", class: "hide-narrow" }, "Created"),
      h("th", { scope: "col", class: "num" }, "Duration"), h("th", { scope: "col", class: "num" }, "RMS (px)"), h("th", { scope: "col" }, "Acceptance"))),
    body));
  const pager = h("nav", { class: "pager", "aria-label": "Pages" }, h("span", { id: "jobs-summary", role: "status" }, "Loading…"));
  const t = state.tenant && state.tenant.acceptance_thresholds;
  show("Jobs", h("h1", {}, "Jobs"), form, table, pager,
    t ? h("p", { class: "muted" }, `Acceptance: residual RMS ≤ ${t.max_rms_px} px, translation 1-σ ≤ ${t.max_sigma_translation_m * 1000} mm, rotation 1-σ ≤ ${t.max_sigma_rotation_deg}°.`) : null);
  loadJobs(view, true);
}

async function loadJobs(view, first) {
  const t0 = performance.now();
  const p = new URLSearchParams({ limit: PAGE_SIZE, offset: view.page * PAGE_SIZE });
  if (view.status) p.set("status", view.status);
  if (view.vehicle) p.set("vehicle_id", view.vehicle);
  if (view.method) p.set("method", view.method);
  if (view.from) p.set("created_after", new Date(view.from + "T00:00:00").toISOString());
  if (view.to) p.set("created_before", new Date(new Date(view.to + "T00:00:00").getTime() + 86400000).toISOString());
  const summary = document.getElementById("jobs-summary");
  try {
    const data = await api(`/v1/jobs?${p}`);
    if (state.view !== view) return;
    const body = document.getElementById("jobs-body");
    body.replaceChildren(...data.jobs.map(jobRow));
    // Which query these rows answer: the filters re-render through a hash change, which
    // lands a task after the form is submitted, so "rows are present" alone does not say
    // they are the filtered ones (the browser test waits on this).
    body.dataset.query = p.toString();
    body.setAttribute("aria-busy", "false");
    if (!data.jobs.length) body.append(h("tr", {}, h("td", { colspan: 9, class: "muted" }, "No jobs match.")));
    const a = data.total ? data.offset + 1 : 0;
    const b = data.offset + data.jobs.length;
    const pages = Math.max(1, Math.ceil(data.total / PAGE_SIZE));
    summary.textContent = `Jobs ${a}–${b} of ${data.total} · page ${view.page + 1} of ${pages}`;
    const pager = summary.parentElement;
    pager.querySelectorAll("a").forEach((x) => x.remove());
    if (view.page > 0) pager.prepend(h("a", { class: "button secondary", href: hashFor(Object.assign({}, view, { page: view.page - 1 })), rel: "prev" }, "← Newer"));
    if (b < data.total) pager.append(h("a", { class: "button secondary", href: hashFor(Object.assign({}, view, { page: view.page + 1 })), rel: "next" }, "Older →"));
    const ms = performance.now() - t0;
    document.body.dataset.jobsRenderMs = ms.toFixed(1);
    if (first) announce(summary.textContent);
  } catch (e) {
    if (summary) summary.replaceChildren(problemBox(e));
  }
}

// ---- One job -----------------------------------------------------------------------

const MOTION_WORDS = {
  general: "General 3D motion: the rig turned about more than one axis, which determines every degree of freedom of every camera.",
  planar: "Planar motion: the rig only moved on a plane and turned about its normal. Motion alone cannot tell the cameras' offsets along that normal.",
  single_axis: "Rotation about a single axis: offsets along the axis are not determined by motion.",
  pure_translation: "Pure translation: the rig never turned, so the translations between cameras are not determined.",
  none: "Too little motion to calibrate from.",
};

function sigmaText(v, scale, digits) {
  return v === null || v === undefined ? null : `± ${fmt(v * scale, digits)}`;
}

function extrinsicsTable(doc) {
  const rows = doc.extrinsics.map((e) => {
    const t = e.translation, r = e.rpy_deg;
    const cell = (field, value, sigma, unitScale, d, sd) => {
      const s = sigmaText(sigma, unitScale, sd);
      return h("td", { class: "num", dataset: { camera: e.camera, field, value: String(value * unitScale) } },
        fmt(value * unitScale, d), " ",
        s === null ? h("span", { class: "unobservable", title: "not observable from this motion" }, "± unobservable") : h("span", { class: "muted" }, s));
    };
    return h("tr", { dataset: { camera: e.camera } },
      h("th", { scope: "row" }, e.camera, e.camera === doc.reference_camera ? h("span", { class: "muted" }, " (reference)") : null),
      cell("x_mm", t[0], e.sigma_translation_m[0], 1000, 1, 2),
      cell("y_mm", t[1], e.sigma_translation_m[1], 1000, 1, 2),
      cell("z_mm", t[2], e.sigma_translation_m[2], 1000, 1, 2),
      cell("roll_deg", r[0], e.sigma_rotation_deg[0], 1, 3, 3),
      cell("pitch_deg", r[1], e.sigma_rotation_deg[1], 1, 3, 3),
      cell("yaw_deg", r[2], e.sigma_rotation_deg[2], 1, 3, 3),
      h("td", { class: "num" }, `${e.observable_dof.translation}+${e.observable_dof.rotation}`));
  });
  return h("div", { class: "table-wrap" }, h("table", { id: "extrinsics" },
    h("caption", { class: "visually-hidden" }, "Extrinsics of every camera relative to the reference camera, with 1-sigma uncertainty"),
    h("thead", {}, h("tr", {}, h("th", { scope: "col" }, "Camera"),
      ...["x (mm)", "y (mm)", "z (mm)", "roll (°)", "pitch (°)", "yaw (°)"].map((c) => h("th", { scope: "col", class: "num" }, c)),
      h("th", { scope: "col", class: "num", title: "observable translation + rotation degrees of freedom" }, "DOF t+r"))),
    h("tbody", {}, rows)));
}

function singularityBox(doc) {
  const s = doc.singularity;
  if (!s) return null;
  const unobs = s.unobservable_directions || [];
  const box = h("section", { class: `box ${unobs.length ? "warn" : "ok"}`, id: "singularity", "aria-labelledby": "sing-h" },
    h("h2", { id: "sing-h" }, unobs.length ? "⚠ Singularity report: some directions were not observable" : "Singularity report: everything observable"),
    h("p", {}, h("strong", {}, `Motion class: ${s.motion_class}. `), MOTION_WORDS[s.motion_class] || ""),
    h("p", { class: "muted" }, `${s.motions} motions, ${s.informative_motions} informative; largest rotation ${fmt(s.max_rotation_deg, 1)}°, largest tilt off the main axis ${fmt(s.max_out_of_axis_deg, 2)}°${s.scene_permutation ? "; scene permutation (U-turn) used" : ""}.`));
  if (unobs.length) {
    box.append(h("h3", {}, "Not observable"), h("ul", { id: "unobservable" }, unobs.map((u) => h("li", {}, u.description,
      u.components && u.components.length ? h("span", { class: "muted" }, ` (cameras: ${u.components.map((c) => c.camera).join(", ")})`) : null))));
  }
  if (s.resolved_by && s.resolved_by.length) box.append(h("h3", {}, "How it was resolved"), h("ul", {}, s.resolved_by.map((r) => h("li", {}, r))));
  if (s.recommendations && s.recommendations.length) box.append(h("h3", {}, "Recommendations"), h("ul", { id: "recommendations" }, s.recommendations.map((r) => h("li", {}, r))));
  return box;
}

function vanishingBox(doc) {
  const v = doc.vanishing;
  if (!v) return null;
  return h("section", { class: `box ${v.ring_closed ? "ok" : "warn"}` },
    h("h2", {}, "Ring"),
    h("p", {}, v.ring_closed ? "The ring was closed" : "Open chain: the ring was not closed, so the global optimisation could not remove the drift.",
      v.closure_error ? ` Closure error before optimisation: ${fmt(v.closure_error.translation_m * 1000, 2)} mm, ${fmt(v.closure_error.rotation_deg, 3)}° (pair ${v.closure_error.pair.join("–")}).` : ""),
    h("div", { class: "table-wrap" }, h("table", {}, h("thead", {}, h("tr", {}, ["Camera", "Target", "Chain", "Transforms", "Residual RMS (px)"].map((c) => h("th", { scope: "col" }, c)))),
      h("tbody", {}, v.cameras.map((c) => h("tr", {}, h("td", {}, c.camera), h("td", {}, c.target), h("td", {}, c.chain.join(" → ")), h("td", { class: "num" }, c.chain_transforms), h("td", { class: "num" }, fmt(c.residuals.rms, 3))))))));
}

function timeline(stages) {
  if (!stages || !stages.length) return null;
  const total = stages.reduce((a, s) => a + s.seconds, 0) || 1;
  const bar = h("div", { class: "timeline", role: "img", "aria-label": stages.map((s) => `${s.name} ${fmt(s.seconds, 3)} s`).join(", ") });
  const legend = h("ul", { class: "timeline-legend" });
  stages.forEach((s, i) => {
    const seg = h("span", { title: `${s.name}: ${fmt(s.seconds, 3)} s` });
    seg.style.width = `${(100 * s.seconds) / total}%`;
    seg.style.background = STAGE_COLOURS[i % STAGE_COLOURS.length];
    bar.append(seg);
    const sw = h("span", { class: "swatch" });
    sw.style.background = STAGE_COLOURS[i % STAGE_COLOURS.length];
    legend.append(h("li", {}, sw, `${s.name} ${fmt(s.seconds, 3)} s`));
  });
  return h("section", { "aria-labelledby": "tl-h" }, h("h2", { id: "tl-h" }, `Stages (${fmt(total, 2)} s)`), bar, legend);
}

function figure(jobId, name, label, wide) {
  const box = h("figure", { class: `figure${wide ? " wide" : ""}`, dataset: { figure: name } }, h("p", { class: "muted" }, `Loading ${label}…`));
  api(`/v1/jobs/${encodeURIComponent(jobId)}/figures/${name}`).then((svg) => {
    const doc = new DOMParser().parseFromString(svg, "image/svg+xml");
    const el = doc.documentElement;
    if (el.nodeName !== "svg") throw new Error("not an SVG figure");
    box.replaceChildren(h("figcaption", {}, label), document.importNode(el, true));
  }).catch((e) => box.replaceChildren(h("p", { class: "muted" }, `${label}: ${e.message}`)));
  return box;
}

async function download(jobId, format, button, camera) {
  button.disabled = true;
  try {
    const cam = camera ? `&camera=${encodeURIComponent(camera)}` : "";
    // The frame chosen on the job page (vehicle-model jobs only); JSON is always the result itself.
    const picked = document.getElementById("export-frame");
    const frame = picked && picked.value === "vehicle" && format !== "json" ? "&frame=vehicle" : "";
    const resp = await api(`/v1/jobs/${encodeURIComponent(jobId)}/result?format=${format}${cam}${frame}`, { raw: true });
    const blob = await resp.blob();
    const cd = resp.headers.get("content-disposition") || "";
    const m = cd.match(/filename="([^"]+)"/);
    const name = m ? m[1] : `rigcal-${jobId}.${format === "json" ? "json" : format === "urdf" ? "urdf" : "yaml"}`;
    const a = h("a", { href: URL.createObjectURL(blob), download: name, hidden: true }, name);
    document.body.append(a);
    a.click();
    setTimeout(() => { URL.revokeObjectURL(a.href); a.remove(); }, 1000);
    announce(`Downloaded ${name}`);
  } catch (e) {
    button.after(problemBox(e));
  } finally {
    button.disabled = false;
  }
}

function failureBox(job, doc) {
  const items = [];
  if (job.error) {
    items.push(h("p", {}, h("strong", {}, job.error.code || "error"), ": ", job.error.detail || ""),
      job.error.field ? h("p", {}, "At fault: ", h("code", { id: "fault-field" }, job.error.field)) : null);
  }
  if (doc && doc.reasons && doc.reasons.length) {
    items.push(h("ul", { id: "reasons" }, doc.reasons.map((r) => h("li", {}, h("code", {}, r.code), r.camera ? ` (camera ${r.camera})` : "", ": ", r.message))));
  }
  const det = doc && doc.detection;
  const skipped = det ? det.images.filter((i) => i.error) : [];
  if (skipped.length) {
    items.push(h("h3", {}, `${skipped.length} image(s) skipped`),
      h("ul", { id: "skipped-images" }, skipped.map((i) => h("li", {}, h("code", {}, i.field), ` ${i.path}: ${i.error}`))));
  }
  if (!items.length) return null;
  const bad = job.status === "failed";
  return h("section", { class: `box ${bad ? "bad" : "warn"}`, role: bad ? "alert" : null, id: "failure" },
    h("h2", {}, bad ? "Why the job failed" : "Findings"), ...items);
}

async function renderJob(id, first = true) {
  const view = { name: "job", id };
  state.view = view;
  let job;
  try {
    job = await api(`/v1/jobs/${encodeURIComponent(id)}`);
  } catch (e) {
    show("Job", h("h1", {}, "Job"), problemBox(e));
    return;
  }
  if (state.view !== view && state.view.id !== id) return;
  state.view = view;
  let doc = null;
  if (TERMINAL.includes(job.status)) {
    try { doc = await api(`/v1/jobs/${encodeURIComponent(id)}/result`); } catch (_) { doc = null; }
  }
  const head = h("section", {},
    h("h1", {}, "Job ", h("code", {}, job.id)),
    h("dl", { class: "meta" },
      h("dt", {}, "Status"), h("dd", { id: "job-progress" }, badge(job.status), " ", progressCell(job)),
      h("dt", {}, "Acceptance"), h("dd", {}, acceptanceMark(job), job.acceptance && job.acceptance.reasons.length ? h("span", { class: "muted" }, " " + job.acceptance.reasons.join("; ")) : null),
      h("dt", {}, "Vehicle"), h("dd", {}, job.vehicle_id ? h("a", { href: `#/vehicles/${encodeURIComponent(job.vehicle_id)}` }, job.vehicle_id) : "–"),
      h("dt", {}, "Vehicle model"), h("dd", {}, job.vehicle_model ? h("a", { href: `#/fleet/${encodeURIComponent(job.vehicle_model)}` }, job.vehicle_model) : "–"),
      h("dt", {}, "Method"), h("dd", {}, job.method),
      h("dt", {}, "Created"), h("dd", {}, when(job.created_at)),
      h("dt", {}, "Duration"), h("dd", {}, duration(job)),
      h("dt", {}, "Residual RMS"), h("dd", { id: "rms" }, job.residual_rms_px === null ? "–" : `${fmt(job.residual_rms_px, 3)} px`),
      h("dt", {}, "Attempts"), h("dd", {}, `${job.attempts} of ${job.max_attempts}`)));
  const parts = [head, failureBox(job, doc), nominalBox(job)];
  if (doc && doc.extrinsics.length) {
    const labels = { json: "JSON", kalibr: "Kalibr", opencv: "OpenCV", urdf: "URDF", colmap: "COLMAP rig", ros2: "ROS 2 tf" };
    const button = (f, label, camera) => {
      const b = h("button", { type: "button", class: "secondary", dataset: camera ? { format: f, camera } : { format: f } }, `Download ${label}`);
      b.addEventListener("click", () => download(id, f, b, camera));
      return b;
    };
    // A failed calibration is downloadable as its JSON result only (the API refuses the rest).
    const failed = doc.status === "failed";
    const dl = h("div", { class: "downloads" },
      ...Object.entries(labels).filter(([f]) => !failed || f === "json").map(([f, label]) => button(f, label)),
      ...(failed ? [] : doc.extrinsics.map((e) => button("camera_info", `camera_info ${e.camera}`, e.camera))));
    // A vehicle model places the rig in the vehicle frame: the exports can be in it.
    const frame = job.vehicle_model && !failed
      ? h("p", {}, h("label", { for: "export-frame" }, "Export frame "),
        h("select", { id: "export-frame" },
          h("option", { value: "reference" }, `reference camera (${doc.reference_camera})`),
          h("option", { value: "vehicle" }, `vehicle frame of ${job.vehicle_model} (not COLMAP)`)))
      : null;
    parts.push(h("h2", {}, `Extrinsics relative to ${doc.reference_camera}`), extrinsicsTable(doc), frame, dl);
  }
  if (doc) {
    parts.push(singularityBox(doc), vanishingBox(doc));
    if (doc.extrinsics.length || doc.residuals) {
      parts.push(h("h2", {}, "Figures"), h("div", { class: "figures" },
        doc.extrinsics.length ? figure(id, "rig.svg", "Rig and drive, top view", true) : null,
        doc.residuals ? figure(id, "residual-histogram.svg", "Residual histogram") : null,
        doc.residuals ? figure(id, "residuals-per-camera.svg", "Residuals per camera") : null,
        doc.residuals ? figure(id, "residuals-per-frame.svg", "Residuals per frame", true) : null));
    }
    parts.push(timeline(doc.stages));
  }
  const title = `Job ${job.id.slice(0, 8)}`;
  if (first) show(title, ...parts.filter(Boolean));
  else { main().replaceChildren(...parts.filter(Boolean)); announce(`Job ${job.status}`); }
}

// Every camera against the vehicle model's nominal rig (when the session names one).
function nominalBox(job) {
  const n = job.acceptance && job.acceptance.nominal;
  if (!n || !n.cameras.length) return null;
  const bound = (b, unit) => Array.isArray(b) ? `per axis ${b.map((x) => fmt(x, 3)).join(" / ")} ${unit}` : `${fmt(b, 3)} ${unit} (norm)`;
  const rows = n.cameras.map((d) => h("tr", { dataset: { camera: d.camera, within: String(d.within_tolerance) } },
    h("th", { scope: "row" }, d.camera),
    h("td", { class: "num" }, d.translation_mm ? d.translation_mm.map((x) => fmt(x, 2)).join(", ") : "–"),
    h("td", { class: "num" }, d.rotation_deg ? d.rotation_deg.map((x) => fmt(x, 3)).join(", ") : "–"),
    h("td", {}, `${bound(d.tolerance.translation_mm, "mm")}; ${bound(d.tolerance.rotation_deg, "°")}`),
    h("td", {}, d.within_tolerance ? h("span", { class: "badge pass" }, "✓ within") : h("span", { class: "badge fail", title: d.exceeded.join("; ") }, "✗ " + d.exceeded.join("; ")))));
  return h("section", { class: "nominal" },
    h("h2", {}, `Against the nominal rig of ${n.vehicle_model}`),
    h("div", { class: "table-wrap" }, h("table", {},
      h("thead", {}, h("tr", {}, ["Camera", "Δt (mm, x y z)", "Δrotation (°, x y z)", "Tolerance", "Verdict"].map((c) => h("th", { scope: "col" }, c)))),
      h("tbody", {}, rows))));
}

// ---- Fleet -------------------------------------------------------------------------

async function renderFleetList() {
  state.view = { name: "fleet" };
  let data;
  try { data = await api("/v1/vehicle-models"); } catch (e) { show("Fleet", h("h1", {}, "Fleet"), problemBox(e)); return; }
  const models = data.vehicle_models;
  show("Fleet", h("h1", {}, "Vehicle models"),
    models.length
      ? h("ul", { class: "models" }, ...models.map((m) => h("li", {}, h("a", { href: `#/fleet/${encodeURIComponent(m.model)}` }, m.model), ` — reference ${m.reference_camera}, ${m.cameras.length} cameras`)))
      : h("p", { class: "muted" }, "No vehicle model yet: PUT /v1/vehicle-models/{model} with the nominal rig (see /docs)."));
}

async function renderFleet(model) {
  const view = { name: "fleet", id: model };
  state.view = view;
  let f;
  try { f = await api(`/v1/vehicle-models/${encodeURIComponent(model)}/fleet`); } catch (e) { show(`Fleet ${model}`, h("h1", {}, `Fleet ${model}`), problemBox(e)); return; }
  const outliers = f.outliers.map((o) => h("tr", { dataset: { vehicle: o.vehicle_id } },
    h("td", {}, h("a", { href: `#/vehicles/${encodeURIComponent(o.vehicle_id)}` }, o.vehicle_id)),
    h("td", {}, h("a", { href: `#/jobs/${o.job_id}` }, h("code", {}, o.job_id.slice(0, 8)))),
    h("td", {}, when(o.finished_at)),
    h("td", { class: "num" }, fmt(o.max_abs_z, 1)),
    h("td", {}, o.axes.map((a) => `${a.camera} ${a.axis} ${fmt(a.value, 3)} ${a.unit} (z ${fmt(a.z, 1)})`).join("; "))));
  const cameras = f.cameras.map((c) => {
    const chart = h("figure", { class: "figure wide", dataset: { camera: c.camera } }, h("p", { class: "muted" }, "Loading fleet chart…"));
    api(`/v1/vehicle-models/${encodeURIComponent(model)}/fleet.svg?camera=${encodeURIComponent(c.camera)}`).then((svg) => {
      const el = new DOMParser().parseFromString(svg, "image/svg+xml").documentElement;
      chart.replaceChildren(document.importNode(el, true));
    }).catch((e) => chart.replaceChildren(problemBox(e)));
    return h("section", {}, h("h2", {}, `Camera ${c.camera}`),
      h("div", { class: "table-wrap" }, h("table", { class: "fleet-axes" },
        h("thead", {}, h("tr", {}, ["Axis", "Median", "Robust spread", "Vehicles"].map((x) => h("th", { scope: "col" }, x)))),
        h("tbody", {}, c.axes.map((a) => h("tr", {}, h("th", { scope: "row" }, `${a.axis} (${a.unit})`), h("td", { class: "num" }, fmt(a.median, 4)), h("td", { class: "num" }, fmt(a.spread, 4)), h("td", { class: "num" }, String(a.count))))))),
      chart);
  });
  show(`Fleet ${model}`, h("h1", {}, `Fleet of ${model}`),
    h("p", {}, `${f.vehicles} vehicle(s), ${f.calibrations} accepted calibration(s). Every number is a camera's deviation from the nominal rig; a vehicle is an outlier when its latest calibration is more than ${f.outlier_z} robust spreads from the fleet median on some axis.`),
    h("h2", {}, `Outliers (${f.outliers.length})`),
    f.outliers.length
      ? h("div", { class: "table-wrap" }, h("table", { id: "outliers" }, h("thead", {}, h("tr", {}, ["Vehicle", "Job", "Finished", "max |z|", "Axes beyond the threshold"].map((x) => h("th", { scope: "col" }, x)))), h("tbody", {}, outliers)))
      : h("p", { class: "muted" }, "No outlier."),
    ...cameras);
}

// ---- A vehicle ---------------------------------------------------------------------

async function renderVehicle(vehicle) {
  state.view = { name: "vehicle", id: vehicle };
  let data;
  try {
    data = await api(`/v1/vehicles/${encodeURIComponent(vehicle)}/calibrations`);
  } catch (e) {
    show(`Vehicle ${vehicle}`, h("h1", {}, `Vehicle ${vehicle}`), problemBox(e));
    return;
  }
  const cals = data.calibrations;
  const rows = cals.slice().reverse().map((c) => h("tr", {},
    h("td", {}, h("a", { href: `#/jobs/${c.job_id}` }, h("code", {}, c.job_id.slice(0, 8)))),
    h("td", {}, when(c.finished_at)), h("td", {}, badge(c.status)),
    h("td", {}, c.accepted ? "yes" : "no"),
    h("td", { class: "num" }, fmt(c.residual_rms_px, 3)),
    h("td", {}, c.change_from_previous_accepted ? c.change_from_previous_accepted.map((x) => `${x.camera}: ${fmt(x.translation_mm, 2)} mm / ${fmt(x.rotation_deg, 3)}°`).join("; ") : h("span", { class: "muted" }, c.accepted ? "first accepted" : "no earlier accepted calibration"))));
  const chart = h("figure", { class: "figure wide" }, h("p", { class: "muted" }, "Loading drift chart…"));
  api(`/v1/vehicles/${encodeURIComponent(vehicle)}/drift.svg`).then((svg) => {
    const el = new DOMParser().parseFromString(svg, "image/svg+xml").documentElement;
    chart.replaceChildren(document.importNode(el, true));
  }).catch((e) => chart.replaceChildren(problemBox(e)));
  show(`Vehicle ${vehicle}`, h("h1", {}, `Vehicle ${vehicle}`),
    h("p", {}, `${cals.length} calibration(s); drift is measured from the previous accepted (succeeded) calibration.`),
    chart,
    h("h2", {}, "History (newest first)"),
    h("div", { class: "table-wrap" }, h("table", {}, h("thead", {}, h("tr", {}, ["Job", "Finished", "Status", "Accepted", "RMS (px)", "Change from previous accepted"].map((c) => h("th", { scope: "col" }, c)))), h("tbody", {}, rows))));
}

// ---- Upload -----------------------------------------------------------------------

// The capture check of a session as it is known now: verdict, reasons, recommendations,
// and how many of its images are detected (the check is partial until all are).
function checkBox(box, view) {
  const check = view.check;
  const complete = view.complete;
  box.dataset.complete = String(complete);
  const verdict = check ? check.verdict : null;
  box.className = `box ${verdict === "ok" ? "ok" : verdict === "insufficient" ? "bad" : verdict ? "warn" : ""}`;
  const progress = h("p", { id: "check-progress" }, view.expected > 0
    ? `${view.detected} of ${view.expected} images detected${complete ? "" : " so far"}.`
    : "The session carries its detections: nothing to detect.");
  const reasons = check && check.reasons.length
    ? h("ul", { id: "check-reasons" }, check.reasons.map((r) => h("li", { dataset: { code: r.code } }, h("code", {}, r.code), " ", r.message)))
    : null;
  const recs = check && check.recommendations.length
    ? [h("h3", {}, "Recommendations"), h("ul", {}, check.recommendations.map((t) => h("li", {}, t)))]
    : null;
  const parts = [
    h("h2", {}, complete ? "Capture check" : "Capture check (partial)"),
    progress,
    verdict ? h("p", {}, "Verdict: ", h("span", { class: `badge ${verdict === "ok" ? "succeeded" : verdict === "insufficient" ? "failed" : "degraded"}`, id: "check-verdict", dataset: { verdict } }, verdict),
      complete ? "" : " (over the images detected so far)") : h("p", { class: "muted" }, "Waiting for the first images to be detected…"),
    reasons, ...(recs || [])];
  box.replaceChildren(...parts.filter((x) => x));
  if (complete) announce(`Capture check complete: ${verdict}`);
}

// Follow a session's capture check until it is complete (or the page changes).
async function followCheck(session, box) {
  const view = {
    check: session.capture_check,
    complete: session.capture_check_complete,
    detected: session.images_detected,
    expected: session.images_to_detect,
  };
  checkBox(box, view);
  if (view.complete) return;
  const ctrl = new AbortController();
  const token = state.view;
  token.abort = ctrl;
  let images = 0;
  try {
    const resp = await fetch(`/v1/sessions/${encodeURIComponent(session.id)}/events`, { headers: authHeaders({ Accept: "text/event-stream" }), signal: ctrl.signal });
    if (!resp.ok) throw new ApiError(resp.status, {});
    await readEvents(resp, (ev) => {
      const e = JSON.parse(ev.data);
      // The stream replays every event from the first: its image events count them all.
      if (ev.event === "image") { images += 1; view.detected = Math.max(view.detected, images); }
      if (ev.event === "check") {
        view.check = e.data.check;
        view.complete = e.data.complete;
        view.detected = e.data.images_detected;
        view.expected = e.data.images_expected;
      }
      if (state.view === token) checkBox(box, view);
    });
  } catch (err) {
    if (!ctrl.signal.aborted && state.view === token) box.append(problemBox(err));
  }
}

function renderUpload() {
  state.view = { name: "upload" };
  const file = h("input", { id: "archive", name: "archive", type: "file", accept: ".tar,.zip,application/x-tar,application/zip", required: true, "aria-describedby": "archive-help" });
  const bar = h("progress", { class: "upload-progress", max: 100, value: 0, hidden: true, "aria-label": "upload progress" });
  const status = h("p", { role: "status", id: "upload-status" });
  const submit = h("button", { type: "submit" }, "Upload");
  const checkPanel = h("section", { id: "capture-check", "aria-live": "polite", hidden: true });
  const start = h("button", { type: "button", id: "start-job", hidden: true }, "Start calibration job");
  let sessionId = null;
  start.addEventListener("click", async () => {
    start.disabled = true;
    try {
      const job = await api("/v1/jobs", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ session_id: sessionId }) });
      location.hash = `#/jobs/${job.id}`;
    } catch (err) {
      status.replaceChildren(problemBox(err));
      start.disabled = false;
    }
  });
  const form = h("form", {
    class: "box", onsubmit: (e) => {
      e.preventDefault();
      const f = file.files[0];
      if (!f) { status.textContent = "Choose a .tar or .zip archive first."; return; }
      const kind = /\.zip$/i.test(f.name) ? "application/zip" : /\.tar$/i.test(f.name) ? "application/x-tar" : null;
      if (!kind) { status.textContent = `${f.name}: expected a .tar or .zip session archive.`; return; }
      submit.disabled = true;
      bar.hidden = false;
      const xhr = new XMLHttpRequest();
      xhr.open("POST", "/v1/sessions");
      if (state.key) xhr.setRequestHeader("Authorization", `Bearer ${state.key}`);
      xhr.setRequestHeader("Content-Type", kind);
      xhr.upload.onprogress = (ev) => {
        if (ev.lengthComputable) {
          const pct = Math.round((100 * ev.loaded) / ev.total);
          bar.value = pct;
          status.textContent = `Uploading ${f.name}: ${pct}%`;
        }
      };
      xhr.onerror = () => { status.replaceChildren(problemBox(new ApiError(0, { detail: "the upload failed (network)" }))); submit.disabled = false; };
      xhr.onload = () => {
        let body = {};
        try { body = JSON.parse(xhr.responseText); } catch (_) { /* not JSON */ }
        if (xhr.status !== 201 && xhr.status !== 200) {
          status.replaceChildren(problemBox(new ApiError(xhr.status, body)));
          submit.disabled = false;
          return;
        }
        bar.value = 100;
        sessionId = body.id;
        status.textContent = `Session ${body.id} stored (${body.images_received} image(s)). Its capture check is below; start the job when you are satisfied, or capture again.`;
        checkPanel.hidden = false;
        start.hidden = false;
        followCheck(body, checkPanel);
      };
      xhr.send(f);
    }
  },
  h("label", { for: "archive" }, "Session archive"),
  h("p", { class: "muted", id: "archive-help" }, "A .tar or .zip with session.json at its root and the images it names (see docs/formats.md). Its images are detected as soon as they are stored, and the capture check tells whether the capture can calibrate before any job runs."),
  file, " ", submit, h("div", {}, bar), status);
  show("Upload", h("h1", {}, "Upload a capture session"), form, checkPanel, start);
}

// ---- Router ------------------------------------------------------------------------

function route() {
  // A page's own stream (the upload page's capture check) ends with the page.
  if (state.view && state.view.abort) state.view.abort.abort();
  if (!state.key && !state.noAuth) { renderKeyForm(); return; }
  const hash = location.hash.replace(/^#/, "") || "/jobs";
  const [path, query] = hash.split("?");
  const parts = path.split("/").filter(Boolean);
  document.querySelectorAll("[data-nav]").forEach((a) => {
    if (a.dataset.nav === parts[0]) a.setAttribute("aria-current", "page"); else a.removeAttribute("aria-current");
  });
  if (!state.stream) startStream();
  if (parts[0] === "jobs" && parts[1]) renderJob(decodeURIComponent(parts[1]));
  else if (parts[0] === "vehicles" && parts[1]) renderVehicle(decodeURIComponent(parts[1]));
  else if (parts[0] === "fleet" && parts[1]) renderFleet(decodeURIComponent(parts[1]));
  else if (parts[0] === "fleet") renderFleetList();
  else if (parts[0] === "upload") renderUpload();
  else renderJobs(query);
}

async function boot() {
  document.getElementById("forget").addEventListener("click", () => forgetKey("API key forgotten."));
  // A server run with --insecure-no-auth answers without a key: no key is asked then.
  try {
    const tenant = await fetchTenant(state.key);
    state.noAuth = !state.key;
    signedIn(tenant);
  } catch (e) {
    if (state.key) { forgetKey(`The stored API key was refused: ${e.message}`); }
    else { renderKeyForm(); }
    window.addEventListener("hashchange", route);
    return;
  }
  window.addEventListener("hashchange", route);
  route();
}

boot();
