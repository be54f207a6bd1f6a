// pose.js — the binary pose messages a page sends on the "pose" data channel (little-endian).
//
//   * encodePose():      "NPO1", one centred pinhole camera, 104 bytes (168 with an anchor;
//                        72 more with a prediction: the horizon and the present camera);
//   * encodePoseViews(): "NPO2", 1..8 views (stereo eyes, …) each with its own GL projection
//                        and viewport in the streamed frame, 32 + 144·n bytes (+64 with an anchor);
//   * orbitPose():       NPO1 of an OrbitCamera (what the viewer and AR pages send);
//   * projectionFromIntrinsics(), frustumTangents(): between pinhole intrinsics, GL
//     projection matrices and the tangents of a frustum's sides;
//   * poseViewCount():   how many views a pose message carries (NPO1 counts as 1).
// Matrices are 16 floats, column-major; cameras look down −z with +y up (OpenGL).

export const POSE_LEN = 104;
export const POSE_WITH_ANCHOR_LEN = 168;
export const POSE_PREDICTION_LEN = 72;
export const POSE_VIEWS_HEADER_LEN = 32;
export const POSE_VIEW_LEN = 144;
export const POSE_ANCHOR_LEN = 64;
export const MAX_POSE_VIEWS = 8;
/** NPO2 flags bit 0: a world_from_anchor follows the views. */
export const FLAG_ANCHOR = 1;
/** NPO2 flags bit 1: a prediction follows (horizon, then each view's present camera). */
export const FLAG_PREDICTED = 2;

const putMagic = (v, text) => { for (let i = 0; i < 4; i++) v.setUint8(i, text.charCodeAt(i)); };
const putMat4 = (v, at, m) => { for (let i = 0; i < 16; i++) v.setFloat32(at + 4 * i, m[i], true); };

/**
 * The single-camera message:
 * "NPO1" | u32 seq | f64 t_client_ms | f32×16 world_from_camera (column-major) |
 * f32×4 fx fy cx cy | u32×2 width height | optional f32×16 world_from_anchor |
 * optional prediction: f64 horizon ms, f32×16 the present world_from_camera (then
 * worldFromCamera is the camera predicted for when the frame will be shown).
 * `predicted`: { horizonMs, presentWorldFromCamera } or undefined.
 */
export function encodePose({ seq, tClientMs, worldFromCamera, intrinsics, width, height, worldFromAnchor, predicted }) {
  const base = worldFromAnchor ? POSE_WITH_ANCHOR_LEN : POSE_LEN;
  const bytes = new Uint8Array(base + (predicted ? POSE_PREDICTION_LEN : 0));
  const v = new DataView(bytes.buffer);
  putMagic(v, 'NPO1');
  v.setUint32(4, seq, true);
  v.setFloat64(8, tClientMs, true);
  putMat4(v, 16, worldFromCamera);
  const { fx, fy, cx, cy } = intrinsics;
  [fx, fy, cx, cy].forEach((x, i) => v.setFloat32(80 + 4 * i, x, true));
  v.setUint32(96, width, true);
  v.setUint32(100, height, true);
  if (worldFromAnchor) putMat4(v, 104, worldFromAnchor);
  if (predicted) {
    v.setFloat64(base, predicted.horizonMs, true);
    putMat4(v, base + 8, predicted.presentWorldFromCamera);
  }
  return bytes;
}

/**
 * The multi-view message:
 * "NPO2" | u32 seq | f64 t_client_ms | u32 width | u32 height (the joined frame size) |
 * u32 view count n (1..8) | u32 flags (bit 0: anchor follows) |
 * n × { f32×16 world_from_camera | f32×16 clip_from_camera (GL projection) |
 *       u32×4 viewport x y w h (pixels of the frame, origin top-left, y down) } |
 * optional f32×16 world_from_anchor |
 * optional prediction: f64 horizon ms, then per view f32×16 its present world_from_camera.
 * `views` is [{ worldFromCamera, clipFromCamera, viewport: [x, y, w, h] }] (the predicted
 * cameras when `predicted` is { horizonMs, presentViews: [worldFromCamera per view] }).
 */
export function encodePoseViews({ seq, tClientMs, width, height, views, worldFromAnchor, predicted }) {
  const n = views.length;
  if (n < 1 || n > MAX_POSE_VIEWS) throw new RangeError(`NPO2 carries 1..${MAX_POSE_VIEWS} views, not ${n}`);
  if (predicted && predicted.presentViews.length !== n) throw new RangeError('a prediction needs one present camera per view');
  const tail = predicted ? 8 + 64 * n : 0;
  const len = POSE_VIEWS_HEADER_LEN + POSE_VIEW_LEN * n + (worldFromAnchor ? POSE_ANCHOR_LEN : 0) + tail;
  const bytes = new Uint8Array(len);
  const v = new DataView(bytes.buffer);
  putMagic(v, 'NPO2');
  v.setUint32(4, seq, true);
  v.setFloat64(8, tClientMs, true);
  v.setUint32(16, width, true);
  v.setUint32(20, height, true);
  v.setUint32(24, n, true);
  v.setUint32(28, (worldFromAnchor ? FLAG_ANCHOR : 0) | (predicted ? FLAG_PREDICTED : 0), true);
  views.forEach(({ worldFromCamera, clipFromCamera, viewport }, i) => {
    const at = POSE_VIEWS_HEADER_LEN + POSE_VIEW_LEN * i;
    putMat4(v, at, worldFromCamera);
    putMat4(v, at + 64, clipFromCamera);
    for (let k = 0; k < 4; k++) v.setUint32(at + 128 + 4 * k, Math.round(viewport[k]), true);
  });
  if (worldFromAnchor) putMat4(v, len - tail - POSE_ANCHOR_LEN, worldFromAnchor);
  if (predicted) {
    v.setFloat64(len - tail, predicted.horizonMs, true);
    predicted.presentViews.forEach((m, i) => putMat4(v, len - tail + 8 + 64 * i, m));
  }
  return bytes;
}

/** NPO1 of an OrbitCamera for a width×height image (centred pinhole from its fovY). */
export function orbitPose(camera, { seq, tClientMs, width, height, worldFromAnchor, predicted }) {
  return encodePose({
    seq,
    tClientMs,
    worldFromCamera: camera.worldFromCamera(),
    intrinsics: camera.intrinsics(width, height),
    width,
    height,
    worldFromAnchor: worldFromAnchor || undefined,
    predicted,
  });
}

/** Number of views in a pose message: NPO1 → 1, NPO2 → its view count, else 0. */
export function poseViewCount(bytes) {
  if (!bytes || bytes.byteLength < 4) return 0;
  const magic = String.fromCharCode(bytes[0], bytes[1], bytes[2], bytes[3]);
  if (magic === 'NPO1') return 1;
  if (magic === 'NPO2' && bytes.byteLength >= POSE_VIEWS_HEADER_LEN) {
    return new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength).getUint32(24, true);
  }
  return 0;
}

/**
 * GL projection (clip_from_camera) of a pinhole camera whose image is width×height pixels,
 * image origin top-left with y down: pixel (u, v) = (cx + fx·x/−z, cy − fy·y/−z).
 * `far` = Infinity gives the infinite-far form.
 */
export function projectionFromIntrinsics({ fx, fy, cx, cy }, width, height, near, far = Infinity) {
  const p = new Float32Array(16);
  p[0] = (2 * fx) / width;
  p[5] = (2 * fy) / height;
  p[8] = 1 - (2 * cx) / width;
  p[9] = (2 * cy) / height - 1;
  p[11] = -1;
  if (Number.isFinite(far)) {
    p[10] = -(far + near) / (far - near);
    p[14] = (-2 * far * near) / (far - near);
  } else {
    p[10] = -1;
    p[14] = -2 * near;
  }
  return p;
}

/** Symmetric GL projection with vertical field of view `fovY` (radians) and aspect w/h. */
export function perspective(fovY, aspect, near, far = Infinity) {
  const f = 1 / Math.tan(fovY / 2);
  return projectionFromIntrinsics({ fx: f / aspect, fy: f, cx: 1, cy: 1 }, 2, 2, near, far);
}

/**
 * Tangents of a GL projection's frustum sides at unit distance in front of the camera:
 * { left, right, bottom, top } (left < right, bottom < top; left/bottom usually negative).
 */
export function frustumTangents(p) {
  return {
    left: (p[8] - 1) / p[0],
    right: (p[8] + 1) / p[0],
    bottom: (p[9] - 1) / p[5],
    top: (p[9] + 1) / p[5],
  };
}
