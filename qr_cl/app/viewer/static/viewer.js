"use strict";
// qr-cl view: camera controls, frame requests and drawing. Every frame is rendered by the server
// (qr-cl on the CPU) and sent as a JPEG; the page only draws it, so it needs no WebGL.
// While the camera moves, frames are requested at a scale that keeps the render near
// scene.camera.target_ms; SETTLE_MS after the last move the full frame is requested.
// The first view is the scene's overview; C / shift+C and the view buttons step through
// scene.camera.views (the overview, then the scene's own cameras) and round again.
// Initial state from the URL: ?mode=rgb|pca|classes|relevancy&q=TEXT&sampler=S&k=K&w=W&h=H&view=I.
// document.body.dataset holds frames (drawn), reduced (drawn below full size), the mode, full
// ("1" at full size) and view (the view's name, "" once the camera left it) of the last frame,
// and the last error.

const SETTLE_MS = 250;
const MIN_SCALE = 0.25;
const el = (id) => document.getElementById(id);
const canvas = el("view");
const ctx = canvas.getContext("2d");
const params = new URLSearchParams(location.search);
const state = { mode: "rgb", query: "", sampler: "quantile", k: 40 };
let scene = null;
let cam = null;
let viewIndex = 0;
let viewName = "";
let inflight = false;
let dirty = false;
let lastMove = -1e9;
let moveScale = 0.5;
let settleTimer = null;
let frames = 0;
let reduced = 0;
let drag = null;

const add = (a, b) => a.map((x, i) => x + b[i]);
const sub = (a, b) => a.map((x, i) => x - b[i]);
const mul = (a, s) => a.map((x) => x * s);
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.sqrt(dot(a, a));
const unit = (a) => mul(a, 1 / Math.max(norm(a), 1e-12));
const clamp = (x, lo, hi) => Math.min(hi, Math.max(lo, x));

function cameraAxes() {
  const forward = unit(sub(cam.target, cam.eye));
  const right = unit(cross(forward, cam.up));
  return { forward, right, up: cross(right, forward) };
}

function orbit(dx, dy) {
  const u = unit(cam.up);
  const a = unit(cross(u, Math.abs(u[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0]));
  const b = cross(u, a);
  const offset = sub(cam.eye, cam.target);
  const r = norm(offset);
  const azimuth = Math.atan2(dot(offset, b), dot(offset, a)) - dx * 0.008;
  const elevation = clamp(Math.asin(clamp(dot(offset, u) / r, -1, 1)) + dy * 0.008, -1.5, 1.5);
  const ring = add(mul(a, Math.cos(azimuth)), mul(b, Math.sin(azimuth)));
  cam.eye = add(cam.target, mul(add(mul(ring, Math.cos(elevation)), mul(u, Math.sin(elevation))), r));
}

function pan(dx, dy) {
  const { right, up } = cameraAxes();
  const s = norm(sub(cam.eye, cam.target)) * 0.0015;
  const shift = add(mul(right, -dx * s), mul(up, dy * s));
  cam.eye = add(cam.eye, shift);
  cam.target = add(cam.target, shift);
}

function zoom(delta) {
  const offset = sub(cam.eye, cam.target);
  const r = norm(offset);
  const radius = scene.camera.radius;
  cam.eye = add(cam.target, mul(offset, clamp(r * Math.exp(delta * 0.001), 0.01 * radius, 20 * radius) / r));
}

function fly(key) {
  const { forward, right, up } = cameraAxes();
  const moves = { w: forward, s: mul(forward, -1), d: right, a: mul(right, -1), e: up, q: mul(up, -1) };
  const shift = mul(moves[key], 0.04 * scene.camera.radius);
  cam.eye = add(cam.eye, shift);
  cam.target = add(cam.target, shift);
}

function selectView(index) {
  const views = scene.camera.views;
  viewIndex = ((index % views.length) + views.length) % views.length;
  const view = views[viewIndex];
  cam = { eye: view.eye, target: view.target, up: view.up, fov_y: view.fov_y };
  viewName = view.name;
  el("view-name").textContent = viewIndex === 0 ? view.name : `${view.name} (${viewIndex}/${views.length - 1})`;
}

function showView(index) {
  selectView(index);
  changed(false);
}

function changed(moving) {
  if (moving) {
    lastMove = performance.now();
    viewName = "";
  }
  dirty = true;
  request();
}

function settle() {
  clearTimeout(settleTimer);
  settleTimer = setTimeout(() => {
    if (performance.now() - lastMove >= SETTLE_MS) changed(false);
    else settle();
  }, SETTLE_MS);
}

function request() {
  if (inflight || !dirty || !scene) return;
  const moving = performance.now() - lastMove < SETTLE_MS;
  const scale = moving ? moveScale : 1;
  const width = Math.max(8, Math.round(canvas.width * scale));
  const height = Math.max(8, Math.round(canvas.height * scale));
  const mode = state.mode;
  const view = viewName;
  const query = new URLSearchParams({
    eye: cam.eye.join(","), target: cam.target.join(","), up: cam.up.join(","), fov_y: cam.fov_y,
    width, height, mode, query: state.query, sampler: state.sampler, k: state.k,
  });
  dirty = false;
  inflight = true;
  const started = performance.now();
  fetch("/api/frame?" + query).then(async (response) => {
    if (!response.ok) throw new Error((await response.json()).error);
    const renderMs = parseFloat(response.headers.get("X-Render-Ms"));
    const bitmap = await createImageBitmap(await response.blob());
    ctx.drawImage(bitmap, 0, 0, canvas.width, canvas.height);
    const fullMs = renderMs / (scale * scale);
    moveScale = clamp(Math.sqrt(scene.camera.target_ms / Math.max(fullMs, 1)), MIN_SCALE, 1);
    frames += 1;
    reduced += scale < 1 ? 1 : 0;
    el("time").textContent = `${width}x${height} · render ${renderMs.toFixed(0)} ms · ` +
      `frame ${(performance.now() - started).toFixed(0)} ms`;
    el("status").textContent = "";
    Object.assign(document.body.dataset, { frames, reduced, mode, view, full: scale === 1 ? "1" : "0",
      error: "" });
  }).catch((err) => {
    el("status").textContent = err.message;
    document.body.dataset.error = err.message;
  }).finally(() => {
    inflight = false;
    if (scale < 1) settle();
    request();
  });
}

function showLegend() {
  const legend = el("legend");
  legend.style.display = state.mode === "classes" && scene.legend.length ? "block" : "none";
  legend.replaceChildren(...scene.legend.map((entry) => {
    const row = document.createElement("div");
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.style.background = entry.colour;
    row.append(swatch, `${entry.name} (${entry.gaussians})`);
    return row;
  }));
}

function setMode(mode) {
  state.mode = mode;
  el("mode").value = mode;
  showLegend();
  changed(false);
}

function options(select, values, enabled) {
  select.replaceChildren(...values.map((value) => {
    const option = document.createElement("option");
    option.value = option.textContent = value;
    option.disabled = !enabled.includes(value);
    return option;
  }));
}

function bindControls() {
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("mousedown", (e) => {
    drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
    canvas.focus();
  });
  window.addEventListener("mouseup", () => { drag = null; });
  window.addEventListener("mousemove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x;
    const dy = e.clientY - drag.y;
    drag.x = e.clientX;
    drag.y = e.clientY;
    if (drag.pan) pan(dx, dy);
    else orbit(dx, dy);
    changed(true);
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    zoom(e.deltaY);
    changed(true);
  }, { passive: false });
  window.addEventListener("keydown", (e) => {
    const key = e.key.toLowerCase();
    if (["INPUT", "SELECT"].includes(e.target.tagName) || key.length !== 1 || e.ctrlKey || e.metaKey || e.altKey) {
      return;
    }
    if (key === "c") {
      showView(viewIndex + (e.shiftKey ? -1 : 1));
    } else if ("wasdqe".includes(key)) {
      fly(key);
      changed(true);
    }
  });
  el("next-view").addEventListener("click", () => showView(viewIndex + 1));
  el("prev-view").addEventListener("click", () => showView(viewIndex - 1));
  el("query").addEventListener("keydown", (e) => {
    if (e.key !== "Enter") return;
    state.query = el("query").value.trim();
    setMode("relevancy");
  });
  el("mode").addEventListener("change", (e) => setMode(e.target.value));
  el("sampler").addEventListener("change", (e) => { state.sampler = e.target.value; changed(false); });
  el("k").addEventListener("change", (e) => { state.k = parseInt(e.target.value, 10) || 1; changed(false); });
}

async function start() {
  scene = await (await fetch("/api/scene")).json();
  canvas.width = parseInt(params.get("w") || scene.camera.width, 10);
  canvas.height = parseInt(params.get("h") || scene.camera.height, 10);
  state.sampler = params.get("sampler") || scene.sampler;
  state.k = parseInt(params.get("k") || scene.k, 10);
  state.query = params.get("q") || "";
  el("name").textContent = `${scene.name} (${scene.gaussians.toLocaleString()} Gaussians)`;
  options(el("mode"), ["rgb", "pca", "classes", "relevancy"], scene.modes);
  options(el("sampler"), scene.samplers, scene.samplers);
  el("sampler").value = state.sampler;
  el("k").value = state.k;
  el("query").value = state.query;
  bindControls();
  selectView(parseInt(params.get("view") || "0", 10) || 0);
  setMode(params.get("mode") || "rgb");
}

start().catch((err) => {
  el("status").textContent = `could not reach the qr-cl viewer: ${err.message}`;
  document.body.dataset.error = err.message;
});
