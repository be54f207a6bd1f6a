// nephele.js — shared browser side of Nephele, used by the viewer (index.html) and AR (ar.html).
//
// What lives here:
//   * OrbitCamera: the camera both pages steer (world up is +z, as in NeRF-synthetic),
//     and attachOrbitControls(): mouse/touch gestures that move it.
//   * encodePose(): the 104/168-byte little-endian "NPO1" pose message.
//   * Connection: signaling over the /signal websocket (join → joined → offer/answer,
//     trickle ICE both ways), the recvonly H.264 video + unordered "pose" data channel,
//     a pose every 20 ms, frame-info/latency bookkeeping, getStats polling, and automatic
//     reconnection with backoff (1, 2, 4, … ≤ 10 s).
//   * ensureCapturePermission(): Chromium only gathers loopback ICE candidates once the page
//     holds a capture permission, so we ask for a camera once and keep the stream.
//   * fetchScenes(), readPageOptions(), describeError(): small helpers for both pages.

// ───────────────────────────── small vector helpers ─────────────────────────────

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };
const clamp = (x, lo, hi) => Math.min(hi, Math.max(lo, x));
const DEG = Math.PI / 180;

// ───────────────────────────────── orbit camera ─────────────────────────────────

/** A camera on a sphere around `center`, looking at it; +z is world up. */
export class OrbitCamera {
  constructor() {
    this.reset([0, 0, 0], 1);
  }

  /** Default view of an asset: distance 2.6·radius, azimuth 35°, elevation 25°, fovY 40°. */
  reset(center, radius) {
    this.center = [...center];
    this.radius = radius > 0 ? radius : 1;
    this.distance = 2.6 * this.radius;
    this.azimuth = 35 * DEG;   // about +z, from +x
    this.elevation = 25 * DEG; // towards +z
    this.fovY = 40 * DEG;
  }

  eye() {
    const ce = Math.cos(this.elevation);
    return add(this.center, scale([ce * Math.cos(this.azimuth), ce * Math.sin(this.azimuth), Math.sin(this.elevation)], this.distance));
  }

  /** Camera axes in world space: right (+x), up (+y), back (+z; the camera looks down −z). */
  axes() {
    const back = norm(sub(this.eye(), this.center));
    const right = norm(cross([0, 0, 1], back)); // elevation stays within ±89°, so never degenerate
    const up = cross(back, right);
    return { right, up, back };
  }

  /** world_from_camera as 16 floats, column-major (OpenGL camera convention). */
  worldFromCamera() {
    const { right, up, back } = this.axes();
    const e = this.eye();
    return new Float32Array([...right, 0, ...up, 0, ...back, 0, ...e, 1]);
  }

  /** Pinhole intrinsics of a centred camera for a width×height viewport. */
  intrinsics(width, height) {
    const f = 0.5 * height / Math.tan(this.fovY / 2);
    return { fx: f, fy: f, cx: width / 2, cy: height / 2 };
  }

  orbit(dAzimuth, dElevation) {
    this.azimuth = (this.azimuth + dAzimuth) % (2 * Math.PI);
    this.elevation = clamp(this.elevation + dElevation, -89 * DEG, 89 * DEG);
  }

  /** Multiply the distance by `factor`, within [0.05, 50]·radius. */
  zoom(factor) {
    this.distance = clamp(this.distance * factor, 0.05 * this.radius, 50 * this.radius);
  }

  /** Move the look-at point by a fraction of the view height (fractions of the viewport). */
  pan(fracX, fracY) {
    const { right, up } = this.axes();
    const viewHeight = 2 * this.distance * Math.tan(this.fovY / 2);
    // Content follows the pointer: dragging right moves the camera left.
    let c = add(this.center, add(scale(right, -fracX * viewHeight), scale(up, fracY * viewHeight)));
    // Keep the camera well within the server's distance limit.
    const far = 100 * this.radius;
    const l = Math.hypot(...c);
    if (l > far) c = scale(c, far / l);
    this.center = c;
  }

  /** World-space ray through viewport pixel (px, py) of a width×height image. */
  ray(px, py, width, height) {
    const { fx, fy, cx, cy } = this.intrinsics(width, height);
    const { right, up, back } = this.axes();
    const dx = (px - cx) / fx, dy = -(py - cy) / fy; // image y grows downwards, camera +y up
    const dir = norm(add(add(scale(right, dx), scale(up, dy)), scale(back, -1)));
    return { origin: this.eye(), dir };
  }
}

/**
 * Mouse and touch gestures on `element` that steer `camera`:
 * left-drag orbits, wheel zooms, right-drag or shift-drag pans; one finger orbits, two
 * fingers pinch-zoom and pan. `onTap(clientX, clientY)` fires for a click/tap that did not
 * move. `viewportHeight()` gives the displayed image height in CSS pixels (for panning).
 */
export function attachOrbitControls(element, camera, { onTap, viewportHeight } = {}) {
  const pointers = new Map(); // pointerId → {x, y}
  let mode = null;            // 'orbit' | 'pan' | 'pinch'
  let tap = null;             // {x, y, t} while a press might still be a tap
  let pinch = null;           // {dist, mid}
  const height = () => (viewportHeight ? viewportHeight() : element.clientHeight) || 1;
  const ORBIT_RAD_PER_PX = 0.008;

  const twoFinger = () => {
    const [a, b] = [...pointers.values()];
    return { dist: Math.hypot(a.x - b.x, a.y - b.y) || 1, mid: [(a.x + b.x) / 2, (a.y + b.y) / 2] };
  };

  element.style.touchAction = 'none';
  element.addEventListener('contextmenu', (e) => e.preventDefault());

  element.addEventListener('pointerdown', (e) => {
    element.setPointerCapture?.(e.pointerId);
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
    if (pointers.size === 1) {
      mode = e.button === 2 || e.shiftKey ? 'pan' : 'orbit';
      tap = { x: e.clientX, y: e.clientY, t: performance.now() };
    } else if (pointers.size === 2) {
      mode = 'pinch';
      pinch = twoFinger();
      tap = null;
    }
    e.preventDefault();
  });

  element.addEventListener('pointermove', (e) => {
    const p = pointers.get(e.pointerId);
    if (!p) return;
    const dx = e.clientX - p.x, dy = e.clientY - p.y;
    p.x = e.clientX; p.y = e.clientY;
    if (tap && Math.hypot(e.clientX - tap.x, e.clientY - tap.y) > 6) tap = null;
    if (mode === 'orbit') {
      camera.orbit(-dx * ORBIT_RAD_PER_PX, dy * ORBIT_RAD_PER_PX);
    } else if (mode === 'pan') {
      camera.pan(dx / height(), dy / height());
    } else if (mode === 'pinch' && pointers.size >= 2) {
      const now = twoFinger();
      camera.zoom(pinch.dist / now.dist);
      camera.pan((now.mid[0] - pinch.mid[0]) / height(), (now.mid[1] - pinch.mid[1]) / height());
      pinch = now;
    }
  });

  const end = (e) => {
    if (!pointers.delete(e.pointerId)) return;
    if (tap && pointers.size === 0 && e.type === 'pointerup' && performance.now() - tap.t < 600) {
      onTap?.(e.clientX, e.clientY);
    }
    tap = null;
    // Lifting one of two fingers continues as a one-finger orbit from the remaining finger.
    mode = pointers.size === 1 ? 'orbit' : pointers.size === 0 ? null : mode;
    if (pointers.size >= 2) pinch = twoFinger();
  };
  element.addEventListener('pointerup', end);
  element.addEventListener('pointercancel', end);

  element.addEventListener('wheel', (e) => {
    e.preventDefault();
    const px = e.deltaMode === 1 ? e.deltaY * 16 : e.deltaMode === 2 ? e.deltaY * 400 : e.deltaY;
    camera.zoom(Math.exp(clamp(px, -200, 200) * 0.0015));
  }, { passive: false });
}

// ───────────────────────────────── pose message ─────────────────────────────────

export const POSE_LEN = 104;
export const POSE_WITH_ANCHOR_LEN = 168;

/**
 * The binary pose message (little-endian):
 * "NPO1" | u32 seq | f64 t_client_ms | f32×16 world_from_camera (column-major) |
 * f32×4 fx fy cx cy | u32×2 width height | optional f32×16 world_from_anchor.
 */
export function encodePose({ seq, tClientMs, worldFromCamera, intrinsics, width, height, worldFromAnchor }) {
  const buf = new ArrayBuffer(worldFromAnchor ? POSE_WITH_ANCHOR_LEN : POSE_LEN);
  const v = new DataView(buf);
  [0x4e, 0x50, 0x4f, 0x31].forEach((b, i) => v.setUint8(i, b)); // "NPO1"
  v.setUint32(4, seq, true);
  v.setFloat64(8, tClientMs, true);
  for (let i = 0; i < 16; i++) v.setFloat32(16 + 4 * i, worldFromCamera[i], true);
  const { fx, fy, cx, cy } = intrinsics;
  [fx, fy, cx, cy].forEach((x, i) => v.setFloat32(80 + 4 * i, x, true));
  v.setUint32(96, width, true);
  v.setUint32(100, height, true);
  if (worldFromAnchor) for (let i = 0; i < 16; i++) v.setFloat32(104 + 4 * i, worldFromAnchor[i], true);
  return buf;
}

// ─────────────────────────────────── helpers ────────────────────────────────────

let capturePromise = null;

/**
 * Ask once per page for a capture stream and hold on to it (never stopped). Chromium only
 * gathers local (loopback) ICE candidates after such a grant. Resolves to the stream, or to
 * null on failure (no camera, denied, insecure context): the session goes on without it.
 * The first caller's constraints win; the AR page asks first for its environment camera.
 */
export function ensureCapturePermission(constraints = { video: true }) {
  if (!capturePromise) {
    const md = navigator.mediaDevices;
    capturePromise = md && md.getUserMedia
      ? md.getUserMedia(constraints).catch((err) => { console.info('nephele: no capture permission:', err.name); return null; })
      : Promise.resolve(null);
    window.__nepheleCapture = capturePromise; // held for the page's lifetime
  }
  return capturePromise;
}

/** GET scenes → {scenes:[...], default}; falls back to trio if the server does not say. */
export async function fetchScenes() {
  try {
    const ctl = new AbortController();
    const timer = setTimeout(() => ctl.abort(), 4000);
    const r = await fetch(new URL('scenes', location.href), { signal: ctl.signal, cache: 'no-store' });
    clearTimeout(timer);
    const j = await r.json();
    const scenes = Array.isArray(j.scenes) && j.scenes.length ? j.scenes.map(String) : ['trio'];
    return { scenes, default: scenes.includes(j.default) ? j.default : scenes[0] };
  } catch {
    return { scenes: ['trio'], default: 'trio' };
  }
}

/** Page options from the query string: ?scene=trio&size=1280x720&fps=50&token=… */
export function readPageOptions() {
  const q = new URLSearchParams(location.search);
  const m = /^(\d+)x(\d+)$/.exec(q.get('size') || '');
  const even = (n) => Math.max(2, Math.round(n / 2) * 2);
  return {
    scene: q.get('scene') || null,
    width: m ? even(+m[1]) : 640,
    height: m ? even(+m[2]) : 480,
    fps: clamp(parseInt(q.get('fps'), 10) || 50, 1, 120),
    token: q.get('token') || undefined,
  };
}

const ERROR_WORDS = {
  no_capacity: 'No render server has room right now',
  master_lost: 'The render server went away',
  rejected: 'The render server refused the session',
  unknown_scene: 'No render server has this scene',
  unauthorized: 'The server needs a valid access token (add ?token=… to the address)',
  bad_request: 'The server did not accept the request',
  bad_message: 'The server did not understand a message',
  too_large: 'A message was too large for the server',
  wrong_role: 'The server got a message this page may not send',
  not_joined: 'The server got a session message before the session existed',
  bad_pose: 'The server refused a camera pose',
  frame_failed: 'The server could not render a frame',
  ended: 'The render server ended the session',
  connection_lost: 'Connection to the server lost',
  unreachable: 'Cannot reach the server',
  peer_failed: 'The video connection failed',
  timeout: 'The video connection did not come up in time',
};

// Codes this page makes up itself: shown without the code.
const LOCAL_CODES = new Set(['connection_lost', 'unreachable', 'peer_failed', 'timeout']);

/** "No render server has room right now (no_capacity): <server text>" */
export function describeError(code, message) {
  const words = ERROR_WORDS[code] || 'Error';
  const tag = LOCAL_CODES.has(code) ? '' : ` (${code})`;
  return message ? `${words}${tag}: ${message}` : `${words}${tag}`;
}

// Errors after which retrying cannot help until the user changes something.
const FATAL_CODES = new Set(['unauthorized', 'bad_request', 'rejected', 'unknown_scene', 'bad_message', 'too_large', 'wrong_role', 'not_joined']);

const POSE_PERIOD_MS = 20;
const STATS_PERIOD_MS = 500;
const DISCONNECTED_GRACE_MS = 3000;
const CONNECT_TIMEOUT_MS = 20000;

// ───────────────────────────────── the session ──────────────────────────────────

/**
 * One streaming session, re-established automatically when it breaks.
 *
 * options:
 *   mode            'viewer' | 'ar'
 *   video           <video> element that shows the stream
 *   camera          OrbitCamera whose pose is sent every 20 ms
 *   anchor()        optional: returns the 16-float world_from_anchor to append (AR)
 *   onSession(msg)  the channel's "session" message (center, radius, up, size, …)
 *   onChange()      something shown on the HUD changed (state, banner, stats)
 *
 * Readable fields: state, banner {text, kind} | null, lastFrame, frameInfos, poseSeq,
 * errors [{code, message, time}], session (last "session" message), hud (see pollStats).
 */
export class Connection {
  constructor({ mode, video, camera, anchor, onSession, onChange }) {
    Object.assign(this, { mode, video, camera, anchorFn: anchor, onSession, onChange });
    this.state = 'idle';
    this.banner = null;
    this.errors = [];
    this.lastFrame = null;
    this.frameInfos = 0;
    this.poseSeq = 0;
    this.session = null;
    this.hud = { fps: 0, latencyMs: null, kbps: 0, width: 0, height: 0, framesDecoded: 0, bytesReceived: 0 };
    this.gen = 0;          // bumps on every (re)connect; stale callbacks compare and bail out
    this.backoffS = 1;
    this.retryTimer = null;
    this.latencies = [];   // [performance.now(), latency ms] over the last second
    this.prevStats = null;
    this.statsTimer = setInterval(() => this.pollStats(), STATS_PERIOD_MS);
    addEventListener('pagehide', () => this.close());
    // Back/forward cache: a restored page starts a fresh session.
    addEventListener('pageshow', (e) => { if (e.persisted && this.params) this.connect(this.params); });
  }

  /** (Re)join with { scene, width, height, fps, token }; resets the backoff. */
  connect(params) {
    this.params = { ...params };
    this.backoffS = 1;
    this.start();
  }

  /** Leave for good (page closing). */
  close() {
    this.teardown();
    this.setState('closed');
  }

  setState(state) {
    this.state = state;
    this.onChange?.();
  }

  setBanner(text, kind = 'error') {
    this.banner = text ? { text, kind } : null;
    clearTimeout(this.bannerTimer);
    this.onChange?.();
  }

  recordError(code, message) {
    this.errors.push({ code, message: message || '', time: Date.now() });
    if (this.errors.length > 100) this.errors.shift();
  }

  // Close everything of the current attempt (telling signaling we leave, if we joined).
  teardown() {
    this.gen++;
    clearTimeout(this.retryTimer);
    clearTimeout(this.disconnectTimer);
    clearTimeout(this.connectTimer);
    clearInterval(this.poseTimer);
    const { ws, pc, dc } = this;
    this.ws = this.pc = this.dc = null;
    if (ws) {
      try { if (ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify({ type: 'leave' })); } catch { /* closing anyway */ }
      try { ws.close(1000, 'leave'); } catch { /* already closed */ }
    }
    try { dc?.close(); } catch { /* ignore */ }
    try { pc?.close(); } catch { /* ignore */ }
    this.prevStats = null;
  }

  // Something broke: show why, and try again after the backoff (unless it is fatal).
  fail(code, message) {
    if (this.state === 'closed') return;
    this.recordError(code, message);
    this.teardown();
    if (FATAL_CODES.has(code)) {
      this.setBanner(`${describeError(code, message)}. Pick another scene or reload to try again.`);
      this.setState('error');
      return;
    }
    const delay = this.backoffS;
    this.backoffS = Math.min(10, this.backoffS * 2);
    this.setBanner(`${describeError(code, message)} — reconnecting in ${delay} s…`);
    this.setState('reconnecting');
    const gen = this.gen;
    this.retryTimer = setTimeout(() => { if (gen === this.gen) this.start(); }, delay * 1000);
  }

  async start() {
    this.teardown();
    const gen = this.gen;
    this.setState('connecting');
    const stale = () => gen !== this.gen;

    await ensureCapturePermission();
    if (stale()) return;

    const url = new URL('signal', location.href);
    url.protocol = location.protocol === 'https:' ? 'wss:' : 'ws:';
    let ws;
    try {
      ws = new WebSocket(url);
    } catch (err) {
      this.fail('unreachable', String(err.message || err));
      return;
    }
    this.ws = ws;
    this.remoteCandidates = [];
    this.localCandidates = [];
    this.offerSent = false;
    this.connectTimer = setTimeout(() => { if (!stale()) this.fail('timeout', `no video after ${CONNECT_TIMEOUT_MS / 1000} s`); }, CONNECT_TIMEOUT_MS);

    let opened = false;
    ws.onopen = () => {
      if (stale()) return;
      opened = true;
      const { scene, width, height, fps, token } = this.params;
      const join = { type: 'join', scene, mode: this.mode, width, height, fps };
      if (token) join.token = token;
      this.send(join);
      this.setState('joining');
    };
    ws.onmessage = (e) => {
      if (stale()) return;
      let msg;
      try { msg = JSON.parse(e.data); } catch { console.warn('nephele: non-JSON signaling message'); return; }
      this.onSignal(msg, gen).catch((err) => { if (!stale()) this.fail('peer_failed', String(err.message || err)); });
    };
    ws.onclose = (e) => {
      if (stale()) return;
      // 1006 (abnormal closure) carries no reason worth showing.
      this.fail(opened ? 'connection_lost' : 'unreachable', e.reason || (e.code === 1006 ? '' : `websocket closed (${e.code})`));
    };
  }

  send(msg) {
    if (this.ws && this.ws.readyState === WebSocket.OPEN) this.ws.send(JSON.stringify(msg));
  }

  async onSignal(msg, gen) {
    const stale = () => gen !== this.gen;
    switch (msg.type) {
      case 'joined':
        this.setState('negotiating');
        await this.createPeer(gen);
        break;
      case 'answer':
        if (!this.pc) return;
        await this.pc.setRemoteDescription({ type: 'answer', sdp: msg.sdp });
        if (stale()) return;
        for (const c of this.remoteCandidates.splice(0)) await this.addRemoteCandidate(c);
        break;
      case 'ice':
        if (!msg.candidate || !msg.candidate.candidate) return; // end-of-candidates
        if (this.pc && this.pc.remoteDescription) await this.addRemoteCandidate(msg.candidate);
        else this.remoteCandidates.push(msg.candidate);
        break;
      case 'error':
        this.fail(msg.code || 'error', msg.message);
        break;
      case 'ended':
        this.fail('ended', msg.reason);
        break;
      default:
        console.warn('nephele: unknown signaling message', msg.type);
    }
  }

  async addRemoteCandidate(c) {
    try { await this.pc.addIceCandidate(c); } catch (err) { console.warn('nephele: bad remote candidate', err); }
  }

  async createPeer(gen) {
    const stale = () => gen !== this.gen;
    const pc = new RTCPeerConnection({ iceServers: [] });
    this.pc = pc;
    pc.addTransceiver('video', { direction: 'recvonly' });
    const dc = pc.createDataChannel('pose', { ordered: false, maxRetransmits: 0 });
    dc.binaryType = 'arraybuffer';
    this.dc = dc;

    pc.ontrack = (e) => {
      if (stale()) return;
      const stream = e.streams[0] || new MediaStream([e.track]);
      this.video.srcObject = stream;
      this.video.play().catch(() => { /* muted autoplay is allowed; retried on the next track */ });
    };
    pc.onicecandidate = (e) => {
      if (stale() || !e.candidate || !e.candidate.candidate) return; // don't send end-of-candidates
      const c = e.candidate.toJSON();
      if (this.offerSent) this.send({ type: 'ice', candidate: c });
      else this.localCandidates.push(c);
    };
    pc.onconnectionstatechange = () => {
      if (stale()) return;
      const s = pc.connectionState;
      clearTimeout(this.disconnectTimer);
      if (s === 'connected') {
        clearTimeout(this.connectTimer);
        this.backoffS = 1;
        this.setBanner(null);
        this.setState('connected');
      } else if (s === 'failed') {
        this.fail('peer_failed', 'ICE/DTLS failed');
      } else if (s === 'disconnected') {
        this.setBanner('Video connection interrupted — waiting for it to recover…', 'warn');
        this.setState('disconnected');
        this.disconnectTimer = setTimeout(() => {
          if (!stale() && pc.connectionState !== 'connected') this.fail('peer_failed', 'disconnected for more than 3 s');
        }, DISCONNECTED_GRACE_MS);
      }
    };

    dc.onopen = () => {
      if (stale()) return;
      this.poseSeq = 0;
      this.sendPose();
      this.poseTimer = setInterval(() => this.sendPose(), POSE_PERIOD_MS);
    };
    dc.onclose = () => { clearInterval(this.poseTimer); };
    dc.onmessage = (e) => { if (!stale()) this.onChannelMessage(e.data); };

    const offer = await pc.createOffer();
    if (stale()) return;
    await pc.setLocalDescription(offer);
    if (stale()) return;
    this.send({ type: 'offer', sdp: pc.localDescription.sdp });
    this.offerSent = true;
    for (const c of this.localCandidates.splice(0)) this.send({ type: 'ice', candidate: c });
  }

  sendPose() {
    const dc = this.dc;
    if (!dc || dc.readyState !== 'open') return;
    if (dc.bufferedAmount > 64 * 1024) return; // congested: a fresher pose follows in 20 ms
    const { width, height } = this.params;
    const anchor = this.anchorFn?.();
    this.poseSeq += 1;
    dc.send(encodePose({
      seq: this.poseSeq,
      tClientMs: performance.now(),
      worldFromCamera: this.camera.worldFromCamera(),
      intrinsics: this.camera.intrinsics(width, height),
      width,
      height,
      worldFromAnchor: anchor || undefined,
    }));
  }

  onChannelMessage(data) {
    if (typeof data !== 'string') return;
    let msg;
    try { msg = JSON.parse(data); } catch { console.warn('nephele: non-JSON channel message'); return; }
    if (msg.type === 'frame') {
      const now = performance.now();
      this.lastFrame = msg;
      this.frameInfos += 1;
      if (Number.isFinite(msg.t_client_ms)) this.latencies.push([now, now - msg.t_client_ms]);
    } else if (msg.type === 'session') {
      this.session = msg;
      this.onSession?.(msg);
    } else if (msg.type === 'error') {
      this.recordError(msg.code || 'error', msg.message);
      this.setBanner(describeError(msg.code || 'error', msg.message), 'warn');
      const gen = this.gen;
      this.bannerTimer = setTimeout(() => { if (gen === this.gen && this.state === 'connected') this.setBanner(null); }, 5000);
    } else if (msg.type === 'notice') {
      // The render farm went away (kept until it is back) or came back (shown briefly).
      const back = msg.code === 'farm_back';
      this.setBanner(msg.message, back ? 'info' : 'warn');
      if (back) {
        const gen = this.gen;
        this.bannerTimer = setTimeout(() => { if (gen === this.gen && this.state === 'connected') this.setBanner(null); }, 3000);
      }
    }
  }

  /** getStats() of the inbound video: {framesDecoded, bytesReceived, frameWidth, frameHeight}. */
  async stats() {
    const out = { framesDecoded: 0, bytesReceived: 0, frameWidth: 0, frameHeight: 0, framesPerSecond: 0 };
    if (!this.pc) return out;
    const report = await this.pc.getStats();
    report.forEach((s) => {
      if (s.type === 'inbound-rtp' && (s.kind === 'video' || s.mediaType === 'video')) {
        out.framesDecoded = s.framesDecoded || 0;
        out.bytesReceived = s.bytesReceived || 0;
        out.frameWidth = s.frameWidth || 0;
        out.frameHeight = s.frameHeight || 0;
        out.framesPerSecond = s.framesPerSecond || 0;
      }
    });
    return out;
  }

  /** Median pose→frame-info latency over the last second, in ms (null if none). */
  latencyP50() {
    const cutoff = performance.now() - 1000;
    while (this.latencies.length && this.latencies[0][0] < cutoff) this.latencies.shift();
    if (!this.latencies.length) return null;
    const v = this.latencies.map((x) => x[1]).sort((a, b) => a - b);
    return v[Math.floor(v.length / 2)];
  }

  // Every 500 ms: decoded fps and bitrate from getStats deltas, latency, resolution.
  async pollStats() {
    const gen = this.gen;
    let s;
    try { s = await this.stats(); } catch { return; }
    if (gen !== this.gen) return;
    const now = performance.now();
    const prev = this.prevStats;
    const hud = this.hud;
    if (prev && this.pc) {
      const dt = (now - prev.t) / 1000;
      hud.fps = Math.max(0, (s.framesDecoded - prev.framesDecoded) / dt);
      hud.kbps = Math.max(0, ((s.bytesReceived - prev.bytesReceived) * 8) / 1000 / dt);
    } else {
      hud.fps = 0;
      hud.kbps = 0;
    }
    this.prevStats = { t: now, framesDecoded: s.framesDecoded, bytesReceived: s.bytesReceived };
    hud.framesDecoded = s.framesDecoded;
    hud.bytesReceived = s.bytesReceived;
    hud.latencyMs = this.latencyP50();
    hud.width = this.video.videoWidth;
    hud.height = this.video.videoHeight;
    this.onChange?.();
  }

  /** The test/debug surface both pages put on window.nephele. */
  exposeApi(extra = {}) {
    const conn = this;
    const api = {
      get state() { return conn.state; },
      get lastFrame() { return conn.lastFrame; },
      get poseSeq() { return conn.poseSeq; },
      get session() { return conn.session; },
      get banner() { return conn.banner ? conn.banner.text : null; },
      get hud() { return { ...conn.hud }; },
      errors: conn.errors,
      framesDecoded: () => conn.hud.framesDecoded,
      stats: () => conn.stats(),
      camera: conn.camera,
      connection: conn,
    };
    // Copy descriptors, not values, so the extra getters stay live.
    Object.defineProperties(api, Object.getOwnPropertyDescriptors(extra));
    window.nephele = api;
    return api;
  }
}

/** HUD text shared by both pages. */
export function hudLines(conn) {
  const h = conn.hud;
  const f = conn.lastFrame;
  return [
    ['state', conn.state],
    ['fps', h.fps.toFixed(1)],
    ['latency', h.latencyMs == null ? '–' : `${h.latencyMs.toFixed(0)} ms`],
    ['bitrate', `${h.kbps.toFixed(0)} kbit/s`],
    ['resolution', h.width ? `${h.width}×${h.height}` : '–'],
    // The server renders at this fraction of the stream size when moving (dynamic
    // resolution) and refines to full size when the camera rests.
    ['render', f ? `${Math.round((f.render_scale ?? 1) * 100)}% · ${f.render_ms.toFixed(0)} ms` : '–'],
    // Several users' views rendered in one task, or a frame reused (camera at rest, or the
    // same view as another user's).
    ['batch', f ? (f.reused ? 'reused' : `${f.batch_views ?? 1} view${(f.batch_views ?? 1) === 1 ? '' : 's'}`) : '–'],
    ['encode', f ? `${f.encode_ms.toFixed(1)} ms` : '–'],
    ['frame', f ? String(f.frame) : '–'],
  ];
}

/** Shows the connection state, the banner and the HUD in the page's `#state`, `#banner`
 *  and `#hud` elements (both pages use the same ids). */
export function renderStatus(conn) {
  const $ = (id) => document.getElementById(id);
  $('state').textContent = conn.state;
  $('state').dataset.state = conn.state;
  const banner = $('banner');
  banner.hidden = !conn.banner;
  if (conn.banner) {
    banner.textContent = conn.banner.text;
    banner.dataset.kind = conn.banner.kind;
  }
  $('hud').replaceChildren(...hudLines(conn).flatMap(([k, v]) => {
    const dt = document.createElement('dt'); dt.textContent = k;
    const dd = document.createElement('dd'); dd.textContent = v;
    return [dt, dd];
  }));
}
