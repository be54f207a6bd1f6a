// quilt.js — logic of the Looking Glass page (quilt.html).
//
// Joins in mode "quilt" with quilt {cols, rows, cone_deg} (query ?quilt=5x9&cone=40, frame
// ?size=600x1440 by default: 5×9 tiles of 120×160, 3420 macroblocks, inside H.264 level 3.1, the level the page negotiates). The frame size is made a multiple of
// cols and rows (tiles rounded down to even sizes). The page sends plain NPO1 poses of the
// CENTRE camera — an orbit camera steered like the viewer's — at the TILE size; the server
// renders all cols×rows views across the cone into one frame: view 0 (leftmost camera) is
// the bottom-left tile, view i at column i % cols and row ⌊i / cols⌋ counted from the
// bottom, so in the top-down frame it starts at y = (rows − 1 − row) · tile height.
//
// The page shows the quilt (scaled to fit) and a preview of one view: the tile chosen by
// the mouse's horizontal position across the page (left edge → view 0, right edge → the
// last). The HUD adds the frame's view count next to its render scale (the server renders
// a smaller quilt while the camera moves and the full one at rest).
//
// Looking Glass: when vendor/holoplay-core.min.js loaded, the page asks the Looking Glass
// Bridge / HoloPlay Service (holoplay-core's Client, a websocket to a local service) for its
// displays. If one answers with a calibration, "Show on Looking Glass" opens a window at
// that display's position and draws the quilt video through holoplay-core's lenticular
// fragment shader (HoloPlayCore.Shader) in WebGL2. Otherwise the page says in words that no
// Looking Glass display was found. None of this may throw.

import { OrbitCamera, attachVideoOrbit, clamp } from './camera.js';
import { Connection, fetchScenes, readPageOptions } from './connection.js';
import { orbitPose } from './pose.js';
import { renderStatus } from './hud.js';

const $ = (id) => document.getElementById(id);
const video = $('video');
const preview = $('preview');
const LKG_TIMEOUT_MS = 5000;

// ───────────────────────────────────── options ──────────────────────────────────

function readQuiltOptions() {
  const q = new URLSearchParams(location.search);
  const m = /^(\d+)x(\d+)$/.exec(q.get('quilt') || '');
  const cols = m ? clamp(+m[1], 1, 16) : 5;
  const rows = m ? clamp(+m[2], 1, 16) : 9;
  const cone = clamp(parseFloat(q.get('cone')) || 40, 1, 120);
  const page = readPageOptions({ width: 600, height: 1440 });
  const even = (n) => Math.max(2, Math.floor(n / 2) * 2);
  const tileWidth = even(page.width / cols), tileHeight = even(page.height / rows);
  return { ...page, cols, rows, cone, tileWidth, tileHeight, width: tileWidth * cols, height: tileHeight * rows };
}

const options = readQuiltOptions();

/** The quilt layout in force: the session's `quilt` when the server sent one, else ours. */
function layout() {
  const q = conn.session?.quilt;
  if (q && q.cols > 0 && q.rows > 0) {
    return { cols: q.cols, rows: q.rows, cone: q.cone_deg, tileWidth: q.tile_width, tileHeight: q.tile_height };
  }
  const { cols, rows, cone, tileWidth, tileHeight } = options;
  return { cols, rows, cone, tileWidth, tileHeight };
}

// ──────────────────────────────────── session ───────────────────────────────────

const camera = new OrbitCamera();
let cameraScene = null;
let previewView = Math.floor((options.cols * options.rows) / 2);
let lkgStatus = 'looking for a Looking Glass…';

const conn = new Connection({
  mode: 'quilt',
  video,
  camera,
  // The centre camera as NPO1 at the tile size.
  pose: (seq, tClientMs) => orbitPose(camera, { seq, tClientMs, width: options.tileWidth, height: options.tileHeight }),
  onSession(msg) {
    if (msg.scene !== cameraScene && Array.isArray(msg.center)) {
      camera.reset(msg.center, msg.radius);
      cameraScene = msg.scene;
    }
  },
  onChange: render,
});
conn.exposeApi({
  get quilt() { return layout(); },
  get previewView() { return previewView; },
  get lookingGlass() { return lkgStatus; },
});

attachVideoOrbit($('stage'), video, camera, () => [options.width, options.height]);

function render() {
  const f = conn.lastFrame;
  const q = layout();
  renderStatus(conn, [
    ['views', f && f.views != null ? String(f.views) : '–'],
    ['quilt', `${q.cols}×${q.rows} · ${q.cone}°`],
    ['tile', `${q.tileWidth}×${q.tileHeight}`],
  ]);
}

// ──────────────────────────────────── preview ───────────────────────────────────

/** Source rectangle [x, y, w, h] of view `i` in a top-down quilt image of size w×h. */
function tileRect(i, q, width, height) {
  const tw = width / q.cols, th = height / q.rows;
  const col = i % q.cols, row = Math.floor(i / q.cols); // row counted from the bottom
  return [col * tw, (q.rows - 1 - row) * th, tw, th];
}

addEventListener('pointermove', (e) => {
  const n = layout().cols * layout().rows;
  previewView = clamp(Math.floor((e.clientX / Math.max(1, innerWidth)) * n), 0, n - 1);
});

function drawPreview() {
  requestAnimationFrame(drawPreview);
  const q = layout();
  if (preview.width !== q.tileWidth || preview.height !== q.tileHeight) {
    preview.width = q.tileWidth;
    preview.height = q.tileHeight;
  }
  $('previewCaption').textContent = `view ${previewView + 1} of ${q.cols * q.rows}`;
  if (video.readyState < 2 || !video.videoWidth) return;
  const [x, y, w, h] = tileRect(previewView, q, video.videoWidth, video.videoHeight);
  preview.getContext('2d').drawImage(video, x, y, w, h, 0, 0, preview.width, preview.height);
}

// ────────────────────────────────── Looking Glass ───────────────────────────────

function setLkgStatus(text) {
  lkgStatus = text;
  $('lkg').textContent = text;
}

/** Ask the Looking Glass service for a calibrated display; resolves to it or null. */
function findLookingGlass() {
  const HPC = window.HoloPlayCore;
  if (!HPC || typeof HPC.Client !== 'function') {
    setLkgStatus(window.NEPHELE_VENDOR_MISSING
      ? `no Looking Glass support: ${window.NEPHELE_VENDOR_MISSING}`
      : 'no Looking Glass support (holoplay-core did not load)');
    return Promise.resolve(null);
  }
  return new Promise((resolve) => {
    let client = null;
    let settled = false;
    const finish = (device, text) => {
      if (settled) return;
      settled = true;
      clearTimeout(timer);
      setLkgStatus(text);
      if (!device) {
        try { client?.disconnect(); } catch { /* already closed */ }
      }
      resolve(device);
    };
    const none = 'no Looking Glass display found';
    const timer = setTimeout(() => finish(null, `${none} (no answer from the Looking Glass Bridge / HoloPlay Service)`), LKG_TIMEOUT_MS);
    const onInfo = (info) => {
      const devices = Array.isArray(info?.devices) ? info.devices : [];
      const device = devices.find((d) => d && d.calibration && d.state !== 'nocalibration');
      if (device) finish(device, `Looking Glass found${device.hardwareVersion ? `: ${device.hardwareVersion}` : ''}`);
      else finish(null, devices.length ? `${none} (the display has no calibration)` : `${none} (the service sees no display)`);
    };
    try {
      // No init callback: we send the info request ourselves, so a refusal is caught here.
      client = new HPC.Client(undefined, () => finish(null, `${none} (no Looking Glass Bridge / HoloPlay Service running)`),
        () => finish(null, `${none} (the Looking Glass service closed the connection)`));
      client.ws.addEventListener('open', () => {
        client.sendMessage(new HPC.InfoMessage(), 5).then(onInfo, () => finish(null, `${none} (the Looking Glass service refused the request)`));
      });
    } catch (err) {
      finish(null, `${none} (${err.message || err})`);
    }
  });
}

const num = (x, fallback = 0) => (x && typeof x === 'object' ? Number(x.value) : Number(x ?? fallback)) || fallback;

/** The configuration holoplay-core's Shader() reads, from a display's calibration. */
function shaderConfig(cal, q) {
  const screenW = num(cal.screenW, 1536), screenH = num(cal.screenH, 2048);
  const slope = num(cal.slope, -5), dpi = num(cal.DPI, 324);
  const flipX = num(cal.flipImageX) ? -1 : 1;
  // Newer displays describe each subpixel's offset per cell (in screen pixels); without that
  // the shader's simple form (red, green, blue one third of a pixel apart) is used.
  const cells = Array.isArray(cal.subpixelCells) ? cal.subpixelCells.slice(0, 10) : [];
  return {
    pitch: num(cal.pitch) * (screenW / dpi) * Math.cos(Math.atan(1 / slope)),
    tilt: (screenH / (screenW * slope)) * flipX,
    subp: 1 / (screenW * 3),
    calibration: { center: { value: num(cal.center) }, screenW: { value: screenW }, screenH: { value: screenH }, subpixelCells: cells },
    subpixelMode: num(cal.CellPatternMode),
    numViews: q.cols * q.rows,
    quiltWidth: q.cols,
    quiltHeight: q.rows,
    tileWidth: q.tileWidth,
    tileHeight: q.tileHeight,
    framebufferWidth: q.cols * q.tileWidth,
    framebufferHeight: q.rows * q.tileHeight,
    filterMode: 1, // blend the two nearest views
    gaussianSigma: 0.01,
    cellData(screen) {
      const data = new Float32Array(60);
      cells.forEach((c, i) => {
        ['R', 'G', 'B'].forEach((ch, k) => {
          data[i * 6 + k * 2] = num(c[`${ch}OffsetX`]) / screen[0];
          data[i * 6 + k * 2 + 1] = num(c[`${ch}OffsetY`]) / screen[1];
        });
      });
      return data;
    },
  };
}

const LKG_VERTEX = `#version 300 es
in vec2 a_position;
out vec2 v_texcoord;
void main() {
  v_texcoord = a_position * 0.5 + 0.5;
  gl_Position = vec4(a_position, 0.0, 1.0);
}`;

/** Draw the quilt video through the lenticular shader into `canvas`, every frame of `win`. */
function drawLenticular(win, canvas, device) {
  const gl = canvas.getContext('webgl2', { antialias: false, alpha: false });
  if (!gl) throw new Error('no WebGL2 in the Looking Glass window');
  const cfg = shaderConfig(device.calibration, layout());
  const compile = (type, src) => {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  };
  const prog = gl.createProgram();
  gl.attachShader(prog, compile(gl.VERTEX_SHADER, LKG_VERTEX));
  gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, window.HoloPlayCore.Shader(cfg)));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  gl.useProgram(prog);
  gl.bindBuffer(gl.ARRAY_BUFFER, gl.createBuffer());
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
  const aPos = gl.getAttribLocation(prog, 'a_position');
  gl.enableVertexAttribArray(aPos);
  gl.vertexAttribPointer(aPos, 2, gl.FLOAT, false, 0, 0);
  const screen = [cfg.calibration.screenW.value, cfg.calibration.screenH.value];
  gl.uniform1i(gl.getUniformLocation(prog, 'u_texture'), 0);
  gl.uniform1i(gl.getUniformLocation(prog, 'u_viewType'), 0); // lenticular
  const cellsAt = gl.getUniformLocation(prog, 'subpixelData');
  if (cellsAt) gl.uniform1fv(cellsAt, cfg.cellData(screen));
  gl.activeTexture(gl.TEXTURE0);
  gl.bindTexture(gl.TEXTURE_2D, gl.createTexture());
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
  // Quilt rows are counted from the bottom, GL textures too: flip the top-down video.
  gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, true);
  const frame = () => {
    if (win.closed) return;
    win.requestAnimationFrame(frame);
    if (video.readyState < 2) return;
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, video);
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
  };
  frame();
}

/** Open a window on the Looking Glass (its desktop position, full size) and draw there. */
function showOnLookingGlass(device) {
  const cal = device.calibration;
  const w = num(cal.screenW, 1536), h = num(cal.screenH, 2048);
  const [x, y] = Array.isArray(device.windowCoords) ? device.windowCoords : [0, 0];
  const win = open('', 'nephele-looking-glass', `popup,left=${x},top=${y},width=${w},height=${h}`);
  if (!win) { setLkgStatus('the browser blocked the Looking Glass window (allow pop-ups for this page)'); return; }
  const doc = win.document;
  doc.title = 'Nephele on Looking Glass';
  doc.body.replaceChildren();
  doc.body.style.cssText = 'margin:0;background:#000;overflow:hidden';
  const canvas = doc.createElement('canvas');
  canvas.width = w;
  canvas.height = h;
  canvas.style.cssText = 'width:100vw;height:100vh;display:block;cursor:pointer';
  canvas.title = 'click: full screen';
  canvas.addEventListener('click', () => canvas.requestFullscreen?.().catch(() => {}));
  doc.body.append(canvas);
  try {
    drawLenticular(win, canvas, device);
    setLkgStatus('showing on the Looking Glass (click its window for full screen)');
  } catch (err) {
    setLkgStatus(`could not draw on the Looking Glass: ${err.message || err}`);
    win.close();
  }
}

// ───────────────────────────────────── start ────────────────────────────────────

async function main() {
  render();
  requestAnimationFrame(drawPreview);

  findLookingGlass().then((device) => {
    if (!device) return;
    const button = $('show');
    button.hidden = false;
    button.addEventListener('click', () => showOnLookingGlass(device));
  }).catch((err) => setLkgStatus(`no Looking Glass display found (${err.message || err})`));

  const sceneSelect = $('scene');
  const { scenes, default: def } = await fetchScenes();
  sceneSelect.replaceChildren(...scenes.map((s) => new Option(s, s)));
  sceneSelect.value = options.scene && scenes.includes(options.scene) ? options.scene : def;
  const connect = () => {
    if (sceneSelect.value !== cameraScene) cameraScene = null;
    const { cols, rows, cone } = options;
    conn.connect({
      scene: sceneSelect.value, width: options.width, height: options.height, fps: options.fps, token: options.token, relay: options.relay,
      quilt: { cols, rows, cone_deg: cone },
    });
  };
  sceneSelect.addEventListener('change', connect);
  connect();
}

main();
