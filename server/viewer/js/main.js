// The quadcast viewer page: connects to the server that served it (WebSocket /ws, the same wire messages as the
// Python client), sends its pose, rebuilds the QUASAR client's layered quad mesh from every frame (quad blob +
// its H.264 atlas picture, paired by frame id) and draws it at the current pose at the display's rate.
//
// URL: ?trace=builtin:walk replays a built-in trace (or load a QUASAR trace file from the overlay); ?size=WxH
// and ?fovy=DEG set the stream's view; ?pose=x,y,z,qx,qy,qz,qw holds a fixed pose; #token=SECRET gives the
// server's token (the fragment never reaches the server's logs; without it the page asks when the server
// wants one). For tests: ?freeze=N stops applying frames after the N-th, ?keep=1 keeps the applied frames'
// bytes (window.quadcast.appliedFrames()), window.quadcast.capture() renders and reads the canvas.
// Desktop: drag to look, WASD to move (Q/E down/up, shift faster), H hides the overlay; with "gaze: pointer" ticked
// (or ?gaze=pointer) each pose carries the pointer's direction as the viewer's gaze, which a foveated operating point
// (quadcast server --point ...,sigma=S or --adapt) centres on. WebXR immersive-vr
// when navigator.xr offers it ("Enter VR"): the head pose is sent, both eyes are drawn from the mesh.
import { ErrorCode, FATAL_CODES, FrameType, Method, MessageType, decodeFramePayload, decodeMessage, encodeBye,
         encodeHello, encodePoseUpdate, encodeReceiveReport, encodeReferenceRequest, peekFrameId } from "./wire.js";
import { LayerKind, decodeQuadBlob, layerCamera } from "./quads.js";
import { QuadCache } from "./cache.js";
import { ClientSession } from "./session.js";
import { gazeAt, parseQuasarTrace, projection, quatFromYawPitch, rotate, symmetricFrustum, tracePoseAt,
         viewMatrix } from "./math.js";
import { AtlasVideo } from "./video.js";
import { MeshRenderer } from "./renderer.js";

// client/quasar.py FILL_DEPTH_SCALE: fill-in layers sit just behind the main one
const FILL_DEPTH_SCALE = { [LayerKind.HIDDEN]: 1.003, [LayerKind.WIDE]: 1.02, [LayerKind.FAR]: 2.0 };
const FILL_KINDS = [LayerKind.REVEALED, LayerKind.HIDDEN, LayerKind.WIDE];
const MAX_PENDING = 32;          // frames waiting for their picture (client/app.py MAX_INBOX)
const POSE_HZ = 30;
const SUPPORTED = { quasar: Method.QUASAR, quadstream: Method.QUADSTREAM };

const params = new URLSearchParams(location.search);
const fragment = new URLSearchParams(location.hash.slice(1));
const stats = {
  framesReceived: 0, framesApplied: 0, framesDisplayed: 0, fps: 0, lastFrameId: -1, holes: null, mbps: 0,
  frameAgeMs: null, quads: 0, referenceRequests: 0, framesRejected: 0, connected: false, sessionId: null,
  size: null, error: null, status: "starting",
};
const kept = [];
window.quadcast = { stats, appliedFrames: () => kept.map(toBase64), capture: null };

const t0 = performance.now();
const clock = () => (performance.now() - t0) / 1000;

function toBase64(bytes) {
  let s = "";
  for (let i = 0; i < bytes.length; i += 0x8000) s += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
  return btoa(s);
}

function fail(message) {
  stats.error = message;
  stats.status = "error";
  console.warn(`quadcast: ${message}`);
  showOverlay();
}

// ------------------------------------------------------------------------------------------------ state

let config, gl, canvas, renderer, video, session, ws = null, fatal = false;
let view = null;                     // {width, height, fovy}: what Hello asked for
let cache = null, reference = null;  // the cached reference frame: QuadCache + its layer's camera/size/rect
let farLayers = [];                  // the far field of the cached reference frame (LayerKind.FAR)
let needsReference = true, frozen = false, newest = null;
const pending = new Map();           // frame id -> {header, quads}
let poseSeq = 0, lastPoseSent = -1;
let byteWindow = [], displayWindow = [];
let trace = null, traceStart = 0, fixedPose = null;
const user = { position: [0, 1.6, 0], yaw: 0, pitch: 0, keys: new Set() };
let xr = null;                       // {session, space} while in immersive VR
let pointerGaze = null;              // [x, y] degrees: the pointer's direction, sent as the gaze ("gaze: pointer")

// ------------------------------------------------------------------------------------------------ setup

async function fetchText(path) {
  const r = await fetch(path, { cache: "no-store" });
  if (!r.ok) throw new Error(`${path}: ${r.status} ${(await r.text()).trim()}`);
  return r.text();
}

function parseSize(text, max) {
  const m = /^(\d+)x(\d+)$/.exec(text || "");
  if (!m) throw new Error(`size must look like 960x540, got ${JSON.stringify(text)}`);
  const [w, h] = [Number(m[1]), Number(m[2])];
  if (w < 16 || h < 16 || w % 2 || h % 2 || w > max[0] || h > max[1]) {
    throw new Error(`size ${text}: expected even sizes from 16x16 to ${max[0]}x${max[1]}`);
  }
  return [w, h];
}

function defaultSize(max) {
  const even = (v) => Math.max(16, Math.floor(v / 2) * 2);
  const scale = Math.min(1, max[0] / innerWidth, max[1] / innerHeight, 1280 / innerWidth);
  return [even(innerWidth * scale), even(innerHeight * scale)];
}

async function start() {
  config = JSON.parse(await fetchText("/config.json"));
  const method = params.get("method") || config.methods.find((m) => m in SUPPORTED);
  if (!(method in SUPPORTED)) throw new Error(`the page draws the quasar and quadstream methods; the server serves ${config.methods.join(", ")}`);
  const [width, height] = params.has("size") ? parseSize(params.get("size"), config.max_size) : defaultSize(config.max_size);
  const fovy = Number(params.get("fovy") || 60);
  if (!(fovy > 0 && fovy < 180)) throw new Error(`fovy must be in (0, 180) degrees, got ${params.get("fovy")}`);
  view = { method, width, height, fovy };
  canvas = document.getElementById("view");
  canvas.width = width;
  canvas.height = height;
  gl = canvas.getContext("webgl2", { antialias: false, alpha: true, premultipliedAlpha: true, xrCompatible: true });
  if (!gl) throw new Error("this browser has no WebGL2");
  if (typeof VideoDecoder === "undefined") throw new Error("this browser has no WebCodecs VideoDecoder (it needs https or localhost)");
  const names = ["quad_expand.vert", "quad_expand.frag", "quad_mesh.vert", "quad_mesh.frag", "quad_mesh_refresh.vert",
                 "quad_mesh_refresh.frag"];
  const [expandVert, expandFrag, meshVert, meshFrag, refreshVert, refreshFrag] =
    await Promise.all(names.map((n) => fetchText(`/shaders/${n}.glsl`)));
  renderer = new MeshRenderer(gl, { expandVert, expandFrag, meshVert, meshFrag, refreshVert, refreshFrag });
  video = new AtlasVideo(onPicture, (message) => reject(clock(), message));
  session = new ClientSession();
  user.position = config.start.position.slice();
  [user.yaw, user.pitch] = yawPitchOf(config.start.quat);
  if (params.has("pose")) {
    const v = params.get("pose").split(",").map(Number);
    if (v.length !== 7 || !v.every(Number.isFinite)) throw new Error("pose must be x,y,z,qx,qy,qz,qw");
    fixedPose = { position: v.slice(0, 3), quat: v.slice(3) };
  }
  if (params.has("trace")) useTrace(JSON.parse(await fetchText(`/trace/${encodeURIComponent(params.get("trace"))}`)));
  stats.size = `${width}x${height}`;
  setupInput();
  setupXR();
  window.quadcast.capture = capture;
  connect();
  requestAnimationFrame(onAnimationFrame);
}

function yawPitchOf(q) {
  const f = rotate(q, [0, 0, -1]);
  return [Math.atan2(-f[0], -f[2]) * 180 / Math.PI, Math.asin(Math.max(-1, Math.min(1, f[1]))) * 180 / Math.PI];
}

function useTrace(t) {
  trace = t;
  traceStart = clock();
  document.getElementById("mode").textContent = `trace ${t.name}`;
}

// ------------------------------------------------------------------------------------------------ connection

function token() {
  return fragment.get("token") || "";
}

function connect() {
  if (fatal) return;
  stats.status = "connecting";
  const url = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`;
  const socket = new WebSocket(url);
  socket.binaryType = "arraybuffer";
  ws = socket;
  socket.onopen = () => {
    if (config.token_required && !token()) askToken("the server needs a token");
    socket.send(encodeHello({ method: view.method, width: view.width, height: view.height, fovyDeg: view.fovy, token: token() }));
  };
  socket.onmessage = (event) => {
    if (socket !== ws) return;
    try {
      onMessage(event.data);
    } catch (e) {
      fail(`malformed message from the server: ${e.message}`);
      socket.close();
    }
  };
  socket.onclose = () => {
    if (socket !== ws) return;
    stats.connected = false;
    ws = null;
    if (!fatal) {
      stats.status = "reconnecting";
      setTimeout(connect, 1000);
    }
  };
}

function askToken(why) {
  const given = typeof prompt === "function" ? prompt(`quadcast: ${why}`) : null;
  if (given) fragment.set("token", given);
  return Boolean(given);
}

function reconnect() {
  if (ws) {
    const old = ws;
    ws = null;
    try { old.send(encodeBye()); } catch (e) { /* closing anyway */ }
    old.close();
  }
  connect();
}

function send(buffer) {
  if (ws && ws.readyState === WebSocket.OPEN && stats.connected) ws.send(buffer);
}

function onMessage(buffer) {
  const msg = decodeMessage(buffer);
  const now = clock();
  if (msg.type === MessageType.WELCOME) {
    stats.connected = true;
    stats.sessionId = msg.sessionId;
    stats.status = "streaming";
    stats.error = null;
    session.connected(now);
    send(encodeReceiveReport(session.announceReports()));    // the server's rate controller may time the link
    video.reset();
    pending.clear();
    lastPoseSent = -1;
  } else if (msg.type === MessageType.ERROR) {
    if (msg.code === ErrorCode.UNAUTHORIZED && askToken(`${msg.text}; token?`)) return;  // reconnects on close
    if (FATAL_CODES.includes(msg.code)) fatal = true;
    fail(`server error ${msg.code}: ${msg.text}`);
  } else if (msg.type === MessageType.FRAME) {
    byteWindow.push([now, buffer.byteLength]);
    let frameId = null;
    try { frameId = peekFrameId(msg.payload); } catch (e) { /* no frame id: onFrame rejects the payload */ }
    if (frameId !== null) send(encodeReceiveReport(session.frameArrived(now, frameId, msg.payload.byteLength)));
    onFrame(now, msg.payload);
  } else if (msg.type === MessageType.BYE) {
    ws && ws.close();
  }
}

function requestReference(reason) {
  if (!reason) return;
  stats.referenceRequests++;
  send(encodeReferenceRequest(reason));
}

function reject(now, reason, lostReference = false) {
  if (lostReference) needsReference = true;
  stats.framesRejected++;
  requestReference(session.frameProcessed(now, false, needsReference || video.needsKeyframe, reason));
}

// ------------------------------------------------------------------------------------------------ frames

function onFrame(now, bytes) {
  stats.framesReceived++;
  if (frozen) return;
  let header;
  try {
    header = decodeFramePayload(bytes);
  } catch (e) {
    session.framesDropped(now, 1, `bad frame: ${e.message}`);
    return;
  }
  if (!session.frameReceived(now, header.frameId, header.selfContained)) {
    requestReference(session.tick(now));
    return;
  }
  if (header.method !== SUPPORTED[view.method]) return reject(now, `got a method ${header.method} frame`);
  let quads;
  try {
    quads = decodeQuadBlob(header.geometry);
  } catch (e) {
    return reject(now, `frame ${header.frameId}: ${e.message}`);
  }
  const why = video.decode(header.frameId, header.video);
  if (why) return reject(now, why, true);
  pending.set(header.frameId, { header, quads, bytes: params.has("keep") ? bytes.slice() : null });
  if (pending.size > MAX_PENDING) {
    session.framesDropped(now, pending.size, "too many frames waiting for their pictures");
    pending.clear();
    video.reset();
  }
}

function onPicture(frameId, picture) {
  const now = clock();
  for (const id of [...pending.keys()]) {            // pictures come in order: older ones never will
    if (id < frameId) {
      pending.delete(id);
      reject(now, `frame ${id}: no picture from the video decoder`, true);
    }
  }
  const entry = pending.get(frameId);
  pending.delete(frameId);
  if (!entry || frozen) {
    picture.close();
    return;
  }
  let applied = false, reason = "";
  try {
    apply(entry, picture);
    applied = true;
  } catch (e) {
    reason = e.message;
  } finally {
    picture.close();
  }
  if (applied) {
    stats.framesApplied++;
    stats.lastFrameId = entry.header.frameId;
    newest = entry.header;
    if (entry.bytes) {
      if (entry.header.frameType === FrameType.REFERENCE) kept.length = 0;
      kept.push(entry.bytes);
    }
    const freezeAt = Number(params.get("freeze") || 0);
    if (freezeAt && stats.framesApplied >= freezeAt) frozen = true;
    requestReference(session.frameProcessed(now, true, needsReference));
  } else {
    reject(now, reason);
  }
}

// client/quasar.py QuasarClient.receive, after the picture arrived: keep or update the cached reference frame,
// then the mesh = cache (reference camera) + this frame's fill layers, textured from this frame's atlas; a residual
// frame's own view (its revealed layer's camera and rect) also colours the cached surfaces it saw.
function apply({ header, quads }, picture) {
  const isReference = header.frameType === FrameType.REFERENCE;
  const layers = quads.layers;
  const visible = layers.find((l) => l.kind === LayerKind.VISIBLE);
  if (isReference && !visible) throw new Error("reference frame has no visible layer");
  if (!isReference && (header.referenceId !== (reference && reference.id) || !cache)) {
    needsReference = true;
    throw new Error(`residual frame ${header.frameId} needs reference ${header.referenceId}, the page has ${reference ? reference.id : "none"}`);
  }
  const width = picture.displayWidth, height = picture.displayHeight;
  layers.forEach((l, i) => {
    const [x, y, w, h] = l.rect;
    if (x + w > width || y + h > height) throw new Error(`layer ${i}: atlas rect ${l.rect} outside the ${width}x${height} video`);
    l.cam = layerCamera(l.camera);
  });
  if (isReference) {
    cache = new QuadCache(visible.width, visible.height);
    cache.reset(visible.rows, visible.count);
    reference = { id: header.frameId, camera: visible.cam, width: visible.width, height: visible.height, rect: visible.rect };
    // the far field comes with reference frames and stays until the next one (its colour is in every atlas)
    farLayers = layers.filter((l) => l.kind === LayerKind.FAR).map((l) => ({
      rows: l.rows, count: l.count, camera: l.cam, width: l.width, height: l.height, rect: l.rect,
      depthScale: FILL_DEPTH_SCALE[LayerKind.FAR] }));
  } else {
    const updated = layers.find((l) => l.kind === LayerKind.UPDATED);
    if (updated) cache.update(updated.rows, updated.count);
  }
  const mesh = [{ rows: cache.rows, count: cache.count, camera: reference.camera, width: reference.width,
                  height: reference.height, rect: reference.rect, depthScale: 1, cached: true }];
  for (const l of layers) {
    if (FILL_KINDS.includes(l.kind)) {
      mesh.push({ rows: l.rows, count: l.count, camera: l.cam, width: l.width, height: l.height, rect: l.rect,
                  depthScale: FILL_DEPTH_SCALE[l.kind] || 1 });
    }
  }
  mesh.push(...farLayers);
  renderer.setAtlas(picture, width, height);
  renderer.setLayers(mesh);
  const revealed = isReference ? null : layers.find((l) => l.kind === LayerKind.REVEALED);
  renderer.setCurrentView(revealed ? revealed.cam : null, revealed ? revealed.rect : null);
  stats.quads = renderer.quadCount;
  needsReference = false;
}

// ------------------------------------------------------------------------------------------------ display

function currentPose(now, dt) {
  if (fixedPose) return fixedPose;
  if (trace) {
    const duration = trace.times[trace.times.length - 1] - trace.times[0];
    return tracePoseAt(trace, trace.times[0] + (duration > 0 ? (now - traceStart) % duration : 0));
  }
  const speed = (user.keys.has("shift") ? 4 : 1.5) * dt;
  const q = quatFromYawPitch(user.yaw, 0);
  const move = (v, s) => rotate(q, v).forEach((c, k) => { user.position[k] += c * s; });
  if (user.keys.has("w")) move([0, 0, -1], speed);
  if (user.keys.has("s")) move([0, 0, 1], speed);
  if (user.keys.has("a")) move([-1, 0, 0], speed);
  if (user.keys.has("d")) move([1, 0, 0], speed);
  if (user.keys.has("e")) user.position[1] += speed;
  if (user.keys.has("q")) user.position[1] -= speed;
  return { position: user.position.slice(), quat: quatFromYawPitch(user.yaw, user.pitch) };
}

function sendPose(now, pose) {
  if (!stats.connected || now - lastPoseSent < 1 / POSE_HZ - 1e-3) return;
  lastPoseSent = now;
  send(encodePoseUpdate(poseSeq++, now, pose.position, pose.quat, xr ? null : pointerGaze));
}

function drawAt(pose) {
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  gl.viewport(0, 0, canvas.width, canvas.height);
  renderer.draw(viewMatrix(pose.position, pose.quat), symmetricFrustum(view.fovy, canvas.width / canvas.height));
}

function readCanvas() {
  const { width, height } = canvas;
  const rgba = new Uint8Array(width * height * 4);
  gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, rgba);
  return rgba;
}

let lastDisplay = null, lastHoles = -1, lastOverlay = -1;

function onAnimationFrame() {
  if (xr) return;                      // the XR session drives frames now
  requestAnimationFrame(onAnimationFrame);
  const now = clock();
  const dt = lastDisplay === null ? 0 : Math.min(now - lastDisplay, 0.1);
  lastDisplay = now;
  const pose = currentPose(now, dt);
  sendPose(now, pose);
  requestReference(session.tick(now));
  drawAt(pose);
  if (newest) {
    stats.framesDisplayed++;
    displayWindow.push(now);
    stats.frameAgeMs = (now - newest.t) * 1e3;
    if (now - lastHoles > 0.5) {      // the share of pixels no quad covers, twice a second
      lastHoles = now;
      const rgba = readCanvas();
      let holes = 0;
      for (let i = 3; i < rgba.length; i += 4) holes += rgba[i] === 0;
      stats.holes = holes / (rgba.length / 4);
    }
  }
  updateRates(now);
}

function updateRates(now) {
  displayWindow = displayWindow.filter((t) => now - t <= 1);
  byteWindow = byteWindow.filter(([t]) => now - t <= 1);
  stats.fps = displayWindow.length;
  stats.mbps = byteWindow.reduce((s, [, n]) => s + n, 0) * 8 / 1e6;
  if (now - lastOverlay > 0.25) {
    lastOverlay = now;
    showOverlay();
  }
}

function showOverlay() {
  const f = (v, d) => (v === null || v === undefined ? "–" : v.toFixed(d));
  const text = stats.error ? stats.error
    : `${stats.fps} fps · ${f(stats.mbps, 1)} Mbps · age ${f(stats.frameAgeMs, 0)} ms · frame ${stats.lastFrameId} · ` +
      `holes ${stats.holes === null ? "–" : (100 * stats.holes).toFixed(1)}% · ${stats.quads} quads · ${stats.status}`;
  document.getElementById("stats").textContent = text;
}

// Render at the current pose and read the canvas back: {width, height, rgba (base64, top row first)}.
function capture() {
  const pose = currentPose(clock(), 0);
  drawAt(pose);
  const { width, height } = canvas;
  const rgba = readCanvas();
  const rows = new Uint8Array(rgba.length), stride = width * 4;
  for (let y = 0; y < height; y++) rows.set(rgba.subarray((height - 1 - y) * stride, (height - y) * stride), y * stride);
  return { width, height, rgba: toBase64(rows), position: pose.position, quat: pose.quat, frameId: stats.lastFrameId };
}

// ------------------------------------------------------------------------------------------------ input

function setupInput() {
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener("pointerup", () => { drag = null; });
  const gazeBox = document.getElementById("gaze-pointer");
  gazeBox.checked = params.get("gaze") === "pointer";
  gazeBox.addEventListener("change", () => { if (!gazeBox.checked) pointerGaze = null; });
  canvas.addEventListener("pointermove", (e) => {
    if (gazeBox.checked) {
      const r = canvas.getBoundingClientRect();
      pointerGaze = gazeAt(e.clientX - (r.left + r.width / 2), r.top + r.height / 2 - e.clientY, r.height, view.fovy);
    }
    if (!drag) return;
    user.yaw -= 0.2 * (e.clientX - drag[0]);
    user.pitch = Math.max(-89, Math.min(89, user.pitch - 0.2 * (e.clientY - drag[1])));
    drag = [e.clientX, e.clientY];
  });
  addEventListener("keydown", (e) => {
    const k = e.key.toLowerCase();
    if (k === "h") document.getElementById("overlay").hidden ^= true;
    user.keys.add(k);
    if (e.shiftKey) user.keys.add("shift");
  });
  addEventListener("keyup", (e) => {
    user.keys.delete(e.key.toLowerCase());
    if (!e.shiftKey) user.keys.delete("shift");
  });
  addEventListener("blur", () => user.keys.clear());
  document.getElementById("trace-file").addEventListener("change", async (e) => {
    const file = e.target.files[0];
    if (!file) return;
    try {
      useTrace(parseQuasarTrace(await file.text(), file.name));
      fixedPose = null;
    } catch (err) {
      fail(err.message);
    }
  });
}

// ------------------------------------------------------------------------------------------------ WebXR

async function setupXR() {
  if (!navigator.xr) return;
  let supported = false;
  try {
    supported = await navigator.xr.isSessionSupported("immersive-vr");
  } catch (e) { /* no XR */ }
  if (!supported) return;
  const button = document.getElementById("enter-vr");
  button.hidden = false;
  button.addEventListener("click", () => startXR().catch((e) => fail(`WebXR: ${e.message}`)));
}

async function startXR() {
  const xrSession = await navigator.xr.requestSession("immersive-vr", { optionalFeatures: ["local-floor"] });
  await gl.makeXRCompatible();
  xrSession.updateRenderState({ baseLayer: new XRWebGLLayer(xrSession, gl) });
  let space, floor = true;
  try {
    space = await xrSession.requestReferenceSpace("local-floor");
  } catch (e) {
    space = await xrSession.requestReferenceSpace("local");
    floor = false;
  }
  // the headset's origin goes where the desktop view was (on the floor below it with local-floor), facing its way
  const here = currentPose(clock(), 0);
  const yaw = quatFromYawPitch(yawPitchOf(here.quat)[0], 0);
  const origin = new XRRigidTransform({ x: here.position[0], y: floor ? 0 : here.position[1], z: here.position[2] },
                                      { x: yaw[0], y: yaw[1], z: yaw[2], w: yaw[3] });
  const desktopView = { width: view.width, height: view.height, fovy: view.fovy };
  xr = { session: xrSession, space: space.getOffsetReferenceSpace(origin.inverse), streamed: false };
  xrSession.addEventListener("end", () => {
    xr = null;
    view = { ...view, ...desktopView };
    reconnect();
    requestAnimationFrame(onAnimationFrame);
  });
  xrSession.requestAnimationFrame(onXRFrame);
}

function onXRFrame(time, frame) {
  if (!xr) return;
  xr.session.requestAnimationFrame(onXRFrame);
  const viewer = frame.getViewerPose(xr.space);
  if (!viewer) return;
  const layer = xr.session.renderState.baseLayer;
  if (!xr.streamed) {                  // ask for the headset's field of view and eye size (one new session)
    const first = viewer.views[0], vp = layer.getViewport(first), p = first.projectionMatrix;
    const top = (1 + p[9]) / p[5], bottom = (p[9] - 1) / p[5];
    const fovy = 2 * Math.max(Math.atan(top), Math.atan(-bottom)) * 180 / Math.PI;
    const scale = Math.min(1, config.max_size[0] / vp.width, config.max_size[1] / vp.height, 1280 / vp.width);
    const even = (v) => Math.max(16, Math.floor(v * scale / 2) * 2);
    view = { ...view, width: even(vp.width), height: even(vp.height), fovy: Math.min(fovy, 170) };
    xr.streamed = true;
    reconnect();
  }
  const now = clock();
  const t = viewer.transform;
  const head = { position: [t.position.x, t.position.y, t.position.z],
                 quat: [t.orientation.x, t.orientation.y, t.orientation.z, t.orientation.w] };
  sendPose(now, head);
  requestReference(session.tick(now));
  gl.bindFramebuffer(gl.FRAMEBUFFER, layer.framebuffer);
  gl.clearColor(0, 0, 0, 1);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  for (const eye of viewer.views) {    // each eye rendered from the mesh (no YORO synthesis in WebGL2 here)
    const vp = layer.getViewport(eye);
    gl.viewport(vp.x, vp.y, vp.width, vp.height);
    renderer.draw(eye.transform.inverse.matrix, eye.projectionMatrix, false);
  }
  if (newest) {
    stats.framesDisplayed++;
    displayWindow.push(now);
    stats.frameAgeMs = (now - newest.t) * 1e3;
  }
  updateRates(now);
}

start().catch((e) => {
  fatal = true;
  fail(e.message);
});
