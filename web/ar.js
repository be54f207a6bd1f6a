// ar.js — logic of the AR page (ar.html). Joins in mode "ar": the server renders the object
// over pure green (0,255,0). A WebGL fragment shader keys the green out (chroma distance to
// green in YCbCr, smoothstep soft edge, green-spill suppression near the edge) and blends the
// object over the device camera feed, or over a checkerboard when there is no camera.
// There is no device tracking: the view is the same orbit camera as the viewer (drag to
// move it). The object stands on a plane anchor: world origin by default; a tap moves it to
// where the tapped ray meets the ground plane z = 0; the slider sets its uniform scale.
// Poses are sent with the 64-byte world_from_anchor appended (168 bytes).

import { OrbitCamera, attachOrbitControls } from './camera.js';
import { Connection, ensureCapturePermission, fetchScenes, readPageOptions } from './connection.js';
import { orbitPose } from './pose.js';
import { makeNote, renderStatus } from './hud.js';

const $ = (id) => document.getElementById(id);
const note = makeNote($('note'));
const canvas = $('canvas');
const video = $('video');       // the stream
const cameraVideo = $('camera'); // the device camera
const options = readPageOptions();

// ─────────────────────────────── camera + anchor ───────────────────────────────

const camera = new OrbitCamera();
let cameraScene = null;
const anchor = { x: 0, y: 0, scale: 1 };

/** world_from_anchor, column-major: uniform scale, then translation on the ground. */
function anchorMatrix() {
  const s = anchor.scale;
  return new Float32Array([s, 0, 0, 0, 0, s, 0, 0, 0, 0, s, 0, anchor.x, anchor.y, 0, 1]);
}

const conn = new Connection({
  mode: 'ar',
  video,
  camera,
  // The orbit camera as NPO1 with the anchor appended (168 bytes), every 20 ms.
  pose: (seq, tClientMs) => orbitPose(camera, {
    seq, tClientMs, width: conn.params.width, height: conn.params.height, worldFromAnchor: anchorMatrix(),
  }),
  onSession(msg) {
    if (msg.scene !== cameraScene && Array.isArray(msg.center)) {
      camera.reset(msg.center, msg.radius);
      cameraScene = msg.scene;
    }
  },
  onChange: render,
});
let cameraOk = false;
conn.exposeApi({
  get anchor() { return { ...anchor }; },
  get cameraFeed() { return cameraOk; },
});

// Canvas pixel (in stream pixels) under a client point; the canvas is letterboxed (contain).
function canvasFit() {
  const r = canvas.getBoundingClientRect();
  const s = Math.min(r.width / canvas.width, r.height / canvas.height) || 1;
  return { s, left: r.left + (r.width - canvas.width * s) / 2, top: r.top + (r.height - canvas.height * s) / 2 };
}

function placeAnchor(clientX, clientY) {
  const { s, left, top } = canvasFit();
  const px = (clientX - left) / s, py = (clientY - top) / s;
  if (px < 0 || py < 0 || px > canvas.width || py > canvas.height) return;
  const { origin, dir } = camera.ray(px, py, canvas.width, canvas.height);
  const t = dir[2] !== 0 ? -origin[2] / dir[2] : -1;
  if (!(t > 0)) { note('Tap below the horizon to place the object on the ground.', 3000); return; }
  anchor.x = origin[0] + t * dir[0];
  anchor.y = origin[1] + t * dir[1];
}

attachOrbitControls($('stage'), camera, {
  onTap: placeAnchor,
  viewportHeight: () => canvas.height * canvasFit().s,
});

$('scale').addEventListener('input', (e) => {
  anchor.scale = Math.min(2, Math.max(0.25, Number(e.target.value) || 1));
  $('scaleOut').textContent = `${anchor.scale.toFixed(2)}×`;
});

// ────────────────────────────────────── HUD ─────────────────────────────────────

function render() { renderStatus(conn); }

// ──────────────────────────────── WebGL chroma key ──────────────────────────────

const VERTEX = `
attribute vec2 aPos;
varying vec2 vUv;
void main() {
  vUv = aPos * 0.5 + 0.5;
  gl_Position = vec4(aPos, 0.0, 1.0);
}`;

// Key: distance of the pixel's chroma (Cb, Cr; BT.601) from pure green's. Below uKey.x the
// pixel is background, above uKey.y it is object, smoothstep in between (soft edge, which
// also absorbs H.264's 4:2:0 chroma blur). Spill: in a band just beyond the key, green is
// pulled down to max(r, b) so edges do not glow green.
const FRAGMENT = `
precision mediump float;
varying vec2 vUv;
uniform sampler2D uCam;
uniform sampler2D uObj;
uniform vec4 uCamRect;   // camera uv = vUv * xy + zw (cover fit)
uniform float uHasObj;   // 0 until the stream has a frame
uniform vec2 uKey;       // chroma distances: fully keyed below x, fully opaque above y
const vec2 GREEN_CBCR = vec2(-0.331264, -0.418688);
void main() {
  vec3 bg = texture2D(uCam, vUv * uCamRect.xy + uCamRect.zw).rgb;
  vec3 c = texture2D(uObj, vUv).rgb;
  vec2 cbcr = vec2(dot(c, vec3(-0.168736, -0.331264, 0.5)), dot(c, vec3(0.5, -0.418688, -0.081312)));
  float d = distance(cbcr, GREEN_CBCR);
  float alpha = smoothstep(uKey.x, uKey.y, d) * uHasObj;
  float spill = 1.0 - smoothstep(uKey.y, uKey.y + 0.2, d);
  c.g = mix(c.g, min(c.g, max(c.r, c.b)), spill);
  gl_FragColor = vec4(mix(bg, c, alpha), 1.0);
}`;

function compile(gl, type, src) {
  const s = gl.createShader(type);
  gl.shaderSource(s, src);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
  return s;
}

function makeTexture(gl) {
  const t = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, t);
  // Video sizes are not powers of two: no mipmaps, clamp, linear.
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, 1, 1, 0, gl.RGB, gl.UNSIGNED_BYTE, new Uint8Array([0, 0, 0]));
  return t;
}

function checkerboard() {
  const c = document.createElement('canvas');
  c.width = c.height = 256;
  const g = c.getContext('2d');
  for (let y = 0; y < 8; y++) for (let x = 0; x < 8; x++) {
    g.fillStyle = (x + y) % 2 ? '#8a8a8a' : '#c8c8c8';
    g.fillRect(x * 32, y * 32, 32, 32);
  }
  return c;
}

function startCompositor() {
  const gl = canvas.getContext('webgl', { alpha: false, antialias: false, premultipliedAlpha: false });
  if (!gl) {
    note('This browser has no WebGL, so the AR view cannot be drawn.');
    return;
  }
  const prog = gl.createProgram();
  gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, VERTEX));
  gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, FRAGMENT));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  gl.useProgram(prog);

  const buf = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, buf);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
  const aPos = gl.getAttribLocation(prog, 'aPos');
  gl.enableVertexAttribArray(aPos);
  gl.vertexAttribPointer(aPos, 2, gl.FLOAT, false, 0, 0);

  const u = (name) => gl.getUniformLocation(prog, name);
  gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, true); // image rows top-down, GL uv bottom-up
  gl.activeTexture(gl.TEXTURE0);
  const texCam = makeTexture(gl);
  gl.activeTexture(gl.TEXTURE1);
  const texObj = makeTexture(gl);
  gl.uniform1i(u('uCam'), 0);
  gl.uniform1i(u('uObj'), 1);
  gl.uniform2f(u('uKey'), 0.12, 0.26);

  let bgSize = null; // [w, h] of what texCam holds
  let hasObj = false;
  if (!cameraOk) {
    const board = checkerboard();
    gl.activeTexture(gl.TEXTURE0);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, board);
    bgSize = [board.width, board.height];
  }

  const ready = (v) => v.readyState >= 2 && v.videoWidth > 0;

  function frame() {
    requestAnimationFrame(frame);
    if (cameraOk && ready(cameraVideo)) {
      gl.activeTexture(gl.TEXTURE0);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, cameraVideo);
      bgSize = [cameraVideo.videoWidth, cameraVideo.videoHeight];
    }
    if (ready(video)) {
      gl.activeTexture(gl.TEXTURE1);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, video);
      hasObj = true;
    }
    // Cover-fit the background into the canvas (crop the longer side, keep aspect).
    let sx = 1, sy = 1;
    if (bgSize) {
      const bgAspect = bgSize[0] / bgSize[1], aspect = canvas.width / canvas.height;
      if (bgAspect > aspect) sx = aspect / bgAspect; else sy = bgAspect / aspect;
    }
    gl.uniform4f(u('uCamRect'), sx, sy, (1 - sx) / 2, (1 - sy) / 2);
    gl.uniform1f(u('uHasObj'), hasObj ? 1 : 0);
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
  }
  requestAnimationFrame(frame);
}

// ───────────────────────────────────── start ────────────────────────────────────

async function main() {
  render();
  canvas.width = options.width;
  canvas.height = options.height;

  // The camera feed doubles as the capture grant connection.js needs for loopback ICE.
  const stream = await ensureCapturePermission({ video: { facingMode: 'environment' }, audio: false });
  if (stream && stream.getVideoTracks().length) {
    cameraOk = true;
    cameraVideo.srcObject = stream;
    cameraVideo.play().catch(() => {});
  } else {
    note('No camera available (permission denied or no device): showing a checkerboard instead.');
  }
  try {
    startCompositor();
  } catch (err) {
    note(`WebGL set-up failed: ${err.message}`);
  }

  const sceneSelect = $('scene');
  const { scenes, default: def } = await fetchScenes();
  sceneSelect.replaceChildren(...scenes.map((s) => new Option(s, s)));
  sceneSelect.value = options.scene && scenes.includes(options.scene) ? options.scene : def;
  const connect = () => {
    if (sceneSelect.value !== cameraScene) cameraScene = null;
    anchor.x = anchor.y = 0;
    conn.connect({ scene: sceneSelect.value, width: options.width, height: options.height, fps: options.fps, token: options.token, relay: options.relay });
  };
  sceneSelect.addEventListener('change', connect);
  connect();
}

main();
