// reconnect.mjs — the viewer survives a server restart: `node tests/browser/reconnect.mjs URL`.
//
// 1. Opens the viewer and waits for decoded frames; prints the line `READY` on stdout.
// 2. The caller then stops the server (and starts it again on the same address).
// 3. Waits for the page to say it lost the connection in words (banner), then to be
//    connected again with frames flowing.
// Prints one JSON line ({"ok":true,...} or {"ok":false,"error":...}); exit 0 or 1.

import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';
import { chromium } from 'playwright-core';

const base = process.argv[2];
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
const state = (page) => page.evaluate(async () => {
  const n = window.nephele;
  if (!n) return { state: 'loading' };
  const s = await n.stats();
  return { state: n.state, banner: n.banner, framesDecoded: s.framesDecoded };
});

async function until(what, page, done, timeoutMs) {
  const end = Date.now() + timeoutMs;
  for (;;) {
    const s = await state(page);
    if (done(s)) return s;
    if (Date.now() > end) throw new Error(`timed out waiting for ${what}; last: ${JSON.stringify(s)}`);
    await sleep(200);
  }
}

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
  await page.goto(new URL('/?size=320x240', base).href);
  const first = await until('first frames', page, (s) => s.state === 'connected' && s.framesDecoded >= 5, 60_000);
  console.log('READY');
  const lost = await until('the page to notice the lost server', page, (s) => s.state !== 'connected' && s.banner, 30_000);
  const back = await until('reconnection', page, (s) => s.state === 'connected' && s.framesDecoded >= 5, 60_000);
  // Frames must flow again, not just a connected state.
  await sleep(1500);
  const later = await state(page);
  if (!(later.framesDecoded > back.framesDecoded)) throw new Error(`no frames after reconnecting: ${JSON.stringify(later)}`);
  console.log(JSON.stringify({ ok: true, first: first.framesDecoded, banner: lost.banner, lostState: lost.state, framesAfter: later.framesDecoded }));
  await ctx.close();
  process.exit(0);
} catch (e) {
  console.log(JSON.stringify({ ok: false, error: String(e && e.message || e) }));
  if (ctx) await ctx.close().catch(() => {});
  process.exit(1);
}
