// mifacerf studio: editing the template on the neutral (hand/template.json, schema mifacerf.template/1).
// The page keeps the template document and its vertices' pixels in every view (S.tpl); every edit is one
// undo step (S.tundo / S.tredo, separate from the expression's hand state) and is saved whole, atomically,
// through PUT /api/template (versioned: a stale save is refused and kept, as for the hand state).
// Deleting a vertex renumbers the vertices after it: the save sends the id map so the server renumbers the
// coarse points and fixes of every expression too (a deleted vertex's own clicks go).
"use strict";

const KIND_COLOURS = {
  dot: "#ffffff", lip_upper: "#ff6f91", lip_lower: "#ff9671", lip_corner: "#ff2050", lid_upper: "#00c9a7",
  lid_lower: "#4ffbdf", lid_corner: "#00a080", nostril: "#c0a0ff", ear: "#ffa94d", nose_bridge: "#ffd23f",
};
const MARGINS = ["lip_upper", "lip_lower", "lid_upper_L", "lid_lower_L", "lid_upper_R", "lid_lower_R"];
const HOLE_OF = { lip: ["mouth", "lip_upper", "lip_lower"], L: ["eye_left", "lid_upper_L", "lid_lower_L"], R: ["eye_right", "lid_upper_R", "lid_lower_R"] };
const TPL_OPS = {
  move: "move a vertex (drag)", add_vertex: "add a vertex (click it in two views)", delete_vertex: "delete a vertex",
  add_triangle: "add a triangle (click three vertices)", delete_triangle: "delete a triangle (click inside)",
  flip_triangle: "flip a triangle (click inside)", kind: "set a vertex's kind", margin: "margin: append vertices in order (Alt: remove)",
  region: "region: add vertices (Alt: remove)", head_point: "head point: set to a vertex", coarse: "coarse point: toggle a vertex",
};

async function loadTemplate() {
  const d = await api("/api/template");
  S.tpl = d.template ? { doc: d.template, uv: d.uv, version: d.version } : null;
  S.tplVersion = d.version;
  S.tundo = []; S.tredo = []; S.tpending = { clicks: {}, tri: [] };
  if (d.template) {
    const sel = document.getElementById("tpl-kind");
    if (!sel.options.length) sel.innerHTML = d.kinds.map((k) => `<option value="${k}">${k}</option>`).join("");
    const rs = document.getElementById("tpl-region");
    if (!rs.options.length) rs.innerHTML = d.region_names.map((k) => `<option value="${k}">${k}</option>`).join("");
  }
  tplStatus(d.template ? `template: ${d.template.vertices.length} vertices, ${d.template.triangles.length} triangles (version ${d.version})` : `no template: ${d.problem || "propose one"}`);
}
function tplStatus(msg, cls) {
  const el = document.getElementById("tpl-status");
  el.textContent = msg; el.className = cls || "muted";
}
function tplSnapshot(map) { return { doc: JSON.stringify(S.tpl.doc), uv: JSON.stringify(S.tpl.uv), map: map || null }; }

// one undoable edit of the template: fn() changes S.tpl.doc / S.tpl.uv; ``map`` (old id -> new id, -1 =
// deleted) when vertices are renumbered, and ``back`` the map that undoes it
function tplEdit(fn, map, back) {
  const snap = tplSnapshot(back);
  fn();
  S.tundo.push(snap);
  if (S.tundo.length > 300) S.tundo.shift();
  S.tredo = [];
  S.tplMap = composeMaps(S.tplMap, map);
  tplSave();
  drawAll();
}
function composeMaps(a, b) {
  if (!a) return b || null;
  if (!b) return a;
  return a.map((v) => (v < 0 ? -1 : b[v]));
}
// undo and redo: restore the top of one history, pushing the current state onto the other; the snapshot's
// map renumbers the hand inputs back, the pushed one carries its inverse (to re-apply it)
function tplStep(from, to) {
  if (!from.length) return;
  const snap = from.pop();
  const cur = tplSnapshot(null);
  cur.map = snap.map ? invertMap(snap.map, JSON.parse(snap.doc).vertices.length) : null;
  to.push(cur);
  S.tpl.doc = JSON.parse(snap.doc); S.tpl.uv = JSON.parse(snap.uv);
  S.tplMap = composeMaps(S.tplMap, snap.map);
  tplSave(); drawAll();
}
function tplUndo() { tplStep(S.tundo, S.tredo); }
function tplRedo() { tplStep(S.tredo, S.tundo); }
function invertMap(map, n) {
  const inv = new Array(n).fill(-1);
  map.forEach((v, i) => { if (v >= 0) inv[v] = i; });
  return inv;
}
function tplSave() {
  clearTimeout(S.tplTimer);
  S.tplDirty = true;
  tplStatus("template: unsaved edits…");
  S.tplTimer = setTimeout(tplSaveNow, 250);
}
async function tplSaveNow() {
  clearTimeout(S.tplTimer);
  if (!S.tplDirty) return;
  if (S.tplSaving) { S.tplTimer = setTimeout(tplSaveNow, 200); return; }
  S.tplSaving = true;
  const sent = JSON.stringify(S.tpl.doc);
  const map = S.tplMap;
  try {
    const r = await api("/api/template", { method: "PUT", body: { version: S.tplVersion, template: S.tpl.doc, renumber: map } });
    S.tplVersion = r.version; S.tpl.version = r.version; S.tplMap = null;
    if (JSON.stringify(S.tpl.doc) === sent) { S.tplDirty = false; S.tpl.uv = r.uv; tplStatus(`template saved (version ${r.version}): ${S.tpl.doc.vertices.length} vertices, ${S.tpl.doc.triangles.length} triangles`); }
    else S.tplTimer = setTimeout(tplSaveNow, 100);
    S.saves += 1;
    banner(null);
  } catch (e) {
    if (e.status === 409) {
      tplStatus("template NOT saved — changed elsewhere", "warn");
      banner(`hand/template.json was changed elsewhere (another tab?). Your version is kept in ${e.data.kept}; nothing is lost.`, [
        ["load theirs", async () => { banner(null); await loadTemplate(); drawAll(); }],
        ["keep mine (overwrite theirs)", () => { S.tplVersion = e.data.version; banner(null); S.tplDirty = true; tplSaveNow(); }],
      ]);
    } else { tplStatus(`template not saved: ${e.message}`, "warn"); }
  } finally { S.tplSaving = false; }
  drawAll();
}

// ------------------------------------------------------------------------------------------ picking
function tplVertexAt(canvas, cam, x, y) {
  const uv = S.tpl.uv[cam.name] || [];
  let best = -1, bd = HIT_PX;
  uv.forEach((p, i) => { if (p[0] < -1000) return; const [sx, sy] = toScreen(canvas, cam, p[0], p[1]); const d = Math.hypot(sx - x, sy - y); if (d < bd) { bd = d; best = i; } });
  return best;
}
function tplTriangleAt(cam, u, v) {
  const uv = S.tpl.uv[cam.name] || [];
  let best = -1, ba = Infinity;
  S.tpl.doc.triangles.forEach((t, k) => {
    const [a, b, c] = t.map((i) => uv[i]);
    if (!a || !b || !c) return;
    const area = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
    if (Math.abs(area) < 1e-9) return;
    const w1 = ((b[0] - u) * (c[1] - v) - (c[0] - u) * (b[1] - v)) / area;
    const w2 = ((c[0] - u) * (a[1] - v) - (a[0] - u) * (c[1] - v)) / area;
    const w3 = 1 - w1 - w2;
    if (w1 >= 0 && w2 >= 0 && w3 >= 0 && Math.abs(area) < ba) { ba = Math.abs(area); best = k; }
  });
  return best;
}
function tplOp() { return document.getElementById("tpl-op").value; }
function setUV(vid, reprojection) {
  for (const cam of S.info.cameras) {
    const list = S.tpl.uv[cam.name] || (S.tpl.uv[cam.name] = []);
    list[vid] = reprojection[cam.name] || [-1e4, -1e4];
  }
}

// ------------------------------------------------------------------------------------------ edits
function deleteVertex(v) {
  const n = S.tpl.doc.vertices.length;
  const map = [], back = [];
  for (let i = 0; i < n; i++) map.push(i < v ? i : i === v ? -1 : i - 1);
  for (let i = 0; i < n - 1; i++) back.push(i < v ? i : i + 1);
  tplEdit(() => {
    const d = S.tpl.doc;
    const m = (i) => map[i];
    d.vertices.splice(v, 1);
    d.triangles = d.triangles.filter((t) => !t.includes(v)).map((t) => t.map(m));
    d.coarse_points = (d.coarse_points || []).filter((i) => i !== v).map(m);
    delete d.coarse_triangles;
    for (const key of ["margins", "regions", "holes"]) {
      if (!d[key]) continue;
      for (const name of Object.keys(d[key])) d[key][name] = d[key][name].filter((i) => i !== v).map(m);
    }
    if (d.head_points) for (const [k, i] of Object.entries(d.head_points)) { if (i === v) delete d.head_points[k]; else d.head_points[k] = m(i); }
    for (const cam of Object.keys(S.tpl.uv)) S.tpl.uv[cam].splice(v, 1);
  }, map, back);
  tplStatus(`vertex ${v} deleted (the vertices after it renumbered, in every expression's hand inputs too)`);
}
function updateHoles(d) {
  if (!d.margins) return;
  d.holes = d.holes || {};
  for (const [hole, up, lo] of Object.values(HOLE_OF)) {
    const a = d.margins[up], b = d.margins[lo];
    if (a && b && a.length >= 2 && b.length >= 2) d.holes[hole] = a.concat(b.slice(1, -1).reverse());
  }
}
async function templateDown(canvas, cam, x, y, u, v, alt) {
  if (!S.tpl) { tplStatus("no template to edit: propose or accept one first", "warn"); return null; }
  const op = tplOp();
  const vid = tplVertexAt(canvas, cam, x, y);
  const d = S.tpl.doc;
  if (op === "move") return vid >= 0 ? { kind: "tvertex", vid, cam: cam.name, u, v, moved: false } : null;
  if (op === "add_vertex") {
    if (!inside(cam, u, v)) return null;
    S.tpending.clicks[cam.name] = [round3(u), round3(v)];
    if (Object.keys(S.tpending.clicks).length < 2) { tplStatus(`new vertex: clicked in ${cam.name}; now click it in another view`); drawAll(); return null; }
    const r = await triangulate(S.tpending.clicks);
    S.tpending.clicks = {};
    if (!r || !r.ok) { tplStatus("new vertex: the two clicks do not meet (triangulation failed); click again", "warn"); drawAll(); return null; }
    const kind = document.getElementById("tpl-kind").value;
    tplEdit(() => {
      const i = d.vertices.length;
      d.vertices.push({ kind, name: `${kind}${i}`, position: r.position });
      setUV(i, r.reprojection);
    });
    tplStatus(`vertex ${d.vertices.length - 1} (${kind}) added; residual ` + Object.entries(r.residual_px).map(([c, e]) => `${c} ${e.toFixed(2)} px`).join(", "));
    return null;
  }
  if (op === "add_triangle") {
    if (vid < 0) return null;
    if (!S.tpending.tri.includes(vid)) S.tpending.tri.push(vid);
    if (S.tpending.tri.length === 3) {
      const t = S.tpending.tri.slice();
      S.tpending.tri = [];
      tplEdit(() => { d.triangles.push(t); });
      tplStatus(`triangle ${t.join(", ")} added (flip it if it faces inwards)`);
    } else { tplStatus(`triangle: ${S.tpending.tri.join(", ")} — click ${3 - S.tpending.tri.length} more`); drawAll(); }
    return null;
  }
  if (op === "delete_triangle" || op === "flip_triangle") {
    const k = tplTriangleAt(cam, u, v);
    if (k < 0) return null;
    if (op === "delete_triangle") { tplEdit(() => { d.triangles.splice(k, 1); }); tplStatus(`triangle ${k} deleted`); }
    else { tplEdit(() => { const t = d.triangles[k]; d.triangles[k] = [t[0], t[2], t[1]]; }); tplStatus(`triangle ${k} flipped`); }
    return null;
  }
  if (vid < 0) return null;
  if (op === "delete_vertex") { deleteVertex(vid); return null; }
  if (op === "kind") {
    const kind = document.getElementById("tpl-kind").value;
    tplEdit(() => { d.vertices[vid].kind = kind; });
    tplStatus(`vertex ${vid} is now a ${kind}`);
  } else if (op === "margin") {
    const name = document.getElementById("tpl-margin").value;
    tplEdit(() => {
      d.margins = d.margins || JSON.parse(JSON.stringify(S.info.template ? S.info.template.margins : {}));
      const list = d.margins[name] || (d.margins[name] = []);
      if (alt) d.margins[name] = list.filter((i) => i !== vid); else if (!list.includes(vid)) list.push(vid);
      if (!d.margins[name].length) delete d.margins[name];
      updateHoles(d);
    });
    tplStatus(`${name}: ${(d.margins[name] || []).join(", ")}`);
  } else if (op === "region") {
    const name = document.getElementById("tpl-region").value;
    tplEdit(() => {
      d.regions = d.regions || {};
      const list = d.regions[name] || (d.regions[name] = []);
      if (alt) d.regions[name] = list.filter((i) => i !== vid);
      else { for (const r of Object.keys(d.regions)) d.regions[r] = d.regions[r].filter((i) => i !== vid); d.regions[name].push(vid); }
    });
    tplStatus(`region ${name}: ${(d.regions[name] || []).length} vertices`);
  } else if (op === "head_point") {
    const name = document.getElementById("tpl-head").value;
    tplEdit(() => { d.head_points = d.head_points || {}; d.head_points[name] = vid; });
    tplStatus(`head point ${name} = vertex ${vid}`);
  } else if (op === "coarse") {
    tplEdit(() => {
      const c = d.coarse_points || (d.coarse_points = []);
      const k = c.indexOf(vid);
      if (k >= 0) c.splice(k, 1); else c.push(vid);
      delete d.coarse_triangles;              // the reader makes the coarse mesh again
    });
    tplStatus(`coarse points: ${d.coarse_points.length}`);
  }
  return null;
}
async function templateUp(drag, cam) {
  if (!drag.moved || !inside(cam, drag.u, drag.v)) { drawAll(); return; }
  const vid = drag.vid;
  const base = S.tpl.doc.vertices[vid].position;
  const clicks = {}; clicks[drag.cam] = [round3(drag.u), round3(drag.v)];
  const r = await triangulate(clicks, base);
  if (!r || !r.ok) { tplStatus("move: no point on that ray", "warn"); drawAll(); return; }
  tplEdit(() => { S.tpl.doc.vertices[vid].position = r.position; setUV(vid, r.reprojection); });
  tplStatus(`vertex ${vid} moved to (${r.position.map((q) => q.toFixed(4)).join(", ")}) m (on ${drag.cam}'s ray, at its depth)`);
}

// ------------------------------------------------------------------------------------------ drawing
function drawTemplate(ctx, canvas, cam) {
  if (!S.tpl) return;
  const uv = S.tpl.uv[cam.name] || [];
  const d = S.tpl.doc;
  const P = (p) => toScreen(canvas, cam, p[0], p[1]);
  ctx.lineWidth = 1; ctx.strokeStyle = "rgba(120,200,255,0.55)"; ctx.beginPath();
  for (const t of d.triangles) {
    const q = t.map((i) => uv[i]);
    if (q.some((p) => !p || p[0] < -1000)) continue;
    const s = q.map(P);
    ctx.moveTo(s[0][0], s[0][1]); ctx.lineTo(s[1][0], s[1][1]); ctx.lineTo(s[2][0], s[2][1]); ctx.closePath();
  }
  ctx.stroke();
  const op = tplOp();
  const region = op === "region" ? new Set((d.regions || {})[document.getElementById("tpl-region").value] || []) : null;
  const coarse = new Set(d.coarse_points || []);
  const head = new Set(Object.values(d.head_points || {}));
  const r = Math.max(2, Math.min(5, 0.5 * scaleOf(canvas, cam)));
  d.vertices.forEach((vx, i) => {
    const p = uv[i];
    if (!p || p[0] < -1000) return;
    const [x, y] = P(p);
    ctx.fillStyle = region && region.has(i) ? "#3ddc4a" : (KIND_COLOURS[vx.kind] || "#fff");
    ctx.beginPath(); ctx.arc(x, y, vx.kind === "dot" ? r * 0.6 : r * 0.8, 0, 2 * Math.PI); ctx.fill();
    if (coarse.has(i) || head.has(i)) { ctx.strokeStyle = coarse.has(i) ? "#ffb000" : "#ffa94d"; ctx.lineWidth = 1.5; ctx.beginPath(); ctx.arc(x, y, r + 2.5, 0, 2 * Math.PI); ctx.stroke(); }
  });
  for (const [name, ids] of Object.entries(d.margins || (S.info.template ? S.info.template.margins : {}))) {
    const pts = ids.map((i) => uv[i]).filter((p) => p && p[0] > -1000).map(P);
    drawPoly(ctx, pts, CURVE_COLOURS[name] || "#fff", false, op === "margin" && name === document.getElementById("tpl-margin").value);
  }
  for (const vid of S.tpending.tri) { const p = uv[vid]; if (p) { const [x, y] = P(p); ctx.strokeStyle = "#ff00ff"; ctx.lineWidth = 2; ctx.strokeRect(x - 4, y - 4, 8, 8); } }
  const c = S.tpending.clicks[cam.name];
  if (c) { const [x, y] = P(c); ctx.strokeStyle = "#ff00ff"; ctx.beginPath(); ctx.moveTo(x - 6, y); ctx.lineTo(x + 6, y); ctx.moveTo(x, y - 6); ctx.lineTo(x, y + 6); ctx.stroke(); }
  if (S.drag && S.drag.kind === "tvertex" && S.drag.cam === cam.name && S.drag.moved) {
    const [x, y] = P([S.drag.u, S.drag.v]);
    ctx.strokeStyle = "#fff"; ctx.setLineDash([3, 2]); ctx.beginPath(); ctx.arc(x, y, r + 3, 0, 2 * Math.PI); ctx.stroke(); ctx.setLineDash([]);
  }
}

function buildTemplateControls() {
  document.getElementById("tpl-op").innerHTML = Object.entries(TPL_OPS).map(([k, t]) => `<option value="${k}">${t}</option>`).join("");
  document.getElementById("tpl-margin").innerHTML = MARGINS.map((k) => `<option value="${k}">${k}</option>`).join("");
  document.getElementById("tpl-head").innerHTML = ["ear_L", "ear_R", "nose_bridge"].map((k) => `<option value="${k}">${k}</option>`).join("");
  for (const id of ["tpl-op", "tpl-kind", "tpl-margin", "tpl-region", "tpl-head"]) document.getElementById(id).addEventListener("change", () => { S.tpending = { clicks: {}, tri: [] }; drawAll(); });
  document.getElementById("tpl-clear-margin").addEventListener("click", () => {
    const name = document.getElementById("tpl-margin").value;
    if (!S.tpl) return;
    tplEdit(() => {
      const d = S.tpl.doc;
      d.margins = d.margins || JSON.parse(JSON.stringify(S.info.template ? S.info.template.margins : {}));
      delete d.margins[name];
      updateHoles(d);
    });
  });
}
