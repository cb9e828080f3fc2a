// nerf view: drives a camera around a trained run and shows the frames the server
// renders for it. The camera is kept as eye, target and the scene's up axis; every change
// sends a `view` request over the WebSocket (the server renders a fast preview, then
// refines once the camera rests). Frames arrive as binary messages: a 16-byte header
// (seq, width, height, mode, final, microseconds) and a JPEG.
"use strict";

const token = new URLSearchParams(location.search).get("token");
const withToken = (url) => (token ? `${url}${url.includes("?") ? "&" : "?"}token=${encodeURIComponent(token)}` : url);
const $ = (id) => document.getElementById(id);

// ---- small vector helpers (3-vectors as arrays) ----
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const unit = (a) => scale(a, 1 / (norm(a) || 1));
// Rotates v about the unit axis k by angle t (Rodrigues).
const rotate = (v, k, t) => add(add(scale(v, Math.cos(t)), scale(cross(k, v), Math.sin(t))), scale(k, dot(k, v) * (1 - Math.cos(t))));

// ---- state ----
const view = { eye: [0, 0, 4], target: [0, 0, 0], up: [0, 0, 1], fov: 40 };
let scene = null;
let home = null;
let socket = null;
let seq = 0;
let shownSeq = -1;
let mode = "rgb";
// Runs trained with --appearance: the training photo whose learned look colours the
// views and rendered paths (null: the mean of the photos').
let appearance = null;
// Models of a moving scene: the moment shown, in [0, 1], and the motion's playback.
let time = 0;
let timePlaying = null;
let restTimer = null;
let lastSent = 0;
let sentAt = new Map();
const keys = [];
let pathPoses = null;
let playing = null;
const held = new Set();
const chart = [];

// The camera-to-world matrix (3 rows of 4, looking down -z, y up) of the current view.
function pose(v = view) {
  const z = unit(sub(v.eye, v.target));
  let x = cross(v.up, z);
  if (norm(x) < 1e-6) x = cross([1, 0, 0], z);
  x = unit(x);
  const y = cross(z, x);
  return [
    [x[0], y[0], z[0], v.eye[0]],
    [x[1], y[1], z[1], v.eye[1]],
    [x[2], y[2], z[2], v.eye[2]],
  ];
}

// Puts the camera at a camera-to-world matrix, keeping the orbit distance.
function setPose(c2w, fov) {
  const eye = [c2w[0][3], c2w[1][3], c2w[2][3]];
  const z = [c2w[0][2], c2w[1][2], c2w[2][2]];
  const dist = Math.max(norm(sub(eye, scene ? scene.center : [0, 0, 0])), 0.1);
  view.eye = eye;
  view.target = sub(eye, scale(z, dist));
  if (fov) view.fov = fov;
  $("fov").value = Math.round(view.fov);
  $("fov-value").textContent = `${Math.round(view.fov)}°`;
}

// ---- the render size ----
function renderSize() {
  const stage = $("stage");
  const aspect = stage.clientWidth / Math.max(stage.clientHeight, 1);
  const choice = $("resolution").value;
  let h = choice === "fit" ? Math.min(stage.clientHeight * (window.devicePixelRatio || 1), 1080) : Number(choice);
  h = Math.max(16, Math.round(h));
  const w = Math.max(16, Math.min(4096, Math.round(h * aspect)));
  return [w, Math.min(h, 4096)];
}

// ---- talking to the server ----
function send(message) {
  if (socket && socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify(message));
}

function requestView(moving) {
  const [width, height] = renderSize();
  seq += 1;
  sentAt.set(seq, performance.now());
  if (sentAt.size > 200) sentAt.delete(sentAt.keys().next().value);
  send({ type: "view", seq, mode, moving, appearance, time, camera: { c2w: pose(), fov_y: view.fov, width, height } });
  lastSent = performance.now();
  drawOverlay();
}

// A camera change: a preview now (at most every 30 ms), the full frame once it rests.
function changed() {
  if (performance.now() - lastSent > 30) requestView(true);
  clearTimeout(restTimer);
  restTimer = setTimeout(() => requestView(false), 150);
}

async function showFrame(data) {
  const head = new DataView(data, 0, 16);
  const frameSeq = head.getUint32(0, true);
  const w = head.getUint16(4, true);
  const h = head.getUint16(6, true);
  const last = head.getUint8(9) === 1;
  const micros = head.getUint32(12, true);
  if (frameSeq < shownSeq) return;
  shownSeq = frameSeq;
  const bitmap = await createImageBitmap(new Blob([data.slice(16)], { type: "image/jpeg" }));
  const canvas = $("frame");
  canvas.width = w;
  canvas.height = h;
  canvas.getContext("2d").drawImage(bitmap, 0, 0);
  const latency = sentAt.has(frameSeq) ? performance.now() - sentAt.get(frameSeq) : 0;
  $("status").textContent = `${w}x${h}${last ? "" : " (refining)"} · render ${(micros / 1000).toFixed(0)} ms · ${latency.toFixed(0)} ms since the request`;
  canvas.dataset.seq = String(frameSeq);
  canvas.dataset.last = String(last);
}

function connect() {
  const url = withToken(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  socket = new WebSocket(url);
  socket.binaryType = "arraybuffer";
  socket.onopen = () => {
    $("status").textContent = "connected";
    requestView(false);
  };
  socket.onclose = () => {
    $("status").textContent = "disconnected: reload the page once `nerf view` runs again";
  };
  socket.onmessage = (event) => {
    if (event.data instanceof ArrayBuffer) {
      showFrame(event.data);
      return;
    }
    const msg = JSON.parse(event.data);
    if (msg.type === "error") $("path-status").textContent = `error: ${msg.message}`;
    else if (msg.type === "path_poses") pathReady(msg);
    else if (msg.type === "saved") $("path-status").textContent = `saved ${msg.file}`;
    else if (msg.type === "render_progress") {
      const p = $("render-progress");
      p.hidden = false;
      p.max = msg.total;
      p.value = msg.done;
      $("path-status").textContent = `rendering frame ${msg.done + 1} of ${msg.total}`;
    } else if (msg.type === "rendered") {
      $("render-progress").hidden = true;
      $("path-status").textContent = `rendered ${msg.folder}${msg.video ? ` and ${msg.video}` : ""}`;
    } else if (msg.type === "training") training(msg);
  };
}

// ---- training cameras: frustums, picking, photos ----
function project(p, c2w, f, w, h) {
  const d = sub(p, [c2w[0][3], c2w[1][3], c2w[2][3]]);
  const x = d[0] * c2w[0][0] + d[1] * c2w[1][0] + d[2] * c2w[2][0];
  const y = d[0] * c2w[0][1] + d[1] * c2w[1][1] + d[2] * c2w[2][1];
  const z = d[0] * c2w[0][2] + d[1] * c2w[1][2] + d[2] * c2w[2][2];
  if (z > -1e-3) return null;
  return [w / 2 + (x / -z) * f, h / 2 - (y / -z) * f];
}

function frustumPoints(cam, size) {
  const m = cam.c2w;
  const o = [m[0][3], m[1][3], m[2][3]];
  const col = (c) => [m[0][c], m[1][c], m[2][c]];
  const ty = Math.tan((cam.fov_y * Math.PI) / 360);
  const tx = ty * (cam.width / cam.height);
  const corner = (sx, sy) => add(o, scale(add(add(scale(col(2), -1), scale(col(0), sx * tx)), scale(col(1), sy * ty)), size));
  return [o, corner(-1, -1), corner(1, -1), corner(1, 1), corner(-1, 1)];
}

let projected = [];
function drawOverlay() {
  const canvas = $("overlay");
  const w = (canvas.width = canvas.clientWidth);
  const h = (canvas.height = canvas.clientHeight);
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, w, h);
  projected = [];
  if (!scene || !$("frustums").checked) return;
  const c2w = pose();
  const f = h / 2 / Math.tan((view.fov * Math.PI) / 360);
  const size = 0.08 * scene.radius;
  for (const cam of scene.cameras) {
    const pts = frustumPoints(cam, size).map((p) => project(p, c2w, f, w, h));
    if (pts.some((p) => !p)) continue;
    ctx.strokeStyle = cam.index === selected ? "#ffcc33" : "#4fa3ffaa";
    ctx.lineWidth = cam.index === selected ? 2 : 1;
    ctx.beginPath();
    for (let i = 1; i <= 4; i++) {
      ctx.moveTo(pts[0][0], pts[0][1]);
      ctx.lineTo(pts[i][0], pts[i][1]);
    }
    ctx.moveTo(pts[4][0], pts[4][1]);
    for (let i = 1; i <= 4; i++) ctx.lineTo(pts[i][0], pts[i][1]);
    ctx.stroke();
    const c = pts.slice(1).reduce((a, p) => [a[0] + p[0] / 4, a[1] + p[1] / 4], [0, 0]);
    projected.push({ cam, at: c, apex: pts[0] });
  }
  if (pathPoses) {
    ctx.strokeStyle = "#ff5fa2";
    ctx.lineWidth = 2;
    ctx.beginPath();
    let started = false;
    for (const p of pathPoses.poses) {
      const q = project([p[0][3], p[1][3], p[2][3]], c2w, f, w, h);
      if (!q) { started = false; continue; }
      if (started) ctx.lineTo(q[0], q[1]); else ctx.moveTo(q[0], q[1]);
      started = true;
    }
    ctx.stroke();
  }
}

let selected = -1;
function pick(x, y) {
  let best = null;
  for (const p of projected) {
    const d = Math.min(Math.hypot(p.at[0] - x, p.at[1] - y), Math.hypot(p.apex[0] - x, p.apex[1] - y));
    if (d < 14 && (!best || d < best.d)) best = { d, cam: p.cam };
  }
  return best && best.cam;
}

function jumpTo(cam) {
  selected = cam.index;
  setPose(cam.c2w, cam.fov_y);
  $("photo-box").hidden = false;
  $("photo-index").textContent = `#${cam.index}`;
  $("photo-look").hidden = !(scene.appearance_photos > cam.index);
  $("photo").src = withToken(`/api/photo/${cam.index}`);
  requestView(false);
}

// ---- mouse and keys ----
function installControls() {
  const stage = $("stage");
  let drag = null;
  stage.addEventListener("contextmenu", (e) => e.preventDefault());
  stage.addEventListener("mousedown", (e) => {
    drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey, moved: false };
  });
  window.addEventListener("mouseup", (e) => {
    if (drag && !drag.moved) {
      const r = stage.getBoundingClientRect();
      const cam = pick(e.clientX - r.left, e.clientY - r.top);
      if (cam) jumpTo(cam);
    }
    drag = null;
  });
  window.addEventListener("mousemove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x;
    const dy = e.clientY - drag.y;
    if (Math.abs(dx) + Math.abs(dy) < 1) return;
    drag.moved = true;
    drag.x = e.clientX;
    drag.y = e.clientY;
    if (drag.pan) pan(dx, dy);
    else orbit(dx, dy);
    changed();
  });
  stage.addEventListener("wheel", (e) => {
    e.preventDefault();
    const offset = sub(view.eye, view.target);
    const d = Math.max(norm(offset) * Math.exp(e.deltaY * 0.001), 0.01);
    view.eye = add(view.target, scale(unit(offset), d));
    changed();
  }, { passive: false });
  window.addEventListener("keydown", (e) => {
    if (e.target.tagName === "INPUT" || e.target.tagName === "SELECT") return;
    held.add(e.key.toLowerCase());
  });
  window.addEventListener("keyup", (e) => held.delete(e.key.toLowerCase()));
  let then = performance.now();
  const fly = (now) => {
    const dt = Math.min((now - then) / 1000, 0.1);
    then = now;
    const dirs = { w: [0, 0, -1], s: [0, 0, 1], a: [-1, 0, 0], d: [1, 0, 0], q: [0, -1, 0], e: [0, 1, 0] };
    let move = [0, 0, 0];
    for (const k of held) if (dirs[k]) move = add(move, dirs[k]);
    if (norm(move) > 0) {
      const m = pose();
      const col = (c) => [m[0][c], m[1][c], m[2][c]];
      const speed = 0.5 * (scene ? scene.radius : 4) * dt;
      const step = add(add(scale(col(0), move[0] * speed), scale(view.up, move[1] * speed)), scale(col(2), move[2] * speed));
      view.eye = add(view.eye, step);
      view.target = add(view.target, step);
      changed();
    }
    requestAnimationFrame(fly);
  };
  requestAnimationFrame(fly);
}

function orbit(dx, dy) {
  let offset = sub(view.eye, view.target);
  offset = rotate(offset, unit(view.up), -dx * 0.006);
  const right = unit(cross(view.up, offset));
  const tilted = rotate(offset, right, -dy * 0.006);
  // Stay clear of the poles, where "up" would flip.
  const c = dot(unit(tilted), unit(view.up));
  if (Math.abs(c) < 0.995) offset = tilted;
  view.eye = add(view.target, offset);
}

function pan(dx, dy) {
  const m = pose();
  const col = (c) => [m[0][c], m[1][c], m[2][c]];
  const d = norm(sub(view.eye, view.target)) * 0.0015;
  const step = add(scale(col(0), -dx * d), scale(col(1), dy * d));
  view.eye = add(view.eye, step);
  view.target = add(view.target, step);
}

// ---- camera path editor ----
function pathSpec() {
  const [width, height] = renderSize();
  return {
    keyframes: keys.map((k) => ({ c2w: k.c2w, fov_y: k.fov_y, time: k.time })),
    seconds: Number($("seconds").value),
    fps: Number($("fps").value),
    width,
    height,
    looped: $("loop").checked,
  };
}

function keysChanged() {
  const list = $("keys");
  list.innerHTML = "";
  keys.forEach((k, i) => {
    const li = document.createElement("li");
    li.textContent = `fov ${Math.round(k.fov_y)}°${k.time === null ? "" : ` · t ${k.time.toFixed(2)}`} `;
    const button = (label, act) => {
      const b = document.createElement("button");
      b.className = "small";
      b.textContent = label;
      b.onclick = act;
      li.appendChild(b);
    };
    button("go", () => {
      setPose(k.c2w, k.fov_y);
      if (k.time !== null) setTime(k.time);
      requestView(false);
    });
    button("↑", () => { if (i > 0) { [keys[i - 1], keys[i]] = [keys[i], keys[i - 1]]; keysChanged(); } });
    button("↓", () => { if (i + 1 < keys.length) { [keys[i + 1], keys[i]] = [keys[i], keys[i + 1]]; keysChanged(); } });
    button("✕", () => { keys.splice(i, 1); keysChanged(); });
    list.appendChild(li);
  });
  const ready = keys.length >= 2;
  for (const id of ["save", "render", "play", "scrub"]) $(id).disabled = !ready;
  pathPoses = null;
  if (ready) send({ type: "preview_path", path: pathSpec() });
  drawOverlay();
}

function pathReady(msg) {
  pathPoses = msg;
  const scrub = $("scrub");
  scrub.max = String(msg.poses.length - 1);
  drawOverlay();
}

function showPathFrame(i) {
  if (!pathPoses) return;
  setPose(pathPoses.poses[i], pathPoses.fov_y[i]);
  if (pathPoses.times) setTime(pathPoses.times[i]);
  changed();
}

function play() {
  if (playing) { clearInterval(playing); playing = null; $("play").textContent = "Play preview"; return; }
  if (!pathPoses) return;
  let i = 0;
  $("play").textContent = "Stop";
  playing = setInterval(() => {
    $("scrub").value = String(i);
    showPathFrame(i);
    i += 1;
    if (i >= pathPoses.poses.length) play();
  }, 1000 / Number($("fps").value || 24));
}

// ---- live training ----
function training(msg) {
  $("training").hidden = false;
  $("run").textContent = `${scene.run} · step ${msg.step} · ${scene.engine} · ${scene.cameras.length} training cameras`;
  $("train-stats").textContent = `step ${msg.step}${msg.steps ? ` of ${msg.steps}` : ""} · loss ${msg.loss.toFixed(5)} · PSNR ${msg.psnr.toFixed(2)} dB · ${(msg.rays_per_second / 1000).toFixed(1)} k rays/s`;
  chart.push([msg.step, msg.psnr, Math.log10(Math.max(msg.loss, 1e-12))]);
  if (chart.length > 500) chart.shift();
  const c = $("chart");
  const ctx = c.getContext("2d");
  ctx.clearRect(0, 0, c.width, c.height);
  const s0 = chart[0][0];
  const s1 = Math.max(chart[chart.length - 1][0], s0 + 1);
  // PSNR (blue) and log10 loss (orange), each scaled to the chart's height.
  const line = (k, colour) => {
    const lo = Math.min(...chart.map((p) => p[k]));
    const hi = Math.max(...chart.map((p) => p[k]), lo + 1e-6);
    ctx.strokeStyle = colour;
    ctx.beginPath();
    chart.forEach((p, i) => {
      const x = ((p[0] - s0) / (s1 - s0)) * (c.width - 10) + 5;
      const y = c.height - 5 - ((p[k] - lo) / (hi - lo)) * (c.height - 30);
      if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y);
    });
    ctx.stroke();
    return [lo, hi];
  };
  const [plo, phi] = line(1, "#4fa3ff");
  const [llo, lhi] = line(2, "#ffa64f");
  ctx.fillStyle = "#4fa3ff";
  ctx.fillText(`PSNR ${plo.toFixed(1)}–${phi.toFixed(1)} dB`, 5, 12);
  ctx.fillStyle = "#ffa64f";
  ctx.fillText(`loss ${(10 ** llo).toExponential(1)}–${(10 ** lhi).toExponential(1)}`, 5, 24);
  // Show the newest model as a preview (the full frame would take the cores from
  // training), at most every two seconds; the full frame once training stops.
  if (!training.last || performance.now() - training.last > 2000) {
    training.last = performance.now();
    if (!held.size) requestView(true);
  }
  clearTimeout(training.done);
  training.done = setTimeout(() => requestView(false), 3000);
}

// Colours views (and rendered paths) with training photo `index`'s look, or the mean's.
function setAppearance(index) {
  appearance = index;
  $("appearance").value = index === null ? "" : String(index);
  requestView(false);
}

// Shows moment `t` of a moving scene.
function setTime(t) {
  time = t;
  $("time").value = String(t);
  $("time-value").textContent = t.toFixed(2);
}

// Plays the motion from the current moment, looping every five seconds (previews while
// it plays, the full frame where it is paused).
function playTime() {
  if (timePlaying) {
    cancelAnimationFrame(timePlaying);
    timePlaying = null;
    $("time-play").textContent = "Play the motion";
    requestView(false);
    return;
  }
  $("time-play").textContent = "Pause";
  let last = performance.now();
  const step = (now) => {
    setTime((time + (now - last) / 5000) % 1);
    last = now;
    changed();
    timePlaying = requestAnimationFrame(step);
  };
  timePlaying = requestAnimationFrame(step);
}

// ---- start ----
async function start() {
  const response = await fetch(withToken("/api/scene"));
  if (!response.ok) {
    $("status").textContent = `error: ${await response.text()}`;
    return;
  }
  scene = await response.json();
  view.up = scene.up;
  $("run").textContent = `${scene.run} · step ${scene.step} · ${scene.engine} · ${scene.cameras.length} training cameras`;
  if (scene.cameras.length) {
    setPose(scene.cameras[0].c2w, scene.cameras[0].fov_y);
    view.target = scene.center;
  } else {
    view.eye = add(scene.center, scale([1, 0, 0.5], scene.radius));
    view.target = scene.center;
  }
  home = { eye: view.eye, target: view.target, fov: view.fov };
  if (scene.live) $("training").hidden = false;
  if (scene.appearance_photos > 0) {
    const list = $("appearance");
    for (let i = 0; i < scene.appearance_photos; i++) list.add(new Option(`photo #${i}`, String(i)));
    $("appearance-box").hidden = false;
  }
  if (scene.dynamic) $("time-box").hidden = false;
  installControls();
  $("mode").onchange = (e) => { mode = e.target.value; requestView(false); };
  $("fov").oninput = (e) => { view.fov = Number(e.target.value); $("fov-value").textContent = `${view.fov}°`; changed(); };
  $("resolution").onchange = () => requestView(false);
  $("frustums").onchange = drawOverlay;
  $("reset").onclick = () => { Object.assign(view, { eye: home.eye, target: home.target, fov: home.fov }); setPose(pose(), home.fov); requestView(false); };
  $("appearance").onchange = (e) => { setAppearance(e.target.value === "" ? null : Number(e.target.value)); };
  $("photo-look").onclick = () => setAppearance(selected);
  $("time").oninput = (e) => { setTime(Number(e.target.value)); changed(); };
  $("time-play").onclick = playTime;
  $("photo-close").onclick = () => { $("photo-box").hidden = true; selected = -1; drawOverlay(); };
  // A moving scene's keyframes keep the moment shown when they were added.
  $("key-add").onclick = () => {
    keys.push({ c2w: pose(), fov_y: view.fov, time: scene.dynamic ? time : null });
    keysChanged();
  };
  for (const id of ["seconds", "fps", "loop"]) $(id).onchange = keysChanged;
  $("scrub").oninput = (e) => showPathFrame(Number(e.target.value));
  $("play").onclick = play;
  $("save").onclick = () => send({ type: "save_path", name: $("path-name").value, path: pathSpec() });
  $("render").onclick = () => send({ type: "render_path", name: $("path-name").value, path: pathSpec(), appearance });
  window.addEventListener("resize", () => { drawOverlay(); requestView(false); });
  connect();
}

start();
