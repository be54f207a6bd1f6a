// xr.mjs — headless Chromium check of the VR and Looking Glass pages against a running server:
// `node tests/browser/xr.mjs http://127.0.0.1:PORT/`.
//
// 1. VR: emulates a Meta Quest 3 with iwer (the WebXR runtime is installed by an init script,
//    before A-Frame loads), opens vr.html?size=640x320&fps=25, enters VR
//    (a-scene.enterVR()), waits until ≥ 20 poses with 2 views were sent from the XR session
//    and ≥ 10 frames were decoded, keeps the head still ≥ 2 s (the server then sends a
//    full-size frame), and grabs the shown video frame together with the pose bytes sent
//    last (window.nephele.lastPoseBytes).
// 2. Looking Glass: opens quilt.html?size=320x432&quilt=5x9 (tiles 64×48) and waits for ≥ 3
//    decoded frames and the session's `quilt` description.
// Neither page may report errors. Prints one JSON line last: {"ok":true, xrActive,
// viewsPerPose, poseB64, width, height, rgbaB64 (raw RGBA, width×height×4), framesDecoded,
// lastFrame, errors, quiltFramesDecoded, quiltSession} or {"ok":false,"error":...}; exit 0
// or 1. The whole run is limited to 150 s.

import fs from 'node:fs';
import path from 'node:path';
import { fileURLToPath } from 'node:url';
import { captureRequests, noErrors, openPage, runInChromium, sleep, waitFor } from './harness.mjs';

const TOTAL_TIMEOUT_MS = 150_000;
const HERE = path.dirname(fileURLToPath(import.meta.url));
const IWER_UMD = path.join(HERE, 'node_modules', 'iwer', 'build', 'iwer.min.js'); // defines window.IWER
const base = process.argv[2];
if (!base) {
  console.log(JSON.stringify({ ok: false, error: 'usage: node tests/browser/xr.mjs <base-url>' }));
  process.exit(1);
}

// What a page says about itself (window.nephele), in one round trip.
const snapshot = (page) => page.evaluate(async () => {
  const n = window.nephele;
  if (!n) return { ready: false };
  const s = await n.stats();
  const sceneEl = document.querySelector('a-scene');
  return {
    ready: true,
    state: n.state,
    banner: n.banner,
    framesDecoded: s.framesDecoded,
    poseSeq: n.poseSeq,
    xrActive: n.xrActive,
    xrPosesSent: n.xrPosesSent,
    viewsPerPose: n.viewsPerPose,
    renderScale: n.lastFrame ? n.lastFrame.render_scale : null,
    session: n.session,
    sceneLoaded: Boolean(sceneEl && sceneEl.hasLoaded && sceneEl.renderer),
    errors: n.errors,
  };
});

const failed = (s, pageErrors) => (s.errors && s.errors.length > 0) || pageErrors.length > 0;

// The emulated headset, installed before any page script (so before A-Frame looks for WebXR).
function installHeadset() {
  const device = new window.IWER.XRDevice(window.IWER.metaQuest3);
  device.stereoEnabled = true;
  device.installRuntime({ forceInstall: true });
  window.__iwerDevice = device;
}

// In the page: the pose bytes sent last and the video frame shown now, both as base64.
const grab = (page) => page.evaluate(() => {
  const b64 = (bytes) => {
    let s = '';
    for (let i = 0; i < bytes.length; i += 0x8000) s += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
    return btoa(s);
  };
  const n = window.nephele;
  const v = document.querySelector('video');
  const c = document.createElement('canvas');
  c.width = v.videoWidth;
  c.height = v.videoHeight;
  const g = c.getContext('2d', { willReadFrequently: true });
  g.drawImage(v, 0, 0);
  const pose = n.lastPoseBytes;
  const rgba = g.getImageData(0, 0, c.width, c.height).data;
  return {
    poseB64: b64(new Uint8Array(pose.buffer, pose.byteOffset, pose.byteLength)),
    width: c.width,
    height: c.height,
    rgbaB64: b64(new Uint8Array(rgba.buffer, rgba.byteOffset, rgba.byteLength)),
    viewsPerPose: n.viewsPerPose,
    lastFrame: n.lastFrame,
    xrActive: n.xrActive,
  };
});

async function run(context, result) {
  // ── VR with an emulated headset ──
  const vrUrl = new URL('vr.html?size=640x320&fps=25', base).href;
  const vr = await openPage(context, vrUrl, [{ path: IWER_UMD }, installHeadset]);
  await waitFor('window.nephele and A-Frame on the VR page', () => snapshot(vr.page),
    (s) => (s.ready && s.sceneLoaded) || vr.pageErrors.length > 0, 20_000);
  noErrors('vr', await snapshot(vr.page), vr.pageErrors);

  await vr.page.evaluate(() => document.querySelector('a-scene').enterVR());
  const entered = await waitFor('the immersive session', () => snapshot(vr.page),
    (s) => s.xrActive || failed(s, vr.pageErrors), 10_000);
  noErrors('vr', entered, vr.pageErrors);
  result.xrActive = true;

  const flowing = await waitFor('20 two-view poses from the XR session and 10 decoded frames', () => snapshot(vr.page),
    (s) => (s.xrPosesSent >= 20 && s.viewsPerPose.length >= 20 && s.viewsPerPose.every((n) => n === 2) && s.framesDecoded >= 10)
      || failed(s, vr.pageErrors), 60_000);
  noErrors('vr', flowing, vr.pageErrors);

  // The headset stays still: after ≥ 2 s the server has sent a full-size frame of this pose.
  await sleep(2000);
  await waitFor('a full-size frame', () => snapshot(vr.page),
    (s) => s.renderScale == null || s.renderScale >= 1 || failed(s, vr.pageErrors), 10_000).catch(() => {});
  await sleep(300); // let the jitter buffer hand the newest frame to the <video>
  const shot = await grab(vr.page);
  const end = await snapshot(vr.page);
  noErrors('vr', end, vr.pageErrors);
  if (!shot.xrActive) throw new Error('the immersive session ended before the frame was grabbed');
  if (shot.width !== 640 || shot.height !== 320) throw new Error(`VR video is ${shot.width}x${shot.height}, not 640x320`);
  Object.assign(result, shot, { framesDecoded: end.framesDecoded, errors: end.errors });
  const vrCaptureRequests = await captureRequests(vr.page);
  await vr.page.close({ runBeforeUnload: false });

  // ── Looking Glass quilt ──
  const quilt = await openPage(context, new URL('quilt.html?size=320x432&quilt=5x9', base).href);
  await waitFor('window.nephele on the quilt page', () => snapshot(quilt.page), (s) => s.ready, 10_000);
  const q = await waitFor('3 decoded frames and the quilt session', () => snapshot(quilt.page),
    (s) => (s.framesDecoded >= 3 && s.session && s.session.quilt) || failed(s, quilt.pageErrors), 60_000);
  noErrors('quilt', q, quilt.pageErrors);
  result.quiltFramesDecoded = q.framesDecoded;
  // Neither page shows a camera, so neither may ask for one.
  result.captureRequests = { vr: vrCaptureRequests, quilt: await captureRequests(quilt.page) };
  if (result.captureRequests.vr !== 0 || result.captureRequests.quilt !== 0) throw new Error(`a page without a camera asked for one: ${JSON.stringify(result.captureRequests)}`);
  result.quiltSession = q.session.quilt;
  await quilt.page.close({ runBeforeUnload: false });
  result.ok = true;
  return result;
}

const result = { ok: false };
runInChromium(
  async (context) => {
    if (!fs.existsSync(IWER_UMD)) throw new Error(`${IWER_UMD} is missing: run npm ci in tests/browser`);
    return run(context, result);
  },
  {
    timeoutMs: TOTAL_TIMEOUT_MS,
    extraArgs: ['--enable-unsafe-swiftshader'], // WebGL without a GPU, for A-Frame
    // What was learned before a failure, without the large payloads.
    partial: () => {
      const { rgbaB64, poseB64, ...rest } = result;
      return rest;
    },
  },
);
