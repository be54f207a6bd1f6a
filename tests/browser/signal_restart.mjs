// signal_restart.mjs — the viewer keeps streaming while signaling restarts:
// `node tests/browser/signal_restart.mjs URL` (URL served by `nephele signal`, with a master).
//
// 1. Opens the viewer and waits for decoded frames; prints `READY` on stdout.
// 2. The caller then kills signaling and starts it again on the same address.
// 3. For SAMPLE_MS the page is sampled every 50 ms: it must stay `connected` and its
//    decoded-frame count must keep rising; the longest time without a new frame is reported.
// Prints one JSON line ({"ok":true,...} or {"ok":false,"error":...}); exit 0 or 1.

import { noErrors, openPage, runInChromium, sleep, waitFor } from './harness.mjs';

const SAMPLE_MS = 6000;
const base = process.argv[2];
const state = (page) => page.evaluate(async () => {
  const n = window.nephele;
  if (!n) return { state: 'loading' };
  const s = await n.stats();
  return { state: n.state, banner: n.banner, errors: n.errors, framesDecoded: s.framesDecoded };
});

await runInChromium(async (context) => {
  const { page, pageErrors } = await openPage(context, new URL('/?size=160x120', base).href);
  const before = await waitFor('frames before the restart', () => state(page), (s) => s.state === 'connected' && s.framesDecoded >= 5, 60_000);
  console.log('READY');
  const start = Date.now();
  let last = { at: start, frames: before.framesDecoded };
  let maxGapMs = 0;
  const states = new Set();
  while (Date.now() - start < SAMPLE_MS) {
    await sleep(50);
    const now = await state(page);
    states.add(now.state);
    if (now.framesDecoded > last.frames) {
      maxGapMs = Math.max(maxGapMs, Date.now() - last.at);
      last = { at: Date.now(), frames: now.framesDecoded };
    }
  }
  maxGapMs = Math.max(maxGapMs, Date.now() - last.at);
  const after = await state(page);
  // The page tells the user signaling went away and the stream goes on (code
  // `connection_lost`); any other reported error, or an uncaught one, fails the check.
  const told = (after.errors || []).filter((e) => e.code === 'connection_lost');
  noErrors('viewer', { errors: (after.errors || []).filter((e) => e.code !== 'connection_lost') }, pageErrors);
  if (states.size !== 1 || !states.has('connected')) throw new Error(`the page left the connected state: ${[...states]}`);
  return { ok: true, maxGapMs, states: [...states], framesDuring: after.framesDecoded - before.framesDecoded, told: told.map((e) => e.message) };
}, { timeoutMs: 120_000 });
