// hud.js — the status shown on every page: the HUD lines (state, fps, latency, bitrate,
// resolution, render scale and time, batch, encode time, frame number, plus any lines a page
// adds) and renderStatus(), which puts them, the state pill and the banner into the page's
// `#hud`, `#state` and `#banner` elements.

/** HUD lines [label, text] of a Connection; `extra` lines (a page's own) go at the end. */
export function hudLines(conn, extra = []) {
  const h = conn.hud;
  const f = conn.lastFrame;
  return [
    ['state', conn.state],
    ['fps', h.fps.toFixed(1)],
    // Pose sent → its frame on screen (matched by RTP timestamp); the frame-info message
    // arrives earlier, before the frame is decoded.
    ['latency', h.latencyMs == null ? '–' : `${h.latencyMs.toFixed(0)} ms`],
    ['info msg', h.infoLatencyMs == null ? '–' : `${h.infoLatencyMs.toFixed(0)} ms`],
    ['bitrate', `${h.kbps.toFixed(0)} kbit/s`],
    ['resolution', h.width ? `${h.width}×${h.height}` : '–'],
    // The server renders at this fraction of the stream size when moving (dynamic
    // resolution) and refines to full size when the camera rests.
    ['render', f ? `${Math.round((f.render_scale ?? 1) * 100)}% · ${Number(f.render_ms ?? 0).toFixed(0)} ms` : '–'],
    // Several users' views rendered in one task, or a frame reused (camera at rest, or the
    // same view as another user's).
    ['batch', f ? (f.reused ? 'reused' : `${f.batch_views ?? 1} view${(f.batch_views ?? 1) === 1 ? '' : 's'}`) : '–'],
    ['encode', f ? `${Number(f.encode_ms ?? 0).toFixed(1)} ms` : '–'],
    ['frame', f ? String(f.frame) : '–'],
    ...extra,
  ];
}

/** Shows the connection state, the banner and the HUD in the page's `#state`, `#banner`
 *  and `#hud` elements (all pages use the same ids); `extra` HUD lines are appended. */
export function renderStatus(conn, extra = []) {
  const $ = (id) => document.getElementById(id);
  $('state').textContent = conn.state;
  $('state').dataset.state = conn.state;
  showBanner($('banner'), conn.banner);
  $('hud').replaceChildren(...hudLines(conn, extra).flatMap(([k, v]) => {
    const dt = document.createElement('dt'); dt.textContent = k;
    const dd = document.createElement('dd'); dd.textContent = v;
    return [dt, dd];
  }));
}

/** Puts `banner` ({text, kind, action?} or null) into `el`, with a button for its action
 *  (rebuilt only when the words change, so a click is never lost to a refresh). */
export function showBanner(el, banner) {
  el.hidden = !banner;
  if (!banner) {
    delete el.dataset.text;
    return;
  }
  el.dataset.kind = banner.kind;
  if (el.dataset.text === banner.text) return;
  el.dataset.text = banner.text;
  el.replaceChildren(document.createTextNode(banner.text));
  if (banner.action) {
    const button = document.createElement('button');
    button.textContent = banner.action.label;
    // The stage under it captures the pointer for orbiting; the button keeps its own.
    button.addEventListener('pointerdown', (e) => e.stopPropagation());
    button.addEventListener('click', () => banner.action.run());
    el.append(' ', button);
  }
}

/** A transient note in `el`: `note(text, ms)` shows it (for `ms`, or until replaced). */
export function makeNote(el) {
  let timer = null;
  return (text, ms = 0) => {
    el.textContent = text || '';
    el.hidden = !text;
    clearTimeout(timer);
    if (ms) timer = setTimeout(() => { el.hidden = true; }, ms);
  };
}
