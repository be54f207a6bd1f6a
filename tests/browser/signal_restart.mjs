// signal_restart.mjs — the viewer keeps streaming while signaling restarts:
// `node tests/browser/signal_restart.mjs URL` (URL served by `nephele signal`, with a master).
//
// 1. Opens the viewer and waits for decoded frames; prints `READY` on stdout.
// 2. The caller then kills signaling and starts it again on the same address.
// 3. For SAMPLE_MS the page is sampled every 50 ms: it must stay `connected` and its
//    decoded-frame count must keep rising; the longest time without a new frame is reported.
// Prints one JSON line ({"ok":true,...} or {"ok":false,"error":...}); exit 0 or 1.

import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';
import { chromium } from 'playwright-core';

const SAMPLE_MS = 6000;
const base = process.argv[2];
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
const state = (page) => page.evaluate(async () => {
  const n = window.nephele;
  if (!n) return { state: 'loading' };
  const s = await n.stats();
  return { state: n.state, banner: n.banner, framesDecoded: s.framesDecoded };
});

const dir = fs.mkdtempSync(path.join(os.tmpdir(), 'nephele-chromium-'));
let ctx;
try {
  ctx = await chromium.launchPersistentContext(dir, {
    executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
    headless: true,
    args: ['--no-sandbox', '--use-fake-ui-for-media-stream', '--use-fake-device-for-media-stream',
      '--allow-loopback-in-peer-connection', '--disable-features=WebRtcHideLocalIpsWithMdns',
      '--disable-background-networking', '--disable-component-update', '--disable-sync', '--no-first-run'],
  });
  const page = await ctx.newPage();
  await page.goto(new URL('/?size=160x120', base).href);
  const end = Date.now() + 60_000;
  let s = await state(page);
  while (!(s.state === 'connected' && s.framesDecoded >= 5)) {
    if (Date.now() > end) throw new Error(`no frames before the restart: ${JSON.stringify(s)}`);
    await sleep(200);
    s = await state(page);
  }
  console.log('READY');
  const start = Date.now();
  let last = { at: start, frames: s.framesDecoded };
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
  const report = { ok: true, maxGapMs, states: [...states], framesDuring: after.framesDecoded - s.framesDecoded, banner: after.banner || '' };
  if (states.size !== 1 || !states.has('connected')) {
    Object.assign(report, { ok: false, error: `the page left the connected state: ${[...states]}` });
  }
  console.log(JSON.stringify(report));
  await ctx.close();
  process.exit(report.ok ? 0 : 1);
} catch (e) {
  console.log(JSON.stringify({ ok: false, error: String(e && e.message || e) }));
  if (ctx) await ctx.close().catch(() => {});
  process.exit(1);
}
