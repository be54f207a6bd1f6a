// viewer.js — logic of the viewer page (index.html): fills the scene picker from /scenes,
// connects on load and again when a picker changes, steers an orbit camera with mouse/touch
// (left-drag orbit, wheel zoom, right/shift-drag pan; one finger orbit, two fingers
// pinch/pan), and shows the HUD (fps, latency, bitrate, resolution, frame, state) and an
// error banner. The session itself (signaling, WebRTC, stats) is in connection.js, the
// camera in camera.js, the pose message in pose.js and the HUD in hud.js.

import { OrbitCamera, attachVideoOrbit } from './camera.js';
import { Connection, fetchScenes, readPageOptions } from './connection.js';
import { orbitPose } from './pose.js';
import { renderStatus } from './hud.js';

const $ = (id) => document.getElementById(id);
const video = $('video');
const sceneSelect = $('scene');
const sizeSelect = $('size');

const options = readPageOptions();
const camera = new OrbitCamera();
let cameraScene = null; // scene the camera was last reset for; a reconnect keeps the view

const conn = new Connection({
  mode: 'viewer',
  video,
  camera,
  // The orbit camera as NPO1 at the joined size, every 20 ms.
  pose: (seq, tClientMs) => orbitPose(camera, { seq, tClientMs, width: conn.params.width, height: conn.params.height }),
  onSession(msg) {
    // First session of a scene: frame the asset. A reconnect to the same scene keeps the view.
    if (msg.scene !== cameraScene && Array.isArray(msg.center)) {
      camera.reset(msg.center, msg.radius);
      cameraScene = msg.scene;
    }
  },
  onChange: render,
});
conn.exposeApi();

attachVideoOrbit($('stage'), video, camera, () => [conn.params?.width || 640, conn.params?.height || 480]);

function render() { renderStatus(conn); }

function connectFromPickers() {
  const [width, height] = sizeSelect.value.split('x').map(Number);
  const scene = sceneSelect.value;
  if (scene !== cameraScene) cameraScene = null; // new scene: reframe when its session arrives
  conn.connect({ scene, width, height, fps: options.fps, token: options.token, relay: options.relay });
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
