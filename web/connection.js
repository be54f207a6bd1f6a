// connection.js — one streaming session with the Nephele server, shared by all pages.
//
//   * Connection: signaling over the /signal websocket (join → joined → offer/answer,
//     trickle ICE both ways), the recvonly H.264 video + unordered "pose" data channel, the
//     page's pose bytes every 20 ms (from its `pose` callback), frame-info/latency
//     bookkeeping, getStats polling, automatic reconnection with backoff (1, 2, 4, … ≤ 10 s),
//     and the window.nephele debug surface (exposeApi).
//   * ensureCapturePermission(): the AR page's camera. Other pages never ask on their own:
//     only where no connection can be made without it (Chromium offers a page without a
//     capture grant only its default route's address, never loopback: a machine with no
//     default route, or a page on 127.0.0.1) the page says so in words and asks when the
//     person agrees.
//   * fetchScenes(), readPageOptions(), describeError(): small helpers for the pages.

import { checkJoin, fetchLimits } from './join.js';
import { poseViewCount } from './pose.js';
import { PresentedLatency } from './presented.js';

// ─────────────────────────────────── helpers ────────────────────────────────────

let capturePromise = null;

/**
 * Ask once per page for a capture stream and hold on to it (never stopped). Resolves to the
 * stream, or to null on failure (no camera, denied, insecure context). The first caller's
 * constraints win: the AR page asks for its environment camera.
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

/** Whether this page holds (or has asked for) a capture stream. */
function captureAsked() {
  return capturePromise !== null;
}

/** A page served from this machine's loopback address. */
export function isLoopbackPage() {
  const h = location.hostname;
  return h === 'localhost' || h === '[::1]' || h === '::1' || /^127\./.test(h);
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

/** Page options from the query string: ?scene=trio&size=1280x720&fps=50&token=…
 *  (`defaults` gives the page's own default size; 640×480 otherwise). */
export function readPageOptions({ width = 640, height = 480 } = {}) {
  const q = new URLSearchParams(location.search);
  const m = /^(\d+)x(\d+)$/.exec(q.get('size') || '');
  const even = (n) => Math.max(2, Math.round(n / 2) * 2);
  return {
    scene: q.get('scene') || null,
    width: m ? even(+m[1]) : width,
    height: m ? even(+m[2]) : height,
    // Out-of-range rates are refused in words at join (the server's published limits).
    fps: parseInt(q.get('fps'), 10) || 50,
    token: q.get('token') || undefined,
    // ?relay=1: TURN relay candidates only (iceTransportPolicy "relay"), to try the relay.
    relay: q.get('relay') === '1',
    // ?reproject=0: show frames as they come (no depth asked for, no warp); ?predict=0: send
    // the present pose, not the one predicted for when its frame is shown (glass.js).
    reproject: q.get('reproject') !== '0',
    predict: q.get('predict') !== '0',
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
  rate_limited: 'This page sent messages too fast and was disconnected',
  bad_pose: 'The server refused a camera pose',
  frame_failed: 'The server could not render a frame',
  ended: 'The render server ended the session',
  connection_lost: 'Connection to the server lost',
  unreachable: 'Cannot reach the server',
  peer_failed: 'The video connection failed',
  timeout: 'The video connection did not come up in time',
  no_candidates: 'No network path for the video',
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
// Failures a hidden loopback candidate explains (see fail()).
const CANDIDATE_CODES = new Set(['no_candidates', 'peer_failed', 'timeout']);
const FATAL_CODES = new Set(['unauthorized', 'bad_request', 'rejected', 'unknown_scene', 'bad_message', 'too_large', 'wrong_role', 'not_joined']);

const POSE_PERIOD_MS = 20;
const POSE_HISTORY = 20; // view counts kept in viewsPerPose
const STATS_PERIOD_MS = 500;
const DISCONNECTED_GRACE_MS = 3000;
const CONNECT_TIMEOUT_MS = 20000;

// ───────────────────────────────── the session ──────────────────────────────────

/**
 * One streaming session, re-established automatically when it breaks.
 *
 * options:
 *   mode             'viewer' | 'ar' | 'vr' | 'quilt' (sent in `join`)
 *   video            <video> element that shows the stream
 *   pose(seq, tMs)   called every 20 ms while the channel is open: the pose message to send
 *                    (Uint8Array, e.g. from pose.js) for sequence number `seq` and client
 *                    time `tMs` (performance.now()), or null to send nothing this tick
 *   camera           optional: the page's OrbitCamera, only shown as window.nephele.camera
 *   onSession(msg)   the channel's "session" message (center, radius, up, size, …)
 *   onBinary(buf)    a binary channel message (a frame's depth, "NDP1": glass.js)
 *   onChange()       something shown on the HUD changed (state, banner, stats)
 *
 * Readable fields: state, banner {text, kind} | null, lastFrame, frameInfos, poseSeq,
 * lastPoseBytes (Uint8Array), viewsPerPose (view counts of the last 20 poses sent),
 * errors [{code, message, time}], session (last "session" message), hud (see pollStats).
 */
export class Connection {
  constructor({ mode, video, pose, camera, onSession, onChange, onBinary }) {
    Object.assign(this, { mode, video, poseFn: pose, camera, onSession, onChange, onBinary });
    this.state = 'idle';
    this.banner = null;
    this.errors = [];
    this.lastFrame = null;
    this.frameInfos = 0;
    this.poseSeq = 0;
    this.lastPoseBytes = null;
    this.viewsPerPose = [];
    this.session = null;
    // latencyMs: pose sent → its frame presented (presented.js); infoLatencyMs: pose sent →
    // its frame-info message (earlier: the frame is not decoded yet).
    this.hud = { fps: 0, latencyMs: null, infoLatencyMs: null, kbps: 0, width: 0, height: 0, framesDecoded: 0, bytesReceived: 0 };
    this.presented = new PresentedLatency();
    this.presented.watch(video);
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

  /** (Re)join with { scene, width, height, fps, token?, quilt?, depth? }; resets the backoff. */
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

  // `action` ({label, run}): a button beside the words.
  setBanner(text, kind = 'error', action = null) {
    this.banner = text ? { text, kind, action } : null;
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
    this.sessionText = null;
    this.presented.reset();
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
    // Without a capture grant Chromium offers a page only the address of its default route
    // (and never loopback): on a machine with no default route (a lab network, a container)
    // it offers nothing, and a page on 127.0.0.1 cannot be reached. The grant helps only
    // there, and never once a connection has worked without it. Ask when the person agrees.
    const hidden = code === 'no_candidates' || (CANDIDATE_CODES.has(code) && isLoopbackPage());
    if (hidden && !this.everConnected && !(navigator.mediaDevices && navigator.mediaDevices.getUserMedia)) {
      // Plain http:// from another machine: the page may not even ask.
      this.setBanner('No video connection: this browser shares this machine\'s network addresses only with a page that may use a camera, and a page on plain http:// from another machine cannot ask. Open it over HTTPS (or as http://localhost on the server), or from a machine with a default route.', 'error');
      this.setState('error');
      return;
    }
    if (hidden && !captureAsked() && !this.everConnected) {
      this.setBanner('No video connection: this browser shares this machine\'s network addresses with a page only when the page may use a camera (here it found no default route). Nephele never turns the camera on for this page or records it.', 'error',
        { label: 'Allow and connect', run: () => this.grantAndRetry() });
      this.setState('needs_grant');
      return;
    }
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

  /** The person agreed to the capture grant: take it (the camera is disabled at once, which
   *  keeps the grant and turns the camera light off) and connect again. */
  async grantAndRetry() {
    const stream = await ensureCapturePermission({ video: true });
    stream?.getTracks().forEach((t) => { t.enabled = false; });
    this.backoffS = 1;
    this.start();
  }

  async start() {
    this.teardown();
    const gen = this.gen;
    this.setState('connecting');
    const stale = () => gen !== this.gen;

    // The join checked against the server's published rules, in its words; not sent if it
    // breaks one. (Without /limits the server's own check still answers.)
    const join = { scene: this.params.scene, mode: this.mode, width: this.params.width, height: this.params.height, fps: this.params.fps, quilt: this.params.quilt };
    const limits = await fetchLimits().catch((err) => { console.warn('nephele: no /limits:', err); return null; });
    if (stale()) return;
    const broken = limits && checkJoin(join, limits);
    if (broken) {
      this.fail('bad_request', broken);
      return;
    }

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
      const { scene, width, height, fps, token, quilt, depth } = this.params;
      const join = { type: 'join', scene, mode: this.mode, width, height, fps };
      if (token) join.token = token;
      if (quilt) join.quilt = quilt;
      if (depth) join.depth = true;
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
      if (this.state === 'connected' || this.state === 'disconnected') {
        // The video is peer to peer and belongs to the master now: it goes on without
        // signaling (a signaling restart, a proxy's timeout). A broken peer still fails.
        this.ws = null;
        this.recordError('connection_lost', 'signaling closed; the stream continues');
        this.setBanner('Signaling connection lost — the stream continues', 'info');
        this.bannerTimer = setTimeout(() => { if (!stale() && this.state === 'connected') this.setBanner(null); }, 3000);
        return;
      }
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
        // The deployment's STUN/TURN servers (TURN with this session's credential).
        this.iceServers = Array.isArray(msg.ice_servers) ? msg.ice_servers : [];
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
    const relay = !!this.params.relay;
    if (relay && !this.iceServers.some((s) => [].concat(s.urls).some((u) => /^turns?:/.test(u)))) {
      this.fail('bad_request', 'relay-only (?relay=1) needs a TURN server, and this server offers none');
      return;
    }
    const pc = new RTCPeerConnection({ iceServers: this.iceServers, iceTransportPolicy: relay ? 'relay' : 'all' });
    this.pc = pc;
    let gathered = 0;
    pc.onicegatheringstatechange = () => {
      if (stale() || pc.iceGatheringState !== 'complete' || gathered > 0) return;
      // Nothing to connect from: no interface (or only loopback, hidden), or relay only and
      // TURN unreachable or refusing the credentials.
      this.fail('no_candidates', relay ? 'no TURN relay address: the TURN server is unreachable or refused the credentials' : 'this browser offered no network address to connect from');
    };
    pc.addTransceiver('video', { direction: 'recvonly' });
    const dc = pc.createDataChannel('pose', { ordered: false, maxRetransmits: 0 });
    dc.binaryType = 'arraybuffer';
    this.dc = dc;

    pc.ontrack = (e) => {
      if (stale()) return;
      // Interactive video: ask the receiver to play frames as soon as they are decoded
      // rather than to buffer for smoothness (measured by `presented`).
      if ('jitterBufferTarget' in e.receiver) e.receiver.jitterBufferTarget = 0;
      else if ('playoutDelayHint' in e.receiver) e.receiver.playoutDelayHint = 0;
      const stream = e.streams[0] || new MediaStream([e.track]);
      this.video.srcObject = stream;
      this.video.play().catch(() => { /* muted autoplay is allowed; retried on the next track */ });
    };
    pc.onicecandidate = (e) => {
      if (stale() || !e.candidate || !e.candidate.candidate) return; // don't send end-of-candidates
      gathered++;
      const c = e.candidate.toJSON();
      if (this.offerSent) this.send({ type: 'ice', candidate: c });
      else this.localCandidates.push(c);
    };
    pc.onconnectionstatechange = () => {
      if (stale()) return;
      const s = pc.connectionState;
      clearTimeout(this.disconnectTimer);
      if (s === 'connected') {
        this.everConnected = true;
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
    const seq = this.poseSeq + 1;
    let bytes;
    try {
      bytes = this.poseFn?.(seq, performance.now());
    } catch (err) {
      console.warn('nephele: pose callback failed', err);
      return;
    }
    if (!bytes) return; // the page has no pose this tick
    if (bytes instanceof ArrayBuffer) bytes = new Uint8Array(bytes);
    this.poseSeq = seq;
    dc.send(bytes);
    this.lastPoseBytes = bytes;
    this.viewsPerPose.push(poseViewCount(bytes));
    if (this.viewsPerPose.length > POSE_HISTORY) this.viewsPerPose.shift();
  }

  onChannelMessage(data) {
    if (typeof data !== 'string') {
      this.onBinary?.(data);
      return;
    }
    let msg;
    try { msg = JSON.parse(data); } catch { console.warn('nephele: non-JSON channel message'); return; }
    if (msg.type === 'frame') {
      const now = performance.now();
      this.lastFrame = msg;
      this.frameInfos += 1;
      if (Number.isFinite(msg.t_client_ms)) this.latencies.push([now, now - msg.t_client_ms]);
      this.presented.addInfo(msg);
    } else if (msg.type === 'session') {
      // The server repeats it until our first pose reaches it (the channel drops what it
      // loses): a copy of the one we have changes nothing.
      if (data === this.sessionText) return;
      this.sessionText = data;
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
    let pairId = null;
    report.forEach((s) => {
      if (s.type === 'inbound-rtp' && (s.kind === 'video' || s.mediaType === 'video')) {
        out.framesDecoded = s.framesDecoded || 0;
        out.bytesReceived = s.bytesReceived || 0;
        out.frameWidth = s.frameWidth || 0;
        out.frameHeight = s.frameHeight || 0;
        out.framesPerSecond = s.framesPerSecond || 0;
      }
      if (s.type === 'transport' && s.selectedCandidatePairId) pairId = s.selectedCandidatePairId;
    });
    // The path the video takes: each end's candidate type (host, srflx, prflx, relay).
    const pair = pairId && report.get(pairId);
    if (pair) {
      out.path = { local: report.get(pair.localCandidateId)?.candidateType, remote: report.get(pair.remoteCandidateId)?.candidateType };
    }
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
    hud.latencyMs = this.presented.p50();
    hud.infoLatencyMs = this.latencyP50();
    hud.width = this.video.videoWidth;
    hud.height = this.video.videoHeight;
    this.onChange?.();
  }

  /** The test/debug surface every page puts on window.nephele (`extra`: the page's own). */
  exposeApi(extra = {}) {
    const conn = this;
    const api = {
      get state() { return conn.state; },
      get lastFrame() { return conn.lastFrame; },
      get poseSeq() { return conn.poseSeq; },
      get lastPoseBytes() { return conn.lastPoseBytes; },
      get viewsPerPose() { return [...conn.viewsPerPose]; },
      get session() { return conn.session; },
      get banner() { return conn.banner ? conn.banner.text : null; },
      get hud() { return { ...conn.hud }; },
      /** Pose → presented frame: frames matched so far and the median of the last second. */
      get presented() { return { matched: conn.presented.matched, p50: conn.presented.p50(), info_p50: conn.latencyP50() }; },
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

