// camera.js — the camera the pages steer, shared by all of them.
//
//   * small vector and 4×4 matrix helpers (matrices are 16 numbers, column-major, as in GL);
//   * OrbitCamera: a camera on a sphere around the scene centre (world up is +z, as in
//     NeRF-synthetic), with its world_from_camera matrix, centred pinhole intrinsics and rays;
//   * attachOrbitControls(): mouse/touch gestures that move an OrbitCamera.

// ───────────────────────────── small vector helpers ─────────────────────────────

export const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
export const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
export const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
export const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
export const norm = (a) => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };
export const clamp = (x, lo, hi) => Math.min(hi, Math.max(lo, x));
export const DEG = Math.PI / 180;

/** a·b of two column-major 4×4 matrices. */
export function mat4Mul(a, b) {
  const out = new Float32Array(16);
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      let x = 0;
      for (let k = 0; k < 4; k++) x += a[k * 4 + r] * b[c * 4 + k];
      out[c * 4 + r] = x;
    }
  }
  return out;
}

/** Column-major matrix that scales uniformly by `s`, then moves by `t`. */
export function mat4TranslateScale(t, s = 1) {
  return new Float32Array([s, 0, 0, 0, 0, s, 0, 0, 0, 0, s, 0, t[0], t[1], t[2], 1]);
}

/** A copy of the rigid column-major `m` moved by `d` (world units) along its own x axis. */
export function offsetAlongX(m, d) {
  const out = Float32Array.from(m);
  for (let i = 0; i < 3; i++) out[12 + i] += m[i] * d;
  return out;
}

// ───────────────────────────────── orbit camera ─────────────────────────────────

/** A camera on a sphere around `center`, looking at it; +z is world up. */
export class OrbitCamera {
  constructor() {
    this.reset([0, 0, 0], 1);
  }

  /** Default view of an asset: distance 2.6·radius, azimuth 35°, elevation 25°, fovY 40°. */
  reset(center, radius) {
    this.center = [...center];
    this.radius = radius > 0 ? radius : 1;
    this.distance = 2.6 * this.radius;
    this.azimuth = 35 * DEG;   // about +z, from +x
    this.elevation = 25 * DEG; // towards +z
    this.fovY = 40 * DEG;
  }

  eye() {
    const ce = Math.cos(this.elevation);
    return add(this.center, scale([ce * Math.cos(this.azimuth), ce * Math.sin(this.azimuth), Math.sin(this.elevation)], this.distance));
  }

  /** Camera axes in world space: right (+x), up (+y), back (+z; the camera looks down −z). */
  axes() {
    const back = norm(sub(this.eye(), this.center));
    const right = norm(cross([0, 0, 1], back)); // elevation stays within ±89°, so never degenerate
    const up = cross(back, right);
    return { right, up, back };
  }

  /** world_from_camera as 16 floats, column-major (OpenGL camera convention). */
  worldFromCamera() {
    const { right, up, back } = this.axes();
    const e = this.eye();
    return new Float32Array([...right, 0, ...up, 0, ...back, 0, ...e, 1]);
  }

  /** Pinhole intrinsics of a centred camera for a width×height viewport. */
  intrinsics(width, height) {
    const f = 0.5 * height / Math.tan(this.fovY / 2);
    return { fx: f, fy: f, cx: width / 2, cy: height / 2 };
  }

  orbit(dAzimuth, dElevation) {
    this.azimuth = (this.azimuth + dAzimuth) % (2 * Math.PI);
    this.elevation = clamp(this.elevation + dElevation, -89 * DEG, 89 * DEG);
  }

  /** Multiply the distance by `factor`, within [0.05, 50]·radius. */
  zoom(factor) {
    this.distance = clamp(this.distance * factor, 0.05 * this.radius, 50 * this.radius);
  }

  /** Move the look-at point by a fraction of the view height (fractions of the viewport). */
  pan(fracX, fracY) {
    const { right, up } = this.axes();
    const viewHeight = 2 * this.distance * Math.tan(this.fovY / 2);
    // Content follows the pointer: dragging right moves the camera left.
    let c = add(this.center, add(scale(right, -fracX * viewHeight), scale(up, fracY * viewHeight)));
    // Keep the camera well within the server's distance limit.
    const far = 100 * this.radius;
    const l = Math.hypot(...c);
    if (l > far) c = scale(c, far / l);
    this.center = c;
  }

  /** World-space ray through viewport pixel (px, py) of a width×height image. */
  ray(px, py, width, height) {
    const { fx, fy, cx, cy } = this.intrinsics(width, height);
    const { right, up, back } = this.axes();
    const dx = (px - cx) / fx, dy = -(py - cy) / fy; // image y grows downwards, camera +y up
    const dir = norm(add(add(scale(right, dx), scale(up, dy)), scale(back, -1)));
    return { origin: this.eye(), dir };
  }
}

/**
 * Mouse and touch gestures on `element` that steer `camera`:
 * left-drag orbits, wheel zooms, right-drag or shift-drag pans; one finger orbits, two
 * fingers pinch-zoom and pan. `onTap(clientX, clientY)` fires for a click/tap that did not
 * move. `viewportHeight()` gives the displayed image height in CSS pixels (for panning).
 */
export function attachOrbitControls(element, camera, { onTap, viewportHeight } = {}) {
  const pointers = new Map(); // pointerId → {x, y}
  let mode = null;            // 'orbit' | 'pan' | 'pinch'
  let tap = null;             // {x, y, t} while a press might still be a tap
  let pinch = null;           // {dist, mid}
  const height = () => (viewportHeight ? viewportHeight() : element.clientHeight) || 1;
  const ORBIT_RAD_PER_PX = 0.008;

  const twoFinger = () => {
    const [a, b] = [...pointers.values()];
    return { dist: Math.hypot(a.x - b.x, a.y - b.y) || 1, mid: [(a.x + b.x) / 2, (a.y + b.y) / 2] };
  };

  element.style.touchAction = 'none';
  element.addEventListener('contextmenu', (e) => e.preventDefault());

  element.addEventListener('pointerdown', (e) => {
    element.setPointerCapture?.(e.pointerId);
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
    if (pointers.size === 1) {
      mode = e.button === 2 || e.shiftKey ? 'pan' : 'orbit';
      tap = { x: e.clientX, y: e.clientY, t: performance.now() };
    } else if (pointers.size === 2) {
      mode = 'pinch';
      pinch = twoFinger();
      tap = null;
    }
    e.preventDefault();
  });

  element.addEventListener('pointermove', (e) => {
    const p = pointers.get(e.pointerId);
    if (!p) return;
    const dx = e.clientX - p.x, dy = e.clientY - p.y;
    p.x = e.clientX; p.y = e.clientY;
    if (tap && Math.hypot(e.clientX - tap.x, e.clientY - tap.y) > 6) tap = null;
    if (mode === 'orbit') {
      camera.orbit(-dx * ORBIT_RAD_PER_PX, dy * ORBIT_RAD_PER_PX);
    } else if (mode === 'pan') {
      camera.pan(dx / height(), dy / height());
    } else if (mode === 'pinch' && pointers.size >= 2) {
      const now = twoFinger();
      camera.zoom(pinch.dist / now.dist);
      camera.pan((now.mid[0] - pinch.mid[0]) / height(), (now.mid[1] - pinch.mid[1]) / height());
      pinch = now;
    }
  });

  const end = (e) => {
    if (!pointers.delete(e.pointerId)) return;
    if (tap && pointers.size === 0 && e.type === 'pointerup' && performance.now() - tap.t < 600) {
      onTap?.(e.clientX, e.clientY);
    }
    tap = null;
    // Lifting one of two fingers continues as a one-finger orbit from the remaining finger.
    mode = pointers.size === 1 ? 'orbit' : pointers.size === 0 ? null : mode;
    if (pointers.size >= 2) pinch = twoFinger();
  };
  element.addEventListener('pointerup', end);
  element.addEventListener('pointercancel', end);

  element.addEventListener('wheel', (e) => {
    e.preventDefault();
    const px = e.deltaMode === 1 ? e.deltaY * 16 : e.deltaMode === 2 ? e.deltaY * 400 : e.deltaY;
    camera.zoom(Math.exp(clamp(px, -200, 200) * 0.0015));
  }, { passive: false });
}

/**
 * Orbit gestures on `stage` over a letterboxed `video` (object-fit: contain) whose frame is
 * `frameSize()` = [width, height] pixels: drags are measured against the image's shown height.
 */
export function attachVideoOrbit(stage, video, camera, frameSize, more = {}) {
  const viewportHeight = () => {
    const r = video.getBoundingClientRect();
    const [w, h] = frameSize();
    return Math.min(r.height, (r.width * h) / w);
  };
  return attachOrbitControls(stage, camera, { ...more, viewportHeight });
}
