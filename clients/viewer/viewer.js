// edmcgs browser viewer: the live stream over WS /stream, scrubbing over GET /render, and a free camera.
//
// No build step and nothing fetched from elsewhere: one file of plain JS, served by edmcgs-serve at /.
// Poses are camera-to-world 4x4, row-major, OpenCV convention (x right, y down, z forward), as on the
// wire. A pose of null means "the event camera's own pose at t", which the server fills in.
"use strict";

// ---------------------------------------------------------------- msgpack (decode only)
// Frames arrive as msgpack maps; subscriptions go out as JSON text, which the server also accepts.

function unpack(bytes) {
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const utf8 = new TextDecoder();
  let pos = 0;
  const need = (n) => {
    if (pos + n > bytes.length) throw new Error("msgpack: truncated message");
  };
  const take = (n) => { need(n); const start = pos; pos += n; return start; };
  const str = (n) => { const s = take(n); return utf8.decode(bytes.subarray(s, s + n)); };
  const bin = (n) => { const s = take(n); return bytes.slice(s, s + n); };
  const arr = (n) => { const out = new Array(n); for (let i = 0; i < n; i++) out[i] = read(); return out; };
  const map = (n) => {
    const out = {};
    for (let i = 0; i < n; i++) { const key = read(); out[key] = read(); }
    return out;
  };
  // Number() of a 64-bit integer is exact below 2^53 (9e15): Unix-epoch microseconds fit.
  const u8 = () => view.getUint8(take(1)), u16 = () => view.getUint16(take(2));
  const u32 = () => view.getUint32(take(4));
  function read() {
    const b = view.getUint8(take(1));
    if (b <= 0x7f) return b;
    if (b >= 0xe0) return b - 0x100;
    if (b >= 0x80 && b <= 0x8f) return map(b & 0x0f);
    if (b >= 0x90 && b <= 0x9f) return arr(b & 0x0f);
    if (b >= 0xa0 && b <= 0xbf) return str(b & 0x1f);
    switch (b) {
      case 0xc0: return null;
      case 0xc2: return false;
      case 0xc3: return true;
      case 0xc4: return bin(u8());
      case 0xc5: return bin(u16());
      case 0xc6: return bin(u32());
      case 0xca: return view.getFloat32(take(4));
      case 0xcb: return view.getFloat64(take(8));
      case 0xcc: return u8();
      case 0xcd: return u16();
      case 0xce: return u32();
      case 0xcf: return Number(view.getBigUint64(take(8)));
      case 0xd0: return view.getInt8(take(1));
      case 0xd1: return view.getInt16(take(2));
      case 0xd2: return view.getInt32(take(4));
      case 0xd3: return Number(view.getBigInt64(take(8)));
      case 0xd9: return str(u8());
      case 0xda: return str(u16());
      case 0xdb: return str(u32());
      case 0xdc: return arr(u16());
      case 0xdd: return arr(u32());
      case 0xde: return map(u16());
      case 0xdf: return map(u32());
      default: throw new Error(`msgpack: unsupported type byte 0x${b.toString(16)}`);
    }
  }
  const value = read();
  if (pos !== bytes.length) throw new Error("msgpack: trailing bytes after the message");
  return value;
}

// ---------------------------------------------------------------- pose math
// A rotation R is 3 rows of 3; R[i][j] with column j the camera's axis j expressed in the world.

const col = (R, j) => [R[0][j], R[1][j], R[2][j]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const norm = (a) => Math.sqrt(dot(a, a));

function matmul3(A, B) {
  return [0, 1, 2].map((i) => [0, 1, 2].map((j) => A[i][0] * B[0][j] + A[i][1] * B[1][j] + A[i][2] * B[2][j]));
}

// Rodrigues: rotation by `angle` radians about the unit vector `axis`.
function axisAngle(axis, angle) {
  const [x, y, z] = scale(axis, 1 / norm(axis));
  const c = Math.cos(angle), s = Math.sin(angle), t = 1 - c;
  return [
    [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
    [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
    [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
  ];
}

function splitPose(m) {  // row-major 16 -> {R, C}
  return {
    R: [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]],
    C: [m[3], m[7], m[11]],
  };
}

function joinPose(R, C) {
  return [...R[0], C[0], ...R[1], C[1], ...R[2], C[2], 0, 0, 0, 1];
}

function quatFromRot(R) {  // (w, x, y, z), Shepperd's method: stable for every rotation
  const tr = R[0][0] + R[1][1] + R[2][2];
  let q;
  if (tr > 0) {
    const s = 2 * Math.sqrt(tr + 1);
    q = [0.25 * s, (R[2][1] - R[1][2]) / s, (R[0][2] - R[2][0]) / s, (R[1][0] - R[0][1]) / s];
  } else if (R[0][0] > R[1][1] && R[0][0] > R[2][2]) {
    const s = 2 * Math.sqrt(1 + R[0][0] - R[1][1] - R[2][2]);
    q = [(R[2][1] - R[1][2]) / s, 0.25 * s, (R[0][1] + R[1][0]) / s, (R[0][2] + R[2][0]) / s];
  } else if (R[1][1] > R[2][2]) {
    const s = 2 * Math.sqrt(1 + R[1][1] - R[0][0] - R[2][2]);
    q = [(R[0][2] - R[2][0]) / s, (R[0][1] + R[1][0]) / s, 0.25 * s, (R[1][2] + R[2][1]) / s];
  } else {
    const s = 2 * Math.sqrt(1 + R[2][2] - R[0][0] - R[1][1]);
    q = [(R[1][0] - R[0][1]) / s, (R[0][2] + R[2][0]) / s, (R[1][2] + R[2][1]) / s, 0.25 * s];
  }
  const n = Math.hypot(...q);
  return q.map((v) => v / n);
}

function rotFromQuat([w, x, y, z]) {
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ];
}

function slerp(q0, q1, a) {
  let d = q0.reduce((s, v, i) => s + v * q1[i], 0);
  if (d < 0) { q1 = q1.map((v) => -v); d = -d; }  // the shorter arc
  if (d > 0.9995) {  // nearly equal: lerp, then normalise
    const q = q0.map((v, i) => v + a * (q1[i] - v));
    const n = Math.hypot(...q);
    return q.map((v) => v / n);
  }
  const th = Math.acos(d), s = Math.sin(th);
  const k0 = Math.sin((1 - a) * th) / s, k1 = Math.sin(a * th) / s;
  return q0.map((v, i) => k0 * v + k1 * q1[i]);
}

// The event camera's pose at tUs from the scene's trajectory samples: slerp + linear, clamped to its
// span (the server's Trajectory.at does the same). Null when the scene has no trajectory.
function poseAt(traj, tUs) {
  if (!traj || !traj.t_us || traj.t_us.length === 0) return null;
  const ts = traj.t_us, n = ts.length;
  if (n === 1 || tUs <= ts[0]) return traj.c2w[0].slice();
  if (tUs >= ts[n - 1]) return traj.c2w[n - 1].slice();
  let lo = 0, hi = n - 1;
  while (hi - lo > 1) { const mid = (lo + hi) >> 1; if (ts[mid] <= tUs) lo = mid; else hi = mid; }
  const a = (tUs - ts[lo]) / (ts[hi] - ts[lo]);
  const p0 = splitPose(traj.c2w[lo]), p1 = splitPose(traj.c2w[hi]);
  const R = rotFromQuat(slerp(quatFromRot(p0.R), quatFromRot(p1.R), a));
  return joinPose(R, p0.C.map((v, i) => v + a * (p1.C[i] - v)));
}

// A turntable camera around a target in front of the base camera: yaw about the base camera's up
// (-y), pitch about its right (x), distance along the view axis, and a pan of the target.
class Orbit {
  constructor(baseC2w, depth) {
    const { R, C } = splitPose(baseC2w);
    this.R0 = R;
    this.up = scale(col(R, 1), -1);
    this.right = col(R, 0);
    this.target = add(C, scale(col(R, 2), depth));
    this.dist = depth;
    this.minDist = depth * 1e-3;
    this.yaw = 0;
    this.pitch = 0;
  }

  rotation() {
    return matmul3(axisAngle(this.up, this.yaw), matmul3(axisAngle(this.right, this.pitch), this.R0));
  }

  rotate(dYaw, dPitch) {
    this.yaw += dYaw;
    this.pitch = Math.max(-1.55, Math.min(1.55, this.pitch + dPitch));  // stay short of the poles
  }

  // dx, dy: image-plane motion in world units at the target's depth; the scene follows the pointer.
  pan(dx, dy) {
    const R = this.rotation();
    this.target = add(this.target, add(scale(col(R, 0), -dx), scale(col(R, 1), -dy)));
  }

  zoom(factor) {
    this.dist = Math.max(this.minDist, this.dist * factor);
  }

  c2w() {
    const R = this.rotation();
    return joinPose(R, add(this.target, scale(col(R, 2), -this.dist)));
  }
}

// How far in front of the camera to orbit: the depth of the scene's centre (the point the training
// cameras look at) if the server states it, else of the world origin (synthetic scenes sit around
// it), else the camera's distance from the origin.
function orbitDepth(scene, c2w) {
  const { R, C } = splitPose(c2w);
  const centre = (scene.training_views && scene.training_views.center) || [0, 0, 0];
  const d = dot(col(R, 2), centre.map((v, i) => v - C[i]));
  if (Number.isFinite(d) && d > 1e-3) return d;
  return Math.max(norm(C), 1);
}

// ---------------------------------------------------------------- far from the training views
// A view is near a training view when its camera centre moved at most FAR_DISTANCE scene scales from
// it (the training cameras' median distance from the scene's centre) and its optical axis turned at
// most FAR_ANGLE_DEG from it; a roll about the axis keeps the same rays and counts for nothing. An
// orbit of 20 degrees about the centre reaches both limits together (2 sin(10 deg) = 0.35). Near no
// training view, the render shows surfaces no training camera saw: the model smears them.

const FAR_ANGLE_DEG = 20;
const FAR_DISTANCE = 0.35;

// The nearest training view to c2w: {distance (scene scales), angleDeg, ratio, far}, ratio being
// the larger of distance / FAR_DISTANCE and angleDeg / FAR_ANGLE_DEG (far: ratio > 1). Null when the
// scene lists no training views.
function nearestTrainingView(views, c2w) {
  if (!views || !views.c2w || views.c2w.length === 0 || !(views.scale > 0)) return null;
  const { R, C } = splitPose(c2w);
  const z = col(R, 2), zn = norm(z);
  let best = null;
  for (const m of views.c2w) {
    const v = splitPose(m);
    const d = norm(add(C, scale(v.C, -1))) / views.scale;
    const zv = col(v.R, 2);
    const cos = Math.max(-1, Math.min(1, dot(z, zv) / (zn * norm(zv))));
    const a = (Math.acos(cos) * 180) / Math.PI;
    const ratio = Math.max(d / FAR_DISTANCE, a / FAR_ANGLE_DEG);
    if (best === null || ratio < best.ratio) best = { distance: d, angleDeg: a, ratio };
  }
  best.far = best.ratio > 1;
  return best;
}

// ---------------------------------------------------------------- a pose typed or pasted
// Camera-to-world, OpenCV convention, as the server's pose= takes it: 16 numbers (the 4x4 row-major) or
// 7, tx,ty,tz,qw,qx,qy,qz with the quaternion's w FIRST (a TUM trajectory file's line puts it last:
// t tx ty tz qx qy qz qw). Numbers are separated by commas, spaces, semicolons or brackets (a JSON array,
// nested or not, or numpy's print of a 4x4 pastes as it is).

const ROTATION_ATOL = 1e-3;  // as the server's pose check (edmcgs.geometry.ROTATION_ATOL)

// The 16 numbers (row-major c2w, its rotation made exactly orthonormal) of a pose's text; throws an Error
// whose message says what is wrong, for a person.
function parsePose(text) {
  const parts = String(text).split(/[\s,;[\]()]+/).filter((p) => p !== "");
  if (parts.length === 0) throw new Error("type 16 numbers (a 4x4 camera-to-world matrix, row-major) or 7 (tx,ty,tz,qw,qx,qy,qz)");
  const nums = parts.map((p, i) => {
    const v = Number(p);
    if (!Number.isFinite(v)) throw new Error(`number ${i + 1}, ${JSON.stringify(p.slice(0, 20))}, is not a finite number`);
    return v;
  });
  let R, C;
  if (nums.length === 7) {
    const q = nums.slice(3);
    const n = Math.hypot(...q);
    if (!(n > 1e-12)) throw new Error("the quaternion (qw,qx,qy,qz) is zero: it describes no rotation");
    R = rotFromQuat(q.map((v) => v / n));
    C = nums.slice(0, 3);
  } else if (nums.length === 16) {
    const bottom = nums.slice(12);
    if (Math.max(...bottom.map((v, i) => Math.abs(v - (i === 3 ? 1 : 0)))) > 1e-6) {
      throw new Error(`the matrix's bottom row must be 0,0,0,1, got ${bottom.join(",")}`);
    }
    ({ R, C } = splitPose(nums));
    let err = 0;
    for (let i = 0; i < 3; i++) {
      for (let j = 0; j < 3; j++) err = Math.max(err, Math.abs(dot(col(R, i), col(R, j)) - (i === j ? 1 : 0)));
    }
    if (err > ROTATION_ATOL) {
      throw new Error(`the 3x3 rotation is not orthonormal (max |RᵀR − I| = ${err.toPrecision(3)} > ${ROTATION_ATOL})`);
    }
    const det = dot(col(R, 0), [R[1][1] * R[2][2] - R[2][1] * R[1][2], R[2][1] * R[0][2] - R[0][1] * R[2][2],
      R[0][1] * R[1][2] - R[1][1] * R[0][2]]);
    if (det < 0) throw new Error("the 3x3 rotation has determinant −1: a reflection, not a rotation");
    R = rotFromQuat(quatFromRot(R));  // exactly orthonormal
  } else {
    throw new Error(`got ${nums.length} numbers: give 16 (a 4x4 camera-to-world matrix, row-major) or 7 ` +
      "(tx,ty,tz,qw,qx,qy,qz, the quaternion's w first)");
  }
  return joinPose(R, C);
}

// ---------------------------------------------------------------- the training cameras as frustums
// The cameras of the frames the checkpoint was trained on (its anchors, posed on its trajectory) as
// wireframe pyramids: the apex the camera's centre, the base its image rectangle FRUSTUM_DEPTH scene
// scales in front of it, and a small triangle on the base's top edge (the camera's up, -y); and the path
// of every training view (GET /scene's training_views) as a line through their centres. Drawn over the
// render, projected with the camera the render was made from (the server's intrinsics, scaled as it
// scales them to the render's size); lines are clipped at a near plane, and a camera whose centre is not
// in front of that one is left out (the render's own camera among them).

const FRUSTUM_DEPTH = 0.06;  // scene scales (the training cameras' median distance from the centre)

// Projection of world points into a canvas of width x height from camera c2w (canvas coordinates: a
// pixel's edges at integers): toCamera(X) -> camera coordinates; segment(a, b) -> [x0, y0, x1, y1] of
// the part of camera-space segment a-b in front of the near plane, or null.
function projector(c2w, intr, width, height, near) {
  const { R, C } = splitPose(c2w);
  const sx = width / intr.width, sy = height / intr.height;
  const toCamera = (X) => { const d = add(X, scale(C, -1)); return [dot(col(R, 0), d), dot(col(R, 1), d), dot(col(R, 2), d)]; };
  const toCanvas = (p) => [sx * (intr.fx * p[0] / p[2] + intr.cx + 0.5), sy * (intr.fy * p[1] / p[2] + intr.cy + 0.5)];
  const segment = (a, b) => {
    if (a[2] <= near && b[2] <= near) return null;
    if (a[2] < near || b[2] < near) {
      const f = (near - a[2]) / (b[2] - a[2]);
      const m = [a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), near];
      if (a[2] < near) a = m; else b = m;
    }
    return [...toCanvas(a), ...toCanvas(b)];
  };
  return { toCamera, segment };
}

// The poses (16 numbers each) of the training frames: the trajectory at each anchor time.
function anchorPoses(trajectory, anchorsUs) {
  if (!trajectory || !anchorsUs) return [];
  return anchorsUs.map((t) => poseAt(trajectory, t)).filter((p) => p !== null);
}

// [{index, segs: [[x0, y0, x1, y1], ...]}]: the 2D segments of each camera of ``poses`` (index: its place
// in ``poses``), a scene of scale ``sceneScale``, drawn from c2w into a canvas of width x height.
function frustumSegments(poses, sceneScale, c2w, intr, width, height) {
  if (!poses || !(sceneScale > 0) || !c2w) return [];
  const size = FRUSTUM_DEPTH * sceneScale;
  const near = 1e-3 * sceneScale;
  const { toCamera, segment } = projector(c2w, intr, width, height, near);
  // The base's corners through the image's edges (pixel centres at integers: edges at -0.5, W - 0.5).
  const ray = (u, v) => [(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, 1];
  const l = -0.5, r = intr.width - 0.5, t = -0.5, b = intr.height - 0.5;
  const base = [ray(l, t), ray(r, t), ray(r, b), ray(l, b)];
  const halfW = (base[1][0] - base[0][0]) / 2, halfH = (base[3][1] - base[0][1]) / 2;
  const mid = (base[0][0] + base[1][0]) / 2;
  const up = [[base[0][0] + 0.5 * halfW, base[0][1], 1], [mid, base[0][1] - 0.45 * halfH, 1],
    [base[1][0] - 0.5 * halfW, base[0][1], 1]];
  const out = [];
  poses.forEach((m, index) => {
    const v = splitPose(m);
    const apex = toCamera(v.C);
    if (apex[2] <= near) return;
    const world = (d) => add(v.C, [dot(v.R[0], d) * size, dot(v.R[1], d) * size, dot(v.R[2], d) * size]);
    const corners = base.map((d) => toCamera(world(d)));
    const tick = up.map((d) => toCamera(world(d)));
    const pairs = [
      ...corners.map((c) => [apex, c]),
      ...corners.map((c, i) => [c, corners[(i + 1) % 4]]),
      [tick[0], tick[1]], [tick[1], tick[2]],
    ];
    const segs = pairs.map(([p, q]) => segment(p, q)).filter((seg) => seg !== null);
    if (segs.length) out.push({ index, segs });
  });
  return out;
}

// The camera path: segments between the centres of consecutive poses, drawn as frustumSegments draws.
function pathSegments(poses, sceneScale, c2w, intr, width, height) {
  if (!poses || poses.length < 2 || !(sceneScale > 0) || !c2w) return [];
  const { toCamera, segment } = projector(c2w, intr, width, height, 1e-3 * sceneScale);
  const centres = poses.map((m) => toCamera(splitPose(m).C));
  return centres.slice(1).map((c, i) => segment(centres[i], c)).filter((seg) => seg !== null);
}

// The frustum of ``frustums`` (frustumSegments) passing nearest (x, y), within ``tolerance`` (canvas
// pixels): its index into the training views, or -1.
function pickFrustum(frustums, x, y, tolerance) {
  let best = -1, bestD = tolerance;
  for (const f of frustums) {
    for (const [x0, y0, x1, y1] of f.segs) {
      const dx = x1 - x0, dy = y1 - y0;
      const len2 = dx * dx + dy * dy;
      const a = len2 > 0 ? Math.max(0, Math.min(1, ((x - x0) * dx + (y - y0) * dy) / len2)) : 0;
      const d = Math.hypot(x - (x0 + a * dx), y - (y0 + a * dy));
      if (d <= bestD) { best = f.index; bestD = d; }
    }
  }
  return best;
}

// ---------------------------------------------------------------- the viewer

const $ = (id) => document.getElementById(id);
const token = new URLSearchParams(location.search).get("token");
const authHeaders = token ? { Authorization: `Bearer ${token}` } : {};

const state = {
  scene: null,
  playing: true,          // live: follow the stream's head; paused: render the slider's time
  orbit: null,            // null: the event camera's own pose
  tUs: null,              // time of the frame on screen
  frames: 0,
  shown: [],              // performance.now() of recent frames on screen, for fps
  latencyMs: null,
  ws: null,
  wsGeneration: 0,
  sentAt: [],             // performance.now() of each subscription sent and not yet answered
  acked: null,            // {sentAt, framesLeft}: the one just answered, until the frame that times it
  eventLatencyMs: null,
  frameAgeMs: null,
  viewDirty: false,       // a change of view waits for the next animation frame (one message per paint)
  rendering: false,       // a GET /render in flight
  renderAgain: false,     // ... and the inputs changed since it was sent
  pending: null,          // the newest frame not yet drawn (older ones are dropped: only the newest matters)
  image: null,            // the render on screen, decoded (ImageBitmap, or ImageData for raw frames)
  eventsLayer: "off",     // the events layer: off, over the render, or beside it
  events: null,           // {tUs, pixels}: the newest event map (GET /events' DV-style PNG, decoded)
  eventsWanted: null,     // the time whose event map is wanted next (newest wins)
  eventsFetching: false,
  drawing: false,
  renderMode: "rgb",      // what the render shows: rgb, depth or alpha (GET /render's mode)
  imageMode: "rgb",       // what the render on screen shows
  depthRange: null,       // {near, far} of the depth render on screen
  cameras: false,         // the training cameras drawn as frustums over the render
  imagePose: null,        // the c2w the render on screen was made from (null: unknown)
  streamPose: undefined,  // the pose of the subscription in force (null: the event camera's)
  cameraPoses: [],        // the training frames' poses (the checkpoint's anchors on its trajectory)
  frustums: [],           // frustumSegments of the render on screen, for picking
  hover: -1,              // the training view under the pointer
};

function showError(message) {
  $("error-text").textContent = message;
  $("error").hidden = false;
  state.errorAt = performance.now();
}

function clearError() {
  // An error stays up for at least 3 s so that one followed by a good frame can still be read.
  if (!$("error").hidden && performance.now() - state.errorAt > 3000) $("error").hidden = true;
}

function setStatus(text) { $("status").textContent = text; }

// An error map of the wire ({error, detail, param, valid_range}) as one line a person can act on.
function describeError(body) {
  let text = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail ?? body);
  if (body.error) text = `${body.error}: ${text}`;
  const r = body.valid_range;
  if (r && r.t_min !== undefined) text += ` (valid t: ${r.t_min.toFixed(3)}–${r.t_max.toFixed(3)} s)`;
  return text;
}

async function errorText(response) {
  let text;
  try {
    text = describeError(await response.json());
  } catch {
    text = response.statusText;
  }
  return `${response.status} ${text}`;
}

function currentPose() { return state.orbit ? state.orbit.c2w() : null; }

// The render's size: "fit" asks the server for the canvas' size on screen in device pixels (the
// splats are drawn at that resolution, not a small image stretched), in the camera's aspect ratio,
// within the server's limits and at most MAX_FIT_SCALE times the camera's size: the model learned
// the scene at the camera's resolution, and past a few times it a render costs more and shows no more
// than the browser's smooth scaling of it; else a multiple of the camera's size.
const MAX_FIT_SCALE = 4;

function renderSize() {
  const intr = state.scene.intrinsics;
  const choice = $("scale").value;
  let k;
  if (choice === "fit") {
    const main = document.querySelector("main");
    const pad = 16;  // main's padding, both sides
    const beside = state.eventsLayer === "beside";
    const w = Math.max(1, (main.clientWidth - pad - (beside ? 8 : 0)) / (beside ? 2 : 1));
    const h = Math.max(1, main.clientHeight - pad);
    k = Math.min(MAX_FIT_SCALE, Math.min(w / intr.width, h / intr.height) * (window.devicePixelRatio || 1));
    const limits = state.scene.limits || {};
    if (limits.max_width) k = Math.min(k, limits.max_width / intr.width);
    if (limits.max_height) k = Math.min(k, limits.max_height / intr.height);
  } else {
    k = Number(choice);  // may pass the server's limits: it says so, and the page shows its answer
  }
  return [Math.max(1, Math.floor(intr.width * k + 1e-9)), Math.max(1, Math.floor(intr.height * k + 1e-9))];
}

const secondsOf = (tUs) => (tUs - state.scene.t_start_us) / 1e6;

// ---- the time slider: milliseconds from the recording's start (a range input holds doubles, and
// Unix-epoch microseconds would not step cleanly)

function layoutSlider() {
  const s = state.scene;
  const slider = $("slider");
  slider.max = String(Math.max(1, Math.round((s.t_end_us - s.t_start_us) / 1000)));
  const ticks = $("ticks");
  ticks.replaceChildren();
  for (const a of s.anchors_us || []) {
    const f = (a - s.t_start_us) / Math.max(1, s.t_end_us - s.t_start_us);
    if (f < 0 || f > 1) continue;
    const tick = document.createElement("span");
    tick.style.left = `${(100 * f).toFixed(3)}%`;
    tick.title = `anchor ${secondsOf(a).toFixed(3)} s`;
    ticks.append(tick);
  }
}

function sliderTimeUs() { return state.scene.t_start_us + Number($("slider").value) * 1000; }

function moveSlider(tUs) {
  const s = state.scene;
  if (tUs > s.t_end_us) {  // a live source grows: widen the slider to the newest time seen
    s.t_end_us = tUs;
    layoutSlider();
  }
  $("slider").value = String(Math.round((tUs - s.t_start_us) / 1000));
}

// ---- drawing: only the newest frame is decoded; frames that arrive while one decodes replace the
// pending one, so a slow page never queues.

function queueFrame(frame) {
  state.pending = frame;
  if (!state.drawing) drawPending();
}

async function drawPending() {
  state.drawing = true;
  try {
    while (state.pending) {
      const frame = state.pending;
      state.pending = null;
      await drawFrame(frame);
    }
  } catch (err) {
    showError(`cannot show a frame: ${err.message}`);
  } finally {
    state.drawing = false;
  }
}

// A frame of a closed stream, or a still while the stream plays, must not land on the canvas: both
// can finish decoding after the switch.
function current(frame) {
  return frame.generation === undefined ? !state.playing
    : state.playing && frame.generation === state.wsGeneration;
}

async function drawFrame(frame) {
  if (!current(frame)) return false;
  let image;
  if (frame.format === "raw") {
    // uint8, row-major [height, width, channels] with 1 (grey), 3 (RGB) or 4 (RGBA) channels
    const { width, height, channels, data } = frame;
    const rgba = new Uint8ClampedArray(width * height * 4);
    for (let i = 0, j = 0; i < width * height; i++, j += channels) {
      rgba[4 * i] = data[j];
      rgba[4 * i + 1] = data[channels >= 3 ? j + 1 : j];
      rgba[4 * i + 2] = data[channels >= 3 ? j + 2 : j];
      rgba[4 * i + 3] = channels === 4 ? data[j + 3] : 255;
    }
    image = new ImageData(rgba, width, height);
  } else {
    const type = frame.format === "png" ? "image/png" : "image/jpeg";
    image = await createImageBitmap(new Blob([frame.data], { type }));
    if (!current(frame)) { image.close(); return false; }
  }
  if (state.image instanceof ImageBitmap) state.image.close();
  state.image = image;
  state.imagePose = frame.pose ?? poseAt(state.scene.trajectory, frame.t_us);
  state.imageMode = frame.render_mode || "rgb";
  state.depthRange = frame.depth_near === null || frame.depth_near === undefined ? null
    : { near: frame.depth_near, far: frame.depth_far };
  paint();
  shown(frame);
  return true;
}

// The render, and the events layer over it or beside it. The event map is at the sensor's size:
// drawn pixel for pixel (nearest neighbour), each sensor pixel a crisp block of the render's pixels.
function paint() {
  const canvas = $("view");
  const image = state.image;
  if (!image) return;
  if (canvas.width !== image.width || canvas.height !== image.height) {
    canvas.width = image.width;
    canvas.height = image.height;
  }
  const ctx = canvas.getContext("2d");
  if (image instanceof ImageData) ctx.putImageData(image, 0, 0);
  else ctx.drawImage(image, 0, 0);
  const events = state.eventsLayer !== "off" ? state.events : null;
  if (events && state.eventsLayer === "over") overlayEvents(ctx, events.pixels);
  drawFrustums(ctx);
  const side = $("events-view");
  side.hidden = state.eventsLayer !== "beside";
  if (!side.hidden) {
    if (side.width !== canvas.width || side.height !== canvas.height) {
      side.width = canvas.width;
      side.height = canvas.height;
    }
    const sctx = side.getContext("2d");
    sctx.fillStyle = "#fff";
    sctx.fillRect(0, 0, side.width, side.height);
    if (events) overlayEvents(sctx, events.pixels);
  }
}

// The training cameras over the render, projected with the render's own camera: the path dim, the
// frustums orange, the one under the pointer white and thicker. Lines about 1.5 screen pixels wide at any
// render size.
function drawFrustums(ctx) {
  const scene = state.scene, views = scene && scene.training_views;
  const on = state.cameras && views && state.imagePose;
  const { width, height } = ctx.canvas;
  state.frustums = on ? frustumSegments(state.cameraPoses, views.scale, state.imagePose, scene.intrinsics,
    width, height) : [];
  if (!on) return;
  const path = pathSegments(views.c2w, views.scale, state.imagePose, scene.intrinsics, width, height);
  const k = screenScale(ctx.canvas);
  const stroke = (segs, style, lineWidth) => {
    if (segs.length === 0) return;
    ctx.beginPath();
    for (const [x0, y0, x1, y1] of segs) { ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); }
    ctx.strokeStyle = style;
    ctx.lineWidth = lineWidth / k;
    ctx.stroke();
  };
  ctx.save();
  ctx.lineCap = "round";
  stroke(path, "rgba(255, 179, 71, 0.55)", 1);
  stroke(state.frustums.filter((f) => f.index !== state.hover).flatMap((f) => f.segs), "rgba(255, 179, 71, 0.95)", 1.5);
  stroke(state.frustums.filter((f) => f.index === state.hover).flatMap((f) => f.segs), "#ffffff", 2.5);
  ctx.restore();
}

// Screen pixels per canvas pixel, and where the canvas' picture lies on the screen: the canvas keeps
// its aspect ratio inside its box (object-fit: contain).
function screenScale(canvas) {
  const r = canvas.getBoundingClientRect();
  return Math.min(r.width / canvas.width, r.height / canvas.height) || 1;
}

function canvasPoint(canvas, clientX, clientY) {
  const r = canvas.getBoundingClientRect();
  const k = screenScale(canvas);
  return { x: (clientX - r.left - (r.width - canvas.width * k) / 2) / k,
    y: (clientY - r.top - (r.height - canvas.height * k) / 2) / k, k };
}

// The training view under a pointer event (-1: none), within 6 screen pixels of its lines.
function frustumAt(e) {
  if (!state.cameras || state.frustums.length === 0) return -1;
  const p = canvasPoint($("view"), e.clientX, e.clientY);
  return pickFrustum(state.frustums, p.x, p.y, 6 / p.k);
}

// Jump to training camera ``index``: the free camera starts from its pose.
function jumpToView(index) {
  const c2w = state.cameraPoses[index];
  state.orbit = new Orbit(c2w, orbitDepth(state.scene, c2w));
  state.hover = -1;
  viewChanged();
}

function setCameras(on) {
  state.cameras = on;
  $("cameras").checked = on;
  if (!on) { state.hover = -1; $("view").style.cursor = ""; }
  paint();
}

// The event map's coloured pixels over what ctx holds, scaled nearest-neighbour: each output pixel
// takes the sensor pixel under its centre (a canvas' own scaling leaves the rounding to the browser).
function overlayEvents(ctx, events) {
  const { width: w, height: h } = ctx.canvas;
  const sw = events.width, sh = events.height, src = events.data;
  const out = ctx.getImageData(0, 0, w, h);
  const xs = new Int32Array(w);
  for (let x = 0; x < w; x++) xs[x] = Math.min(sw - 1, Math.floor(((x + 0.5) * sw) / w));
  for (let y = 0; y < h; y++) {
    const row = Math.min(sh - 1, Math.floor(((y + 0.5) * sh) / h)) * sw;
    for (let x = 0; x < w; x++) {
      const s = 4 * (row + xs[x]);
      if (src[s + 3] === 0) continue;  // no events at this sensor pixel: the render shows through
      const d = 4 * (y * w + x);
      out.data[d] = src[s];
      out.data[d + 1] = src[s + 1];
      out.data[d + 2] = src[s + 2];
      out.data[d + 3] = 255;
    }
  }
  ctx.putImageData(out, 0, 0);
}

// ---- the events layer: GET /events for the time on screen, one request in flight, the newest wins.
// Live, the map of a frame arrives just after the frame: the layer lags the render by one event map.

function wantEvents(tUs) {
  if (state.eventsLayer === "off" || tUs === undefined || tUs === null) return;
  if (state.events && state.events.tUs === tUs) return;
  state.eventsWanted = tUs;
  if (!state.eventsFetching) fetchEvents();
}

async function fetchEvents() {
  state.eventsFetching = true;
  try {
    while (state.eventsWanted !== null && state.eventsLayer !== "off") {
      const tUs = state.eventsWanted;
      state.eventsWanted = null;
      const url = new URL("events", location.href);
      url.search = "";
      url.searchParams.set("t_us", String(tUs));
      url.searchParams.set("format", "png");
      const response = await fetch(url, { headers: authHeaders });
      if (response.status === 503 && state.playing) continue;  // busy: the next frame asks again
      if (!response.ok) {
        showError(`events: ${await errorText(response)}`);
        continue;
      }
      // The sensor's pixels as they are (opaque colours or fully transparent: no rounding).
      const bitmap = await createImageBitmap(await response.blob());
      const decode = new OffscreenCanvas(bitmap.width, bitmap.height).getContext("2d");
      decode.drawImage(bitmap, 0, 0);
      bitmap.close();
      const pixels = decode.getImageData(0, 0, decode.canvas.width, decode.canvas.height);
      state.events = { tUs: Number(response.headers.get("X-Edmcgs-T-Us")), pixels };
      paint();
    }
  } catch (err) {
    showError(`events: ${err.message}`);
  } finally {
    state.eventsFetching = false;
  }
}

function setEventsLayer(layer) {
  const resized = (layer === "beside") !== (state.eventsLayer === "beside");
  state.eventsLayer = layer;
  if (layer === "off") state.events = null;  // switched on again, it shows no stale map meanwhile
  $("events-layer").value = layer;
  document.querySelector("main").classList.toggle("beside", layer === "beside");
  paint();
  wantEvents(state.tUs);
  if (resized && $("scale").value === "fit") viewChanged();  // the render's share of the width changed
}

// ---- the screenshot: the canvas as it is (the render, the events layer over it), or the render and
// the events side by side, as a PNG download named for the time on screen.

function screenshotCanvas() {
  const view = $("view");
  if (state.eventsLayer !== "beside") return view;
  const side = $("events-view");
  const out = document.createElement("canvas");
  out.width = view.width + side.width;
  out.height = Math.max(view.height, side.height);
  const ctx = out.getContext("2d");
  ctx.drawImage(view, 0, 0);
  ctx.drawImage(side, view.width, 0);
  return out;
}

function download(blob, name) {
  const link = document.createElement("a");
  link.href = URL.createObjectURL(blob);
  link.download = name;
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(link.href), 10_000);
}

function timeName() {
  return state.tUs === null || state.tUs === undefined ? "head" : `${secondsOf(state.tUs).toFixed(3)}s`;
}

function saveScreenshot() {
  if (!state.image) { showError("screenshot: nothing on screen yet"); return; }
  screenshotCanvas().toBlob((blob) => {
    if (!blob) { showError("screenshot: the browser could not encode the PNG"); return; }
    download(blob, `edmcgs-t${timeName()}.png`);
  }, "image/png");
}

// ---- the PLY download: GET /ply at the time on screen (the deformed Gaussians, 3DGS layout)

async function savePly() {
  if (state.tUs === null || state.tUs === undefined) { showError("PLY: nothing on screen yet"); return; }
  const url = new URL("ply", location.href);
  url.search = "";
  url.searchParams.set("t_us", String(state.tUs));
  try {
    const response = await fetch(url, { headers: authHeaders });
    if (!response.ok) { showError(`PLY: ${await errorText(response)}`); return; }
    download(await response.blob(), `edmcgs-t${timeName()}.ply`);
  } catch (err) {
    showError(`PLY: ${err.message}`);
  }
}

// ---- the far-view notice

function updateFarNotice() {
  const notice = $("far-notice");
  const pose = currentPose();
  const near = pose && state.scene ? nearestTrainingView(state.scene.training_views, pose) : null;
  notice.hidden = !(near && near.far);
  if (!notice.hidden) {
    $("far-text").textContent = `This view is far from every training view (the nearest is ` +
      `${near.angleDeg.toFixed(0)}° turned and ${near.distance.toFixed(2)}× the scene's distance away). ` +
      "The model only saw the scene from its training cameras: from here it shows surfaces no camera saw, " +
      "smeared. Reset (r) goes back to the event camera.";
  }
}

function shown(frame) {
  const now = performance.now();
  state.frames += 1;
  state.shown.push(now);
  if (frame.requestedAt !== undefined) state.latencyMs = now - frame.requestedAt;  // request to screen
  if (frame.arrived_unix_us !== undefined && frame.arrived_unix_us !== null) {
    // Event to screen against the page's clock: exact on the server's machine, else as good as NTP.
    state.eventLatencyMs = Date.now() - frame.arrived_unix_us / 1000;
  }
  if (frame.head_arrived_unix_us !== undefined && frame.head_arrived_unix_us !== null) {
    state.frameAgeMs = Date.now() - frame.head_arrived_unix_us / 1000;
  }
  state.tUs = frame.t_us;
  if (frame.t_us !== undefined && frame.t_us !== null) {
    $("time").textContent = `${secondsOf(frame.t_us).toFixed(3)} s`;
    if (state.playing) moveSlider(frame.t_us);
  }
  if (frame.anchor_us !== undefined && frame.anchor_us !== null) {
    $("anchor").textContent = `${secondsOf(frame.anchor_us).toFixed(3)} s${anchorNote(frame)}`;
    const anchors = state.scene.anchors_us || [];
    if (!anchors.includes(frame.anchor_us)) {  // a live source took a new anchor frame
      anchors.push(frame.anchor_us);
      state.scene.anchors_us = anchors;
      layoutSlider();
    }
  }
  if (frame.events !== undefined) $("events").textContent = String(frame.events);
  if (frame.model_version !== undefined) {
    $("model").textContent = modelText(frame.model_version, state.scene.learning);
    if (frame.model_version !== state.modelVersion) {
      const first = state.modelVersion === undefined;
      state.modelVersion = frame.model_version;
      if (!first) reloadScene();  // a learnt model went live: its anchors, trajectory and cameras
    }
  }
  wantEvents(frame.t_us);
  if (frame.render_ms !== undefined) $("render-ms").textContent = `${frame.render_ms.toFixed(1)} ms`;
  $("depth-range").textContent = depthText(state.depthRange, state.imageMode);
  if (frame.dropped !== undefined) $("dropped").textContent = String(frame.dropped);
  $("frames").textContent = String(state.frames);
  clearError();
}

// The depth render's range as the readout says it: bright is near, dark far, black nothing.
function depthText(range, mode) {
  if (mode !== "depth") return "–";
  if (!range) return "nothing in view";
  const digits = (v) => (Math.abs(v) >= 10 ? v.toFixed(1) : v.toFixed(3));
  return `${digits(range.near)}–${digits(range.far)} m`;
}

// Which model rendered: the checkpoint given, the n-th a cold start learnt (with what GET /scene says of
// it), or none yet (the stream's newest frame moved by the events since).
function modelText(version, learning) {
  if (version === null) return "learning… (frame + events)";
  if (!learning || version === 0) return "checkpoint";
  const m = learning.model;
  if (!m || m.version !== version) return `learnt v${version}`;
  const span = (m.span_us[1] - m.span_us[0]) / 1e6;
  const psnr = m.heldout && Number.isFinite(m.heldout.psnr) ? `, held-out ${m.heldout.psnr.toFixed(1)} dB` : "";
  return `learnt v${version} (${span.toFixed(1)} s, ${m.anchors} anchors, step ${m.steps}${psnr})`;
}

async function reloadScene() {
  try {
    const response = await fetch(new URL("scene", location.href), { headers: authHeaders });
    if (!response.ok) return;
    state.scene = await response.json();
    state.cameraPoses = anchorPoses(state.scene.trajectory, state.scene.anchors_us);
    $("model").textContent = modelText(state.modelVersion, state.scene.learning);
    layoutSlider();
    paint();
  } catch (err) {
    showError(`cannot reload the scene: ${err.message}`);
  }
}

// Past the span the anchor is an online one (predicted, or corrected against its frame), and the event
// camera's view is projected onto the events since that frame; within it, nothing to add.
function anchorNote(frame) {
  if (!frame.anchor || frame.anchor === "checkpoint") return "";
  return ` (${frame.anchor}${frame.projected ? ", events-bounded" : ""})`;
}

// Readouts are refreshed on a timer so that fps falls to 0 when frames stop coming.
function updateReadouts() {
  const now = performance.now();
  while (state.shown.length && now - state.shown[0] > 1000) state.shown.shift();
  const n = state.shown.length;
  const fps = n >= 2 ? (1000 * (n - 1)) / Math.max(1, state.shown[n - 1] - state.shown[0]) : n;
  $("fps").textContent = fps.toFixed(1);
  const ms = (v) => (v === null ? "–" : `${v.toFixed(0)} ms`);
  $("latency").textContent = ms(state.latencyMs);
  $("event-latency").textContent = state.playing ? ms(state.eventLatencyMs) : "–";
  $("frame-age").textContent = state.playing ? ms(state.frameAgeMs) : "–";
  const pose = currentPose();
  $("pose").textContent = pose ? `[${pose.map((v) => v.toFixed(3)).join(", ")}]` : "event camera";
}

// ---- live: WS /stream

function streamUrl() {
  const url = new URL("stream", location.href);
  url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
  url.search = "";
  if (token) url.searchParams.set("token", token);  // a browser cannot set headers on a websocket
  return url;
}

function subscribe() {
  const ws = state.ws;
  if (!ws || ws.readyState !== WebSocket.OPEN) return;
  const [width, height] = renderSize();
  ws.send(JSON.stringify({ mode: "live", pose: currentPose(), width, height, format: "jpeg",
    render_mode: state.renderMode }));
  state.sentAt.push(performance.now());
}

function openStream() {
  closeStream();
  const generation = ++state.wsGeneration;
  const ws = new WebSocket(streamUrl());
  ws.binaryType = "arraybuffer";
  state.ws = ws;
  setStatus("live: connecting…");
  ws.onopen = () => {
    setStatus("live");
    state.sentAt = [];
    state.acked = null;
    state.streamPose = undefined;
    subscribe();
  };
  ws.onmessage = (event) => {
    if (generation !== state.wsGeneration) return;  // in flight when the stream was closed: stale
    let msg;
    try {
      msg = typeof event.data === "string" ? JSON.parse(event.data) : unpack(new Uint8Array(event.data));
    } catch (err) {
      showError(`bad message from the server: ${err.message}`);
      return;
    }
    if (msg.type === "error") {
      // The connection stays open and the previous subscription stays in force.
      showError(`stream: ${describeError(msg)}`);
      state.sentAt.shift();
    } else if (msg.type === "subscribed") {
      // Answers come in the order of the subscriptions. The server renders one frame at a time and
      // sends a finished frame before an answer, so at most the first frame after the answer was
      // rendered before it (with the previous pose): the second one certainly uses the new
      // subscription. Timing to it is exact while the stream is busy (the usual case), and at most
      // one frame interval long when the server was idle.
      state.acked = { sentAt: state.sentAt.shift(), framesLeft: 2 };
      const pose = msg.subscription && msg.subscription.pose;
      state.streamPose = Array.isArray(pose) && pose.length === 16 ? pose : null;
    } else if (msg.type === "frame") {
      if (state.acked && state.acked.sentAt !== undefined && --state.acked.framesLeft === 0) {
        msg.requestedAt = state.acked.sentAt;
        state.acked = null;
      }
      msg.generation = generation;
      if (state.streamPose !== undefined) msg.pose = state.streamPose;
      queueFrame(msg);
    }
  };
  ws.onclose = (event) => {
    if (generation !== state.wsGeneration) return;  // replaced or closed on purpose
    state.ws = null;
    const why = event.reason || `code ${event.code}`;
    showError(`stream closed (${why}); reconnecting`);
    setStatus("live: disconnected");
    setTimeout(() => { if (state.playing && generation === state.wsGeneration) openStream(); }, 1000);
  };
}

function closeStream() {
  state.wsGeneration += 1;
  state.pending = null;
  if (state.ws) state.ws.close(1000, "viewer paused");
  state.ws = null;
}

// The stream's latency is measured once per subscription; re-subscribe now and then (the same
// subscription: nothing changes on screen) so that the readout stays current.
function resubscribeForLatency() {
  if (state.playing && state.sentAt.length === 0) subscribe();
}

// ---- paused: GET /render at the slider's time, one request in flight, the newest inputs win

async function renderStill() {
  if (state.rendering) { state.renderAgain = true; return; }
  state.rendering = true;
  try {
    do {
      state.renderAgain = false;
      const [width, height] = renderSize();
      const url = new URL("render", location.href);
      url.search = "";
      url.searchParams.set("t_us", String(sliderTimeUs()));
      url.searchParams.set("width", String(width));
      url.searchParams.set("height", String(height));
      url.searchParams.set("format", "jpeg");
      url.searchParams.set("mode", state.renderMode);
      const pose = currentPose();
      if (pose) url.searchParams.set("pose", pose.map((v) => v.toPrecision(9)).join(","));
      const sent = performance.now();
      const response = await fetch(url, { headers: authHeaders });
      if (!response.ok) {
        showError(`render: ${await errorText(response)}`);
        continue;
      }
      const data = new Uint8Array(await response.arrayBuffer());
      const header = (name) => response.headers.get(name);
      const frame = {
        format: "jpeg", data,
        t_us: Number(header("X-Edmcgs-T-Us")),
        anchor_us: header("X-Edmcgs-Anchor-Us") === null ? null : Number(header("X-Edmcgs-Anchor-Us")),
        events: Number(header("X-Edmcgs-Events")),
        render_ms: Number(header("X-Edmcgs-Render-Ms")),
        anchor: header("X-Edmcgs-Anchor"),
        projected: header("X-Edmcgs-Projected") === "true",
        render_mode: header("X-Edmcgs-Mode"),
        depth_near: header("X-Edmcgs-Depth-Near") === null ? null : Number(header("X-Edmcgs-Depth-Near")),
        depth_far: header("X-Edmcgs-Depth-Far") === null ? null : Number(header("X-Edmcgs-Depth-Far")),
        pose,
      };
      frame.requestedAt = sent;
      await drawFrame(frame);
    } while (state.renderAgain && !state.playing);
  } catch (err) {
    showError(`render: ${err.message}`);
  } finally {
    state.rendering = false;
  }
}

// Whatever changed the view: tell the stream, or render the still; at most once per paint, however
// fast the pointer events come.
function viewChanged() {
  if (state.viewDirty) return;
  state.viewDirty = true;
  requestAnimationFrame(() => {
    state.viewDirty = false;
    updateFarNotice();
    if (state.playing) subscribe();
    else renderStill();
  });
}

function setPlaying(playing) {
  state.playing = playing;
  $("play").textContent = playing ? "Pause" : "Play";
  if (playing) {
    openStream();
  } else {
    closeStream();
    setStatus("paused");
    renderStill();
  }
}

// ---- mouse: drag orbits, shift- or right-drag pans, the wheel zooms

function ensureOrbit() {
  if (state.orbit) return state.orbit;
  const t = state.tUs ?? state.scene.head_us ?? state.scene.t_start_us;
  const base = poseAt(state.scene.trajectory, t) || [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];
  state.orbit = new Orbit(base, orbitDepth(state.scene, base));
  return state.orbit;
}

const CLICK_SLOP = 4;  // screen pixels a press may wander and still be a click

function bindMouse() {
  const canvas = $("view");
  let drag = null;
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointerdown", (e) => {
    // a press on a training camera's frustum jumps there when released without a drag
    drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey, moved: 0,
      view: e.button === 0 ? frustumAt(e) : -1 };
    canvas.setPointerCapture(e.pointerId);
    canvas.focus();
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) {
      const hover = frustumAt(e);
      if (hover !== state.hover) {
        state.hover = hover;
        canvas.style.cursor = hover >= 0 ? "pointer" : "";
        paint();
      }
      return;
    }
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    if (dx === 0 && dy === 0) return;
    drag.x = e.clientX;
    drag.y = e.clientY;
    drag.moved += Math.abs(dx) + Math.abs(dy);
    if (drag.view >= 0 && drag.moved <= CLICK_SLOP) return;  // still a click on the frustum
    const orbit = ensureOrbit();
    if (drag.pan) {
      // Pointer pixels to world units at the target's depth: the scene under the pointer follows it.
      const intr = state.scene.intrinsics;
      const perPixel = (orbit.dist * intr.width) / (canvas.clientWidth * intr.fx);
      orbit.pan(dx * perPixel, dy * perPixel);
    } else {
      orbit.rotate(-dx * 0.008, dy * 0.008);
    }
    viewChanged();
  });
  canvas.addEventListener("pointerup", () => {
    if (drag && drag.view >= 0 && drag.moved <= CLICK_SLOP) jumpToView(drag.view);
    drag = null;
  });
  canvas.addEventListener("pointercancel", () => { drag = null; });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    ensureOrbit().zoom(Math.exp(e.deltaY * 0.001));
    viewChanged();
  }, { passive: false });
}

function setRenderMode(mode) {
  state.renderMode = mode;
  $("render-mode").value = mode;
  document.querySelector("#depth-range").parentElement.hidden = mode !== "depth";
  viewChanged();
}

// The pose field: go to the pose typed or pasted, or say what is wrong with it.
function goToTypedPose() {
  const input = $("pose-input");
  let c2w;
  try {
    c2w = parsePose(input.value);
  } catch (err) {
    input.setAttribute("aria-invalid", "true");
    showError(`pose: ${err.message}`);
    return;
  }
  input.removeAttribute("aria-invalid");
  $("error").hidden = true;
  state.orbit = new Orbit(c2w, orbitDepth(state.scene, c2w));
  viewChanged();
}

function bindControls() {
  $("play").addEventListener("click", () => setPlaying(!state.playing));
  $("reset").addEventListener("click", () => { state.orbit = null; viewChanged(); });
  $("scale").addEventListener("change", viewChanged);
  $("events-layer").addEventListener("change", () => setEventsLayer($("events-layer").value));
  $("screenshot").addEventListener("click", saveScreenshot);
  $("render-mode").addEventListener("change", () => setRenderMode($("render-mode").value));
  $("cameras").addEventListener("change", () => setCameras($("cameras").checked));
  $("pose-form").addEventListener("submit", (e) => { e.preventDefault(); goToTypedPose(); });
  $("pose-input").addEventListener("input", () => $("pose-input").removeAttribute("aria-invalid"));
  $("ply").addEventListener("click", savePly);
  // A new window size is a new render size in "fit"; the observer fires for every step of a drag.
  let lastSize = "";
  new ResizeObserver(() => {
    if (!state.scene || $("scale").value !== "fit") return;
    const size = renderSize().join("x");
    if (size !== lastSize) { lastSize = size; viewChanged(); }
  }).observe(document.querySelector("main"));
  $("error-close").addEventListener("click", () => { $("error").hidden = true; });
  $("slider").addEventListener("input", () => {
    if (state.playing) setPlaying(false);  // grabbing the slider leaves the live head
    $("time").textContent = `${secondsOf(sliderTimeUs()).toFixed(3)} s`;
    renderStill();
  });
  document.addEventListener("keydown", (e) => {
    if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
    if (e.key === " ") { e.preventDefault(); setPlaying(!state.playing); }
    if (e.key === "r") { state.orbit = null; viewChanged(); }
    if (e.key === "e") setEventsLayer(state.eventsLayer === "off" ? "over" : "off");
    if (e.key === "c") setCameras(!state.cameras);
  });
}

// ---------------------------------------------------------------- scene picker
// Under the Ray gateway the page is /scenes/<name>/ and GET /scenes lists the scenes: a picker switches
// to another one's viewer (the same page, the token passed on). Served alone, there is no picker.

const SCENE_PATH = /^(.*)\/scenes\/([^/]+)\/$/;

async function loadScenePicker() {
  const match = SCENE_PATH.exec(location.pathname);
  if (!match) return;
  const [, base, current] = match;
  let scenes;
  try {
    const response = await fetch(new URL(`${base}/scenes`, location.href), { headers: authHeaders });
    if (!response.ok) return;  // a gateway token this page lacks: no picker, the scene still plays
    scenes = (await response.json()).scenes;
  } catch {
    return;
  }
  if (!Array.isArray(scenes) || scenes.length === 0) return;
  const picker = $("scene-picker");
  for (const scene of scenes) {
    const ready = scene.health && scene.health.ready;
    const option = new Option(ready ? scene.name : `${scene.name} (not ready)`, scene.name);
    option.selected = scene.name === decodeURIComponent(current);
    picker.append(option);
  }
  picker.addEventListener("change", () => {
    const url = new URL(`${base}/scenes/${encodeURIComponent(picker.value)}/`, location.href);
    if (token) url.searchParams.set("token", token);
    location.assign(url);
  });
  picker.hidden = false;
}

async function start() {
  loadScenePicker();
  bindControls();
  bindMouse();
  setInterval(updateReadouts, 250);
  setInterval(resubscribeForLatency, 2000);
  try {
    const response = await fetch(new URL("scene", location.href), { headers: authHeaders });
    if (!response.ok) throw new Error(await errorText(response));
    state.scene = await response.json();
  } catch (err) {
    showError(`cannot load the scene: ${err.message}`);
    setStatus("no scene");
    return;
  }
  // the checkpoint's own anchors, before a live source's new ones join the list
  state.cameraPoses = anchorPoses(state.scene.trajectory, state.scene.anchors_us);
  layoutSlider();
  moveSlider(state.scene.head_us ?? state.scene.t_start_us);
  setPlaying(true);
}

// The pure parts, for a console or a test page.
window.edmcgsViewer = {
  state, unpack, poseAt, Orbit, quatFromRot, rotFromQuat, currentPose, renderSize, nearestTrainingView,
  anchorNote, modelText, parsePose, anchorPoses, frustumSegments, pathSegments, pickFrustum, depthText, canvasPoint,
  FAR_ANGLE_DEG, FAR_DISTANCE, MAX_FIT_SCALE, FRUSTUM_DEPTH,
};

// index.html inserts this script from <head>: wait for the page's elements.
if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
else start();
