// relay.mjs — the viewer forced through TURN (`?relay=1`: iceTransportPolicy "relay") in
// headless Chromium: `node tests/browser/relay.mjs http://127.0.0.1:PORT/ [relay|direct]`.
// Waits for ≥ 10 decoded frames and requires the browser's end of the selected candidate
// pair to be a TURN relay (`direct`: not a relay, the page as a user opens it), with no
// camera request and no page error. Prints one JSON line and exits 0 or 1.

import { captureRequests, noErrors, openPage, runInChromium, waitFor } from './harness.mjs';

const base = process.argv[2];
const mode = process.argv[3] || 'relay';

async function run(context) {
  const query = mode === 'relay' ? '?relay=1&size=320x240' : '?size=320x240';
  const { page, pageErrors } = await openPage(context, new URL('index.html' + query, base).href);
  const snap = () => page.evaluate(async () => {
    const n = window.nephele;
    if (!n) return { ready: false };
    const s = await n.stats();
    return { ready: true, state: n.state, framesDecoded: s.framesDecoded, path: s.path || null, errors: n.errors, banner: n.banner };
  });
  const s = await waitFor(`10 frames (${mode})`, snap,
    (s) => (s.framesDecoded >= 10 && s.path) || (s.errors && s.errors.length > 0) || pageErrors.length > 0, 60_000);
  noErrors(`viewer (${mode})`, s, pageErrors);
  if (mode === 'relay' && s.path?.local !== 'relay') throw new Error(`the video does not come through the relay: ${JSON.stringify(s.path)}`);
  if (mode === 'direct' && s.path?.local === 'relay') throw new Error(`asked for a direct path, got a relay: ${JSON.stringify(s.path)}`);
  const requests = await captureRequests(page);
  if (requests !== 0) throw new Error(`the viewer asked for the camera ${requests} time(s)`);
  return { ok: true, mode, framesDecoded: s.framesDecoded, path: s.path };
}

runInChromium(run, { timeoutMs: 90_000 });
