// viewer.js — logic of the viewer page (index.html): fills the scene picker from /scenes,
// connects on load and again when a picker changes, steers an orbit camera with mouse/touch
// (left-drag orbit, wheel zoom, right/shift-drag pan; one finger orbit, two fingers
// pinch/pan), and shows the HUD (fps, latency, bitrate, resolution, frame, state) and an
// error banner. The session itself (signaling, WebRTC, stats) is in connection.js, the
// camera in camera.js, the pose message in pose.js and the HUD in hud.js.
//
// Latency at the glass (glass.js): the page asks for each frame's depth and, at every
// animation frame, draws the newest decoded frame reprojected to where the camera is now
// (a WebGL2 canvas over the video); it sends the camera it predicts for when the frame will
// be shown (the pose→presented latency it measures, plus half a display period). The
// "reproject" box turns the warp off on the spot; ?reproject=0 and ?predict=0 turn each off
// from the start.

import { OrbitCamera, attachVideoOrbit } from './camera.js';
import { Connection, fetchScenes, readPageOptions } from './connection.js';
import { orbitPose } from './pose.js';
import { renderStatus } from './hud.js';
import { PosePredictor, Reprojector } from './glass.js';

const $ = (id) => document.getElementById(id);
const video = $('video');
const sceneSelect = $('scene');
const sizeSelect = $('size');

const options = readPageOptions();
const camera = new OrbitCamera();
const predictor = new PosePredictor();
const canvas = $('warp');
const reprojectBox = $('reproject');
let reprojector = null;
let horizonMs = 0; // what the last pose was predicted ahead by
let cameraScene = null; // scene the camera was last reset for; a reconnect keeps the view

const conn = new Connection({
  mode: 'viewer',
  video,
  camera,
  // The orbit camera as NPO1 at the joined size, every 20 ms: predicted for when its frame
  // will be shown, unless ?predict=0.
  pose: (seq, tClientMs) => {
    const present = camera.worldFromCamera();
    predictor.observe(tClientMs, present);
    const latency = conn.presented.p50();
    horizonMs = options.predict && latency !== null ? Math.min(latency + 8, 250) : 0;
    const ahead = horizonMs > 0 ? predictor.predict(horizonMs) : null;
    const view = ahead ? { worldFromCamera: () => ahead, intrinsics: (w, h) => camera.intrinsics(w, h) } : camera;
    const predicted = ahead ? { horizonMs, presentWorldFromCamera: present } : undefined;
    return orbitPose(view, { seq, tClientMs, width: conn.params.width, height: conn.params.height, predicted });
  },
  onBinary: (data) => reprojector?.addDepth(data),
  onSession(msg) {
    // A new session (a reconnect too) numbers its RTP ticks from 0 again: old depth must go.
    reprojector?.reset();
    // First session of a scene: frame the asset. A reconnect to the same scene keeps the view.
    if (msg.scene !== cameraScene && Array.isArray(msg.center)) {
      camera.reset(msg.center, msg.radius);
      cameraScene = msg.scene;
    }
  },
  onChange: render,
});
conn.exposeApi({
  get glass() {
    return {
      available: Boolean(reprojector?.available),
      enabled: Boolean(reprojector?.enabled) && !canvas.hidden,
      predict: options.predict,
      horizonMs,
      /** The pose the frame on screen answers (from its depth message), if known. */
      shownPoseSeq: reprojector?.currentDepth()?.poseSeq ?? null,
      ...(reprojector ? reprojector.stats : {}),
    };
  },
  /** Tests: keep the frame on screen (no new uploads) while the camera moves. */
  freezeWarp(on) { if (reprojector) reprojector.frozen = on; },
  reprojector: () => reprojector,
});

// The warp: WebGL2 over the video, drawn every animation frame.
if (options.reproject) {
  try {
    reprojector = new Reprojector(canvas, video, { background: [1, 1, 1], rtpOffset: () => conn.presented.offset });
  } catch (err) {
    console.warn('nephele: no reprojection:', err);
  }
}
reprojectBox.checked = Boolean(reprojector?.available);
reprojectBox.disabled = !reprojector?.available;
reprojectBox.addEventListener('change', () => { if (reprojector) reprojector.enabled = reprojectBox.checked; });
function frame() {
  const on = Boolean(reprojector?.available && reprojector.enabled && reprojector.frame);
  canvas.hidden = !on;
  if (on) {
    const { width, height } = reprojector.frame;
    if (canvas.width !== width || canvas.height !== height) Object.assign(canvas, { width, height });
    reprojector.draw([{ worldFromCamera: camera.worldFromCamera(), k: camera.intrinsics(width, height), viewport: [0, 0, width, height], view: 0 }]);
  }
  requestAnimationFrame(frame);
}
requestAnimationFrame(frame);

attachVideoOrbit($('stage'), video, camera, () => [conn.params?.width || 640, conn.params?.height || 480]);

// The HUD's glass line: "warp · 687 B · +120 ms" (frames warped, the last depth message's
// size, how far ahead the pose is predicted) or "off".
function render() {
  const on = Boolean(reprojector?.available && reprojector.enabled);
  const depth = reprojector?.stats.depthBytes ? ` · ${reprojector.stats.depthBytes} B` : '';
  const ahead = horizonMs > 0 ? ` · +${horizonMs.toFixed(0)} ms` : '';
  renderStatus(conn, [['glass', on ? `warp${depth}${ahead}` : 'off']]);
}

function connectFromPickers() {
  const [width, height] = sizeSelect.value.split('x').map(Number);
  const scene = sceneSelect.value;
  if (scene !== cameraScene) cameraScene = null; // new scene: reframe when its session arrives
  conn.connect({ scene, width, height, fps: options.fps, token: options.token, relay: options.relay, depth: Boolean(reprojector?.available) });
}

async function main() {
  render();
  // A size from the URL that is not in the list becomes an extra option.
  const size = `${options.width}x${options.height}`;
  if (![...sizeSelect.options].some((o) => o.value === size)) sizeSelect.add(new Option(size.replace('x', '×'), size));
  sizeSelect.value = size;

  const { scenes, default: def } = await fetchScenes();
  sceneSelect.replaceChildren(...scenes.map((s) => new Option(s, s)));
  sceneSelect.value = options.scene && scenes.includes(options.scene) ? options.scene : def;

  sceneSelect.addEventListener('change', connectFromPickers);
  sizeSelect.addEventListener('change', connectFromPickers);
  connectFromPickers();
}

main();
