// iwsim play: drive the world model from the browser.
// The page owns the command (the action: for T-push the pushers' targets) and sends it when
// it changes; the server applies the latest one at every control step and streams frames
// back. Frames are binary: uint32 header length, JSON header, then each view's RGB bytes.
// How keys, gamepad axes and mouse drags move the command's dimensions comes from the
// task's bindings in the server's hello (keys: {key: [dim, sign]}, axes: [[axis, dim,
// sign]], speed per dim, drag: [[x dim, y dim]] positions in the image); every dimension
// also has a slider.
"use strict";

const STICK_DEADZONE = 0.15;
const COLOURS = ["#2e6beb", "#9e38c7", "#46a758", "#e5484d"];

const $ = (id) => document.getElementById(id);
const wmCanvas = $("wm"), twinCanvas = $("twin");
const state = {
  ws: null, hello: null, target: null, seq: 0, sent: null, sentAt: 0, held: new Set(), drag: null, mouse: null,
  pads: {}, lastTick: performance.now(), header: null, frames: 0,
  frameTimes: [], latencies: [], pending: null,  // pending: {seq, t} of the last press not yet seen
};
// For tests and benchmarks: what the page has seen.
window.iwsim = { state, stats: { fps: 0, latencyP95: null, latencyLast: null, frames: 0 } };

function connect() {
  // The server embeds its token in the page it serves to this machine; remote users give it as ?token=.
  const meta = document.querySelector('meta[name="iwsim-token"]');
  const token = new URLSearchParams(location.search).get("token") || (meta && meta.content);
  const url = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws` +
    (token ? `?token=${encodeURIComponent(token)}` : "");
  const ws = new WebSocket(url);
  ws.binaryType = "arraybuffer";
  state.ws = ws;
  ws.onopen = () => setConn("connected");
  ws.onclose = (e) => setConn(`disconnected${e.reason ? ` (${e.reason})` : ""} — reload to reconnect`);
  ws.onmessage = (e) => (typeof e.data === "string" ? onEvent(JSON.parse(e.data)) : onFrame(e.data));
}

function send(msg) {
  if (state.ws && state.ws.readyState === WebSocket.OPEN) state.ws.send(JSON.stringify(msg));
}

function setConn(text) { $("conn").textContent = text; }

function say(text, kind = "") {
  const m = $("message");
  m.textContent = text;
  m.className = kind;
}

// ---- server events --------------------------------------------------------------------
function onEvent(msg) {
  if (msg.type === "hello") {
    state.hello = msg;
    setupTask(msg);
    $("reset-store").disabled = !msg.reset_sources.includes("store");
    $("record").disabled = !msg.recording_to;
    $("rate").textContent = `control rate ${msg.hz} Hz` +
      (msg.recording_to ? ` · recording to ${msg.recording_to}` : " · recording off (--record-to)");
  } else if (msg.type === "status") {
    say(msg.message);
  } else if (msg.type === "saved") {
    say(`saved episode ${msg.episode} (${msg.steps} steps) to ${msg.store}`, "ok");
  } else if (msg.type === "error" || msg.type === "busy") {
    say(msg.message, "error");
    if (msg.type === "busy") setConn("busy");
  }
}

function onFrame(buf) {
  const view = new DataView(buf);
  const n = view.getUint32(0, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
  const size = header.size, px = size * size * 3;
  const now = performance.now();
  if (state.target === null || (header.step === 0 && state.header && state.header.step !== 0) ||
      (state.header && (header.seed !== state.header.seed || header.source !== state.header.source))) {
    state.target = header.action.slice();  // a new episode: the robot starts where it is
    state.sent = state.target.slice();
    showCommand();
  }
  state.header = header;
  header.views.forEach((name, v) => {
    draw(viewCanvas(name), new Uint8Array(buf, 4 + n + v * px, px), size, name === "world_model");
  });
  $("twin-view").hidden = !header.views.includes("mujoco");
  for (const [name, canvas] of Object.entries(extraViews)) {  // another camera's view, e.g. "mujoco:side"
    canvas.parentElement.hidden = !header.views.includes(name);
  }
  if (state.pending && header.ack >= state.pending.seq) {
    state.latencies.push(now - state.pending.t);
    if (state.latencies.length > 200) state.latencies.shift();
    state.pending = null;
  }
  state.frameTimes.push(now);
  while (state.frameTimes.length && now - state.frameTimes[0] > 2000) state.frameTimes.shift();
  state.frames += 1;
  updateHud(header, now);
}

function updateHud(h, now) {
  const st = window.iwsim.stats;
  const ft = state.frameTimes;
  st.fps = ft.length > 1 ? (ft.length - 1) / ((ft[ft.length - 1] - ft[0]) / 1000) : 0;
  st.frames = state.frames;
  const lat = state.latencies;
  if (lat.length) {
    const sorted = lat.slice().sort((a, b) => a - b);
    st.latencyLast = lat[lat.length - 1];
    st.latencyP95 = sorted[Math.min(sorted.length - 1, Math.floor(0.95 * sorted.length))];
    $("latency").textContent = `${st.latencyLast.toFixed(0)} ms (p95 ${st.latencyP95.toFixed(0)} ms)`;
  }
  $("fps").textContent = st.fps.toFixed(1);
  $("step").textContent = h.step;
  $("iou").textContent = h.iou === null ? "no scorer" : h.iou.toFixed(3);
  $("twin-iou").textContent = h.mujoco_iou === null ? "–" : h.mujoco_iou.toFixed(3);
  $("step-ms").textContent = `${h.step_ms.toFixed(1)} ms · ${h.sessions} session${h.sessions === 1 ? "" : "s"}`;
  $("episode").textContent = `${h.source} seed ${h.seed}`;
  $("rec").textContent = h.recording === null ? "" :
    `● REC ${h.recording} steps${h.recording >= h.record_limit ? " (limit reached: save or discard)" : ""}`;
}

// ---- drawing --------------------------------------------------------------------------
// The first camera's views are the page's own canvases; another camera's ("world_model:side",
// "mujoco:side") gets a canvas of its own beside them when it first arrives.
const extraViews = {};
function viewCanvas(name) {
  if (name === "world_model") return wmCanvas;
  if (name === "mujoco") return twinCanvas;
  if (!extraViews[name]) {
    const [source, camera] = name.split(":");
    const div = document.createElement("div");
    div.className = "view";
    const canvas = document.createElement("canvas");
    canvas.className = "frame";
    canvas.width = canvas.height = 512;
    canvas.dataset.view = name;
    const caption = document.createElement("span");
    caption.textContent = `${source === "mujoco" ? "MuJoCo" : "world model"}, ${camera} camera`;
    div.append(canvas, caption);
    document.querySelector("main").insertBefore(div, document.querySelector("aside"));
    extraViews[name] = canvas;
  }
  return extraViews[name];
}

const scratch = document.createElement("canvas");
function draw(canvas, rgb, size, overlay) {
  scratch.width = scratch.height = size;
  const sctx = scratch.getContext("2d");
  const img = sctx.createImageData(size, size);
  for (let i = 0, j = 0; i < rgb.length; i += 3, j += 4) {
    img.data[j] = rgb[i]; img.data[j + 1] = rgb[i + 1]; img.data[j + 2] = rgb[i + 2]; img.data[j + 3] = 255;
  }
  sctx.putImageData(img, 0, 0);
  const ctx = canvas.getContext("2d");
  ctx.imageSmoothingEnabled = false;  // crisp pixels
  ctx.drawImage(scratch, 0, 0, canvas.width, canvas.height);
  if (overlay && state.target) drawTargets(ctx, canvas);
}

// ---- the task: bindings, sliders, legend -------------------------------------------------
function bindings() { return state.hello.bindings; }

function setupTask(hello) {
  $("score-name").textContent = hello.score_name ? `${hello.score_name} (model)` : "score";
  for (const el of document.querySelectorAll(".twin-score")) el.hidden = !hello.side_by_side;
  $("side-row").hidden = !hello.side_by_side;
  $("reset-mujoco").firstChild.textContent = hello.start_source === "mujoco" ? "MuJoCo start " :
    `${hello.start_source[0].toUpperCase()}${hello.start_source.slice(1)} start `;
  $("legend").replaceChildren(...hello.bindings.legend.map((line) => {
    const div = document.createElement("div");
    div.textContent = line;
    return div;
  }));
  $("wm-caption").textContent = hello.bindings.drag.length ? "world model — drag a ring to move it" : "world model";
  const box = $("sliders");
  box.replaceChildren();
  state.sliders = hello.action_names.map((name, d) => {
    const row = document.createElement("label");
    row.className = "slider";
    const label = document.createElement("span");
    label.textContent = name;
    const input = document.createElement("input");
    Object.assign(input, { type: "range", min: hello.action_low[d], max: hello.action_high[d],
                           step: (hello.action_high[d] - hello.action_low[d]) / 1000 });
    input.dataset.dim = d;
    const value = document.createElement("output");
    input.addEventListener("input", () => setDim(d, Number(input.value)));
    row.append(label, input, value);
    box.append(row);
    return { input, value };
  });
}

// Set one dimension of the command from its slider, and send it at once.
function setDim(d, v) {
  if (!state.target || !state.hello) return;
  state.target[d] = v;
  state.target = clip(state.target);
  state.pending = null;
  sendTarget(performance.now());
}

function showCommand() {
  if (!state.target || !state.sliders) return;
  state.sliders.forEach(({ input, value }, d) => {
    if (document.activeElement !== input) input.value = state.target[d];
    value.textContent = state.target[d].toFixed(3);
  });
}

function toCanvas(x, y, canvas) {
  const vh = state.hello.view_half;
  return [(x + vh) / (2 * vh) * canvas.width, (vh - y) / (2 * vh) * canvas.height];
}

function toWorld(cx, cy, canvas) {
  const vh = state.hello.view_half, r = canvas.getBoundingClientRect();
  return [(cx - r.left) / r.width * 2 * vh - vh, vh - (cy - r.top) / r.height * 2 * vh];
}

function drawTargets(ctx, canvas) {
  const drag = state.hello.bindings.drag;
  for (let p = 0; p < drag.length; p++) {
    const [x, y] = toCanvas(state.target[drag[p][0]], state.target[drag[p][1]], canvas);
    ctx.strokeStyle = COLOURS[p % COLOURS.length];
    ctx.lineWidth = 3;
    ctx.beginPath();
    ctx.arc(x, y, 16, 0, 2 * Math.PI);
    ctx.moveTo(x - 22, y); ctx.lineTo(x - 10, y); ctx.moveTo(x + 10, y); ctx.lineTo(x + 22, y);
    ctx.moveTo(x, y - 22); ctx.lineTo(x, y - 10); ctx.moveTo(x, y + 10); ctx.lineTo(x, y + 22);
    ctx.stroke();
  }
}

// ---- controls -------------------------------------------------------------------------
function clip(a) {
  const lo = state.hello.action_low, hi = state.hello.action_high;
  return a.map((v, i) => Math.min(hi[i], Math.max(lo[i], v)));
}

// Move the command by velocity (units/s per dimension) for dt seconds. A press (its event
// time given) is sent at once; continuous motion at most twice per control step, as the
// server only uses the latest command of each step.
function move(vel, dt, press) {
  if (!state.target || !state.hello) return;
  const next = clip(state.target.map((v, i) => v + vel[i] * dt));
  if (next.some((v, i) => Math.abs(v - state.target[i]) > 1e-6)) state.target = next;
  sendTarget(press);
}

function sendTarget(press) {
  const now = performance.now();
  const changed = !state.sent || state.target.some((v, i) => v !== state.sent[i]);
  if (changed && (press || now - state.sentAt >= 500 / state.hello.hz)) {
    state.seq += 1;
    if (press && !state.pending) state.pending = { seq: state.seq, t: press };
    state.sent = state.target.slice();
    state.sentAt = now;
    send({ type: "action", seq: state.seq, action: state.target });
    showCommand();
  }
}

function zeros() { return state.hello.action_low.map(() => 0); }

function keyVelocity() {
  const vel = zeros(), b = bindings();
  for (const k of state.held) {
    const [d, sign] = b.keys[k];
    vel[d] += sign * b.speed[d];
  }
  return vel;
}

function padVelocity() {
  const vel = zeros(), b = bindings();
  for (const pad of navigator.getGamepads ? navigator.getGamepads() : []) {
    if (!pad) continue;
    const ax = pad.axes.map((v) => (Math.abs(v) < STICK_DEADZONE ? 0 : v));
    for (const [axis, d, sign] of b.axes) vel[d] += sign * (ax[axis] || 0) * b.speed[d];
    const was = state.pads[pad.index] || [];
    const pressed = pad.buttons.map((b) => b.pressed);
    const edge = (i) => pressed[i] && !was[i];
    if (edge(2)) command("record");
    if (edge(3)) command("save");
    if (edge(1)) command("discard");
    if (edge(9)) resetMujoco();
    state.pads[pad.index] = pressed;
  }
  return vel;
}

function dragVelocity(dt) {
  const vel = zeros(), b = bindings();
  if (state.drag === null || !state.mouse || !state.target) return vel;
  const [ix, iy] = b.drag[state.drag];
  const dx = state.mouse[0] - state.target[ix], dy = state.mouse[1] - state.target[iy];
  const dist = Math.hypot(dx, dy);
  if (dist > 1e-6 && dt > 0) {
    const speed = Math.min(b.drag_speed, dist / dt);  // reach the cursor, no faster than drag_speed
    vel[ix] = dx / dist * speed;
    vel[iy] = dy / dist * speed;
  }
  return vel;
}

function frameLoop(now) {
  const dt = Math.min(0.1, (now - state.lastTick) / 1000);
  state.lastTick = now;
  if (state.hello) {
    const k = keyVelocity(), g = padVelocity(), d = dragVelocity(dt);
    move(k.map((v, i) => v + g[i] + d[i]), dt, null);
  }
  requestAnimationFrame(frameLoop);
}

function command(name) { send({ type: name }); }

function resetMujoco() {  // the task's own start (T-push: a MuJoCo reset)
  const v = $("seed").value.trim();
  const msg = { type: "reset", source: state.hello ? state.hello.start_source : "mujoco" };
  if (v !== "") msg.seed = Number(v);
  state.target = null;
  send(msg);
}

function resetStore() { state.target = null; send({ type: "reset", source: "store" }); }

document.addEventListener("keydown", (e) => {
  if (e.target instanceof HTMLInputElement && e.target.type === "number") return;
  const key = e.key.toLowerCase();
  if (e.key === "Enter" || (e.key === "S" && e.shiftKey)) { command("save"); e.preventDefault(); return; }
  if (e.ctrlKey || e.metaKey || e.altKey) return;
  if (state.hello && Object.hasOwn(bindings().keys, key)) {
    e.preventDefault();
    if (!state.held.has(key)) {
      state.held.add(key);
      // a press moves the command by one control step at once (a tap nudges); holding
      // keeps it moving in the frame loop
      const [d, sign] = bindings().keys[key];
      const vel = zeros();
      vel[d] = sign * bindings().speed[d];
      move(vel, 1 / state.hello.hz, performance.now());
    }
    return;
  }
  if (e.repeat) return;
  if (key === "c") command("record");
  else if (key === "q") command("discard");
  else if (key === "r") resetMujoco();
  else if (key === "t" && !$("reset-store").disabled) resetStore();
  else if (key === "b" && !$("side-row").hidden) { $("side").checked = !$("side").checked; sideBySide(); }
});
document.addEventListener("keyup", (e) => state.held.delete(e.key.toLowerCase()));
window.addEventListener("blur", () => state.held.clear());

function sideBySide() { state.target = null; send({ type: "side_by_side", on: $("side").checked }); }

wmCanvas.addEventListener("pointerdown", (e) => {
  if (!state.target || !state.hello || !bindings().drag.length) return;
  const [x, y] = toWorld(e.clientX, e.clientY, wmCanvas);
  const d = bindings().drag.map(([ix, iy]) => Math.hypot(x - state.target[ix], y - state.target[iy]));
  state.drag = d.indexOf(Math.min(...d));  // the nearest; a tie goes to the first
  state.mouse = [x, y];
  state.pending = null;
  wmCanvas.setPointerCapture(e.pointerId);
  wmCanvas.classList.add("dragging");
  move(dragVelocity(1 / state.hello.hz), 1 / state.hello.hz, performance.now());
});
wmCanvas.addEventListener("pointermove", (e) => {
  if (state.drag !== null) state.mouse = toWorld(e.clientX, e.clientY, wmCanvas);
});
const endDrag = () => { state.drag = null; wmCanvas.classList.remove("dragging"); };
wmCanvas.addEventListener("pointerup", endDrag);
wmCanvas.addEventListener("pointercancel", endDrag);

$("record").onclick = () => command("record");
$("save").onclick = () => command("save");
$("discard").onclick = () => command("discard");
$("reset-mujoco").onclick = resetMujoco;
$("reset-store").onclick = resetStore;
$("side").onchange = sideBySide;
window.addEventListener("gamepadconnected", (e) => say(`gamepad connected: ${e.gamepad.id}`));

connect();
requestAnimationFrame(frameLoop);
