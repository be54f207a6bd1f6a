// harness.mjs — what the headless Chromium checks share: polling, page-error collection, and
// one launch of Debian's Chromium (playwright-core, never a downloaded browser) with a
// whole-run time limit that prints exactly one JSON line and sets the exit code.

import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';
import { chromium } from 'playwright-core';

export const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

/** Poll `probe()` until `done(value)` holds; throws `what` with the last value on timeout. */
export async function waitFor(what, probe, done, timeoutMs) {
  const end = Date.now() + timeoutMs;
  let last;
  for (;;) {
    last = await probe();
    if (done(last)) return last;
    if (Date.now() > end) throw new Error(`timed out waiting for ${what}; last: ${JSON.stringify(last)}`);
    await sleep(250);
  }
}

/** Throws when the page threw, or reported errors in `window.nephele.errors`. */
export function noErrors(name, snap, pageErrors) {
  if (pageErrors.length) throw new Error(`${name}: uncaught page error: ${pageErrors[0]}`);
  if (snap.errors && snap.errors.length) throw new Error(`${name}: page reported errors: ${JSON.stringify(snap.errors)}`);
}

/** Counts the page's camera/microphone requests (getUserMedia) in
 *  `window.__nepheleCaptureRequests`: a page that never shows the camera must make none. */
function countCaptureRequests() {
  window.__nepheleCaptureRequests = 0;
  const md = navigator.mediaDevices;
  if (!md || !md.getUserMedia) return;
  const real = md.getUserMedia.bind(md);
  md.getUserMedia = (constraints) => { window.__nepheleCaptureRequests++; return real(constraints); };
}

/** How many times the page asked for the camera or microphone. */
export const captureRequests = (page) => page.evaluate(() => window.__nepheleCaptureRequests);

/** Opens `url` in a new page (after `initScripts`), collecting uncaught page errors and
 *  counting its capture requests ([`captureRequests`]). */
export async function openPage(context, url, initScripts = []) {
  const page = await context.newPage();
  const pageErrors = [];
  page.on('pageerror', (err) => pageErrors.push(String(err && err.message ? err.message : err)));
  await page.addInitScript(countCaptureRequests);
  for (const script of initScripts) await page.addInitScript(script);
  await page.goto(url, { waitUntil: 'load' });
  return { page, pageErrors };
}

/**
 * Runs `work(context)` in a fresh headless Chromium within `timeoutMs`, prints its result
 * (or `{...partial(), ok: false, error}`) as one JSON line, and exits 0 or 1.
 */
export async function runInChromium(work, { timeoutMs, extraArgs = [], partial = () => ({}) }) {
  const userDataDir = fs.mkdtempSync(path.join(os.tmpdir(), 'nephele-chromium-'));
  let context = null;
  let timer = null;
  try {
    const timeout = new Promise((_, reject) => {
      timer = setTimeout(() => reject(new Error(`whole run exceeded ${timeoutMs / 1000} s`)), timeoutMs);
    });
    const run = (async () => {
      context = await chromium.launchPersistentContext(userDataDir, {
        executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
        headless: true,
        viewport: { width: 1024, height: 768 },
        args: [
          '--no-sandbox',
          '--use-fake-ui-for-media-stream',
          '--use-fake-device-for-media-stream',
          '--allow-loopback-in-peer-connection',
          '--disable-features=WebRtcHideLocalIpsWithMdns',
          '--disable-background-networking',
          '--disable-component-update',
          '--disable-sync',
          '--no-first-run',
          ...extraArgs,
        ],
      });
      return work(context);
    })();
    console.log(JSON.stringify(await Promise.race([run, timeout])));
    process.exitCode = 0;
  } catch (err) {
    // Playwright's messages carry a call log with terminal colours: keep the first line.
    const text = String(err && err.message ? err.message : err).replace(/\u001b\[[0-9;]*m/g, '').split('\n')[0];
    console.log(JSON.stringify({ ...partial(), ok: false, error: text }));
    process.exitCode = 1;
  } finally {
    clearTimeout(timer);
    if (context) await Promise.race([context.close().catch(() => {}), sleep(10_000)]);
    fs.rmSync(userDataDir, { recursive: true, force: true });
  }
  // A launch still in flight when the timeout hit would keep the process alive.
  process.exit(process.exitCode);
}
