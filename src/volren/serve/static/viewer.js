// volren viewer page: one WebSocket per page (docs/SERVE.md). The page owns its camera (orbit, or walk in fog
// scenes), sends it with an increasing id, and draws each JPEG frame the server answers with; the frame's camera_id
// gives the round-trip latency. Each frame drawn is acknowledged ({type: "ack", tick}): the server sends the next
// one only then, so no frame waits in a socket buffer. No build step, no dependencies.
"use strict";

const $ = (id) => document.getElementById(id);
const canvas = $("view");
const ctx = canvas.getContext("2d");
const overlay = $("overlay");
const statusLine = $("status");
const SEND_INTERVAL_MS = 16; // camera and light messages at most ~60 per second (latest wins on the server anyway)

// State the page shows, also read by tests/test_browser.py.
const state = (window.volren = {
  connected: false, welcome: null, frames: 0, lastHeader: null, latencies: [], errors: [],
  fps: 0, cameraId: 0, lastCamera: null, shownCameraId: -1, shownStereo: false, stereo: false, playing: true, walk: false,
});

// ---- camera: orbit about a target, or walk (eye fixed, look around) --------------------------------------------
const cam = { target: [0, 0, 0], radius: 3, yaw: 0, pitch: 0, eye: [0, 0, 3], up: [0, 1, 0], fov: 45 };
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const clamp = (x, lo, hi) => Math.min(hi, Math.max(lo, x));
const PITCH_LIMIT = 1.5; // rad, short of the poles where look-at with up = +y degenerates
const WALK_SPEED = 2.0; // [m/s] a brisk walk (fog scenes are in metres)

function direction() { // unit vector from the eye towards where it looks
  const c = Math.cos(cam.pitch);
  return [-c * Math.sin(cam.yaw), -Math.sin(cam.pitch), -c * Math.cos(cam.yaw)];
}

function setCamera(c) {
  cam.up = c.up || [0, 1, 0];
  cam.fov = c.fov || 45;
  const d = sub(c.position, c.look_at);
  cam.radius = Math.max(norm(d), 1e-3);
  cam.yaw = Math.atan2(d[0], d[2]);
  cam.pitch = Math.asin(clamp(d[1] / cam.radius, -1, 1));
  cam.target = c.look_at.slice();
  cam.eye = c.position.slice();
}

function cameraMessage() {
  const dir = direction();
  const position = state.walk ? cam.eye : sub(cam.target, scale(dir, cam.radius));
  const lookAt = state.walk ? add(cam.eye, dir) : cam.target;
  state.lastCamera = { type: "camera", id: ++state.cameraId, position, look_at: lookAt, up: cam.up, fov: cam.fov };
  return state.lastCamera;
}

// ---- socket --------------------------------------------------------------------------------------------------------
// Opened as /?token=T, the page got the server's token cookie (HttpOnly, SameSite=Strict) with it: the browser sends
// that with the page's files, this socket's handshake and later loads. So the token leaves the address bar (history,
// bookmarks, copied links, screen shares) at once, other query parameters and the hash kept, and the socket's URL
// carries none (docs/SERVE.md, "token").
const params = new URLSearchParams(location.search);
if (params.has("token")) {
  params.delete("token");
  const query = params.toString();
  history.replaceState(history.state, "", location.pathname + (query ? `?${query}` : "") + location.hash);
}
const wsUrl = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`;
const ws = new WebSocket(wsUrl);
ws.binaryType = "arraybuffer";
const sentAt = new Map(); // camera id -> performance.now() when sent

function send(msg) {
  if (ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(msg));
}

// Throttled senders: the newest value is sent at most every SEND_INTERVAL_MS.
function throttled(build) {
  let timer = null, last = 0;
  const schedule = () => {
    if (timer !== null) return;
    schedule.pending = true;
    timer = setTimeout(() => {
      timer = null; last = performance.now();
      schedule.pending = false;
      const msg = build();
      if (msg.type === "camera") sentAt.set(msg.id, performance.now());
      send(msg);
    }, Math.max(0, SEND_INTERVAL_MS - (performance.now() - last)));
  };
  schedule.pending = false; // a newer value waits to be sent
  return schedule;
}
const sendCamera = throttled(cameraMessage);
Object.defineProperty(state, "cameraPending", { get: () => sendCamera.pending });

function canvasSize() {
  const r = canvas.getBoundingClientRect();
  return { width: Math.max(1, Math.round(r.width)), height: Math.max(1, Math.round(r.height)) };
}

ws.addEventListener("open", () => {
  state.connected = true;
  send({ type: "hello", ...canvasSize(), stereo: state.stereo });
});
ws.addEventListener("close", (e) => {
  state.connected = false;
  showStatus(`disconnected (${e.code}${e.reason ? ": " + e.reason : ""})`, 0);
});
ws.addEventListener("message", (e) => {
  if (typeof e.data === "string") onText(JSON.parse(e.data));
  else onFrame(e.data);
});

function onText(msg) {
  if (msg.type === "welcome") {
    state.welcome = msg;
    $("scene").textContent = msg.scene;
    fill($("method"), msg.methods, msg.method);
    fill($("quality"), msg.qualities, msg.quality);
    fill($("tf"), msg.tfs, msg.tf);
    setMode(msg);
    state.walk = msg.walk ?? msg.method === "fog";
    setCamera(msg.camera);
    if (msg.light_dir) setLight(msg.light_dir);
    if (typeof msg.playing === "boolean") setPlaying(msg.playing);
    $("play").disabled = msg.animated === false;
    if (typeof msg.stereo === "boolean") $("stereo").checked = state.stereo = msg.stereo;
    if (msg.locked) { // the operator locked the shared settings (--lock-settings)
      for (const id of ["method", "quality", "tf", "mode", "iso_value", "play"]) $(id).disabled = true;
      pad.style.pointerEvents = "none";
    }
    sendCamera();
  } else if (msg.type === "settings") { // another viewer switched a shared setting
    if (msg.method) $("method").value = msg.method;
    if (msg.quality) $("quality").value = msg.quality;
    if (msg.tf) $("tf").value = msg.tf;
    setMode(msg);
    if (msg.light_dir) setLight(msg.light_dir);
    if (typeof msg.playing === "boolean") setPlaying(msg.playing);
  } else if (msg.type === "error") {
    state.errors.push(msg.message);
    showStatus(msg.message, 4000);
  } else if (msg.type === "notice") { // a server event (a render shard lost): shown until the next one
    showStatus(msg.message, 0);
  }
}

function fill(select, values, current) {
  select.replaceChildren(...(values || []).map((v) => new Option(v, v)));
  select.disabled = !values || values.length < 2;
  if (current) select.value = current;
}

let frameTimes = [];
let drawing = false; // decode at most one frame at a time; a newer frame replaces a waiting one
let waiting = null;

function onFrame(buf) {
  const n = new DataView(buf).getUint32(0, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
  const now = performance.now();
  const t = sentAt.get(header.camera_id);
  if (t !== undefined) { // first frame answering this camera: its round trip
    state.latencies.push(now - t);
    if (state.latencies.length > 60) state.latencies.shift();
    for (const id of sentAt.keys()) if (id <= header.camera_id) sentAt.delete(id);
  }
  frameTimes.push(now);
  frameTimes = frameTimes.filter((x) => now - x < 1000);
  state.fps = frameTimes.length;
  state.lastHeader = header;
  waiting = { header, blob: new Blob([new Uint8Array(buf, 4 + n)], { type: "image/jpeg" }) };
  if (!drawing) drawNext();
  showOverlay(header);
}

async function drawNext() {
  drawing = true;
  while (waiting) {
    const { header, blob } = waiting;
    waiting = null;
    try {
      const img = await createImageBitmap(blob);
      if (canvas.width !== img.width || canvas.height !== img.height) {
        canvas.width = img.width; canvas.height = img.height;
      }
      ctx.drawImage(img, 0, 0);
      img.close();
      state.frames += 1;
      state.shownCameraId = header.camera_id; // the camera of the image on the canvas
      state.shownStereo = header.stereo;
    } catch (err) {
      showStatus(`could not decode a frame: ${err}`, 4000);
    }
    send({ type: "ack", tick: header.tick }); // drawn (or undecodable): the server may send the next
  }
  drawing = false;
}

function median(xs) {
  if (!xs.length) return NaN;
  const s = [...xs].sort((a, b) => a - b);
  return s[s.length >> 1];
}

function showOverlay(h) {
  const passes = Object.entries(h.pass_ms || {}).map(([k, v]) => `  ${k.padEnd(14)} ${v.toFixed(1)} ms`);
  overlay.textContent = [
    `${h.width}x${h.height}${h.stereo ? " stereo" : ""}  ${state.fps} fps  viewers ${h.viewers}  tick ${h.tick}`,
    `latency ${median(state.latencies).toFixed(0)} ms (median of ${state.latencies.length})`,
    `render ${h.render_ms.toFixed(1)} ms`, ...passes,
  ].join("\n");
}

let statusTimer = null;
function showStatus(text, ms) {
  statusLine.textContent = text;
  clearTimeout(statusTimer);
  if (ms) statusTimer = setTimeout(() => (statusLine.textContent = ""), ms);
}

// ---- mouse: orbit / look, wheel: zoom ------------------------------------------------------------------------------
let drag = null;
canvas.addEventListener("pointerdown", (e) => {
  drag = { x: e.clientX, y: e.clientY };
  canvas.setPointerCapture(e.pointerId);
  canvas.classList.add("dragging");
  canvas.focus();
});
canvas.addEventListener("pointermove", (e) => {
  if (!drag) return;
  const k = 0.01; // rad per CSS pixel
  const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
  drag = { x: e.clientX, y: e.clientY };
  // Orbit: the scene follows the hand (drag right turns it right, drag down shows its top); walk: the gaze does.
  cam.yaw -= dx * k;
  cam.pitch = clamp(cam.pitch + dy * k, -PITCH_LIMIT, PITCH_LIMIT);
  sendCamera();
});
const endDrag = () => { drag = null; canvas.classList.remove("dragging"); };
canvas.addEventListener("pointerup", endDrag);
canvas.addEventListener("pointercancel", endDrag);
canvas.addEventListener("wheel", (e) => {
  e.preventDefault();
  if (state.walk) cam.eye = add(cam.eye, scale(direction(), -e.deltaY * 0.002 * WALK_SPEED));
  else cam.radius = clamp(cam.radius * Math.exp(e.deltaY * 0.001), 0.05, 1e4);
  sendCamera();
}, { passive: false });

// ---- keyboard: WASD walk (fog scenes), Q/E down/up -----------------------------------------------------------------
const held = new Set();
let walkTimer = null, walkLast = 0;
const WALK_KEYS = new Set(["w", "a", "s", "d", "q", "e"]);
window.addEventListener("keydown", (e) => {
  const k = e.key.toLowerCase();
  if (!state.walk || !WALK_KEYS.has(k) || e.target.tagName === "SELECT") return;
  held.add(k);
  if (walkTimer === null) { walkLast = performance.now(); walkTimer = setInterval(walkStep, 16); }
});
window.addEventListener("keyup", (e) => held.delete(e.key.toLowerCase()));
window.addEventListener("blur", () => held.clear());

function walkStep() {
  if (!held.size) { clearInterval(walkTimer); walkTimer = null; return; }
  const now = performance.now(), step = WALK_SPEED * (now - walkLast) / 1000;
  walkLast = now;
  const f = [-Math.sin(cam.yaw), 0, -Math.cos(cam.yaw)]; // forward on the ground plane
  const r = [-f[2], 0, f[0]];
  let m = [0, 0, 0];
  if (held.has("w")) m = add(m, f);
  if (held.has("s")) m = sub(m, f);
  if (held.has("d")) m = add(m, r);
  if (held.has("a")) m = sub(m, r);
  if (held.has("e")) m = add(m, [0, 1, 0]);
  if (held.has("q")) m = sub(m, [0, 1, 0]);
  const len = norm(m);
  if (len > 0) { cam.eye = add(cam.eye, scale(m, step / len)); sendCamera(); }
}

// ---- panel: shared settings ----------------------------------------------------------------------------------------
for (const key of ["method", "quality", "tf", "mode"]) {
  $(key).addEventListener("change", (e) => send({ type: "settings", [key]: e.target.value }));
}
$("mode").addEventListener("change", () => setMode({}));
$("iso_value").addEventListener("change", (e) => {
  const v = Number(e.target.value);
  if (Number.isFinite(v) && v > 0) send({ type: "settings", iso_value: v });
});
function setMode(msg) { // the sci-vis mode (dssrm/cmsrm/cacrm) and its iso value, shared by every viewer
  if (msg.mode) $("mode").value = msg.mode;
  if (typeof msg.iso_value === "number") $("iso_value").value = msg.iso_value;
  $("iso_value").disabled = $("mode").disabled || $("mode").value !== "iso";
}
$("stereo").addEventListener("change", (e) => {
  state.stereo = e.target.checked;
  send({ type: "settings", stereo: state.stereo });
});
function setPlaying(p) {
  state.playing = p;
  $("play").textContent = p ? "pause" : "play";
}
$("play").addEventListener("click", () => {
  setPlaying(!state.playing);
  send({ type: "settings", playing: state.playing });
});

// Light direction pad: the dot is the light's position on the upper hemisphere seen from above (x right, z down);
// the direction sent is the way the light travels, from there towards the scene.
const pad = $("light"), padCtx = pad.getContext("2d");
let lightUV = [0.5, 0.3];
function setLight(dir) {
  const n = norm(dir) || 1;
  lightUV = [-dir[0] / n, -dir[2] / n];
  drawPad();
}
function lightDir() {
  const [u, v] = lightUV;
  return [-u, -Math.sqrt(Math.max(0, 1 - u * u - v * v)), -v];
}
function drawPad() {
  const R = pad.width / 2;
  padCtx.clearRect(0, 0, pad.width, pad.height);
  padCtx.strokeStyle = "#555";
  padCtx.beginPath(); padCtx.arc(R, R, R - 1, 0, 2 * Math.PI); padCtx.stroke();
  padCtx.fillStyle = "#fd5";
  padCtx.beginPath(); padCtx.arc(R + lightUV[0] * (R - 6), R + lightUV[1] * (R - 6), 5, 0, 2 * Math.PI); padCtx.fill();
}
const sendLight = throttled(() => ({ type: "settings", light_dir: lightDir() }));
let padDrag = false;
function padMove(e) {
  const r = pad.getBoundingClientRect(), R = r.width / 2 - 6;
  let u = (e.clientX - r.left - r.width / 2) / R, v = (e.clientY - r.top - r.height / 2) / R;
  const len = Math.hypot(u, v);
  if (len > 0.999) { u *= 0.999 / len; v *= 0.999 / len; } // stay above the horizon
  lightUV = [u, v];
  drawPad();
  sendLight();
}
pad.addEventListener("pointerdown", (e) => { padDrag = true; pad.setPointerCapture(e.pointerId); padMove(e); });
pad.addEventListener("pointermove", (e) => padDrag && padMove(e));
pad.addEventListener("pointerup", () => (padDrag = false));
drawPad();

// ---- canvas size: sent on every change (the server clamps it) ------------------------------------------------------
let lastSize = null;
const sendResize = throttled(() => ({ type: "resize", ...canvasSize() }));
new ResizeObserver(() => {
  const s = canvasSize();
  if (lastSize && (s.width !== lastSize.width || s.height !== lastSize.height)) sendResize();
  lastSize = s;
}).observe(canvas);
