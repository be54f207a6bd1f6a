// viewer.mjs — headless Chromium end-to-end check of the Nephele web pages against a running
// server: `node tests/browser/viewer.mjs http://127.0.0.1:PORT/`.
//
// 1. Opens the viewer (640×480), waits for ≥ 10 decoded frames (getStats via window.nephele).
// 2. Grabs the shown video frame (image A), drags the mouse ~200 px across the video, waits for
//    a frame info answering a pose sent after the drag plus ≥ 5 more decoded frames, grabs
//    image B, and requires a mean absolute RGB difference > 2 (the scene turned).
//    Then waits for the page to have matched ≥ 20 presented frames to their poses (by RTP
//    timestamp) and requires a pose → presented latency between 1 ms and 2 s.
// 3. Opens ar.html and waits for ≥ 5 decoded frames there.
// The viewer must never have asked for the camera (it shows none); the AR page must have.
// Neither page may report errors. Prints one JSON line ({"ok":true,...} or {"ok":false,
// "error":...}) and exits 0 or 1. The whole run is limited to 120 s.

import { captureRequests, noErrors, openPage, runInChromium, sleep, waitFor } from './harness.mjs';

const TOTAL_TIMEOUT_MS = 120_000;
const base = process.argv[2];
if (!base) {
  console.log(JSON.stringify({ ok: false, error: 'usage: node tests/browser/viewer.mjs <base-url>' }));
  process.exit(1);
}

// What a page says about itself (window.nephele), in one round trip.
const snapshot = (page) => page.evaluate(async () => {
  const n = window.nephele;
  if (!n) return { ready: false };
  const s = await n.stats();
  return {
    ready: true,
    state: n.state,
    banner: n.banner,
    framesDecoded: s.framesDecoded,
    frameWidth: s.frameWidth,
    frameHeight: s.frameHeight,
    poseSeq: n.poseSeq,
    frameSeq: n.lastFrame ? n.lastFrame.pose_seq : 0,
    errors: n.errors,
  };
});

// Draw the video's current frame into a canvas; keep the pixels in the page under `slot`.
const grab = (page, slot) => page.evaluate((slot) => {
  const v = document.querySelector('video');
  const c = document.createElement('canvas');
  c.width = v.videoWidth;
  c.height = v.videoHeight;
  const g = c.getContext('2d', { willReadFrequently: true });
  g.drawImage(v, 0, 0);
  window.__nepheleTest = window.__nepheleTest || {};
  window.__nepheleTest[slot] = g.getImageData(0, 0, c.width, c.height);
  return { width: c.width, height: c.height };
}, slot);

// Mean absolute difference over R, G, B of two grabbed frames of the same size.
const meanAbsDiff = (page, a, b) => page.evaluate(([a, b]) => {
  const A = window.__nepheleTest[a], B = window.__nepheleTest[b];
  if (A.width !== B.width || A.height !== B.height) throw new Error(`frame size changed: ${A.width}x${A.height} → ${B.width}x${B.height}`);
  let sum = 0;
  for (let i = 0; i < A.data.length; i += 4) {
    sum += Math.abs(A.data[i] - B.data[i]) + Math.abs(A.data[i + 1] - B.data[i + 1]) + Math.abs(A.data[i + 2] - B.data[i + 2]);
  }
  return sum / ((A.data.length / 4) * 3);
}, [a, b]);

async function run(context) {
  const result = { ok: true };

  // ── viewer ──
  const viewerUrl = new URL('index.html?size=640x480', base).href;
  const { page, pageErrors } = await openPage(context, viewerUrl);
  await waitFor('window.nephele on the viewer', () => snapshot(page), (s) => s.ready, 10_000);
  const first = await waitFor('10 decoded frames on the viewer', () => snapshot(page),
    (s) => s.framesDecoded >= 10 || (s.errors && s.errors.length > 0) || pageErrors.length > 0, 60_000);
  noErrors('viewer', first, pageErrors);
  if (first.framesDecoded < 10) throw new Error(`viewer decoded only ${first.framesDecoded} frames`);

  const size = await grab(page, 'A');

  // Drag horizontally across the middle of the video by 200 px.
  const box = await page.locator('video').boundingBox();
  const cx = box.x + box.width / 2, cy = box.y + box.height / 2;
  await page.mouse.move(cx - 100, cy);
  await page.mouse.down();
  await page.mouse.move(cx + 100, cy, { steps: 20 });
  await page.mouse.up();
  const afterDrag = await snapshot(page);

  await waitFor('a frame answering a pose sent after the drag', () => snapshot(page),
    (s) => s.frameSeq > afterDrag.poseSeq && s.framesDecoded >= afterDrag.framesDecoded + 5, 20_000);
  await sleep(200); // let the jitter buffer hand the newest frame to the <video>
  await grab(page, 'B');
  const diff = await meanAbsDiff(page, 'A', 'B');
  const end = await snapshot(page);
  noErrors('viewer', end, pageErrors);
  if (!(diff > 2.0)) throw new Error(`the view did not change after dragging (mean abs diff ${diff.toFixed(3)} ≤ 2)`);
  const presented = await waitFor('20 presented frames matched to their poses', () => page.evaluate(() => window.nephele.presented),
    (p) => p.matched >= 20 && p.p50 != null, 20_000);
  if (!(presented.p50 > 1 && presented.p50 < 2000)) throw new Error(`pose → presented latency ${presented.p50} ms is not plausible`);
  Object.assign(result, {
    framesDecoded: end.framesDecoded, meanAbsDiff: Number(diff.toFixed(3)), width: size.width, height: size.height,
    presentedMatched: presented.matched, presentedP50Ms: Number(presented.p50.toFixed(1)), infoP50Ms: presented.info_p50 == null ? null : Number(presented.info_p50.toFixed(1)),
  });
  // A banner's button (e.g. "Allow and connect") takes a click over the orbiting stage.
  await page.evaluate(async () => {
    const { showBanner } = await import('/hud.js');
    // A banner of its own, beside the page's (which the connection re-renders), placed alike.
    const el = document.getElementById('banner').cloneNode(false);
    el.id = 'test-banner';
    document.getElementById('banner').after(el);
    showBanner(el, { text: 'test', kind: 'error', action: { label: 'Act', run() { window.__bannerClicked = true; } } });
  });
  await page.click('#test-banner button', { timeout: 5000 });
  if (!(await page.evaluate(() => window.__bannerClicked))) throw new Error("the banner's button did not act on a click");
  result.viewerCaptureRequests = await captureRequests(page);
  if (result.viewerCaptureRequests !== 0) throw new Error(`the viewer asked for the camera ${result.viewerCaptureRequests} time(s)`);
  await page.close({ runBeforeUnload: false });

  // ── AR ──
  const ar = await openPage(context, new URL('ar.html', base).href);
  await waitFor('window.nephele on the AR page', () => snapshot(ar.page), (s) => s.ready, 10_000);
  const arSnap = await waitFor('5 decoded frames on the AR page', () => snapshot(ar.page),
    (s) => s.framesDecoded >= 5 || (s.errors && s.errors.length > 0) || ar.pageErrors.length > 0, 60_000);
  noErrors('ar', arSnap, ar.pageErrors);
  result.arFramesDecoded = arSnap.framesDecoded;
  result.arCaptureRequests = await captureRequests(ar.page);
  if (!(result.arCaptureRequests >= 1)) throw new Error('the AR page streamed without asking for its camera');
  await ar.page.close({ runBeforeUnload: false });
  return result;
}

runInChromium(run, { timeoutMs: TOTAL_TIMEOUT_MS });
