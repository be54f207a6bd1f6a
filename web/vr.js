// vr.js — logic of the headset page (vr.html), on A-Frame (served by the server at
// vendor/aframe.min.js from web/node_modules; see README.md).
//
// Joins in mode "vr": the server renders two eyes side by side into one frame, the left eye
// into [0, 0, W/2, H] and the right eye into [W/2, 0, W/2, H] (default 1280×640: two 640×640
// eyes). Every 20 ms the page sends an NPO2 pose (pose.js) with both eyes:
//
//   * In an immersive WebXR session: each frame, inside A-Frame's render loop (an XRFrame is
//     only usable there), the viewer pose in three.js's XR reference space (local-floor:
//     metres, +y up, origin on the floor at the start position) is kept; the pose callback
//     sends its views in XR order — views[0] → left half, views[1] → right half, which is
//     also the order three.js gives its eye cameras (layer 1 = views[0], layer 2 = views[1]);
//     a one-view session sends that view for both halves. Per view:
//       world_from_camera = WORLD_FROM_XR · view.transform.matrix,
//       clip_from_camera  = view.projectionMatrix,
//     where WORLD_FROM_XR is the +90° rotation about x taking XR +y (up) to world +z (up).
//     The scene is placed by the anchor: its bounding sphere (centre c, radius r from the
//     `session` message) appears SCENE_DIAMETER_M = 0.5 m across (uniform scale
//     s = 0.25 / r), its centre at ANCHOR_XR = (0, 1.4, −1.0) in XR space — 1.0 m in front of
//     the start position (XR −z), 1.4 m above the floor — i.e. world (0, 1.0, 1.4):
//       world_from_anchor = translate(WORLD_FROM_XR · ANCHOR_XR − s·c) · scale(s).
//     No pose is sent until there is both an XR viewer pose and a session message.
//   * Each eye sees its own half of the ONE video texture (a THREE.VideoTexture of the page's
//     <video>): two planes on three.js layers 1 (left) and 2 (right), their UVs remapped to
//     the left/right half. Each is drawn head-locked in front of its eye, sized from that
//     eye's projection to fill exactly its field of view (placed at draw time from the eye
//     camera three.js renders with), so the frame, rendered for that eye's pose and
//     projection, lines up with it.
//   * Outside a headset (flat preview): the whole side-by-side video is shown on the page and
//     the orbit camera (drag like the viewer) is sent as two eyes ±EYE_OFFSET_M·(1/s) along
//     its x axis, each with a 90° vertical field of view (square for the default sizes, the
//     eye viewport's aspect otherwise), in scene units and without an anchor.
//
// Debug surface: window.nephele as on the viewer, plus lastPoseBytes, viewsPerPose, xrActive
// and xrPosesSent (poses sent from XR views).

import { OrbitCamera, attachVideoOrbit, DEG, mat4Mul, mat4TranslateScale, offsetAlongX } from './camera.js';
import { Connection, fetchScenes, readPageOptions } from './connection.js';
import { encodePoseViews, perspective, frustumTangents } from './pose.js';
import { makeNote, renderStatus, showBanner } from './hud.js';

/** XR → world: +90° about x (XR +y up → world +z up, XR −z forward → world +y). */
export const WORLD_FROM_XR = new Float32Array([1, 0, 0, 0, 0, 0, 1, 0, 0, -1, 0, 0, 0, 0, 0, 1]);
/** Where the scene's centre appears, in XR local-floor space (metres). */
export const ANCHOR_XR = [0, 1.4, -1.0];
/** Diameter at which the scene's bounding sphere appears, metres. */
export const SCENE_DIAMETER_M = 0.5;
/** Half the distance between the eyes of the flat preview, metres. */
export const EYE_OFFSET_M = 0.032;
const PREVIEW_FOV_Y = 90 * DEG;

const $ = (id) => document.getElementById(id);
const note = makeNote($('note'));
const video = $('video');
const sceneEl = document.querySelector('a-scene');
const enterButton = $('enter');
const options = readPageOptions({ width: 1280, height: 640 });

const camera = new OrbitCamera();
let cameraScene = null;
let sceneInfo = null;   // {center, radius} of the current session's scene
let xrViews = null;     // latest XR viewer pose: [{worldFromCamera, clipFromCamera}], XR order
let xrPosesSent = 0;
let pageBanner = null;  // page-level problem (A-Frame missing), shown under the connection's banner

const AFRAME = window.AFRAME;
const xrActive = () => Boolean(AFRAME && sceneEl?.renderer?.xr?.isPresenting && sceneEl.is('vr-mode'));

/** Uniform scale from scene units to metres in XR: the bounding sphere becomes 0.5 m across. */
const sceneScale = (radius) => SCENE_DIAMETER_M / 2 / (radius > 0 ? radius : 1);

/** world_from_anchor placing the scene's centre at ANCHOR_XR, scaled by sceneScale. */
function worldFromAnchor({ center, radius }) {
  const s = sceneScale(radius);
  const [x, y, z] = ANCHOR_XR;
  const target = [x, -z, y]; // WORLD_FROM_XR · ANCHOR_XR
  return mat4TranslateScale([0, 1, 2].map((i) => target[i] - s * center[i]), s);
}

/** Viewports [x, y, w, h] of the left and right eye in a width×height frame. */
const eyeViewports = (width, height) => [[0, 0, width / 2, height], [width / 2, 0, width / 2, height]];

/** The pose callback: NPO2 with two eyes, from the headset or from the orbit camera. */
function pose(seq, tClientMs) {
  const { width, height } = conn.params;
  const viewports = eyeViewports(width, height);
  if (xrActive()) {
    if (!xrViews || !sceneInfo) return null;
    const views = [0, 1].map((i) => ({ ...xrViews[Math.min(i, xrViews.length - 1)], viewport: viewports[i] }));
    xrPosesSent += 1;
    return encodePoseViews({ seq, tClientMs, width, height, views, worldFromAnchor: worldFromAnchor(sceneInfo) });
  }
  const half = EYE_OFFSET_M / sceneScale(camera.radius);
  const wfc = camera.worldFromCamera();
  const clipFromCamera = perspective(PREVIEW_FOV_Y, width / 2 / height, 0.01 * camera.radius, 1000 * camera.radius);
  const views = [-half, half].map((d, i) => ({ worldFromCamera: offsetAlongX(wfc, d), clipFromCamera, viewport: viewports[i] }));
  return encodePoseViews({ seq, tClientMs, width, height, views });
}

const conn = new Connection({
  mode: 'vr',
  video,
  camera,
  pose,
  onSession(msg) {
    if (Array.isArray(msg.center)) sceneInfo = { center: msg.center, radius: msg.radius };
    if (msg.scene !== cameraScene && Array.isArray(msg.center)) {
      camera.reset(msg.center, msg.radius);
      cameraScene = msg.scene;
    }
  },
  onChange: render,
});
conn.exposeApi({
  get banner() { return bannerText(); },
  get xrActive() { return xrActive(); },
  get xrPosesSent() { return xrPosesSent; },
});

attachVideoOrbit($('stage'), video, camera, () => [options.width, options.height]);

function render() {
  const f = conn.lastFrame;
  renderStatus(conn, [
    ['views', f && f.views != null ? String(f.views) : '–'],
    ['xr', xrActive() ? 'immersive' : 'flat preview'],
  ]);
  if (pageBanner) showBanner($('banner'), { text: bannerText(), kind: conn.banner ? conn.banner.kind : 'error', action: conn.banner?.action });
}

/** The connection's banner and the page's own problem (A-Frame missing), one per line. */
function bannerText() {
  return [conn.banner?.text, pageBanner].filter(Boolean).join('\n') || null;
}


// ───────────────────────────────── WebXR via A-Frame ─────────────────────────────

let eyeLocal = null; // scratch THREE.Matrix4

/** Put `mesh` in front of eye camera `cam`, filling its field of view at distance 1. */
function placeInFrontOf(mesh, cam) {
  const t = frustumTangents(cam.projectionMatrix.elements);
  const d = 1; // between the camera's near (0.05) and far (100)
  eyeLocal = eyeLocal || new AFRAME.THREE.Matrix4();
  const local = eyeLocal.set(
    (t.right - t.left) * d, 0, 0, ((t.left + t.right) / 2) * d,
    0, (t.top - t.bottom) * d, 0, ((t.bottom + t.top) / 2) * d,
    0, 0, 1, -d,
    0, 0, 0, 1,
  );
  mesh.matrixWorld.multiplyMatrices(cam.matrixWorld, local);
}

function setUpXr() {
  const THREE = AFRAME.THREE;
  AFRAME.registerComponent('nephele-xr', {
    init() {
      const texture = new THREE.VideoTexture(video);
      texture.colorSpace = THREE.SRGBColorSpace;
      // One plane per eye: layer 1 is drawn only for the left eye, layer 2 only for the right.
      [1, 2].forEach((layer, half) => {
        const geometry = new THREE.PlaneGeometry(1, 1);
        const uv = geometry.attributes.uv;
        for (let k = 0; k < uv.count; k++) uv.setX(k, 0.5 * half + 0.5 * uv.getX(k));
        const material = new THREE.MeshBasicMaterial({ map: texture, toneMapped: false, depthTest: false, depthWrite: false });
        const mesh = new THREE.Mesh(geometry, material);
        mesh.layers.set(layer);
        mesh.frustumCulled = false;
        mesh.onBeforeRender = (renderer, scene, cam) => placeInFrontOf(mesh, cam);
        this.el.object3D.add(mesh);
      });
    },
    // Runs inside the render loop, where the XRFrame is active: keep the eyes' poses.
    tick() {
      const xr = this.el.renderer.xr;
      const frame = xr.isPresenting ? xr.getFrame() : null;
      const viewerPose = frame?.getViewerPose(xr.getReferenceSpace());
      if (!viewerPose || !viewerPose.views.length) return; // tracking lost: keep the last
      xrViews = viewerPose.views.slice(0, 2).map((v) => ({
        worldFromCamera: mat4Mul(WORLD_FROM_XR, v.transform.matrix),
        clipFromCamera: Float32Array.from(v.projectionMatrix),
      }));
    },
  });
  sceneEl.setAttribute('nephele-xr', '');

  const update = () => {
    const active = xrActive();
    document.body.classList.toggle('xr-active', active);
    enterButton.textContent = active ? 'Exit VR' : 'Enter VR';
    if (!active) xrViews = null;
    render();
  };
  sceneEl.addEventListener('enter-vr', update);
  sceneEl.addEventListener('exit-vr', update);

  enterButton.addEventListener('click', () => {
    const go = xrActive() ? sceneEl.exitVR() : sceneEl.enterVR();
    Promise.resolve(go).catch((err) => note(`Could not enter VR: ${err.message || err}`, 6000));
  });
  const supported = navigator.xr?.isSessionSupported?.('immersive-vr') ?? Promise.resolve(false);
  supported.catch(() => false).then((ok) => {
    enterButton.disabled = !ok;
    enterButton.title = ok ? '' : 'No WebXR headset (immersive-vr) available in this browser';
  });
}

// ───────────────────────────────────── start ────────────────────────────────────

async function main() {
  if (AFRAME && sceneEl) {
    setUpXr();
  } else {
    pageBanner = window.NEPHELE_VENDOR_MISSING
      || 'A-Frame (vendor/aframe.min.js) did not load, so the headset mode is not available; the flat preview still works.';
    enterButton.disabled = true;
  }
  render();

  const sceneSelect = $('scene');
  const { scenes, default: def } = await fetchScenes();
  sceneSelect.replaceChildren(...scenes.map((s) => new Option(s, s)));
  sceneSelect.value = options.scene && scenes.includes(options.scene) ? options.scene : def;
  const connect = () => {
    if (sceneSelect.value !== cameraScene) cameraScene = null;
    sceneInfo = null;
    conn.connect({ scene: sceneSelect.value, width: options.width, height: options.height, fps: options.fps, token: options.token, relay: options.relay });
  };
  sceneSelect.addEventListener('change', connect);
  connect();
}

main();
