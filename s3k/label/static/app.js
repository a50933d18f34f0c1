// s3k label: the page. Everything geometric (triangulation, reprojection, residuals, epipolar curves) comes
// from the server; this file only draws what it is given and sends clicks.
"use strict";

const SVG = "http://www.w3.org/2000/svg";
// a suggestion is accepted only in views where the run is confident: a calibrated confidence of 0.5 means about
// half such views lie within 2 sigma of the truth (docs/method.md); a part hidden in a view gets a low one there
const CONFIDENT = 0.5;
const TOKEN = new URLSearchParams(location.search).get("token");
const app = {
  meta: null, frames: [], frameIndex: 0, frame: null, kp: 0, brightness: 1,
  views: {}, hover: null, queue: Promise.resolve(), ranking: [], run: false, pending: 0,
  loading: 0,  // frame loads not yet answered
  versions: {},  // frame -> the version this page last saw, sent with the next edit of that frame
  unlocked: new Set(),  // the test frame the user unlocked for editing (locked again when left)
  visited: new Set(),  // frames shown in this page: n skips them
};

// 15 colours far apart in CIELAB (each pair more than 25 apart; none dark, for a dark page), one a keypoint;
// beyond 15 keypoints, hues spread over the circle
const PALETTE = ["#e6194b", "#3cb44b", "#ffe119", "#4363d8", "#f58231", "#46f0f0", "#f032e6", "#bcf60c",
                 "#fabebe", "#9a6324", "#e6beff", "#aaffc3", "#808000", "#fffac8", "#911eb4"];
function colour(k, n) {
  if (n <= PALETTE.length) return PALETTE[k];
  return `hsl(${Math.round((360 * k) / Math.max(n, 1) + 10) % 360}, 85%, 58%)`;
}

async function api(path, options = {}) {
  const headers = Object.assign({ "Content-Type": "application/json" }, options.headers || {});
  if (TOKEN) headers["X-S3K-Token"] = TOKEN;
  const response = await fetch(path, Object.assign({}, options, { headers }));
  let body = null;
  try { body = await response.json(); } catch (e) { body = null; }
  return { ok: response.ok, status: response.status, body };
}

function setStatus(text, kind) {
  const el = document.getElementById("status");
  el.textContent = text;
  el.className = kind || "";
}

function el(tag, attrs = {}, parent = null) {
  const node = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (parent) parent.appendChild(node);
  return node;
}

function titled(node, text) {  // the tooltip of an SVG marker
  el("title", {}, node).textContent = text;
  return node;
}

// ---- views ---------------------------------------------------------------------------------------------

function buildViews() {
  const [W, H] = app.meta.image_size;
  const box = document.getElementById("views");
  box.innerHTML = "";
  for (const cam of app.meta.cameras) {
    const div = document.createElement("div");
    div.className = "view";
    div.dataset.camera = cam;
    div.innerHTML = `<div class="bar"><span class="name"></span><span class="residual"></span>` +
      `<span class="spacer"></span><button class="occlude" title="the current keypoint is not visible in this view (x)">not visible</button>` +
      `<button class="remove" title="remove the current keypoint's label in this view (Delete)">remove</button></div>`;
    div.querySelector(".name").textContent = cam;
    const svg = el("svg", { viewBox: `${-0.5} ${-0.5} ${W} ${H}`, "data-camera": cam });
    const image = el("image", { x: -0.5, y: -0.5, width: W, height: H, preserveAspectRatio: "none" }, svg);
    const overlay = el("g", { class: "overlay" }, svg);
    div.appendChild(svg);
    box.appendChild(div);
    const view = { cam, div, svg, image, overlay, box: [-0.5, -0.5, W, H] };
    app.views[cam] = view;
    div.querySelector(".occlude").addEventListener("click", () => markOccluded(cam));
    div.querySelector(".remove").addEventListener("click", () => removeLabel(cam));
    div.addEventListener("pointerenter", () => { app.hover = cam; div.classList.add("hover"); });
    div.addEventListener("pointerleave", () => { if (app.hover === cam) app.hover = null; div.classList.remove("hover"); });
    attachPointer(view);
    svg.addEventListener("wheel", (ev) => { ev.preventDefault(); zoom(view, ev); }, { passive: false });
  }
  layoutViews();
}

function layoutViews() {
  // the views fill the space beside the sidebar: the number of columns that shows the images largest
  const box = document.getElementById("views");
  const n = app.meta.cameras.length;
  const [W, H] = app.meta.image_size;
  const style = getComputedStyle(box);
  const gap = parseFloat(style.columnGap) || 0;
  const aw = box.clientWidth - parseFloat(style.paddingLeft) - parseFloat(style.paddingRight);
  const ah = box.clientHeight - parseFloat(style.paddingTop) - parseFloat(style.paddingBottom);
  const first = box.querySelector(".view");
  const frame = first ? first.offsetHeight - first.querySelector("svg").clientHeight : 28;  // bar and border
  const side = first ? first.offsetWidth - first.clientWidth : 4;
  let cols = 1;
  let best = -1;
  for (let c = 1; c <= n; c++) {
    const rows = Math.ceil(n / c);
    const scale = Math.min(((aw - gap * (c - 1)) / c - side) / W, ((ah - gap * (rows - 1)) / rows - frame) / H);
    if (scale > best + 1e-9) { cols = c; best = scale; }
  }
  box.style.gridTemplateColumns = `repeat(${cols}, minmax(0, 1fr))`;
  box.style.gridTemplateRows = `repeat(${Math.ceil(n / cols)}, minmax(0, 1fr))`;
}

function toImage(view, clientX, clientY) {
  const pt = view.svg.createSVGPoint();
  pt.x = clientX; pt.y = clientY;
  const p = pt.matrixTransform(view.svg.getScreenCTM().inverse());
  return [p.x, p.y];
}

function toClient(cam, u, v) {  // for tests and tools: where image pixel (u, v) of a view is on the page
  const view = app.views[cam];
  const pt = view.svg.createSVGPoint();
  pt.x = u; pt.y = v;
  const p = pt.matrixTransform(view.svg.getScreenCTM());
  return [p.x, p.y];
}

function unitsPerPixel(view) {  // image pixels per screen pixel (the view keeps the image's aspect)
  const m = view.svg.getScreenCTM();
  return m && m.a > 0 ? 1 / m.a : view.box[2] / Math.max(view.svg.clientWidth, 1);
}

function setBox(view, box) {
  view.box = box;
  view.svg.setAttribute("viewBox", box.join(" "));
  drawView(view);
}

function zoom(view, ev) {
  const [u, v] = toImage(view, ev.clientX, ev.clientY);
  const f = Math.exp(Math.sign(ev.deltaY) * 0.15);
  const [x, y, w, h] = view.box;
  const [W] = app.meta.image_size;
  const nw = Math.min(Math.max(w * f, 4), W * 4);
  const s = nw / w;
  setBox(view, [u - (u - x) * s, v - (v - y) * s, w * s, h * s]);
}

function resetZoom() {
  const [W, H] = app.meta.image_size;
  for (const view of Object.values(app.views)) setBox(view, [-0.5, -0.5, W, H]);
}

function markersOf(cam, kp) {  // image positions of a keypoint's label, reprojection and suggestion in a view
  const out = [];
  const lab = labelOf(cam, kp);
  if (lab && lab.visible && lab.u !== null) out.push([lab.u, lab.v]);
  const geo = (app.frame.geometry || {})[kp];
  if (geo && geo.views[cam] && geo.views[cam].reproj) out.push(geo.views[cam].reproj);
  const sug = (app.frame.suggestions || {})[kp];
  if (sug && sug[cam] && !lab) out.push([sug[cam].u, sug[cam].v]);
  return out;
}

function nearestOtherKeypoint(view, clientX, clientY) {
  // Shift+click: the keypoint, other than the current one, whose marker is nearest (within 15 screen pixels)
  if (!app.frame) return null;
  const [u, v] = toImage(view, clientX, clientY);
  const reach = 15 * unitsPerPixel(view);
  let best = null;
  let bestD = reach;
  app.meta.keypoints.forEach((kp, k) => {
    if (k === app.kp) return;
    for (const [x, y] of markersOf(view.cam, kp)) {
      const d = Math.hypot(x - u, y - v);
      if (d <= bestD) { best = kp; bestD = d; }
    }
  });
  return best;
}

function attachPointer(view) {
  let drag = null;
  view.svg.addEventListener("pointerdown", (ev) => {
    if (ev.button !== 0 && ev.button !== 1) return;
    const target = ev.target.closest("[data-keypoint]");
    const current = app.meta.keypoints[app.kp];
    // Switching keypoints is explicit: Shift+click on another keypoint's marker selects it. A plain click
    // always places the current keypoint where it lands, however close another keypoint's marker is; only the
    // current keypoint's own marker can be dragged.
    if (ev.button === 0 && ev.shiftKey) {
      const kp = nearestOtherKeypoint(view, ev.clientX, ev.clientY) || (target && target.dataset.keypoint);
      if (kp) { selectKeypoint(app.meta.keypoints.indexOf(kp)); return; }
    }
    const own = target && target.dataset.keypoint === current && target.dataset.draggable === "1";
    const mode = ev.button === 0 && own ? "point" : "pan";
    drag = { mode, x: ev.clientX, y: ev.clientY, moved: false, button: ev.button, box: view.box.slice(),
             kp: current, kind: target ? target.dataset.kind : null };
    view.svg.setPointerCapture(ev.pointerId);
  });
  view.svg.addEventListener("pointermove", (ev) => {
    if (!drag) return;
    if (Math.hypot(ev.clientX - drag.x, ev.clientY - drag.y) > 3) drag.moved = true;
    if (!drag.moved) return;
    if (drag.mode === "pan") {
      const s = unitsPerPixel(view);
      const [x, y, w, h] = drag.box;
      setBox(view, [x - (ev.clientX - drag.x) * s, y - (ev.clientY - drag.y) * s, w, h]);
    } else {
      const [u, v] = toImage(view, ev.clientX, ev.clientY);
      drag.to = [u, v];
      drawView(view, { kp: drag.kp, uv: [u, v] });
    }
  });
  view.svg.addEventListener("pointerup", (ev) => {
    if (!drag) return;
    const d = drag;
    drag = null;
    if (d.mode === "point" && d.moved && d.to) {
      saveEdits([{ camera: view.cam, keypoint: d.kp, u: d.to[0], v: d.to[1], visible: true }], "drag");
    } else if (!d.moved && d.button === 0) {
      const [u, v] = toImage(view, ev.clientX, ev.clientY);
      const kp = app.meta.keypoints[app.kp];
      saveEdits([{ camera: view.cam, keypoint: kp, u, v, visible: true }], "click");
    }
  });
}

// ---- drawing -------------------------------------------------------------------------------------------

function pointIn(cam, kp, preview = null) {  // where a skeleton edge meets the keypoint in a view
  if (preview && preview.kp === kp) return preview.uv;
  return markersOf(cam, kp)[0] || null;  // its label, else its reprojection, else the run's suggestion
}

function labelOf(cam, kp) {
  return (app.frame ? app.frame.labels : []).find((l) => l.camera === cam && l.keypoint === kp) || null;
}

function drawView(view, preview = null) {
  const g = view.overlay;
  while (g.firstChild) g.removeChild(g.firstChild);
  if (!app.frame) return;
  const s = unitsPerPixel(view);
  const kps = app.meta.keypoints;
  const current = kps[app.kp];
  const geometry = app.frame.geometry || {};
  const suggestions = app.frame.suggestions || {};
  const order = kps.map((_, k) => k).filter((k) => k !== app.kp).concat([app.kp]);  // current on top
  const bones = el("g", { class: "skeleton" }, g);  // the skeleton's edges, under the markers
  for (const [a, b] of app.meta.skeleton || []) {
    const pa = pointIn(view.cam, a, preview);
    const pb = pointIn(view.cam, b, preview);
    if (!pa || !pb) continue;
    const at = { x1: pa[0], y1: pa[1], x2: pb[0], y2: pb[1], "data-edge": `${a}-${b}` };
    el("line", Object.assign({ class: "bone-halo" }, at), bones);
    el("line", Object.assign({ class: "bone" }, at), bones);
  }
  for (const k of order) {
    const kp = kps[k];
    const col = colour(k, kps.length);
    const isCurrent = kp === current;
    const layer = el("g", { class: isCurrent ? "kp current" : "kp dim", "data-kp": kp }, g);
    const geo = geometry[kp] || { views: {}, epipolar: {} };
    const lab = labelOf(view.cam, kp);
    const rp = geo.views[view.cam] ? geo.views[view.cam].reproj : null;
    if (isCurrent && geo.epipolar && geo.epipolar[view.cam] && geo.epipolar[view.cam].length > 1) {
      el("polyline", { class: "epipolar", stroke: col, "data-keypoint": kp,
                       points: geo.epipolar[view.cam].map((p) => p.join(",")).join(" ") }, layer);
    }
    const sug = suggestions[kp] && suggestions[kp][view.cam];
    if (sug && !lab) {
      el("circle", { class: "suggestion-halo", cx: sug.u, cy: sug.v, r: 7 * s }, layer);
      titled(el("circle", { class: "suggestion", cx: sug.u, cy: sug.v, r: 7 * s, stroke: col, "data-keypoint": kp,
                            "data-kind": "suggestion", "data-draggable": "1" }, layer),
             `${kp}: the run's suggestion (confidence ${(+sug.confidence).toFixed(2)})`);
    }
    let at = lab && lab.visible && lab.u !== null ? [lab.u, lab.v] : null;
    if (preview && preview.kp === kp) at = preview.uv;
    if (rp) {
      if (at) el("line", { class: "residual-line", x1: at[0], y1: at[1], x2: rp[0], y2: rp[1] }, layer);
      const r = 5 * s;
      const rot = `rotate(45 ${rp[0]} ${rp[1]})`;
      el("rect", { class: "reproj-halo", x: rp[0] - r, y: rp[1] - r, width: 2 * r, height: 2 * r, transform: rot },
         layer);
      titled(el("rect", { class: "reproj", x: rp[0] - r, y: rp[1] - r, width: 2 * r, height: 2 * r, stroke: col,
                          transform: rot, "data-keypoint": kp, "data-kind": "reproj",
                          "data-draggable": at ? "0" : "1" }, layer), `${kp}: reprojection of its 3D point`);
    }
    if (at) {
      const mark = el("g", { class: "label", "data-keypoint": kp, "data-kind": "label", "data-draggable": "1" }, layer);
      titled(mark, `${kp}: label`);
      el("circle", { class: "marker", cx: at[0], cy: at[1], r: 5 * s, fill: "none", stroke: "#fff" }, mark);
      el("circle", { class: "marker-core", cx: at[0], cy: at[1], r: 2.5 * s, fill: col, stroke: "#000" }, mark);
      el("circle", { cx: at[0], cy: at[1], r: 11 * s, fill: "transparent" }, mark);  // easier to grab
    } else if (lab && !lab.visible) {
      const [W] = app.meta.image_size;
      const r = 6 * s;
      const x = 8 * s + (k % 8) * 16 * s;
      const y = 8 * s;
      const mark = el("g", { class: "occluded", "data-keypoint": kp, "data-kind": "occluded", stroke: col }, layer);
      titled(mark, `${kp}: not visible in this view`);
      el("line", { x1: x - r, y1: y - r, x2: x + r, y2: y + r }, mark);
      el("line", { x1: x - r, y1: y + r, x2: x + r, y2: y - r }, mark);
      void W;
    }
  }
  showResidual(view, geometry[current], labelOf(view.cam, current));
}

// the current keypoint's residual in the view's bar, coloured as the server judged it: green (ok) up to a few
// times the camera's median residual over the labelled frames, amber (high) above, red (disagrees) when the
// label lies farther than the threshold from where the other views put it
function showResidual(view, geo, lab) {
  const out = view.div.querySelector(".residual");
  const v = geo && geo.views[view.cam] ? geo.views[view.cam] : {};
  const res = v.residual === undefined ? null : v.residual;
  const rule = (app.frame && app.frame.agreement) || {};
  const cam = (rule.cameras || {})[view.cam] || {};
  out.className = "residual";
  out.removeAttribute("data-level");
  let text = "";
  let title = "residual: pixels between the label and the reprojection of the 3D point";
  if (lab && !lab.visible) text = "not visible";
  else if (res !== null) {
    text = `${res.toFixed(2)} px`;
    if (v.level) {
      out.classList.add(v.level);
      out.dataset.level = v.level;
    }
    const median = cam.median_px === null || cam.median_px === undefined ? "none yet" : `${cam.median_px.toFixed(2)} px`;
    title += `; green up to ${rule.green_factor} x this camera's median residual over the labelled frames ` +
      `(${median}; at least up to ${rule.green_floor_px} px), amber above`;
    if (v.offset !== null && v.offset !== undefined) {
      title += `; ${v.offset.toFixed(1)} px from where the other views put it (red beyond ${rule.threshold_px} px)`;
    }
    if (v.level === "disagrees") text += ` \u00b7 ${v.offset.toFixed(1)} px from the others`;
  }
  out.textContent = text;
  out.title = title;
}

function drawAll() { for (const view of Object.values(app.views)) drawView(view); drawKeypointList(); }

function drawKeypointList() {
  const list = document.getElementById("keypoints");
  list.innerHTML = "";
  app.meta.keypoints.forEach((kp, k) => {
    const li = document.createElement("li");
    li.dataset.keypoint = kp;
    if (k === app.kp) li.classList.add("current");
    const n = app.frame ? app.frame.labels.filter((l) => l.keypoint === kp && l.visible).length : 0;
    const point = app.frame && app.frame.geometry[kp] && app.frame.geometry[kp].point;
    li.innerHTML = `<span class="swatch"></span><span class="name"></span><span class="state"></span>`;
    li.querySelector(".swatch").style.background = colour(k, app.meta.keypoints.length);
    li.querySelector(".name").textContent = kp;
    li.querySelector(".state").textContent = `${n} view${n === 1 ? "" : "s"}${point ? ", 3D" : ""}`;
    li.addEventListener("click", () => selectKeypoint(k));
    list.appendChild(li);
  });
}

function selectKeypoint(k, redraw = true) {
  const n = app.meta.keypoints.length;
  app.kp = ((k % n) + n) % n;
  if (redraw) drawAll();
}

// ---- frames and saving ---------------------------------------------------------------------------------

function showFrame(state) {
  if (app.frame && app.frame.frame !== state.frame) app.unlocked.clear();  // a test frame locks when left
  app.frame = state;
  app.visited.add(state.frame);
  app.versions[state.frame] = state.version;
  const f = state.frame;
  for (const view of Object.values(app.views)) {
    const src = `api/frame/${f}/image/${encodeURIComponent(view.cam)}`;
    if (view.image.getAttribute("href") !== src) view.image.setAttribute("href", src);
  }
  document.getElementById("frame-input").value = f;
  document.getElementById("frame-info").textContent = `${state.split}, version ${state.version} ` +
    `(${app.frameIndex + 1} of ${app.frames.length})`;
  document.body.dataset.frame = f;
  document.body.dataset.version = state.version;
  drawAll();
  showLock();
  markRanking();
  markDisagreements();
  // a queued frame that has been labelled leaves the queue: the list is fetched again without it
  if (state.split !== "unlabelled" && app.ranking.some((r) => r.queue !== undefined && r.frame === f)) loadRanking();
}

function markRanking() {  // the current frame's entry of the ranking: highlighted and scrolled into sight
  const f = app.frame ? app.frame.frame : null;
  const list = document.getElementById("ranking");
  for (const li of list.querySelectorAll("li")) {
    const on = +li.dataset.frame === f;
    li.classList.toggle("current", on);
    if (!on) continue;
    // the list's own scroll only: the sidebar and the page stay where the user left them
    const outer = list.getBoundingClientRect();
    const inner = li.getBoundingClientRect();
    if (inner.top < outer.top) list.scrollTop -= outer.top - inner.top;
    else if (inner.bottom > outer.bottom) list.scrollTop += inner.bottom - outer.bottom;
  }
}

async function loadFrame(index) {
  if (!app.frames.length) return;
  app.frameIndex = Math.min(Math.max(index, 0), app.frames.length - 1);
  const f = app.frames[app.frameIndex].frame;
  app.loading += 1;
  let r;
  try {
    await app.queue;
    r = await api(`api/frame/${f}`);
  } finally {
    app.loading -= 1;
  }
  // keys pressed in quick succession load several frames at once and their answers may come back in any
  // order: only the frame navigated to last is shown (an earlier answer arriving late would put the next
  // clicks on the wrong frame)
  if (app.frames[app.frameIndex].frame !== f) return;
  if (!r.ok) { setStatus(r.body ? r.body.detail : `error ${r.status}`, "error"); return; }
  showFrame(r.body);
  if (!app.pending) setStatus(`frame ${f}`, "");
}

function isLocked() {
  return !!app.frame && app.frame.split === "test" && !app.unlocked.has(app.frame.frame);
}

function refuseLocked() {
  setStatus(`frame ${app.frame.frame} is a test frame: read-only (its labels are held out for evaluation); ` +
            "press unlock to edit it", "error");
}

function saveEdits(edits, source, note = "") {
  if (!app.frame) return Promise.resolve();
  if (isLocked()) { refuseLocked(); return Promise.resolve(); }
  // optimistic display; the server's answer replaces it
  for (const e of edits) {
    app.frame.labels = app.frame.labels.filter((l) => !(l.camera === e.camera && l.keypoint === e.keypoint));
    if (!e.remove) app.frame.labels.push({ camera: e.camera, keypoint: e.keypoint, u: e.u ?? null, v: e.v ?? null, visible: e.visible });
  }
  drawAll();
  app.pending += 1;
  setStatus("saving", "pending");
  const frame = app.frame.frame;
  const unlock = app.unlocked.has(frame);
  app.queue = app.queue.then(async () => {
    const version = app.versions[frame];
    const r = await api(`api/frame/${frame}/label`, { method: "POST",
      body: JSON.stringify({ version, edits, source, unlock }) });
    app.pending -= 1;
    if (r.status === 409) {
      app.versions[frame] = r.body.current.version;
      if (app.frame.frame === frame) showFrame(r.body.current);
      setStatus(`not saved: ${r.body.detail}; showing the newer labels`, "error");
      return;
    }
    if (!r.ok) {
      const detail = r.body && typeof r.body.detail === "string" ? r.body.detail : `HTTP ${r.status}`;
      setStatus(`not saved: ${detail}`, "error");
      if (app.frame.frame === frame) await loadFrame(app.frameIndex);
      return;
    }
    app.versions[frame] = r.body.version;
    if (app.frame.frame === frame) showFrame(r.body);
    loadDisagreements();
    const entry = app.frames.find((x) => x.frame === frame);
    if (entry) { entry.split = r.body.split; entry.labels = r.body.labels.filter((l) => l.visible).length; }
    if (!app.pending) setStatus(`saved (frame ${frame}, version ${r.body.version})${note}`, "saved");
  });
  return app.queue;
}

// Ctrl+Z: the frame's latest edit not yet undone; Ctrl+Shift+Z or Ctrl+Y: the latest undo not yet redone
// (both from the label history, on the server)
function undo() { return step("undo", "undoing", "undone"); }
function redo() { return step("redo", "redoing", "redone"); }

function step(kind, doing, done) {
  if (!app.frame) return Promise.resolve();
  if (isLocked()) { refuseLocked(); return Promise.resolve(); }
  const frame = app.frame.frame;
  const unlock = app.unlocked.has(frame);
  app.pending += 1;
  setStatus(doing, "pending");
  app.queue = app.queue.then(async () => {
    const r = await api(`api/frame/${frame}/${kind}`, { method: "POST",
      body: JSON.stringify({ version: app.versions[frame], unlock }) });
    app.pending -= 1;
    const body = r.body || {};
    if (r.status === 409) {
      app.versions[frame] = body.current.version;
      if (app.frame.frame === frame) showFrame(body.current);
      setStatus(`not ${done}: ${body.detail}; showing the newer labels`, "error");
      return;
    }
    if (!r.ok) { setStatus(`not ${done}: ${typeof body.detail === "string" ? body.detail : r.status}`, "error"); return; }
    app.versions[frame] = body.version;
    if (app.frame.frame === frame) showFrame(body);
    loadDisagreements();
    if (!app.pending) setStatus(`${done} (frame ${frame}, version ${body.version})`, "saved");
  });
  return app.queue;
}

function toggleLock() {  // unlock the test frame shown, or lock it again
  if (!app.frame) return;
  const f = app.frame.frame;
  if (isLocked()) {
    app.unlocked.add(f);
    setStatus(`frame ${f} unlocked: edits to this test frame are saved until you lock it or leave it`, "");
  } else {
    app.unlocked.delete(f);
    setStatus(`frame ${f} locked again: read-only`, "");
  }
  showLock();
}

function showLock() {
  const button = document.getElementById("unlock");
  const test = !!app.frame && app.frame.split === "test";
  button.hidden = !test;
  button.textContent = isLocked() ? "unlock test frame" : "lock test frame";
  button.classList.toggle("unlocked", test && !isLocked());
  document.body.dataset.locked = isLocked() ? "1" : "0";
}

function markOccluded(cam) {
  const kp = app.meta.keypoints[app.kp];
  return saveEdits([{ camera: cam, keypoint: kp, visible: false }], "not visible");
}

function removeLabel(cam) {
  const kp = app.meta.keypoints[app.kp];
  if (!labelOf(cam, kp)) return Promise.resolve();
  return saveEdits([{ camera: cam, keypoint: kp, remove: true }], "remove");
}

function acceptSuggestions(all) {
  if (!app.frame) return Promise.resolve();
  const sug = app.frame.suggestions || {};
  const kps = all ? app.meta.keypoints : [app.meta.keypoints[app.kp]];
  const edits = [];
  const unsure = [];  // views without a label where the run is not confident
  let offered = 0;
  for (const kp of kps) {
    for (const [cam, s] of Object.entries(sug[kp] || {})) {
      const [W, H] = app.meta.image_size;
      if (labelOf(cam, kp) || s.u < -0.5 || s.v < -0.5 || s.u > W - 0.5 || s.v > H - 0.5) continue;
      offered += 1;
      if (!(s.confidence >= CONFIDENT)) {  // not confident in this view: the part may be hidden there
        unsure.push(`${kp} in ${cam}: ${(+s.confidence).toFixed(2)}`);
        continue;
      }
      edits.push({ camera: cam, keypoint: kp, u: s.u, v: s.v, visible: true });
    }
  }
  const which = all ? "any keypoint" : `keypoint ${kps[0]}`;
  const listed = unsure.slice(0, 4).join(", ") + (unsure.length > 4 ? `, ${unsure.length - 4} more` : "");
  const below = `the run's confidence is below ${CONFIDENT} (${listed})`;
  if (edits.length) return saveEdits(edits, "accept", unsure.length ? `; not accepted where ${below}` : "");
  if (isLocked()) refuseLocked();
  else if (offered) setStatus(`nothing accepted: in every view without a label of ${which}, ${below}; ` +
                              "place those by hand", "note");
  else setStatus(`nothing to accept: the run suggests no unlabelled view of ${which} in this frame`, "note");
  return Promise.resolve();
}

async function loadRanking() {  // the frames s3k add-frames queued first (by rank), then the run's ranking
  const by = app.run ? document.getElementById("rank-by").value : "doubt";
  const r = await api(`api/ranking?split=unlabelled&limit=200&by=${by}`);
  if (!r.ok) return;
  app.ranking = r.body;
  const list = document.getElementById("ranking");
  list.innerHTML = "";
  const fixed = (x, unit) => (x === null ? "-" : `${x.toFixed(unit === "mm" ? 1 : 2)}${unit ? " " + unit : ""}`);
  r.body.forEach((row, i) => {
    const li = document.createElement("li");
    li.dataset.frame = row.frame;
    li.innerHTML = `<span class="rank"></span><span class="entry"></span>`;
    li.querySelector(".rank").textContent = `${i + 1}.`;
    const entry = li.querySelector(".entry");
    if (row.queue !== undefined) {  // queued by s3k add-frames: the tracker's doubt
      li.classList.add("queued");
      entry.textContent = `frame ${row.frame}: ${fixed(row.doubt, "")} queued`;
      li.title = `queued by s3k add-frames (rank ${row.queue}` +
        (row.video_frame === null ? "" : `, video frame ${row.video_frame}`) +
        (row.source ? ` of ${row.source}` : "") + "): the tracker's doubt";
    } else if (by === "coverage" || by === "representative") {
      // greedy: each frame above counts as labelled, so labelling down the list covers the poses in turn
      entry.textContent = `frame ${row.frame}: ${fixed(row.pose_mm, "mm")}`;
      li.title = "distance of the run's 3D keypoints from the nearest labelled pose (and from the frames above)";
    } else {
      entry.textContent = `frame ${row.frame}: ${fixed(row.score, "")}`;
      li.title = `residual ${fixed(row.residual_px, "px")}, worst view ${fixed(row.worst_view_px, "px")}, ` +
        `confidence ${row.confidence.toFixed(2)}`;
    }
    li.addEventListener("click", () => gotoFrame(row.frame));
    list.appendChild(li);
  });
  document.getElementById("ranking-box").hidden = false;
  markRanking();
}

// the frames with a label farther than the threshold from where the other views put it (the server's check),
// worst first; a click opens the frame at the keypoint of its worst label
async function loadDisagreements() {
  const r = await api("api/disagreements");
  if (!r.ok) return;
  const found = r.body;
  const list = document.getElementById("disagreements");
  list.innerHTML = "";
  for (const row of found.frames) {
    const worst = row.labels[0];
    const li = document.createElement("li");
    li.dataset.frame = row.frame;
    li.dataset.keypoint = worst.keypoint;
    li.dataset.camera = worst.camera;
    const more = row.labels.length > 1 ? `, ${row.labels.length - 1} more` : "";
    li.textContent = `frame ${row.frame}: ${worst.keypoint} in ${worst.camera}, ${worst.offset_px.toFixed(1)} px${more}`;
    li.title = row.labels.map((l) => `${l.keypoint} in ${l.camera}: ${l.offset_px.toFixed(1)} px from the other views`).join("\n");
    li.addEventListener("click", async () => {
      await gotoFrame(row.frame);
      selectKeypoint(app.meta.keypoints.indexOf(worst.keypoint));
    });
    list.appendChild(li);
  }
  document.getElementById("disagree-count").textContent = `(${found.frames.length})`;
  document.getElementById("disagree-rule").textContent = `frames with a label more than ${found.threshold_px} px ` +
    "from where the other views put it (two or more of them), worst first";
  document.getElementById("disagree-empty").hidden = found.frames.length > 0;
  markDisagreements();
  document.body.dataset.disagreements = found.frames.length;
}

function markDisagreements() {  // the current frame's entry highlighted
  const f = app.frame ? app.frame.frame : null;
  for (const li of document.querySelectorAll("#disagreements li")) li.classList.toggle("current", +li.dataset.frame === f);
}

function gotoFrame(f) {
  const i = app.frames.findIndex((x) => x.frame === +f);
  if (i >= 0) return loadFrame(i);
  setStatus(`no frame ${f}`, "error");
  return Promise.resolve();
}

function nextRanked() {  // n: the best-placed frame of the ranking (worst first) not yet opened in this page
  if (!app.ranking.length) return Promise.resolve();
  const cur = app.frame ? app.frame.frame : null;
  let row = app.ranking.find((r) => r.frame !== cur && !app.visited.has(r.frame));
  let note = "";
  if (!row) {  // every frame of the list seen: start again from the top
    app.visited = new Set(cur === null ? [] : [cur]);
    row = app.ranking.find((r) => r.frame !== cur);
    note = "every frame of the list has been opened: n starts again from the top";
  }
  if (!row) return Promise.resolve();
  return gotoFrame(row.frame).then(() => { if (note) setStatus(note, "note"); });
}

// ---- propagation and skeleton ---------------------------------------------------------------------------

function detailOf(r) { return r.body && typeof r.body.detail === "string" ? r.body.detail : `HTTP ${r.status}`; }

async function propagate(preview) {  // the form's "preview" (nothing written) and "copy"
  if (!app.frame) return;
  const value = (id) => document.getElementById(id).value;
  const body = { first: +value("prop-first"), last: +value("prop-last"), source: app.frame.frame,
                 max_changed: +value("prop-max"), overwrite: document.getElementById("prop-overwrite").checked,
                 allow_test: document.getElementById("prop-test").checked, dry_run: preview };
  await app.queue;
  const r = await api("api/propagate", { method: "POST", body: JSON.stringify(body) });
  const out = document.getElementById("prop-result");
  if (!r.ok) { out.textContent = ""; setStatus(`not propagated: ${detailOf(r)}`, "error"); return; }
  const p = r.body;
  out.textContent = Object.entries(p.per_frame)
    .map(([f, [fresh, old]]) => `frame ${f}: ${fresh} new label(s)${old ? `, ${old} replaced` : ""}`).join("\n");
  const what = `frame ${p.source}'s ${p.keypoints.length} keypoint(s) to ${p.frames.length} frame(s): ` +
    `${p.labels} label(s)${p.replaced ? `, ${p.replaced} of them replacing existing ones` : ""}`;
  if (preview) { setStatus(`preview: would copy ${what}; nothing was written`, "note"); return; }
  await loadFrame(app.frameIndex);  // the frame's labels, versions of the frames written
  loadDisagreements();
  setStatus(`copied ${what}; 'undo last propagation' puts them back`, "saved");
}

async function undoPropagation() {
  await app.queue;
  const r = await api("api/propagate/undo", { method: "POST", body: "{}" });
  if (!r.ok) { setStatus(`nothing undone: ${detailOf(r)}`, "error"); return; }
  document.getElementById("prop-result").textContent = "";
  await loadFrame(app.frameIndex);
  loadDisagreements();
  setStatus(`undid the propagation from frame ${r.body.source}: frame(s) ${r.body.frames.join(", ")}`, "saved");
}

function startSkeleton() {
  for (const id of ["edge-a", "edge-b"]) {
    const select = document.getElementById(id);
    for (const kp of app.meta.keypoints) select.appendChild(new Option(kp, kp));
  }
  document.getElementById("edge-b").selectedIndex = Math.min(1, app.meta.keypoints.length - 1);
  document.getElementById("skeleton-add").addEventListener("submit", (ev) => {
    ev.preventDefault();
    editSkeleton({ add: [document.getElementById("edge-a").value, document.getElementById("edge-b").value] });
  });
  drawSkeletonList();
}

function drawSkeletonList() {
  const list = document.getElementById("skeleton");
  list.innerHTML = "";
  for (const [a, b] of app.meta.skeleton) {
    const li = document.createElement("li");
    li.dataset.edge = `${a}-${b}`;
    li.innerHTML = `<span class="edge"></span><button type="button" title="remove this edge">remove</button>`;
    li.querySelector(".edge").textContent = `${a} \u2013 ${b}`;
    li.querySelector("button").addEventListener("click", () => editSkeleton({ remove: [a, b] }));
    list.appendChild(li);
  }
  document.getElementById("skeleton-empty").hidden = app.meta.skeleton.length > 0;
}

async function editSkeleton(change) {  // written to the dataset's s3k.json by the server
  await app.queue;
  const r = await api("api/skeleton", { method: "POST", body: JSON.stringify(change) });
  if (!r.ok) { setStatus(`skeleton not changed: ${detailOf(r)}`, "error"); return; }
  app.meta.skeleton = r.body.skeleton;
  drawSkeletonList();
  drawAll();
  const [a, b] = change.add || change.remove;
  setStatus(`skeleton saved: edge ${a} \u2013 ${b} ${change.add ? "added" : "removed"}`, "saved");
}

// ---- start ---------------------------------------------------------------------------------------------

function onKey(ev) {
  if (["INPUT", "SELECT", "TEXTAREA"].includes(ev.target.tagName)) return;
  const k = ev.key;
  const mod = (ev.ctrlKey || ev.metaKey) && !ev.altKey;
  if (mod && (((k === "z" || k === "Z") && ev.shiftKey) || k === "y" || k === "Y")) redo();
  else if (mod && (k === "z" || k === "Z")) undo();
  else if (ev.ctrlKey || ev.metaKey || ev.altKey) return;  // the browser's own shortcuts
  else if (k === "ArrowRight" || k === ".") loadFrame(app.frameIndex + 1);
  else if (k === "ArrowLeft" || k === ",") loadFrame(app.frameIndex - 1);
  else if (k === "ArrowDown" || (k === "Tab" && !ev.shiftKey)) selectKeypoint(app.kp + 1);
  else if (k === "ArrowUp" || (k === "Tab" && ev.shiftKey)) selectKeypoint(app.kp - 1);
  else if (k === "x" && app.hover) markOccluded(app.hover);
  else if ((k === "Delete" || k === "Backspace") && app.hover) removeLabel(app.hover);
  else if (k === "a") acceptSuggestions(false);
  else if (k === "A") acceptSuggestions(true);
  else if (k === "n") nextRanked();
  else if (k === "0") resetZoom();
  else return;
  ev.preventDefault();
}

async function start() {
  const r = await api("api/meta");
  if (!r.ok) { setStatus(r.body ? r.body.detail : `error ${r.status}`, "error"); return; }
  app.meta = r.body;
  app.frames = r.body.frames;
  document.getElementById("dataset").textContent = r.body.path;
  document.getElementById("dataset").title = r.body.path;
  buildViews();
  document.getElementById("prev-frame").addEventListener("click", () => loadFrame(app.frameIndex - 1));
  document.getElementById("next-frame").addEventListener("click", () => loadFrame(app.frameIndex + 1));
  document.getElementById("frame-input").addEventListener("change", (ev) => gotoFrame(ev.target.value));
  document.getElementById("reset-zoom").addEventListener("click", resetZoom);
  document.getElementById("unlock").addEventListener("click", toggleLock);
  document.getElementById("brightness").addEventListener("input", (ev) => {
    app.brightness = +ev.target.value;
    for (const view of Object.values(app.views)) view.image.style.filter = `brightness(${app.brightness})`;
  });
  document.getElementById("accept-one").addEventListener("click", () => acceptSuggestions(false));
  document.getElementById("accept-all").addEventListener("click", () => acceptSuggestions(true));
  document.getElementById("propagate").addEventListener("submit", (ev) => { ev.preventDefault(); propagate(false); });
  document.getElementById("prop-preview").addEventListener("click", () => propagate(true));
  document.getElementById("prop-undo").addEventListener("click", undoPropagation);
  startSkeleton();
  window.addEventListener("keydown", onKey);
  window.addEventListener("resize", () => { layoutViews(); drawAll(); });
  app.run = r.body.run;
  if (app.run) {
    document.getElementById("suggest-tools").hidden = false;
    document.getElementById("rank-by").addEventListener("change", loadRanking);
  }
  document.getElementById("rank-by-label").hidden = !app.run;  // without a run the list is the queue alone
  loadRanking();  // without a run and a queue: none (404), the list stays hidden
  loadDisagreements();
  const want = new URLSearchParams(location.search).get("frame");
  const i = want === null ? 0 : Math.max(0, app.frames.findIndex((x) => x.frame === +want));
  await loadFrame(i);
  document.body.dataset.ready = "1";
}

window.s3kLabel = { app, toClient, saveEdits, loadFrame, gotoFrame, undo, redo, colour };
start();
