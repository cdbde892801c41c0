// mifacerf studio: the single-page app (plain JavaScript, no build step, no network beyond this server).
// Coordinates: image pixels in OpenCV convention (integer = pixel centre); a view draws pixel (u, v) at
// screen ((u + 0.5) * s + ox, (v + 0.5) * s + oy) with s = canvas width / image width * zoom, shared by
// every view so zoom and pan stay in sync.
"use strict";

const STATUS_COLOURS = {
  snapped: "#3ddc4a", consensus: "#2fb7ff", single_view: "#ffd23f", failed: "#ff4040",
  flagged: "#ff40ff", hand_fixed: "#ffffff", placed: "#7fae7f", predicted: "#a05050",
};
const CURVE_COLOURS = {
  lip_upper: "#ff6f91", lip_lower: "#ff9671", lid_upper_L: "#00c9a7", lid_lower_L: "#4ffbdf",
  lid_upper_R: "#c493ff", lid_lower_R: "#e0c3fc", iris_L: "#ffc75f", iris_R: "#f9f871",
};
const PROPOSAL_COLOUR = "#ff00ff";
const HIT_PX = 7;

const S = {
  token: null, info: null, expr: null, data: null, state: null, version: null,
  view: { zoom: 1, ox: 0, oy: 0 }, images: {}, kind: "diffuse", light: 0, exposure: 0, gamma: 2.2,
  tool: "navigate", undo: [], redo: [], saving: false, dirty: false, saveTimer: null,
  tri: {}, fixTri: {}, proposal: null, templateProposal: null, job: null, drag: null, conflict: null,
  saves: 0,
};
window.studio = S;   // for the browser tests and the curious

// ------------------------------------------------------------------------------------------ server
function api(path, opts = {}) {
  const headers = Object.assign({ "X-Studio-Token": S.token }, opts.headers || {});
  if (opts.body !== undefined) headers["Content-Type"] = "application/json";
  return fetch(path, {
    method: opts.method || "GET", headers, cache: "no-store",
    body: opts.body === undefined ? undefined : JSON.stringify(opts.body),
  }).then(async (r) => {
    let d = null;
    try { d = await r.json(); } catch (e) { d = { error: r.statusText }; }
    if (!r.ok) { const err = new Error(d.error || r.statusText); err.status = r.status; err.data = d; throw err; }
    return d;
  });
}
function imageUrl(cam) {
  const q = new URLSearchParams({ kind: S.kind, light: S.light, exposure: S.exposure, gamma: S.gamma, token: S.token });
  return `/api/image/${encodeURIComponent(S.expr)}/${encodeURIComponent(cam)}.png?${q}`;
}
function say(msg, cls) {
  const el = document.getElementById("save-status");
  el.textContent = msg;
  el.className = cls || "muted";
}
function banner(html, buttons) {
  const b = document.getElementById("banner");
  if (!html) { b.classList.add("hidden"); b.innerHTML = ""; return; }
  b.innerHTML = "";
  const span = document.createElement("span");
  span.textContent = html;
  b.appendChild(span);
  for (const [label, fn] of buttons || []) {
    const btn = document.createElement("button");
    btn.textContent = label;
    btn.onclick = fn;
    b.appendChild(btn);
  }
  b.classList.remove("hidden");
}

// ------------------------------------------------------------------------------------------ start
async function start() {
  const params = new URLSearchParams(location.search);
  S.token = params.get("token") || sessionStorage.getItem("studio-token");
  if (!S.token) { banner("No token: open the URL the server printed (it ends in ?token=...)."); return; }
  sessionStorage.setItem("studio-token", S.token);
  const keep = params.get("expression");
  history.replaceState(null, "", location.pathname + (keep ? `?expression=${encodeURIComponent(keep)}` : ""));
  try { S.info = await api("/api/session"); }
  catch (e) { banner(`Cannot open the session: ${e.message}`); return; }
  document.getElementById("capture-path").textContent = S.info.capture;
  buildControls();
  renderExpressions();
  const first = keep && S.info.expressions.some((e) => e.name === keep) ? keep : S.info.neutral;
  await selectExpression(first);
}

function buildControls() {
  const legend = document.getElementById("legend");
  legend.innerHTML = "";
  for (const [k, c] of Object.entries(STATUS_COLOURS).concat([["proposal", PROPOSAL_COLOUR]])) {
    const span = document.createElement("span");
    const dot = document.createElement("i");
    dot.style.background = c;      // CSSOM, allowed by the page's content security policy
    span.appendChild(dot);
    span.appendChild(document.createTextNode(k.replace("_", "-")));
    legend.appendChild(span);
  }
  const cs = document.getElementById("curve-select");
  cs.innerHTML = S.info.curve_names.map((n) => `<option value="${n}">${n}</option>`).join("");
  const ps = document.getElementById("point-select");
  ps.innerHTML = S.info.point_names.map((n) => `<option value="${n}">${n}</option>`).join("");
  fillCoarseSelect();
  document.getElementById("light").max = S.info.n_lights - 1;
  const views = document.getElementById("views");
  views.innerHTML = "";
  for (const cam of S.info.cameras) {
    const div = document.createElement("div");
    div.className = "view";
    div.dataset.camera = cam.name;
    const canvas = document.createElement("canvas");
    canvas.width = 512; canvas.height = Math.round(512 * cam.height / cam.width);
    canvas.id = `canvas-${cam.name}`;
    canvas.dataset.camera = cam.name;
    div.appendChild(canvas);
    const label = document.createElement("div");
    label.className = "label"; label.textContent = cam.name;
    div.appendChild(label);
    views.appendChild(div);
    attachView(canvas, cam);
  }
  const on = (id, ev, fn) => document.getElementById(id).addEventListener(ev, fn);
  on("kind", "change", (e) => { S.kind = e.target.value; document.getElementById("light-row").classList.toggle("hidden", S.kind !== "light"); loadImages(); });
  on("light", "change", (e) => { S.light = Math.max(0, Math.min(S.info.n_lights - 1, parseInt(e.target.value || "0", 10))); loadImages(); });
  on("exposure", "change", (e) => { S.exposure = parseFloat(e.target.value); document.getElementById("exposure-val").textContent = S.exposure; loadImages(); });
  on("gamma", "change", (e) => { S.gamma = parseFloat(e.target.value); document.getElementById("gamma-val").textContent = S.gamma; loadImages(); });
  on("reset-view", "click", () => { S.view = { zoom: 1, ox: 0, oy: 0 }; drawAll(); });
  for (const id of ["ov-fiducials", "ov-wireframe", "ov-coarse", "ov-curves", "ov-marks", "ov-proposals"]) on(id, "change", drawAll);
  for (const r of document.querySelectorAll("input[name=tool]")) r.addEventListener("change", (e) => { S.tool = e.target.value; toolChanged(); });
  buildTemplateControls();
  on("coarse-select", "change", drawAll);
  on("curve-select", "change", drawAll);
  on("point-select", "change", drawAll);
  on("clear-curve", "click", () => {
    const name = document.getElementById("curve-select").value;
    if (!S.state.rotoscope.curves[name]) return;
    edit(() => { delete S.state.rotoscope.curves[name]; });
  });
  on("undo", "click", () => (S.tool === "template" ? tplUndo() : undo()));
  on("redo", "click", () => (S.tool === "template" ? tplRedo() : redo()));
  on("propose", "click", propose);
  on("accept-proposal", "click", acceptProposal);
  on("discard-proposal", "click", () => { S.proposal = null; proposalButtons(); drawAll(); });
  on("propose-template", "click", () => proposeTemplate(false));
  on("accept-template", "click", () => proposeTemplate(true));
  on("register", "click", registerExpression);
  document.addEventListener("keydown", (e) => {
    if (e.target.tagName === "INPUT" && e.target.type !== "radio" && e.target.type !== "checkbox") return;
    const t = S.tool === "template";
    if ((e.ctrlKey || e.metaKey) && e.key.toLowerCase() === "z") { e.preventDefault(); e.shiftKey ? (t ? tplRedo() : redo()) : (t ? tplUndo() : undo()); }
    else if ((e.ctrlKey || e.metaKey) && e.key.toLowerCase() === "y") { e.preventDefault(); t ? tplRedo() : redo(); }
  });
}

async function toolChanged() {
  const t = S.tool === "template";
  document.getElementById("template-bar").classList.toggle("hidden", !t);
  if (t && !S.tpl) await loadTemplate();
  if (!t && S.tplDirty) await tplSaveNow();
  if (!t && S.tplEdited) { S.tplEdited = false; await refreshSession(); await loadExpression(); }
  drawAll();
}

function fillCoarseSelect() {
  const sel = document.getElementById("coarse-select");
  const t = S.info.template;
  if (!t) { sel.innerHTML = "<option value=''>no template</option>"; return; }
  sel.innerHTML = t.coarse.map((v) => `<option value="${v}">${v} ${t.names[v] || t.kinds[v]}</option>`).join("");
}

function renderExpressions() {
  const ul = document.getElementById("expressions");
  ul.innerHTML = "";
  for (const e of S.info.expressions) {
    const li = document.createElement("li");
    li.dataset.name = e.name;
    if (e.name === S.expr) li.classList.add("current");
    let badge, cls;
    if (e.missing_images) { badge = `${e.missing_images} images missing`; cls = "warn"; }
    else if (e.registered) { badge = `${(100 * e.registered_fraction).toFixed(1)}% (${e.dots_registered}/${e.n_dots})`; cls = e.registered_fraction >= 0.98 ? "ok" : "warn"; }
    else { badge = "not registered"; cls = ""; }
    li.innerHTML = `<span>${e.name}</span><span class="badge ${cls}" title="coarse points clicked in ≥2 views: ${e.coarse_points}; curves: ${e.curves}; marks: ${e.points}">${badge} · ${e.coarse_points}c ${e.curves}l</span>`;
    li.onclick = () => selectExpression(e.name);
    ul.appendChild(li);
  }
}

async function refreshSession() {
  S.info = await api("/api/session");
  fillCoarseSelect();
  renderExpressions();
}

async function selectExpression(name) {
  if (S.dirty) await saveNow();
  S.expr = name;
  S.proposal = null; S.templateProposal = null; S.undo = []; S.redo = []; S.tri = {}; S.fixTri = {};
  proposalButtons();
  renderExpressions();
  await loadExpression();
  loadImages();
  const neutralNoTemplate = name === S.info.neutral;
  document.getElementById("propose-template").classList.toggle("hidden", !neutralNoTemplate);
  document.getElementById("accept-template").classList.toggle("hidden", !neutralNoTemplate);
  document.getElementById("tool-template-label").classList.toggle("hidden", !neutralNoTemplate);
  if (!neutralNoTemplate && S.tool === "template") { document.querySelector("input[name=tool][value=navigate]").click(); }
}

async function loadExpression() {
  S.loading = true;
  const d = await api(`/api/expression/${encodeURIComponent(S.expr)}`);
  S.data = d; S.state = d.state; S.version = d.version; S.dirty = false;
  say(`${S.expr}: saved (version ${S.version})`);
  const rep = d.geometry && d.geometry.report;
  document.getElementById("report").textContent = rep ? `registration of ${S.expr} (${d.geometry.source}): ` + JSON.stringify(rep, null, 1).slice(0, 4000) : (d.geometry && d.geometry.source ? `overlays from: ${d.geometry.source}` : "no template yet");
  await retriangulateAll();
  drawAll();
  S.loading = false;
}

function loadImages() {
  for (const cam of S.info.cameras) {
    const img = new Image();
    const url = imageUrl(cam.name);
    // only the latest request counts: an earlier, slower answer (the slider moved on) is dropped
    const latest = () => imageUrl(cam.name) === url;
    img.onload = () => { if (latest()) { S.images[cam.name] = img; drawView(cam.name); } };
    img.onerror = () => { if (latest()) { S.images[cam.name] = null; drawView(cam.name); } };
    img.src = url;
  }
}

// ------------------------------------------------------------------------------------------ geometry
function camInfo(name) { return S.info.cameras.find((c) => c.name === name); }
function scaleOf(canvas, cam) { return canvas.width / cam.width * S.view.zoom; }
function toScreen(canvas, cam, u, v) {
  const s = scaleOf(canvas, cam);
  return [(u + 0.5) * s + S.view.ox, (v + 0.5) * s + S.view.oy];
}
function toImage(canvas, cam, x, y) {
  const s = scaleOf(canvas, cam);
  return [(x - S.view.ox) / s - 0.5, (y - S.view.oy) / s - 0.5];
}
function eventPos(canvas, ev) {
  const r = canvas.getBoundingClientRect();
  return [(ev.clientX - r.left) * canvas.width / r.width, (ev.clientY - r.top) * canvas.height / r.height];
}
// where a test should click: client-pixel offsets from the canvas' top-left corner for image point (u, v)
S.clientOffset = (camName, u, v) => {
  const canvas = document.getElementById(`canvas-${camName}`);
  const [x, y] = toScreen(canvas, camInfo(camName), u, v);
  const r = canvas.getBoundingClientRect();
  return [x * r.width / canvas.width, y * r.height / canvas.height];
};
function inside(cam, u, v) { return u >= -0.5 && v >= -0.5 && u <= cam.width - 0.5 && v <= cam.height - 0.5; }
// a drag that leaves the image stops at its edge (the server refuses a position outside it)
function clampInside(cam, u, v) { return [Math.max(-0.5, Math.min(cam.width - 0.5, u)), Math.max(-0.5, Math.min(cam.height - 0.5, v))]; }

function vertexUV(camIndex, vid) {
  const g = S.data && S.data.geometry;
  if (!g || !g.uv) return null;
  const p = g.uv[camIndex][vid];
  return p[0] < -1000 ? null : p;
}

// ------------------------------------------------------------------------------------------ editing
function snapshot() { return JSON.stringify(S.state); }
function edit(fn) {
  S.undo.push(snapshot());
  if (S.undo.length > 500) S.undo.shift();
  S.redo = [];
  fn();
  afterEdit();
}
function afterEdit() {
  S.dirty = true;
  say(`${S.expr}: unsaved edits…`);
  drawAll();
  clearTimeout(S.saveTimer);
  S.saveTimer = setTimeout(saveNow, 300);
}
function undo() {
  if (!S.undo.length) return;
  S.redo.push(snapshot());
  S.state = JSON.parse(S.undo.pop());
  retriangulateAll().then(drawAll);
  afterEdit();
}
function redo() {
  if (!S.redo.length) return;
  S.undo.push(snapshot());
  S.state = JSON.parse(S.redo.pop());
  retriangulateAll().then(drawAll);
  afterEdit();
}
async function saveNow(force) {
  clearTimeout(S.saveTimer);
  if (!S.dirty || S.saving) { if (S.saving) S.saveTimer = setTimeout(saveNow, 200); return; }
  S.saving = true;
  const sent = snapshot();
  try {
    const r = await api(`/api/expression/${encodeURIComponent(S.expr)}/hand`, { method: "PUT", body: { version: S.version, state: S.state } });
    S.version = r.version;
    S.saves += 1;
    if (snapshot() === sent) { S.dirty = false; say(`${S.expr}: saved (version ${S.version})`, "muted"); }
    else S.saveTimer = setTimeout(saveNow, 100);
    banner(null);
  } catch (e) {
    if (e.status === 409) {
      S.conflict = e.data;
      say(`${S.expr}: NOT saved — changed in another tab`, "warn");
      banner(`${S.expr} was changed elsewhere (another tab?) since this page loaded it. Your version is kept in ${e.data.kept}; nothing is lost.`, [
        ["load theirs (undo brings mine back)", () => {
          S.undo.push(snapshot()); S.state = e.data.current; S.version = e.data.version; S.dirty = false; S.conflict = null;
          banner(null); retriangulateAll().then(drawAll); say(`${S.expr}: loaded the other version`);
        }],
        ["keep mine (overwrite theirs)", () => { S.version = e.data.version; S.conflict = null; banner(null); S.dirty = true; saveNow(); }],
      ]);
    } else {
      say(`${S.expr}: save failed: ${e.message}`, "warn");
      banner(`Save failed: ${e.message}`);
    }
  } finally {
    S.saving = false;
  }
}

async function triangulate(clicks, depthFrom) {
  if (Object.keys(clicks).length < (depthFrom ? 1 : 2)) return null;
  try { return await api("/api/triangulate", { method: "POST", body: { clicks, depth_from: depthFrom || null } }); }
  catch (e) { say(`triangulation: ${e.message}`, "warn"); return null; }
}
async function retriangulateAll() {
  S.tri = {};
  const jobs = Object.entries(S.state.coarse || {}).map(async ([vid, item]) => {
    const r = await triangulate(item.clicks || {});
    if (r && r.ok) S.tri[vid] = r;
  });
  await Promise.all(jobs);
}

function coarseClick(cam, u, v, alt) {
  const vid = document.getElementById("coarse-select").value;
  if (vid === "") return;
  edit(() => {
    const item = S.state.coarse[vid] || (S.state.coarse[vid] = { clicks: {}, position: null });
    if (alt) delete item.clicks[cam.name]; else item.clicks[cam.name] = [round3(u), round3(v)];
    if (!Object.keys(item.clicks).length) delete S.state.coarse[vid];
  });
  updateCoarse(vid);
}
async function updateCoarse(vid) {
  const item = S.state.coarse[vid];
  if (!item) { delete S.tri[vid]; drawAll(); return; }
  const r = await triangulate(item.clicks);
  if (r && r.ok) { S.tri[vid] = r; item.position = r.position; } else { delete S.tri[vid]; item.position = null; }
  S.dirty = true; clearTimeout(S.saveTimer); S.saveTimer = setTimeout(saveNow, 150);
  const info = document.getElementById("coarse-info");
  info.textContent = r && r.ok ? `coarse ${vid}: (${r.position.map((x) => x.toFixed(4)).join(", ")}) m; residual ` + Object.entries(r.residual_px).map(([c, e]) => `${c} ${e.toFixed(2)} px`).join(", ") : `coarse ${vid}: click it in a second view`;
  drawAll();
}
function round3(x) { return Math.round(x * 1000) / 1000; }

function pointClick(cam, u, v, alt) {
  const name = document.getElementById("point-select").value;
  edit(() => {
    const pts = S.state.rotoscope.points;
    const p = pts[name] || (pts[name] = {});
    if (alt) delete p[cam.name]; else p[cam.name] = [round3(u), round3(v)];
    if (!Object.keys(p).length) delete pts[name];
  });
}

function nearestCurveVertex(canvas, cam, x, y) {
  const name = document.getElementById("curve-select").value;
  const poly = ((S.state.rotoscope.curves[name] || {})[cam.name]) || [];
  let best = -1, bd = HIT_PX;
  poly.forEach((p, i) => { const [sx, sy] = toScreen(canvas, cam, p[0], p[1]); const d = Math.hypot(sx - x, sy - y); if (d < bd) { bd = d; best = i; } });
  return [name, best];
}
function curveDown(canvas, cam, x, y, alt) {
  const [name, i] = nearestCurveVertex(canvas, cam, x, y);
  const [u, v] = toImage(canvas, cam, x, y);
  if (i >= 0 && alt) {
    edit(() => {
      const poly = S.state.rotoscope.curves[name][cam.name];
      poly.splice(i, 1);
      if (poly.length === 0) delete S.state.rotoscope.curves[name][cam.name];
      if (!Object.keys(S.state.rotoscope.curves[name]).length) delete S.state.rotoscope.curves[name];
    });
    return null;
  }
  if (i >= 0) { S.undo.push(snapshot()); S.redo = []; return { kind: "curve", name, i, cam: cam.name }; }
  if (alt || !inside(cam, u, v)) return null;
  edit(() => {
    const c = S.state.rotoscope.curves[name] || (S.state.rotoscope.curves[name] = {});
    (c[cam.name] || (c[cam.name] = [])).push([round3(u), round3(v)]);
  });
  return null;
}

function nearestFiducial(canvas, cam, x, y) {
  const t = S.info.template;
  const g = S.data.geometry;
  if (!t || !g || !g.uv) return -1;
  const ci = S.info.cameras.indexOf(cam);
  let best = -1, bd = HIT_PX;
  for (let vid = 0; vid < t.n_vertices; vid++) {
    if (t.kinds[vid] !== "dot") continue;
    const ov = S.state.overrides[vid];
    const p = ov && ov.clicks[cam.name] ? ov.clicks[cam.name] : vertexUV(ci, vid);
    if (!p) continue;
    const [sx, sy] = toScreen(canvas, cam, p[0], p[1]);
    const d = Math.hypot(sx - x, sy - y);
    if (d < bd) { bd = d; best = vid; }
  }
  return best;
}
async function finishFix(vid, camName, u, v) {
  const base = S.data.geometry.positions ? S.data.geometry.positions[vid] : null;
  const prev = S.undo.length ? null : null;
  edit(() => {
    const ov = S.state.overrides[vid] || (S.state.overrides[vid] = { clicks: {}, position: base });
    ov.clicks[camName] = [round3(u), round3(v)];
  });
  const ov = S.state.overrides[vid];
  const r = await triangulate(ov.clicks, Object.keys(ov.clicks).length === 1 ? base : null);
  if (r && r.ok) { ov.position = r.position; S.fixTri[vid] = r; }
  S.dirty = true; clearTimeout(S.saveTimer); S.saveTimer = setTimeout(saveNow, 150);
  document.getElementById("coarse-info").textContent = r && r.ok ? `fiducial ${vid} hand-fixed at (${r.position.map((x) => x.toFixed(4)).join(", ")}) m` : "";
  drawAll();
  return prev;
}

// ------------------------------------------------------------------------------------------ mouse
function attachView(canvas, cam) {
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const [x, y] = eventPos(canvas, e);
    const f = Math.exp(-e.deltaY * 0.0015);
    const z = Math.max(0.5, Math.min(40, S.view.zoom * f));
    const k = z / S.view.zoom;
    S.view.ox = x - (x - S.view.ox) * k; S.view.oy = y - (y - S.view.oy) * k; S.view.zoom = z;
    drawAll();
  }, { passive: false });
  canvas.addEventListener("pointerdown", (e) => {
    const [x, y] = eventPos(canvas, e);
    const [u, v] = toImage(canvas, cam, x, y);
    canvas.setPointerCapture(e.pointerId);
    if (e.button === 2 || e.button === 1 || S.tool === "navigate") { S.drag = { kind: "pan", x, y, moved: false }; return; }
    if (e.button !== 0) return;
    const alt = e.altKey;
    if (S.tool === "template") { templateDown(canvas, cam, x, y, u, v, alt).then((d) => { S.drag = d; S.tplEdited = true; }); return; }
    if (S.tool === "curve") { S.drag = curveDown(canvas, cam, x, y, alt); return; }
    if (!inside(cam, u, v)) { say("click outside the image: ignored", "warn"); return; }
    if (S.tool === "coarse") coarseClick(cam, u, v, alt);
    else if (S.tool === "point") pointClick(cam, u, v, alt);
    else if (S.tool === "fix") {
      const vid = nearestFiducial(canvas, cam, x, y);
      if (vid >= 0) S.drag = { kind: "fix", vid, cam: cam.name, u, v };
    }
  });
  canvas.addEventListener("pointermove", (e) => {
    const [x, y] = eventPos(canvas, e);
    const [u0, v0] = toImage(canvas, cam, x, y);
    hover(canvas, cam, x, y, u0, v0);
    const d = S.drag;
    if (!d) return;
    const [u, v] = clampInside(cam, u0, v0);
    if (d.kind === "pan") { S.view.ox += x - d.x; S.view.oy += y - d.y; d.x = x; d.y = y; drawAll(); }
    else if (d.kind === "curve" && d.cam === cam.name) { S.state.rotoscope.curves[d.name][d.cam][d.i] = [round3(u), round3(v)]; drawAll(); }
    else if (d.kind === "fix" && d.cam === cam.name) { d.u = u; d.v = v; d.moved = true; drawAll(); }
    else if (d.kind === "tvertex" && d.cam === cam.name) { d.u = u; d.v = v; d.moved = true; drawAll(); }
  });
  canvas.addEventListener("pointerup", (e) => {
    const d = S.drag;
    S.drag = null;
    if (!d) return;
    if (d.kind === "curve") afterEdit();
    else if (d.kind === "tvertex") templateUp(d, cam);
    else if (d.kind === "fix" && d.moved && inside(cam, d.u, d.v)) finishFix(d.vid, d.cam, d.u, d.v);
  });
}

function hover(canvas, cam, x, y, u, v) {
  const el = document.getElementById("hover");
  let txt = `${cam.name} (${u.toFixed(1)}, ${v.toFixed(1)})`;
  const t = S.info.template;
  const g = S.data && S.data.geometry;
  if (t && g && g.uv) {
    const ci = S.info.cameras.indexOf(cam);
    let best = -1, bd = HIT_PX;
    for (let vid = 0; vid < t.n_vertices; vid++) {
      const p = vertexUV(ci, vid);
      if (!p) continue;
      const [sx, sy] = toScreen(canvas, cam, p[0], p[1]);
      const dd = Math.hypot(sx - x, sy - y);
      if (dd < bd) { bd = dd; best = vid; }
    }
    if (best >= 0) txt += ` · vertex ${best} ${t.names[best] || ""} (${t.kinds[best]}) ${g.status ? g.status[best] : ""}`;
  }
  el.textContent = txt;
}

// ------------------------------------------------------------------------------------------ drawing
function drawAll() { if (!S.info) return; for (const c of S.info.cameras) drawView(c.name); }
function checked(id) { return document.getElementById(id).checked; }

function drawView(camName) {
  const canvas = document.getElementById(`canvas-${camName}`);
  if (!canvas || !S.state) return;
  const cam = camInfo(camName);
  const ci = S.info.cameras.indexOf(cam);
  const ctx = canvas.getContext("2d");
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = "#000"; ctx.fillRect(0, 0, canvas.width, canvas.height);
  const s = scaleOf(canvas, cam);
  const img = S.images[camName];
  if (img) {
    ctx.imageSmoothingEnabled = S.view.zoom < 2;
    ctx.setTransform(s, 0, 0, s, S.view.ox, S.view.oy);
    ctx.drawImage(img, 0, 0);
    ctx.setTransform(1, 0, 0, 1, 0, 0);
  } else {
    ctx.fillStyle = "#f88"; ctx.fillText("image unavailable", 10, 20);
  }
  const P = (u, v) => toScreen(canvas, cam, u, v);
  if (S.tool === "template") { drawTemplate(ctx, canvas, cam); return; }
  const t = S.info.template;
  const g = S.data && S.data.geometry;
  const r = Math.max(2, Math.min(6, 0.6 * s));
  // wireframe
  if (checked("ov-wireframe") && t && g && g.uv) {
    ctx.strokeStyle = "rgba(120,200,255,0.35)"; ctx.lineWidth = 1; ctx.beginPath();
    for (const [a, b] of t.edges) {
      const pa = vertexUV(ci, a), pb = vertexUV(ci, b);
      if (!pa || !pb || !(g.visible[ci][a] && g.visible[ci][b])) continue;
      const [x0, y0] = P(pa[0], pa[1]), [x1, y1] = P(pb[0], pb[1]);
      ctx.moveTo(x0, y0); ctx.lineTo(x1, y1);
    }
    ctx.stroke();
  }
  // fiducials by status
  if (checked("ov-fiducials") && t && g && g.uv) {
    for (let vid = 0; vid < t.n_vertices; vid++) {
      if (t.kinds[vid] !== "dot" || !g.visible[ci][vid]) continue;
      const p = vertexUV(ci, vid);
      if (!p) continue;
      const st = S.state.overrides[vid] ? "hand_fixed" : (g.status ? g.status[vid] : null);
      const [x, y] = P(p[0], p[1]);
      ctx.strokeStyle = st ? STATUS_COLOURS[st] : "rgba(255,255,255,0.5)";
      ctx.lineWidth = st === "failed" || st === "flagged" ? 2 : 1.2;
      ctx.beginPath(); ctx.arc(x, y, r, 0, 2 * Math.PI); ctx.stroke();
    }
    for (const [vid, ov] of Object.entries(S.state.overrides || {})) {
      const c = ov.clicks[camName];
      let p = c;
      const tr = S.fixTri[vid];
      if (!p && tr) p = tr.reprojection[camName];
      if (!p) continue;
      const [x, y] = P(p[0], p[1]);
      ctx.fillStyle = STATUS_COLOURS.hand_fixed;
      ctx.beginPath(); ctx.arc(x, y, r * 0.6, 0, 2 * Math.PI); ctx.fill();
    }
    if (S.drag && S.drag.kind === "fix" && S.drag.cam === camName) {
      const [x, y] = P(S.drag.u, S.drag.v);
      ctx.strokeStyle = "#fff"; ctx.setLineDash([3, 2]); ctx.beginPath(); ctx.arc(x, y, r + 3, 0, 2 * Math.PI); ctx.stroke(); ctx.setLineDash([]);
    }
  }
  // rotoscoped curves
  if (checked("ov-curves")) {
    const sel = document.getElementById("curve-select").value;
    for (const [name, views] of Object.entries(S.state.rotoscope.curves || {})) {
      const poly = views[camName];
      if (!poly) continue;
      drawPoly(ctx, poly.map((q) => P(q[0], q[1])), CURVE_COLOURS[name] || "#fff", name.startsWith("iris"), S.tool === "curve" && name === sel);
    }
  }
  // marks
  if (checked("ov-marks")) {
    for (const [name, views] of Object.entries(S.state.rotoscope.points || {})) {
      const p = views[camName];
      if (!p) continue;
      const [x, y] = P(p[0], p[1]);
      ctx.strokeStyle = name === "lower_teeth" ? "#fff27a" : "#ffa94d"; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.moveTo(x - 6, y); ctx.lineTo(x + 6, y); ctx.moveTo(x, y - 6); ctx.lineTo(x, y + 6); ctx.stroke();
      ctx.fillStyle = ctx.strokeStyle; ctx.font = "11px sans-serif"; ctx.fillText(name, x + 7, y - 5);
    }
  }
  // coarse points: clicks (filled), reprojections (crosses) with the residual
  if (checked("ov-coarse")) {
    const selv = document.getElementById("coarse-select").value;
    for (const [vid, item] of Object.entries(S.state.coarse || {})) {
      const isSel = S.tool === "coarse" && vid === selv;
      const c = item.clicks[camName];
      if (c) {
        const [x, y] = P(c[0], c[1]);
        ctx.fillStyle = isSel ? "#ff8c00" : "#ffb000";
        ctx.beginPath(); ctx.arc(x, y, isSel ? 4 : 3, 0, 2 * Math.PI); ctx.fill();
      }
      const tr = S.tri[vid];
      if (tr && tr.reprojection[camName]) {
        const q = tr.reprojection[camName];
        const [x, y] = P(q[0], q[1]);
        ctx.strokeStyle = isSel ? "#ff8c00" : "#ffe0a0"; ctx.lineWidth = 1.5;
        ctx.beginPath(); ctx.moveTo(x - 5, y - 5); ctx.lineTo(x + 5, y + 5); ctx.moveTo(x - 5, y + 5); ctx.lineTo(x + 5, y - 5); ctx.stroke();
        const res = tr.residual_px[camName];
        if (isSel) {
          ctx.fillStyle = "#ffe0a0"; ctx.font = "11px sans-serif";
          ctx.fillText(res !== undefined ? `${vid}: ${res.toFixed(2)} px` : `${vid}`, x + 6, y + 12);
        }
      }
    }
  }
  // proposals
  if (checked("ov-proposals") && S.proposal && S.proposal.state) {
    const st = S.proposal.state;
    ctx.strokeStyle = PROPOSAL_COLOUR; ctx.fillStyle = PROPOSAL_COLOUR; ctx.lineWidth = 1.2;
    const flagged = (S.proposal.flagged && S.proposal.flagged.coarse) || {};
    for (const [vid, item] of Object.entries(st.coarse || {})) {
      const c = item.clicks[camName];
      if (!c) continue;
      const [x, y] = P(c[0], c[1]);
      if (flagged[vid]) {                     // a proposal that looks wrong: the flagged colour, its id
        ctx.save(); ctx.strokeStyle = STATUS_COLOURS.flagged; ctx.fillStyle = STATUS_COLOURS.flagged; ctx.lineWidth = 2;
        ctx.beginPath(); ctx.rect(x - 5, y - 5, 10, 10); ctx.stroke();
        ctx.font = "11px sans-serif"; ctx.fillText(`${vid}?`, x + 6, y - 6); ctx.restore();
      } else { ctx.beginPath(); ctx.rect(x - 3, y - 3, 6, 6); ctx.stroke(); }
    }
    ctx.setLineDash([4, 3]);
    for (const [name, views] of Object.entries(st.rotoscope.curves || {})) {
      const poly = views[camName];
      if (poly) drawPoly(ctx, poly.map((q) => P(q[0], q[1])), PROPOSAL_COLOUR, name.startsWith("iris"), false);
    }
    ctx.setLineDash([]);
    for (const views of Object.values(st.rotoscope.points || {})) {
      const p = views[camName];
      if (!p) continue;
      const [x, y] = P(p[0], p[1]);
      ctx.beginPath(); ctx.moveTo(x - 5, y - 5); ctx.lineTo(x + 5, y + 5); ctx.moveTo(x - 5, y + 5); ctx.lineTo(x + 5, y - 5); ctx.stroke();
    }
  }
  if (S.templateProposal && S.templateProposal.uv && checked("ov-proposals")) {
    ctx.fillStyle = PROPOSAL_COLOUR;
    for (const p of S.templateProposal.uv[camName] || []) {
      const [x, y] = P(p[0], p[1]);
      ctx.fillRect(x - 2, y - 2, 4, 4);
    }
  }
}

function drawPoly(ctx, pts, colour, closed, withVertices) {
  if (pts.length < 1) return;
  ctx.strokeStyle = colour; ctx.lineWidth = 1.5; ctx.beginPath();
  pts.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
  if (closed && pts.length > 2) ctx.closePath();
  ctx.stroke();
  if (withVertices) {
    ctx.fillStyle = colour;
    for (const [x, y] of pts) ctx.fillRect(x - 2, y - 2, 4, 4);
  }
}

// ------------------------------------------------------------------------------------------ proposals
function proposalButtons() {
  document.getElementById("accept-proposal").disabled = !(S.proposal && S.proposal.state);
  document.getElementById("discard-proposal").disabled = !S.proposal;
  document.getElementById("accept-template").disabled = !(S.templateProposal && S.templateProposal.template);
}
async function propose() {
  say(`${S.expr}: proposing…`);
  try {
    S.proposal = await api(`/api/proposals/${encodeURIComponent(S.expr)}`);
    say(S.proposal.note || "proposal ready");
  } catch (e) { say(`proposal failed: ${e.message}`, "warn"); S.proposal = null; }
  proposalButtons(); drawAll();
}
function acceptProposal() {
  const p = S.proposal && S.proposal.state;
  if (!p) return;
  edit(() => {
    for (const [vid, item] of Object.entries(p.coarse || {})) if (!S.state.coarse[vid]) S.state.coarse[vid] = item;
    for (const [name, views] of Object.entries(p.rotoscope.curves || {})) if (!S.state.rotoscope.curves[name]) S.state.rotoscope.curves[name] = views;
    for (const [name, views] of Object.entries(p.rotoscope.points || {})) if (!S.state.rotoscope.points[name]) S.state.rotoscope.points[name] = views;
    if (S.state.rotoscope.eyes_look_at == null && p.rotoscope.eyes_look_at != null) S.state.rotoscope.eyes_look_at = p.rotoscope.eyes_look_at;
  });
  S.proposal = null; proposalButtons();
  retriangulateAll().then(drawAll);
}
async function proposeTemplate(accept) {
  say(accept ? "writing the proposed template…" : "proposing a template from the neutral's images (dots in every view)…");
  try {
    const r = await api("/api/proposals/template", { method: "POST", body: { accept } });
    S.templateProposal = r;
    say(r.note || "template proposal ready");
    if (accept && r.accepted) { S.templateProposal = null; S.tpl = null; await refreshSession(); await loadExpression(); }
  } catch (e) { say(`template proposal failed: ${e.message}`, "warn"); }
  proposalButtons(); drawAll();
}

// ------------------------------------------------------------------------------------------ registration
async function registerExpression() {
  if (S.dirty) await saveNow();
  const bar = document.getElementById("progress");
  const st = document.getElementById("job-status");
  try {
    S.job = await api(`/api/register/${encodeURIComponent(S.expr)}`, { method: "POST", body: {} });
  } catch (e) { st.textContent = `cannot register: ${e.message}`; return; }
  bar.classList.remove("hidden");
  document.getElementById("register").disabled = true;
  const expr = S.expr;
  while (true) {
    await new Promise((r) => setTimeout(r, 700));
    let j;
    try { j = await api(`/api/jobs/${S.job.id}`); } catch (e) { st.textContent = `lost the job: ${e.message}`; break; }
    S.job = j;
    bar.value = j.fraction;
    st.textContent = `${j.expression}: ${j.state} — ${j.step} (${j.elapsed_s} s)`;
    if (j.state === "done" || j.state === "failed") {
      if (j.state === "failed") st.textContent = `${j.expression}: registration failed: ${j.error}`;
      break;
    }
  }
  document.getElementById("register").disabled = false;
  bar.classList.add("hidden");
  await refreshSession();
  if (S.expr === expr) { await loadExpression(); loadImages(); }
}

start();
