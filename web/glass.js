// glass.js — latency at the glass on the page: each frame's depth (decoded from the "NDP1"
// binary message on the pose channel), the reprojection that moves the newest decoded video
// frame to the camera of this display frame, and the pose predictor. The same rules as the
// Rust client (server/client/src/glass.rs, server/wire/src/depth.rs), which `nephele bench
// glass` measures; docs/architecture.md §5 "Depth" and "Reprojection".
//
//   * decodeDepth(ArrayBuffer) → Promise<DepthFrame> (throws in words on a corrupt message):
//     raw-deflate inflated with DecompressionStream, the object mask, LEB128 zig-zag
//     residuals against LOCO-I's MED predictor, inverse depth in `levels` steps.
//   * Reprojector: a WebGL2 grid mesh over a <canvas> laid on the <video>. Each presented
//     video frame (requestVideoFrameCallback) is uploaded with its RTP timestamp; each
//     animation frame draws the newest one warped by its depth from the camera it was
//     rendered with to the camera the page has now. Vertices with no depth are directions
//     (at infinity); a cell between the object's edge and the background stretches (the
//     depth grid takes the nearest depth at edges, so it is the background that stretches);
//     what no cell covers shows the mode's background. Without depth for a frame (lost,
//     corrupt, not yet matched to its RTP timestamp) the frame is drawn as it came.
//   * PosePredictor: constant linear and angular velocity from the last two samples, never
//     faster than now, not past where the motion stops if its speed keeps changing as over
//     the last four samples (speed, rate, jerk), at most MAX_HORIZON_MS ahead and
//     MAX_PREDICTED_TURN_DEG, restarted across a jump (teleport) or a gap.

export const MAX_HORIZON_MS = 250;
export const MAX_PREDICTED_TURN_DEG = 45;
export const JUMP_TURN_DEG_PER_S = 1500;
export const JUMP_SPEED_PER_S = 50;
export const MAX_SAMPLE_GAP_MS = 200;
const MAX_QUILT_VIEWS = 100;
const MAX_DEPTH_VERTICES = 16384;
const HEADER_LEN = 24;
const VIEW_LEN = 108;

// ─────────────────────────────────── depth ────────────────────────────────────

const gridSize = (w, h, s) => [Math.ceil(w / s) + 1, Math.ceil(h / s) + 1];

function med(a, b, c) {
  if (c >= Math.max(a, b)) return Math.min(a, b);
  if (c <= Math.min(a, b)) return Math.max(a, b);
  return a + b - c;
}

function predicted(codes, cols, at, last) {
  const i = at % cols, j = (at / cols) | 0;
  const a = i > 0 && codes[at - 1] ? codes[at - 1] : 0;
  const b = j > 0 && codes[at - cols] ? codes[at - cols] : 0;
  const c = i > 0 && j > 0 && codes[at - cols - 1] ? codes[at - cols - 1] : 0;
  if (a && b && c) return med(a, b, c);
  return a || b || last;
}

async function inflateRaw(bytes, limit) {
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream('deflate-raw'));
  const reader = stream.getReader();
  const parts = [];
  let total = 0;
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    total += value.byteLength;
    if (total > limit) { reader.cancel(); throw new Error('depth codes are longer than their grids'); }
    parts.push(value);
  }
  const out = new Uint8Array(total);
  let at = 0;
  for (const p of parts) { out.set(p, at); at += p.byteLength; }
  return out;
}

/**
 * A depth message → { frame, poseSeq, rtpTicks, views: [{ worldFromCamera (Float32Array 16),
 * k: {fx, fy, cx, cy}, viewport: [x, y, w, h], stride, levels, near, far, cols, rows,
 * z: Float32Array (view-axis depth per vertex, 0 = background) }] }. Throws in words.
 */
export async function decodeDepth(buffer) {
  const bytes = new Uint8Array(buffer);
  if (bytes.byteLength < HEADER_LEN) throw new Error(`depth message is ${bytes.byteLength} bytes, shorter than its header`);
  if (String.fromCharCode(...bytes.subarray(0, 4)) !== 'NDP1') throw new Error('depth message does not start with "NDP1"');
  const v = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const n = v.getUint32(20, true);
  if (n < 1 || n > MAX_QUILT_VIEWS) throw new Error(`depth message has ${n} views`);
  const body = HEADER_LEN + VIEW_LEN * n;
  if (bytes.byteLength < body) throw new Error('depth message is shorter than its views');
  const views = [];
  let vertices = 0;
  for (let index = 0; index < n; index++) {
    const o = HEADER_LEN + VIEW_LEN * index;
    const worldFromCamera = new Float32Array(16);
    for (let i = 0; i < 16; i++) worldFromCamera[i] = v.getFloat32(o + 4 * i, true);
    const [fx, fy, cx, cy] = [0, 1, 2, 3].map((i) => v.getFloat32(o + 64 + 4 * i, true));
    const viewport = [0, 1, 2, 3].map((i) => v.getUint32(o + 80 + 4 * i, true));
    const stride = v.getUint16(o + 96, true), levels = v.getUint16(o + 98, true);
    const near = v.getFloat32(o + 100, true), far = v.getFloat32(o + 104, true);
    const finite = [...worldFromCamera, fx, fy, cx, cy].every(Number.isFinite);
    if (!finite || fx <= 0 || fy <= 0) throw new Error(`depth view ${index}: camera is not finite`);
    if (!viewport[2] || !viewport[3] || stride < 1 || stride > 256 || levels < 1) throw new Error(`depth view ${index}: bad grid`);
    const background = near === 0 && far === 0;
    if (!background && !(Number.isFinite(near) && Number.isFinite(far) && near > 0 && far >= near)) throw new Error(`depth view ${index}: depth range ${near}..${far}`);
    const [cols, rows] = gridSize(viewport[2], viewport[3], stride);
    vertices += cols * rows;
    if (vertices > MAX_DEPTH_VERTICES) throw new Error(`depth message has ${vertices} grid vertices`);
    views.push({ worldFromCamera, k: { fx, fy, cx, cy }, viewport, stride, levels, near, far, cols, rows });
  }
  const stream = await inflateRaw(bytes.subarray(body), 4 * vertices + n);
  let at = 0;
  for (const [index, view] of views.entries()) {
    const count = view.cols * view.rows;
    const maskLen = Math.ceil(count / 8);
    if (at + maskLen > stream.length) throw new Error(`depth view ${index} ends in its mask`);
    const mask = stream.subarray(at, at + maskLen);
    at += maskLen;
    const codes = new Uint16Array(count);
    let last = 0;
    for (let k = 0; k < count; k++) {
      if (!((mask[k >> 3] >> (k & 7)) & 1)) continue;
      if (view.near === 0) throw new Error(`depth view ${index} is all background yet has a depth code`);
      let z = 0, shift = 0;
      for (;;) {
        if (at >= stream.length) throw new Error(`depth view ${index} ends early`);
        const b = stream[at++];
        z |= (b & 0x7f) << shift;
        if (!(b & 0x80)) break;
        shift += 7;
        if (shift > 14) throw new Error('a depth residual is longer than 16 bits');
      }
      const r = (z >>> 1) ^ -(z & 1);
      const code = (predicted(codes, view.cols, k, last) + r) & 0xffff;
      if (code === 0 || code > view.levels) throw new Error(`depth view ${index} has code ${code} outside 1..${view.levels}`);
      codes[k] = last = code;
    }
    // Codes → view-axis depth (0 = background).
    const invNear = 1 / view.near, invFar = 1 / view.far;
    view.z = new Float32Array(count);
    for (let k = 0; k < count; k++) {
      if (!codes[k]) continue;
      if (invNear <= invFar || view.levels === 1) { view.z[k] = view.near; continue; }
      view.z[k] = 1 / (invFar + ((codes[k] - 1) / (view.levels - 1)) * (invNear - invFar));
    }
  }
  if (at !== stream.length) throw new Error(`${stream.length - at} bytes after the last depth code`);
  return { frame: Number(v.getBigUint64(4, true)), poseSeq: v.getUint32(12, true), rtpTicks: v.getUint32(16, true), views };
}

// ─────────────────────────────── small matrix maths ───────────────────────────────

/** Inverse of a rigid column-major 4×4 (rotation + translation). */
export function rigidInverse(m) {
  const o = new Float32Array(16);
  for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) o[c * 4 + r] = m[r * 4 + c];
  for (let r = 0; r < 3; r++) o[12 + r] = -(o[r] * m[12] + o[4 + r] * m[13] + o[8 + r] * m[14]);
  o[15] = 1;
  return o;
}

function mul(a, b) {
  const out = new Float32Array(16);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
    let x = 0;
    for (let k = 0; k < 4; k++) x += a[k * 4 + r] * b[c * 4 + k];
    out[c * 4 + r] = x;
  }
  return out;
}

// Quaternions [x, y, z, w].
function quatFromMatrix(m) {
  const [m00, m10, m20, m01, m11, m21, m02, m12, m22] = [m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]];
  const t = m00 + m11 + m22;
  let q;
  if (t > 0) { const s = Math.sqrt(t + 1) * 2; q = [(m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, s / 4]; }
  else if (m00 > m11 && m00 > m22) { const s = Math.sqrt(1 + m00 - m11 - m22) * 2; q = [s / 4, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s]; }
  else if (m11 > m22) { const s = Math.sqrt(1 + m11 - m00 - m22) * 2; q = [(m01 + m10) / s, s / 4, (m12 + m21) / s, (m02 - m20) / s]; }
  else { const s = Math.sqrt(1 + m22 - m00 - m11) * 2; q = [(m02 + m20) / s, (m12 + m21) / s, s / 4, (m10 - m01) / s]; }
  const l = Math.hypot(...q);
  return q.map((x) => x / l);
}
const quatMul = ([ax, ay, az, aw], [bx, by, bz, bw]) => [
  aw * bx + ax * bw + ay * bz - az * by,
  aw * by - ax * bz + ay * bw + az * bx,
  aw * bz + ax * by - ay * bx + az * bw,
  aw * bw - ax * bx - ay * by - az * bz,
];
const quatConj = ([x, y, z, w]) => [-x, -y, -z, w];
function quatAxisAngle(axis, angle) {
  const s = Math.sin(angle / 2);
  return [axis[0] * s, axis[1] * s, axis[2] * s, Math.cos(angle / 2)];
}
function matrixFrom(q, p) {
  const [x, y, z, w] = q;
  return new Float32Array([
    1 - 2 * (y * y + z * z), 2 * (x * y + z * w), 2 * (x * z - y * w), 0,
    2 * (x * y - z * w), 1 - 2 * (x * x + z * z), 2 * (y * z + x * w), 0,
    2 * (x * z + y * w), 2 * (y * z - x * w), 1 - 2 * (x * x + y * y), 0,
    p[0], p[1], p[2], 1,
  ]);
}
/** Rotation from quaternion a to b as a world-axis vector × angle (radians), short way. */
function rotationVector(a, b) {
  let d = quatMul(b, quatConj(a));
  if (d[3] < 0) d = d.map((x) => -x);
  const s = Math.hypot(d[0], d[1], d[2]);
  if (s < 1e-12) return [0, 0, 0];
  const angle = 2 * Math.atan2(s, d[3]);
  return [d[0] / s * angle, d[1] / s * angle, d[2] / s * angle];
}

// ─────────────────────────────────── prediction ───────────────────────────────────

/** How far a motion goes in h s from speeds [[t s, speed]], newest last (see glass.rs). */
function reach(speeds, h) {
  const n = speeds.length;
  if (!n) return 0;
  const [tNow, v] = speeds[n - 1];
  const rate = (k) => (speeds[k][1] - speeds[k - 1][1]) / Math.max(speeds[k][0] - speeds[k - 1][0], 1e-6);
  let a = n >= 2 ? rate(n - 1) : 0;
  const j = n >= 3 ? (rate(n - 1) - rate(n - 2)) / Math.max((speeds[n - 1][0] - speeds[n - 3][0]) / 2, 1e-6) : 0;
  const gap = n >= 2 ? tNow - speeds[n - 2][0] : 0;
  a += j * gap / 2;
  const steps = 64, end = h + gap / 2, dt = end / steps;
  let travelled = 0;
  for (let k = 0; k < steps; k++) {
    const t = (k + 0.5) * dt;
    const speed = Math.min(v + a * t + 0.5 * j * t * t, v);
    if (speed <= 0) break;
    const counted = Math.min(t + dt / 2, end) - Math.max(t - dt / 2, gap / 2);
    travelled += speed * Math.max(counted, 0);
  }
  return Math.min(travelled, v * h);
}

export class PosePredictor {
  constructor() {
    this.samples = []; // {t (ms), p [3], q [4]}, the last four
    this.jumps = 0;
  }

  /** Records world_from_camera (16 floats) at tMs; see glass.rs for what is ignored. */
  observe(tMs, m) {
    if (!Number.isFinite(tMs) || !m || m.length !== 16 || !Array.prototype.every.call(m, Number.isFinite)) return;
    const s = { t: tMs, p: [m[12], m[13], m[14]], q: quatFromMatrix(m) };
    const last = this.samples[this.samples.length - 1];
    if (last) {
      if (tMs <= last.t) return;
      const dt = (tMs - last.t) / 1000;
      const w = rotationVector(last.q, s.q);
      const turn = Math.hypot(...w) / dt * 180 / Math.PI;
      const speed = Math.hypot(s.p[0] - last.p[0], s.p[1] - last.p[1], s.p[2] - last.p[2]) / dt;
      if (tMs - last.t > MAX_SAMPLE_GAP_MS) this.samples = [];
      else if (turn > JUMP_TURN_DEG_PER_S || speed > JUMP_SPEED_PER_S) { this.samples = []; this.jumps += 1; }
    }
    this.samples.push(s);
    if (this.samples.length > 4) this.samples.shift();
  }

  /** world_from_camera expected horizonMs after the last sample (null before any). */
  predict(horizonMs) {
    const n = this.samples.length;
    if (!n) return null;
    const last = this.samples[n - 1];
    const h = Number.isFinite(horizonMs) ? Math.min(Math.max(horizonMs, 0), MAX_HORIZON_MS) / 1000 : 0;
    if (n < 2 || h === 0) return matrixFrom(last.q, last.p);
    const lin = [], ang = [];
    for (let i = 1; i < n; i++) {
      const a = this.samples[i - 1], b = this.samples[i];
      const dt = (b.t - a.t) / 1000, mid = (a.t + b.t) / 2000;
      lin.push([mid, Math.hypot(b.p[0] - a.p[0], b.p[1] - a.p[1], b.p[2] - a.p[2]) / dt]);
      ang.push([mid, Math.hypot(...rotationVector(a.q, b.q)) / dt]);
    }
    const prev = this.samples[n - 2];
    const w = rotationVector(prev.q, last.q), wl = Math.hypot(...w);
    const d = [0, 1, 2].map((i) => last.p[i] - prev.p[i]), dl = Math.hypot(...d);
    const turn = Math.min(reach(ang, h), MAX_PREDICTED_TURN_DEG * Math.PI / 180);
    const travel = reach(lin, h);
    const q = wl > 1e-12 ? quatMul(quatAxisAngle(w.map((x) => x / wl), turn), last.q) : last.q;
    const p = dl > 1e-12 ? last.p.map((x, i) => x + d[i] / dl * travel) : last.p;
    return matrixFrom(q, p);
  }
}

// ─────────────────────────────────── the warp ─────────────────────────────────────

const VERTEX = `#version 300 es
in vec2 a_grid;
in float a_z;
uniform float u_stride;
uniform vec2 u_src_size;
uniform vec4 u_src_k;
uniform mat4 u_target_from_source;
uniform vec4 u_dst_k;
uniform vec2 u_dst_size;
out vec2 v_src;
out float v_valid;
void main() {
  vec2 px = min(a_grid * u_stride, u_src_size);
  vec3 dir = vec3((px.x - u_src_k.z) / u_src_k.x, -(px.y - u_src_k.w) / u_src_k.y, -1.0);
  vec3 p = a_z > 0.0 ? (u_target_from_source * vec4(dir * a_z, 1.0)).xyz : mat3(u_target_from_source) * dir;
  float inv = a_z > 0.0 ? 1.0 / -p.z : 0.0;
  v_valid = p.z < -1e-6 ? 1.0 : 0.0;
  vec2 t = vec2(u_dst_k.z + u_dst_k.x * p.x / -p.z, u_dst_k.w - u_dst_k.y * p.y / -p.z);
  // Affine interpolation in display pixels (w = 1), depth = inverse depth: nearer wins.
  gl_Position = vec4(2.0 * t.x / u_dst_size.x - 1.0, 1.0 - 2.0 * t.y / u_dst_size.y, 1.0 - 2.0 * clamp(inv * 0.01, 0.0, 1.0), 1.0);
  v_src = px;
}`;

const FRAGMENT = `#version 300 es
precision highp float;
in vec2 v_src;
in float v_valid;
uniform sampler2D u_video;
uniform vec4 u_src_rect;
uniform vec2 u_tex_size;
out vec4 color;
void main() {
  if (v_valid < 0.999) discard;
  vec2 p = clamp(v_src, vec2(0.5), u_src_rect.zw - 0.5);
  color = vec4(texture(u_video, (u_src_rect.xy + p) / u_tex_size).rgb, 1.0);
}`;

/**
 * Draws the newest presented frame of `video`, reprojected, on `canvas`.
 * `rtpOffset()` gives the stream's first RTP timestamp (presented.js) or null.
 */
export class Reprojector {
  constructor(canvas, video, { background = [1, 1, 1], rtpOffset }) {
    this.canvas = canvas;
    this.video = video;
    this.background = background;
    this.rtpOffset = rtpOffset;
    this.depth = new Map(); // rtp ticks → depth frame
    this.enabled = true;
    this.frozen = false;    // tests: keep the current frame (no new uploads)
    this.stats = { depthFrames: 0, depthErrors: 0, lastDepthError: null, depthBytes: 0, uploads: 0, warped: 0, unwarped: 0 };
    this.frame = null;      // {rtp, width, height} of the uploaded texture
    const gl = canvas.getContext('webgl2', { antialias: false, preserveDrawingBuffer: true, alpha: false });
    this.gl = gl;
    if (!gl) return;
    const shader = (type, src) => {
      const s = gl.createShader(type);
      gl.shaderSource(s, src);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
      return s;
    };
    const prog = gl.createProgram();
    gl.attachShader(prog, shader(gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(prog, shader(gl.FRAGMENT_SHADER, FRAGMENT));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
    this.prog = prog;
    this.loc = Object.fromEntries(['u_stride', 'u_src_size', 'u_src_k', 'u_target_from_source', 'u_dst_k', 'u_dst_size', 'u_video', 'u_src_rect', 'u_tex_size'].map((n) => [n, gl.getUniformLocation(prog, n)]));
    this.texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    for (const [p, v] of [[gl.TEXTURE_MIN_FILTER, gl.LINEAR], [gl.TEXTURE_MAG_FILTER, gl.LINEAR], [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE]]) gl.texParameteri(gl.TEXTURE_2D, p, v);
    this.vao = gl.createVertexArray();
    this.gridBuf = gl.createBuffer();
    this.zBuf = gl.createBuffer();
    this.indexBuf = gl.createBuffer();
    this.gridKey = null;
    if (typeof video.requestVideoFrameCallback === 'function') {
      const onFrame = (now, meta) => { this.upload(meta); video.requestVideoFrameCallback(onFrame); };
      video.requestVideoFrameCallback(onFrame);
    }
  }

  get available() { return Boolean(this.gl); }

  /** A binary message from the pose channel: decoded and kept by its RTP ticks. */
  async addDepth(buffer) {
    try {
      const d = await decodeDepth(buffer);
      this.depth.set(d.rtpTicks >>> 0, d);
      if (this.depth.size > 120) this.depth.delete(this.depth.keys().next().value);
      this.stats.depthFrames += 1;
      this.stats.depthBytes = buffer.byteLength;
    } catch (err) {
      this.stats.depthErrors += 1;
      this.stats.lastDepthError = String(err.message || err);
    }
  }

  /** Forget the stream's depth and picture (a new session: its RTP ticks start again). */
  reset() {
    this.depth.clear();
    this.frame = null;
  }

  upload(meta) {
    if (this.frozen || !this.gl || !this.video.videoWidth) return;
    const gl = this.gl;
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, this.video);
    this.frame = { rtp: Number.isFinite(meta?.rtpTimestamp) ? meta.rtpTimestamp >>> 0 : null, width: this.video.videoWidth, height: this.video.videoHeight };
    this.stats.uploads += 1;
  }

  /** The depth of the uploaded frame, if it came and its RTP clock is known. */
  currentDepth() {
    const offset = this.rtpOffset?.();
    if (!this.frame || this.frame.rtp === null || offset === null || offset === undefined) return null;
    const d = this.depth.get((this.frame.rtp - offset) >>> 0);
    // Depth whose views do not lie inside this picture (another stream's) is not used.
    const fits = (v) => v.viewport[0] + v.viewport[2] <= this.frame.width && v.viewport[1] + v.viewport[3] <= this.frame.height;
    return d && d.views.every(fits) ? d : null;
  }

  setGrid(view) {
    const gl = this.gl;
    const key = `${view.cols}x${view.rows}`;
    if (key === this.gridKey) return;
    const grid = new Float32Array(2 * view.cols * view.rows);
    for (let j = 0; j < view.rows; j++) for (let i = 0; i < view.cols; i++) grid.set([i, j], 2 * (j * view.cols + i));
    const idx = new Uint16Array(6 * (view.cols - 1) * (view.rows - 1));
    let n = 0;
    for (let j = 0; j < view.rows - 1; j++) for (let i = 0; i < view.cols - 1; i++) {
      const a = j * view.cols + i, b = a + 1, c = a + view.cols + 1, d = a + view.cols;
      idx.set([a, b, c, a, c, d], n);
      n += 6;
    }
    gl.bindVertexArray(this.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.gridBuf);
    gl.bufferData(gl.ARRAY_BUFFER, grid, gl.STATIC_DRAW);
    const aGrid = gl.getAttribLocation(this.prog, 'a_grid');
    gl.enableVertexAttribArray(aGrid);
    gl.vertexAttribPointer(aGrid, 2, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.indexBuf);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, idx, gl.STATIC_DRAW);
    this.indexCount = idx.length;
    this.gridKey = key;
  }

  /**
   * Draws the current frame for `targets`: [{ worldFromCamera, k: {fx, fy, cx, cy}, viewport:
   * [x, y, w, h] (canvas pixels, top-left origin), view: index of the frame's view }]. A view
   * without depth (or with reprojection off) is drawn as it came, into its viewport.
   */
  draw(targets) {
    const gl = this.gl;
    if (!gl || !this.frame) return false;
    const depth = this.enabled ? this.currentDepth() : null;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    gl.disable(gl.SCISSOR_TEST);
    gl.clearColor(...this.background, 1);
    gl.clearDepth(1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.depthFunc(gl.LEQUAL);
    gl.useProgram(this.prog);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.uniform1i(this.loc.u_video, 0);
    gl.uniform2f(this.loc.u_tex_size, this.frame.width, this.frame.height);
    let warped = false;
    for (const t of targets) {
      const view = depth?.views[t.view];
      // Unwarped: the frame's own view with a flat grid at its own camera (identity).
      const source = view || this.flatView(t);
      this.setGrid(source);
      gl.bindVertexArray(this.vao);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.zBuf);
      gl.bufferData(gl.ARRAY_BUFFER, source.z, gl.DYNAMIC_DRAW);
      const aZ = gl.getAttribLocation(this.prog, 'a_z');
      gl.enableVertexAttribArray(aZ);
      gl.vertexAttribPointer(aZ, 1, gl.FLOAT, false, 0, 0);
      const [vx, vy, vw, vh] = t.viewport;
      gl.viewport(vx, this.canvas.height - vy - vh, vw, vh);
      gl.enable(gl.SCISSOR_TEST);
      gl.scissor(vx, this.canvas.height - vy - vh, vw, vh);
      const targetFromSource = view ? mul(rigidInverse(t.worldFromCamera), view.worldFromCamera) : new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
      const k = view ? t.k : source.k;
      gl.uniform1f(this.loc.u_stride, source.stride);
      gl.uniform2f(this.loc.u_src_size, source.viewport[2], source.viewport[3]);
      gl.uniform4f(this.loc.u_src_k, source.k.fx, source.k.fy, source.k.cx, source.k.cy);
      gl.uniformMatrix4fv(this.loc.u_target_from_source, false, targetFromSource);
      gl.uniform4f(this.loc.u_dst_k, k.fx, k.fy, k.cx, k.cy);
      gl.uniform2f(this.loc.u_dst_size, vw, vh);
      gl.uniform4f(this.loc.u_src_rect, ...source.viewport);
      gl.drawElements(gl.TRIANGLES, this.indexCount, gl.UNSIGNED_SHORT, 0);
      warped ||= Boolean(view);
    }
    gl.disable(gl.SCISSOR_TEST);
    this.stats[warped ? 'warped' : 'unwarped'] += 1;
    return warped;
  }

  /** A grid at infinity over a target's source viewport, with the target's own lens: drawn
   *  with the identity it reproduces the frame pixel for pixel. */
  flatView(t) {
    const src = t.sourceViewport || t.viewport;
    const stride = 64;
    const [cols, rows] = gridSize(src[2], src[3], stride);
    return { viewport: src, stride, cols, rows, k: t.k, z: new Float32Array(cols * rows) };
  }
}
