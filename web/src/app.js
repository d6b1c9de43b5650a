// The live page: the camera -> MediaPipe's PoseLandmarker in this browser -> COCO-17 keypoints
// (pixels, with each landmark's visibility as confidence, and the image size) -> one
// blapose session over the server's WebSocket, which carries the same
// StreamRequest / StreamResponse messages as gRPC's Stream. The server lifts the
// keypoints (server_lifter), adjusts the bone lengths and runs the causal motion
// stage; the page draws the adjusted skeleton (three.js), the bone lengths as they
// settle, frames/s and the capture-to-answer latency. Its figures are
// window.blapose.stats, which the browser test reads.
import * as THREE from "./vendor/three/three.module.js";

const WS_PATH = "/v1/stream";
// MediaPipe Pose landmark of each COCO-17 joint, in COCO order.
const COCO_FROM_MEDIAPIPE = [0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28];
// Human3.6M-17 parents (the answers' joint order).
const PARENTS = [-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 8, 11, 12, 8, 14, 15];
// Frames in flight at most: a slow server or network costs frames, never a queue.
const MAX_IN_FLIGHT = 4;
const HISTORY = 150;

const stats = {
  frames_sent: 0,
  frames_answered: 0,
  frames_skipped: 0,
  detections: 0,
  camera_frames: 0,
  errors: 0,
  last_error: null,
  fps: 0,
  latency_p50_ms: null,
  latency_p99_ms: null,
  lengths_m: null,
  lengths_std_mm_last_50: null,
  session_id: null,
  motion: false,
};
let paused = false;
window.blapose = {
  stats,
  pause: () => { paused = true; },
  resume: () => { paused = false; },
  // The take as a file (bvh, c3d, trc or npz), written by the server: a Blob.
  exportTake: (format) => exportTake(format),
};

const statusEl = document.getElementById("status");
const status = (text) => { statusEl.textContent = text; };
const fail = (text) => { status("error: " + text); stats.errors++; stats.last_error = text; };

// ---- the protocol: the server's own proto, field names as written there --------------
const protoText = await (await fetch("blapose.proto")).text();
const root = protobuf.parse(protoText, { keepCase: true }).root;
const Req = root.lookupType("blapose.v1.StreamRequest");
const Resp = root.lookupType("blapose.v1.StreamResponse");
const encode = (msg) => Req.encode(Req.create(msg)).finish();

// ---- the camera ------------------------------------------------------------------------
const video = document.getElementById("video");
try {
  video.srcObject = await navigator.mediaDevices.getUserMedia({ video: { width: 640, height: 480 }, audio: false });
  await video.play();
} catch (e) {
  fail("no camera: " + e.message);
  throw e;
}
const W = video.videoWidth, H = video.videoHeight;

// ---- the session -------------------------------------------------------------------------
let ws = null, opened = false, nextIndex = 0;
const sentAt = new Map(), sentTime = new Map();
function subject() {
  const h = parseFloat(document.getElementById("height").value);
  const sex = parseInt(document.getElementById("sex").value, 10) || 0;
  return Number.isFinite(h) ? { height_m: h, sex } : undefined;
}
function connect() {
  const token = new URLSearchParams(location.search).get("token");
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  ws = new WebSocket(`${scheme}://${location.host}${WS_PATH}` + (token ? `?token=${encodeURIComponent(token)}` : ""));
  ws.binaryType = "arraybuffer";
  opened = false;
  sentAt.clear(); sentTime.clear();
  const socket = ws;
  take.clear();
  ws.onopen = () => socket.send(encode({
    open: {
      input_format: { layout: 3, image_size: { width: W, height: H } }, // COCO-17, pixels
      server_lifter: true,
      client_label: "live page",
      motion: { enabled: true, frame_rate_hz: 30 },
      subject: subject(),
    },
  }));
  ws.onmessage = (ev) => {
    // A text message is the stream's final error status (then the socket closes with 4000 + its code).
    if (typeof ev.data === "string") {
      const s = JSON.parse(ev.data);
      stats.errors++;
      stats.last_error = `${s.status}: ${s.message}`;
      return;
    }
    answer(Resp.toObject(Resp.decode(new Uint8Array(ev.data)), { longs: Number, defaults: true }));
  };
  ws.onclose = (ev) => {
    if (socket !== ws) return;
    opened = false;
    status(`disconnected (${ev.code}${ev.reason ? ": " + ev.reason : ""}); reconnecting`);
    setTimeout(connect, 1000);
  };
}
document.getElementById("person").addEventListener("submit", (ev) => {
  ev.preventDefault();
  const old = ws;
  connect();
  old.close();
});

// ---- the take: what was sent and answered, for the download --------------------------------
// The last TAKE_FRAMES answered frames of this session (5 minutes at 30 frames/s, the size the
// server's export takes): the keypoints sent, the server lifter's poses, the adjusted poses and
// the last bone lengths. The server writes the file with the CLI's and Python's writers.
const TAKE_FRAMES = 9000;
const take = {
  pending: new Map(), frames: [], lengths: null,
  clear() { this.pending.clear(); this.frames = []; this.lengths = null; },
  sent(index, kp, conf) { this.pending.set(index, { kp, conf }); },
  add(f) {
    const s = this.pending.get(f.frame_index);
    this.pending.delete(f.frame_index);
    if (!s || f.lifted_pose_3d.length !== 51 || f.adjusted_pose_3d.length !== 51) return;
    this.frames.push({ kp: s.kp, conf: s.conf, lifted: f.lifted_pose_3d, adjusted: f.adjusted_pose_3d });
    if (this.frames.length > TAKE_FRAMES) this.frames.shift();
    this.lengths = f.bone_lengths;
  },
};
async function exportTake(format) {
  if (!take.frames.length) throw new Error("nothing to download yet: no frame answered");
  // Rounded (0.01 px, 0.001 confidence, 0.01 mm) so that 5 minutes stay under the server's limit.
  const round = (scale) => (v) => Math.round(v * scale) / scale;
  const body = JSON.stringify({
    fps: 30, layout: "coco17", image_size: [W, H],
    keypoints_2d: take.frames.flatMap((f) => f.kp.map(round(1e2))),
    confidence: take.frames.flatMap((f) => f.conf.map(round(1e3))),
    pose_3d: take.frames.flatMap((f) => f.lifted.map(round(1e5))),
    adjusted: take.frames.flatMap((f) => f.adjusted.map(round(1e5))),
    bone_lengths: take.lengths.map(round(1e5)),
  });
  const token = new URLSearchParams(location.search).get("token");
  const url = `/v1/export/${format}` + (token ? `?token=${encodeURIComponent(token)}` : "");
  const res = await fetch(url, { method: "POST", headers: { "content-type": "application/json" }, body });
  if (!res.ok) throw new Error(`${res.status}: ${await res.text()}`);
  return res.blob();
}
document.getElementById("download").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const format = document.getElementById("format").value;
  try {
    const blob = await exportTake(format);
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = `blapose-take.${format}`;
    a.click();
    setTimeout(() => URL.revokeObjectURL(a.href), 10000);
    document.getElementById("download-status").textContent = `${take.frames.length} frames, ${blob.size} bytes`;
  } catch (e) {
    document.getElementById("download-status").textContent = e.message;
  }
});

// ---- answers -------------------------------------------------------------------------------
const latencies = [], answeredAt = [], lengthHistory = [];
// Where the time goes: stats.<name>_ms_p50 / _p99 over the last 300 frames.
const timings = {};
function timing(name, ms) {
  const t = (timings[name] ??= []);
  t.push(ms);
  if (t.length > 300) t.shift();
  stats[`${name}_ms_p50`] = percentile(t, 0.5);
  stats[`${name}_ms_p99`] = percentile(t, 0.99);
}
function percentile(values, p) {
  const s = [...values].sort((a, b) => a - b);
  return s.length ? s[Math.min(s.length - 1, Math.floor(p * s.length))] : null;
}
function answer(msg) {
  if (msg.opened) {
    opened = true;
    stats.session_id = msg.opened.session_id;
    stats.motion = !!(msg.opened.motion && msg.opened.motion.enabled);
    status(`live: session ${msg.opened.session_id.slice(0, 8)}, lifter ${msg.opened.lifter || "?"}`);
    return;
  }
  if (msg.error) {
    sentAt.delete(msg.error.frame_index); sentTime.delete(msg.error.frame_index); take.pending.delete(msg.error.frame_index);
    stats.errors++;
    stats.last_error = msg.error.message;
    return;
  }
  if (!msg.frame) return;
  const f = msg.frame, now = performance.now();
  take.add(f);
  const t0 = sentAt.get(f.frame_index);
  sentAt.delete(f.frame_index);
  stats.frames_answered++;
  if (t0 !== undefined) latencies.push(now - t0);
  if (sentTime.has(f.frame_index)) timing("answer", now - sentTime.get(f.frame_index));
  sentTime.delete(f.frame_index);
  if (latencies.length > 300) latencies.shift();
  answeredAt.push(now);
  while (answeredAt.length && answeredAt[0] < now - 2000) answeredAt.shift();
  stats.fps = answeredAt.length / 2;
  stats.latency_p50_ms = percentile(latencies, 0.5);
  stats.latency_p99_ms = percentile(latencies, 0.99);
  stats.lengths_m = f.bone_lengths;
  lengthHistory.push(f.bone_lengths);
  if (lengthHistory.length > HISTORY) lengthHistory.shift();
  const last = lengthHistory.slice(-50);
  if (last.length === 50) {
    let worst = 0;
    for (let b = 0; b < 16; b++) {
      const m = last.reduce((s, l) => s + l[b], 0) / 50;
      worst = Math.max(worst, Math.sqrt(last.reduce((s, l) => s + (l[b] - m) ** 2, 0) / 50));
    }
    stats.lengths_std_mm_last_50 = worst * 1000;
  }
  drawSkeleton(f.adjusted_pose_3d);
}

// ---- MediaPipe's PoseLandmarker, frame by frame (pose-worker.js) -----------------------------------
const overlay = document.getElementById("overlay");
function onPose(lm, captureTime) {
  stats.camera_frames++;
  if (overlay.width !== W || overlay.height !== H) { overlay.width = W; overlay.height = H; }
  const g = overlay.getContext("2d");
  g.clearRect(0, 0, W, H);
  if (!lm) return;
  stats.detections++;
  const kp = [], conf = [];
  for (const i of COCO_FROM_MEDIAPIPE) {
    kp.push(lm[i].x * W, lm[i].y * H);
    conf.push(Math.min(1, Math.max(0, lm[i].visibility ?? 1)));
  }
  g.fillStyle = "#22c55e";
  for (let j = 0; j < 17; j++) { g.beginPath(); g.arc(kp[2 * j], kp[2 * j + 1], 4, 0, 2 * Math.PI); g.fill(); }
  if (paused || !opened || ws.readyState !== WebSocket.OPEN || !kp.every(Number.isFinite)) return;
  if (sentAt.size >= MAX_IN_FLIGHT) { stats.frames_skipped++; return; }
  const index = nextIndex++;
  sentAt.set(index, captureTime);
  sentTime.set(index, performance.now());
  take.sent(index, kp, conf);
  ws.send(encode({ frame: { frame_index: index, keypoints_2d: kp, confidence: conf } }));
  stats.frames_sent++;
}
const worker = new Worker("pose-worker.js", { type: "module" });
await new Promise((resolve, reject) => {
  worker.onmessage = ({ data }) => (data.ready ? resolve() : reject(new Error(data.error)));
  worker.onerror = (e) => reject(new Error(e.message));
  worker.postMessage({ init: true });
}).catch((e) => { fail("pose: " + e.message); throw e; });
worker.onerror = (e) => fail("pose: " + e.message);
connect();
// One frame with the model at a time, the newest: a slow model costs frames, never a queue.
// It sees at most 256 x 256 pixels, so it gets a 320-pixel copy.
const SCALE = Math.min(1, 320 / Math.max(W, H));
let busy = false, fresh = false, captureTime = 0;
async function pump() {
  if (busy || !fresh || video.readyState < 2) return;
  busy = true; fresh = false;
  captureTime = performance.now();
  try {
    const frame = await createImageBitmap(video, { resizeWidth: Math.round(W * SCALE), resizeHeight: Math.round(H * SCALE) });
    timing("capture", performance.now() - captureTime);
    worker.postMessage({ frame, time: captureTime }, [frame]);
  } catch (e) { busy = false; fail("pose: " + e.message); }
}
worker.onmessage = ({ data }) => {
  busy = false;
  if (data.error) fail("pose: " + data.error);
  else {
    timing("pose", data.ms);
    timing("model_wait", performance.now() - captureTime);
    onPose(data.landmarks, captureTime);
  }
  pump();
};
function newFrame() {
  fresh = true;
  pump();
  if (video.requestVideoFrameCallback) video.requestVideoFrameCallback(newFrame);
  else setTimeout(newFrame, 1000 / 30);
}
newFrame();

// ---- the 3D view ---------------------------------------------------------------------------------
const holder = document.getElementById("view3d");
// No antialiasing where WebGL is software (SwiftShader: no GPU), where it costs the most.
const software = (() => {
  const gl = document.createElement("canvas").getContext("webgl2");
  const info = gl && gl.getExtension("WEBGL_debug_renderer_info");
  const yes = !!info && /swiftshader|llvmpipe|software/i.test(gl.getParameter(info.UNMASKED_RENDERER_WEBGL));
  gl?.getExtension("WEBGL_lose_context")?.loseContext();
  return yes;
})();
const renderer = new THREE.WebGLRenderer({ antialias: !software, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio || 1);
holder.append(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0xf1f3f7);
const camera = new THREE.PerspectiveCamera(40, 4 / 3, 0.1, 50);
camera.position.set(1.6, 0.4, 3.2);
camera.lookAt(0, -0.1, 0);
const grid = new THREE.GridHelper(4, 16, 0x8a94a6, 0xc9ced8);
grid.position.y = -0.95;
scene.add(grid);
const bones = new THREE.BufferGeometry();
bones.setAttribute("position", new THREE.BufferAttribute(new Float32Array(16 * 2 * 3), 3));
bones.setAttribute("color", new THREE.BufferAttribute(new Float32Array(16 * 2 * 3), 3));
scene.add(new THREE.LineSegments(bones, new THREE.LineBasicMaterial({ vertexColors: true, linewidth: 3 })));
const joints = new THREE.InstancedMesh(new THREE.SphereGeometry(0.025, 12, 8), new THREE.MeshBasicMaterial({ color: 0x1d2330 }), 17);
scene.add(joints);
let redraw = true;
const LEFT = new Set([4, 5, 6, 11, 12, 13]), RIGHT = new Set([1, 2, 3, 14, 15, 16]);
function resize3d() {
  const w = holder.clientWidth, h = holder.clientHeight;
  renderer.setSize(w, h, false);
  renderer.domElement.style.width = "100%"; renderer.domElement.style.height = "100%";
  camera.aspect = w / h; camera.updateProjectionMatrix();
  redraw = true;
}
window.addEventListener("resize", resize3d);
resize3d();
// Camera axes (x right, y down, z forward) to three's (y up, z towards the viewer).
const toScene = (p, j) => [p[3 * j], -p[3 * j + 1], -p[3 * j + 2]];
function drawSkeleton(p) {
  if (!p || p.length !== 51) return;
  const pos = bones.attributes.position.array, col = bones.attributes.color.array;
  const m = new THREE.Matrix4();
  for (let j = 0; j < 17; j++) { const [x, y, z] = toScene(p, j); m.makeTranslation(x, y, z); joints.setMatrixAt(j, m); }
  joints.instanceMatrix.needsUpdate = true;
  for (let b = 0; b < 16; b++) {
    const c = b + 1, pa = PARENTS[c];
    pos.set([...toScene(p, pa), ...toScene(p, c)], 6 * b);
    const rgb = LEFT.has(c) ? [0.15, 0.39, 0.92] : RIGHT.has(c) ? [0.86, 0.15, 0.15] : [0.22, 0.25, 0.32];
    col.set([...rgb, ...rgb], 6 * b);
  }
  bones.attributes.position.needsUpdate = true;
  bones.attributes.color.needsUpdate = true;
  bones.computeBoundingSphere();
  redraw = true;
}

// ---- figures and the lengths chart, a few times a second ------------------------------------------
const chart = document.getElementById("lengths");
function drawLengths() {
  const dpr = window.devicePixelRatio || 1;
  chart.width = chart.clientWidth * dpr; chart.height = chart.clientHeight * dpr;
  const g = chart.getContext("2d"), w = chart.width, h = chart.height;
  g.clearRect(0, 0, w, h);
  if (lengthHistory.length < 2) return;
  let lo = Infinity, hi = -Infinity;
  for (const l of lengthHistory) for (const v of l) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  const y = (v) => h - 6 * dpr - (v - lo) / Math.max(hi - lo, 1e-3) * (h - 12 * dpr);
  const x = (i) => i / (HISTORY - 1) * w;
  for (let b = 0; b < 16; b++) {
    g.strokeStyle = `hsl(${(b * 360) / 16}, 60%, 45%)`; g.lineWidth = 1.5 * dpr; g.beginPath();
    lengthHistory.forEach((l, i) => (i ? g.lineTo(x(i), y(l[b])) : g.moveTo(x(i), y(l[b]))));
    g.stroke();
  }
  g.fillStyle = "#667085"; g.font = `${11 * dpr}px system-ui`;
  g.fillText(`${(hi * 1000).toFixed(0)}`, 4 * dpr, 12 * dpr); g.fillText(`${(lo * 1000).toFixed(0)}`, 4 * dpr, h - 4 * dpr);
}
const fmt = (v, d = 1) => (v == null ? "-" : v.toFixed(d));
// Drawn when something changed: a browser without a GPU renders in software.
(function frame() {
  if (redraw) { renderer.render(scene, camera); redraw = false; }
  requestAnimationFrame(frame);
})();
setInterval(() => {
  drawLengths();
  document.getElementById("fps").textContent = fmt(stats.fps);
  document.getElementById("latency").textContent = `${fmt(stats.latency_p50_ms)} / ${fmt(stats.latency_p99_ms)} ms`;
  document.getElementById("counts").textContent = `${stats.frames_sent} / ${stats.frames_answered} / ${stats.errors}`;
  document.getElementById("spread").textContent = stats.lengths_std_mm_last_50 == null ? "-" : `${fmt(stats.lengths_std_mm_last_50, 2)} mm (largest bone)`;
}, 250);
