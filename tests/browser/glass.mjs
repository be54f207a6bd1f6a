// glass.mjs — reprojection in the viewer page, in headless Chromium against a running server:
// `node tests/browser/glass.mjs http://127.0.0.1:PORT/`.
//
// 1. Opens the viewer with ?predict=0 (the server renders exactly the camera the page has),
//    waits for ≥ 10 decoded frames and ≥ 5 depth messages decoded in the page (none corrupt)
//    and for the canvas to show warped frames.
// 2. Still camera: the warped canvas equals the decoded video frame (the warp to the camera a
//    frame was rendered with is the identity): PSNR ≥ 40 dB.
// 3. With the frame frozen on the canvas (no new uploads; the still picture above is that
//    frame: the stale one), turns the orbit camera by 5° of azimuth and 3° of elevation
//    (rotation and translation: the depth matters) and grabs the canvas (warped). Then lets
//    frames in again, waits until the frame on screen answers a pose sent after the turn and
//    grabs it (the truth: the server's render of the turned camera, through H.264, drawn by
//    the identity warp), and turns the warp off with the page's box. The warped picture must
//    be nearer the truth than the stale one by ≥ 1 dB (measured: 24.8 against 22.6 dB on the
//    trio; what the warp cannot fix is view-dependent — the shiny sphere's highlight moves
//    with the eye — and the translucent torus, which has one depth per pixel).
//    GLASS_DUMP=DIR writes the pictures compared as PNG files.
// Prints one JSON line ({"ok":true, ...} or {"ok":false,"error":...}); 120 s at most.

import fs from 'node:fs';
import path from 'node:path';
import { noErrors, openPage, runInChromium, sleep, waitFor } from './harness.mjs';

const base = process.argv[2];

const snapshot = (page) => page.evaluate(async () => {
  const n = window.nephele;
  if (!n) return { ready: false };
  const s = await n.stats();
  return { ready: true, state: n.state, framesDecoded: s.framesDecoded, poseSeq: n.poseSeq, frameSeq: n.lastFrame ? n.lastFrame.pose_seq : 0, errors: n.errors, glass: n.glass };
});

// Pixels of the video's current frame or of the warp canvas, kept in the page under `slot`.
const grab = (page, what, slot) => page.evaluate(([what, slot]) => {
  const src = what === 'video' ? document.querySelector('video') : document.getElementById('warp');
  const w = what === 'video' ? src.videoWidth : src.width, h = what === 'video' ? src.videoHeight : src.height;
  const c = document.createElement('canvas');
  Object.assign(c, { width: w, height: h });
  const g = c.getContext('2d', { willReadFrequently: true });
  g.drawImage(src, 0, 0);
  window.__glass = window.__glass || {};
  window.__glass[slot] = g.getImageData(0, 0, w, h);
  return [w, h];
}, [what, slot]);

const psnr = (page, a, b) => page.evaluate(([a, b]) => {
  const A = window.__glass[a], B = window.__glass[b];
  if (A.width !== B.width || A.height !== B.height) throw new Error(`${a} is ${A.width}x${A.height}, ${b} is ${B.width}x${B.height}`);
  let se = 0;
  for (let i = 0; i < A.data.length; i += 4) for (let c = 0; c < 3; c++) se += (A.data[i + c] - B.data[i + c]) ** 2;
  const mse = se / ((A.data.length / 4) * 3);
  return mse === 0 ? 99 : 10 * Math.log10((255 * 255) / mse);
}, [a, b]);

// GLASS_DUMP=DIR: the grabbed pictures as PNG files, to look at.
async function dump(page, slots) {
  const dir = process.env.GLASS_DUMP;
  if (!dir) return;
  fs.mkdirSync(dir, { recursive: true });
  for (const slot of slots) {
    const url = await page.evaluate((slot) => {
      const img = window.__glass[slot];
      const c = document.createElement('canvas');
      Object.assign(c, { width: img.width, height: img.height });
      c.getContext('2d').putImageData(img, 0, 0);
      return c.toDataURL('image/png');
    }, slot);
    fs.writeFileSync(path.join(dir, `${slot}.png`), Buffer.from(url.split(',')[1], 'base64'));
  }
}

const nextFrames = (page) => page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));

async function run(context) {
  const { page, pageErrors } = await openPage(context, new URL('index.html?size=320x240&predict=0', base).href);
  await waitFor('window.nephele', () => snapshot(page), (s) => s.ready, 10_000);
  const ready = await waitFor('frames, depth and a warped canvas', () => snapshot(page),
    (s) => (s.framesDecoded >= 10 && s.glass.depthFrames >= 5 && s.glass.warped >= 5) || s.errors.length > 0 || pageErrors.length > 0 || s.glass.depthErrors > 0, 60_000);
  noErrors('viewer', ready, pageErrors);
  if (!ready.glass.available || !ready.glass.enabled) throw new Error(`no WebGL2 reprojection: ${JSON.stringify(ready.glass)}`);
  if (ready.glass.depthErrors > 0) throw new Error(`a depth message did not decode: ${ready.glass.lastDepthError}`);

  // Still: the canvas shows the frame itself.
  await page.evaluate(() => window.nephele.freezeWarp(true));
  await nextFrames(page);
  await grab(page, 'canvas', 'stillWarped');
  await grab(page, 'video', 'stillVideo');
  const still = await psnr(page, 'stillWarped', 'stillVideo');
  if (!(still >= 40)) throw new Error(`a still camera's warp differs from its frame: ${still.toFixed(2)} dB`);

  // Turned: the frozen frame warped to the turned camera, and as it was (stale), against the
  // server's render of the turned camera (truth: the first frame on screen that answers a
  // pose sent after the turn, drawn by the identity warp).
  await page.evaluate(() => { const c = window.nephele.camera; c.azimuth += 5 * Math.PI / 180; c.elevation += 3 * Math.PI / 180; });
  await nextFrames(page);
  await grab(page, 'canvas', 'warped');
  const turnedAt = await snapshot(page);
  await page.evaluate(() => window.nephele.freezeWarp(false));
  await waitFor('a frame of the turned camera on screen', () => snapshot(page), (s) => s.glass.shownPoseSeq > turnedAt.poseSeq + 1, 20_000);
  await nextFrames(page);
  await grab(page, 'canvas', 'truth');
  await page.evaluate(() => { document.getElementById('reproject').click(); });
  await nextFrames(page);
  const warpedDb = await psnr(page, 'warped', 'truth');
  const staleDb = await psnr(page, 'stillWarped', 'truth');
  const end = await snapshot(page);
  noErrors('viewer', end, pageErrors);
  if (end.glass.enabled) throw new Error('the reproject box did not turn the warp off');
  if (!(warpedDb >= staleDb + 1)) throw new Error(`warped ${warpedDb.toFixed(2)} dB is not 1 dB nearer the truth than stale ${staleDb.toFixed(2)} dB`);
  return { ok: true, stillDb: Number(still.toFixed(2)), warpedDb: Number(warpedDb.toFixed(2)), staleDb: Number(staleDb.toFixed(2)), depthFrames: end.glass.depthFrames, depthBytes: end.glass.depthBytes, warpedFrames: end.glass.warped };
}

if (!base) {
  console.log(JSON.stringify({ ok: false, error: 'usage: node tests/browser/glass.mjs <base-url>' }));
  process.exit(1);
}
runInChromium(run, { timeoutMs: 120_000 });
