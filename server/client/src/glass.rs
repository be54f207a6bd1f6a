//! Latency at the glass, on the client (docs/architecture.md §5 "Reprojection"): the warp
//! that moves a decoded view from the camera it was rendered with to the camera of the
//! display frame, by the depth grid that came with it, and the pose predictor.
//!
//! The warp is the pages' WebGL2 grid mesh done on the CPU, so it can be measured headless
//! and frame-exactly (`nephele bench glass`): each grid vertex is unprojected at its depth
//! (a background vertex as a direction, at infinity), moved into the display camera and
//! projected; each grid cell is two triangles, rasterised with a depth test (the nearest
//! surface wins), sampling the decoded picture bilinearly where the vertex came from.
//! Texture coordinates are interpolated linearly in the display's pixels (cells are 8 pixels:
//! the perspective error within one is far below a pixel). Disocclusions are filled by
//! stretching: a cell between the object's edge and the background stretches, and since a
//! vertex takes the nearest depth around it (`nephele_wire::depth`), what stretches is the
//! background next to the object, never the object. Display pixels no triangle covers (turned
//! beyond the rendered field of view) get the mode's background colour.
//!
//! The predictor extrapolates the camera along its present linear and angular velocity (from
//! the last two samples), and clamps it: never faster than now, not past where the motion
//! stops if its speed keeps changing as it did over the last four samples (speed, its rate
//! and jerk: no overshoot past a stop), not beyond [`MAX_HORIZON_MS`] or
//! [`MAX_PREDICTED_TURN_DEG`], not across a jump (a teleport resets it), and not from a single
//! sample or a non-finite one.

use glam::{DMat3, DMat4, DQuat, DVec3};
use nephele_renderer::{Intrinsics, View};
use nephele_wire::depth::DepthView;

/// The longest the predictor looks ahead, ms.
pub const MAX_HORIZON_MS: f64 = 250.0;
/// Largest rotation a prediction may add, degrees.
pub const MAX_PREDICTED_TURN_DEG: f64 = 45.0;
/// Motion faster than this between two samples is a jump (a teleport, a reset view), not
/// motion: the predictor starts again from the new pose. Degrees per second, and scene units
/// per second.
pub const JUMP_TURN_DEG_PER_S: f64 = 1500.0;
pub const JUMP_SPEED_PER_S: f64 = 50.0;
/// Samples further apart than this do not make a velocity (the stream paused), ms.
pub const MAX_SAMPLE_GAP_MS: f64 = 200.0;

/// One display-space vertex of the warp: where it lands, its inverse depth (0 at infinity)
/// and where it came from in the decoded picture.
#[derive(Debug, Clone, Copy)]
struct Vertex {
    x: f64,
    y: f64,
    inv_z: f64,
    src_x: f64,
    src_y: f64,
}

/// Reprojects one view of a decoded frame to `target`.
///
/// `frame` is the whole decoded picture (RGBA8, `frame_width` wide); the view's pixels are at
/// `depth.viewport` in it. Returns RGBA8 at `target`'s size, or `None` when the depth's
/// viewport does not lie inside the picture (depth of another stream, or corrupt): the
/// caller then shows the picture as it came.
pub fn warp(frame: &[u8], frame_width: u32, depth: &DepthView, target: &View, background: [u8; 3]) -> Option<Vec<u8>> {
    let vp = depth.viewport;
    let frame_height = frame.len() / 4 / (frame_width.max(1) as usize);
    if u64::from(vp.x) + u64::from(vp.width) > u64::from(frame_width) || u64::from(vp.y) + u64::from(vp.height) > frame_height as u64 {
        return None;
    }
    let tk = target.intrinsics;
    let (tw, th) = (tk.width as usize, tk.height as usize);
    let (cols, rows) = depth.grid();
    let src = depth.world_from_camera.as_dmat4();
    let camera_from_world = target.world_from_camera.inverse();
    let target_from_source = camera_from_world * src;
    let rot = DMat3::from_mat4(target_from_source);
    let sk = depth.intrinsics;
    let vertices: Vec<Option<Vertex>> = (0..rows)
        .flat_map(|j| (0..cols).map(move |i| (i, j)))
        .map(|(i, j)| {
            let (x, y) = depth.vertex_px(i, j);
            let (x, y) = (f64::from(x), f64::from(y));
            let dir = DVec3::new((x - f64::from(sk.cx)) / f64::from(sk.fx), -(y - f64::from(sk.cy)) / f64::from(sk.fy), -1.0);
            let (p, inv_z) = match depth.z_at(i, j) {
                Some(z) => {
                    let p = target_from_source.transform_point3(dir * f64::from(z));
                    (p, 1.0 / -p.z)
                }
                None => (rot * dir, 0.0),
            };
            if !(p.z < -1e-9) || !p.is_finite() {
                return None;
            }
            let (px, py) = (f64::from(tk.cx) + f64::from(tk.fx) * p.x / -p.z, f64::from(tk.cy) - f64::from(tk.fy) * p.y / -p.z);
            // A vertex far outside the display cannot cover it sensibly (a grazing view).
            let limit = 16.0 * (tw + th) as f64;
            (px.abs() < limit && py.abs() < limit).then_some(Vertex { x: px, y: py, inv_z, src_x: x, src_y: y })
        })
        .collect();

    // Per display pixel: the nearest surface's inverse depth and where to sample.
    let mut best = vec![f64::NEG_INFINITY; tw * th];
    let mut from = vec![(0.0f32, 0.0f32); tw * th];
    for j in 0..rows - 1 {
        for i in 0..cols - 1 {
            let at = |di: usize, dj: usize| vertices[(j + dj) * cols + i + di];
            let (Some(a), Some(b), Some(c), Some(d)) = (at(0, 0), at(1, 0), at(1, 1), at(0, 1)) else { continue };
            for tri in [[a, b, c], [a, c, d]] {
                raster(&tri, tw, th, &mut best, &mut from);
            }
        }
    }

    let mut out = Vec::with_capacity(4 * tw * th);
    for (k, &(sx, sy)) in from.iter().enumerate() {
        if best[k] == f64::NEG_INFINITY {
            out.extend_from_slice(&[background[0], background[1], background[2], 255]);
        } else {
            out.extend_from_slice(&sample(frame, frame_width, vp, sx, sy));
        }
    }
    Some(out)
}

/// Rasterises one triangle: pixel centres inside it (edges included) whose surface is nearer
/// than what is there.
fn raster(t: &[Vertex; 3], tw: usize, th: usize, best: &mut [f64], from: &mut [(f32, f32)]) {
    let area = (t[1].x - t[0].x) * (t[2].y - t[0].y) - (t[2].x - t[0].x) * (t[1].y - t[0].y);
    if area.abs() < 1e-12 {
        return;
    }
    let min_x = t.iter().map(|v| v.x).fold(f64::INFINITY, f64::min);
    let max_x = t.iter().map(|v| v.x).fold(f64::NEG_INFINITY, f64::max);
    let min_y = t.iter().map(|v| v.y).fold(f64::INFINITY, f64::min);
    let max_y = t.iter().map(|v| v.y).fold(f64::NEG_INFINITY, f64::max);
    let x0 = (min_x - 0.5).ceil().max(0.0) as usize;
    let y0 = (min_y - 0.5).ceil().max(0.0) as usize;
    let x1 = ((max_x - 0.5).floor() as i64).min(tw as i64 - 1);
    let y1 = ((max_y - 0.5).floor() as i64).min(th as i64 - 1);
    if x1 < x0 as i64 || y1 < y0 as i64 {
        return;
    }
    let eps = 1e-9 * area.abs();
    for py in y0..=y1 as usize {
        let cy = py as f64 + 0.5;
        for px in x0..=x1 as usize {
            let cx = px as f64 + 0.5;
            // Barycentric weights, positive inside whichever way the triangle turns.
            let w0 = ((t[1].x - cx) * (t[2].y - cy) - (t[2].x - cx) * (t[1].y - cy)) / area;
            let w1 = ((t[2].x - cx) * (t[0].y - cy) - (t[0].x - cx) * (t[2].y - cy)) / area;
            let w2 = 1.0 - w0 - w1;
            if w0 < -eps || w1 < -eps || w2 < -eps {
                continue;
            }
            let inv_z = w0 * t[0].inv_z + w1 * t[1].inv_z + w2 * t[2].inv_z;
            let k = py * tw + px;
            if inv_z > best[k] {
                best[k] = inv_z;
                from[k] = ((w0 * t[0].src_x + w1 * t[1].src_x + w2 * t[2].src_x) as f32, (w0 * t[0].src_y + w1 * t[1].src_y + w2 * t[2].src_y) as f32);
            }
        }
    }
}

/// Bilinear sample of the view at `vp` in `frame`, at view pixel coordinates `(x, y)` (pixel
/// centres at +0.5), clamped to the view.
fn sample(frame: &[u8], frame_width: u32, vp: nephele_wire::Viewport, x: f32, y: f32) -> [u8; 4] {
    let u = (x - 0.5).clamp(0.0, (vp.width - 1) as f32);
    let v = (y - 0.5).clamp(0.0, (vp.height - 1) as f32);
    let (u0, v0) = (u.floor() as u32, v.floor() as u32);
    let (u1, v1) = ((u0 + 1).min(vp.width - 1), (v0 + 1).min(vp.height - 1));
    let (fu, fv) = (u - u0 as f32, v - v0 as f32);
    let px = |uu: u32, vv: u32| {
        let at = 4 * ((vp.y + vv) as usize * frame_width as usize + (vp.x + uu) as usize);
        &frame[at..at + 4]
    };
    let (a, b, c, d) = (px(u0, v0), px(u1, v0), px(u0, v1), px(u1, v1));
    std::array::from_fn(|ch| {
        let top = f32::from(a[ch]) * (1.0 - fu) + f32::from(b[ch]) * fu;
        let bottom = f32::from(c[ch]) * (1.0 - fu) + f32::from(d[ch]) * fu;
        (top * (1.0 - fv) + bottom * fv).round() as u8
    })
}

/// The centre `display` pixels of a frame rendered with a guard band around them: the
/// picture a client without reprojection shows.
pub fn crop(frame: &[u8], frame_width: u32, frame_height: u32, display_width: u32, display_height: u32) -> Vec<u8> {
    let (ox, oy) = ((frame_width - display_width) / 2, (frame_height - display_height) / 2);
    let mut out = Vec::with_capacity(4 * (display_width * display_height) as usize);
    for y in 0..display_height {
        let at = 4 * (((oy + y) * frame_width + ox) as usize);
        out.extend_from_slice(&frame[at..at + 4 * display_width as usize]);
    }
    out
}

/// The intrinsics of a stream rendered with a guard band of `overscan` (a fraction of the
/// display's size on each side) around a display of `display` intrinsics: same focal length,
/// more pixels. Sizes stay even (the encoder's 4:2:0).
pub fn overscanned(display: &Intrinsics, overscan: f64) -> Intrinsics {
    let pad = |n: u32| 2 * ((f64::from(n) * overscan.clamp(0.0, 1.0) / 2.0).round() as u32);
    let (px, py) = (pad(display.width), pad(display.height));
    Intrinsics {
        width: display.width + 2 * px,
        height: display.height + 2 * py,
        cx: display.cx + px as f32,
        cy: display.cy + py as f32,
        ..*display
    }
}

/// A pose sample: a camera-to-world matrix at a time on the client's clock.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Sample {
    t_ms: f64,
    position: DVec3,
    rotation: DQuat,
}

/// Constant-velocity pose prediction with clamps (see the module notes).
#[derive(Debug, Clone, Default)]
pub struct PosePredictor {
    /// The last four samples, newest last.
    samples: Vec<Sample>,
    /// Jumps seen (the history was restarted).
    pub jumps: u64,
}

/// Linear and angular velocity between two samples: scene units/s, radians/s (world axes).
fn velocity(a: &Sample, b: &Sample) -> (DVec3, DVec3) {
    let dt = (b.t_ms - a.t_ms) / 1e3;
    let (axis, angle) = (b.rotation * a.rotation.inverse()).normalize().to_axis_angle();
    // The short way round.
    let angle = if angle > std::f64::consts::PI { angle - std::f64::consts::TAU } else { angle };
    ((b.position - a.position) / dt, axis * (angle / dt))
}

/// How far a motion goes in `h` seconds, from its speed at the last few times `(t s, speed)`,
/// newest last. Never faster than its speed now (a speed-up is not extrapolated: that would
/// overshoot the start of every stop), and not past where it stops if its speed keeps
/// changing as it did: the speed's rate `a` and, with three speeds, that rate's rate `j` (the
/// jerk: a minimum-jerk head turn starts braking with rising deceleration, and constant
/// deceleration alone would still overshoot its stop by half the turn) extrapolate
/// `v(t) = v + a t + j t² / 2`, integrated until it reaches zero or `h`.
fn reach(speeds: &[(f64, f64)], h: f64) -> f64 {
    let Some(&(t_now, v)) = speeds.last() else { return 0.0 };
    let n = speeds.len();
    let rate = |k: usize| (speeds[k].1 - speeds[k - 1].1) / (speeds[k].0 - speeds[k - 1].0).max(1e-6);
    let a = if n >= 2 { rate(n - 1) } else { 0.0 };
    let j = if n >= 3 { (rate(n - 1) - rate(n - 2)) / ((speeds[n - 1].0 - speeds[n - 3].0) / 2.0).max(1e-6) } else { 0.0 };
    // From the newest speed's time (the middle of the last gap) to the horizon after the
    // last sample: half a gap more.
    let gap = if n >= 2 { t_now - speeds[n - 2].0 } else { 0.0 };
    // `a` is the rate half a gap before the newest speed: carried to it by `j`.
    let a = a + j * gap / 2.0;
    let (steps, end) = (64, h + gap / 2.0);
    let dt = end / f64::from(steps);
    let mut travelled = 0.0;
    for k in 0..steps {
        let t = (f64::from(k) + 0.5) * dt;
        let speed = (v + a * t + 0.5 * j * t * t).min(v);
        if speed <= 0.0 {
            break;
        }
        // The half gap before the last sample is already behind us.
        let counted = (t + dt / 2.0).min(end) - (t - dt / 2.0).max(gap / 2.0);
        travelled += speed * counted.max(0.0);
    }
    travelled.min(v * h)
}

impl PosePredictor {
    pub fn new() -> Self {
        Self::default()
    }

    /// Records the camera at `t_ms`. A non-finite or non-rigid matrix, or a time not after
    /// the last, is ignored; a jump (faster than [`JUMP_TURN_DEG_PER_S`] or
    /// [`JUMP_SPEED_PER_S`]) or a gap over [`MAX_SAMPLE_GAP_MS`] starts the history again.
    pub fn observe(&mut self, t_ms: f64, world_from_camera: DMat4) {
        if !t_ms.is_finite() || !world_from_camera.is_finite() {
            return;
        }
        let r = DMat3::from_mat4(world_from_camera);
        if nephele_renderer::camera::rotation_deviation(&r) > 1e-3 || r.determinant() <= 0.0 {
            return;
        }
        let s = Sample { t_ms, position: world_from_camera.w_axis.truncate(), rotation: DQuat::from_mat3(&r).normalize() };
        if let Some(last) = self.samples.last() {
            if t_ms <= last.t_ms {
                return;
            }
            let (v, w) = velocity(last, &s);
            if t_ms - last.t_ms > MAX_SAMPLE_GAP_MS {
                self.samples.clear();
            } else if w.length().to_degrees() > JUMP_TURN_DEG_PER_S || v.length() > JUMP_SPEED_PER_S {
                self.samples.clear();
                self.jumps += 1;
            }
        }
        self.samples.push(s);
        if self.samples.len() > 4 {
            self.samples.remove(0);
        }
    }

    /// The camera expected `horizon_ms` after the last sample (clamped to 0..=
    /// [`MAX_HORIZON_MS`]); the last sample itself when there is no velocity yet. `None`
    /// before any sample.
    pub fn predict(&self, horizon_ms: f64) -> Option<DMat4> {
        let last = *self.samples.last()?;
        let h = if horizon_ms.is_finite() { horizon_ms.clamp(0.0, MAX_HORIZON_MS) / 1e3 } else { 0.0 };
        let n = self.samples.len();
        if n < 2 || h == 0.0 {
            return Some(DMat4::from_rotation_translation(last.rotation, last.position));
        }
        // Speeds (linear, angular) at the midpoints of the last three sample gaps, newest
        // last: the last gives the direction and speed, the others the speed's change.
        let speeds: Vec<(f64, f64, f64)> = self.samples.windows(2).map(|p| {
            let (v, w) = velocity(&p[0], &p[1]);
            ((p[0].t_ms + p[1].t_ms) / 2e3, v.length(), w.length())
        }).collect();
        let (v, w) = velocity(&self.samples[n - 2], &last);
        let linear: Vec<(f64, f64)> = speeds.iter().map(|s| (s.0, s.1)).collect();
        let angular: Vec<(f64, f64)> = speeds.iter().map(|s| (s.0, s.2)).collect();
        let turn = reach(&angular, h).min(MAX_PREDICTED_TURN_DEG.to_radians());
        let travel = reach(&linear, h);
        let rotation = if w.length() > 1e-12 { DQuat::from_axis_angle(w.normalize(), turn) * last.rotation } else { last.rotation };
        let position = if v.length() > 1e-12 { last.position + v.normalize() * travel } else { last.position };
        Some(DMat4::from_rotation_translation(rotation.normalize(), position))
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use nephele_renderer::{
        Backend, Instance, RenderSettings, ViewRequest,
        fast::FastCpuBackend,
        procedural::{ProceduralConfig, Scene, generate},
        render::psnr_rgb,
    };
    use nephele_wire::{Viewport, depth::DepthFrame};

    use super::*;

    /// The procedural checkered box, prepared for the fast CPU renderer.
    fn diffuse() -> Box<dyn nephele_renderer::PreparedAsset> {
        FastCpuBackend.prepare(Arc::new(generate(&ProceduralConfig::small(Scene::Diffuse)).unwrap())).unwrap()
    }

    fn render(prepared: &dyn nephele_renderer::PreparedAsset, view: View) -> nephele_renderer::Frame {
        let req = ViewRequest { view, instance: Instance::default(), background: glam::Vec3::ONE };
        prepared.render(&[req], &RenderSettings::default()).unwrap().frames.remove(0)
    }

    /// Mean squared error over the pixels `keep` says, as PSNR.
    fn psnr_where(a: &[u8], b: &[u8], keep: impl Fn(usize) -> bool) -> f64 {
        let (mut se, mut n) = (0.0, 0usize);
        for (k, (pa, pb)) in a.chunks_exact(4).zip(b.chunks_exact(4)).enumerate() {
            if keep(k) {
                for c in 0..3 {
                    se += (f64::from(pa[c]) - f64::from(pb[c])).powi(2);
                }
                n += 3;
            }
        }
        10.0 * (255.0f64.powi(2) / (se / n as f64).max(1e-12)).log10()
    }

    #[test]
    fn a_warp_to_the_same_camera_is_the_picture_itself() {
        let prepared = diffuse();
        let view = View::orbit(DVec3::ZERO, 3.0, 30.0, 20.0, Intrinsics::from_fov_x(160, 120, 0.9));
        let f = render(prepared.as_ref(), view);
        let grid = DepthView::build(&view, Viewport::full(160, 120), &[&f.depth], 160, 120, 8, nephele_wire::depth::DEPTH_LEVELS);
        let warped = warp(&f.rgba, 160, &grid, &grid.view(), [255, 255, 255]).unwrap();
        assert_eq!(psnr_rgb(&warped, &f.rgba), f64::INFINITY);
        // Depth whose viewport lies outside the picture is not used.
        let mut stray = grid.clone();
        stray.viewport.x = 8;
        assert!(warp(&f.rgba, 160, &stray, &grid.view(), [255, 255, 255]).is_none());
        assert!(warp(&f.rgba[..4 * 160 * 100], 160, &grid, &grid.view(), [255, 255, 255]).is_none());
    }

    /// The warp of a pure rotation equals a direct render at the turned camera away from the
    /// edges the turn reveals: a rotation needs no depth, so only resampling differs.
    #[test]
    fn a_turned_camera_is_reprojected_within_tolerance() {
        let prepared = diffuse();
        let k = Intrinsics::from_fov_x(160, 120, 0.9);
        let view = View::orbit(DVec3::ZERO, 3.0, 30.0, 20.0, k);
        let turned = View { world_from_camera: view.world_from_camera * DMat4::from_rotation_y(4f64.to_radians()) * DMat4::from_rotation_x(2f64.to_radians()), ..view };
        let (f, direct) = (render(prepared.as_ref(), view), render(prepared.as_ref(), turned));
        let grid = DepthView::build(&view, Viewport::full(160, 120), &[&f.depth], 160, 120, 8, nephele_wire::depth::DEPTH_LEVELS);
        let bytes = DepthFrame { frame: 1, pose_seq: 1, rtp_ticks: 0, views: vec![grid] }.encode();
        let grid = DepthFrame::decode(&bytes).unwrap().views.remove(0);
        let warped = warp(&f.rgba, 160, &grid, &turned, [255, 255, 255]).unwrap();
        // 4° is ~12 px at this focal length: leave 16 px at each edge.
        let inner = |k: usize| (16..144).contains(&(k % 160)) && (16..104).contains(&(k / 160));
        let warp_db = psnr_where(&warped, &direct.rgba, inner);
        let stale_db = psnr_where(&f.rgba, &direct.rgba, inner);
        eprintln!("turned camera: warp {warp_db:.2} dB, stale {stale_db:.2} dB");
        assert!(warp_db > 30.0, "warp {warp_db:.2} dB (stale {stale_db:.2} dB)");
        assert!(warp_db > stale_db + 10.0, "warp {warp_db:.2} dB, stale {stale_db:.2} dB");
    }

    /// A moved camera (translation too) needs the depth: the warp must beat the stale frame.
    #[test]
    fn a_moved_camera_is_reprojected_by_its_depth() {
        let prepared = diffuse();
        let k = Intrinsics::from_fov_x(160, 120, 0.9);
        let view = View::orbit(DVec3::ZERO, 3.0, 30.0, 20.0, k);
        let moved = View::orbit(DVec3::ZERO, 2.9, 34.0, 22.0, k);
        let (f, direct) = (render(prepared.as_ref(), view), render(prepared.as_ref(), moved));
        let grid = DepthView::build(&view, Viewport::full(160, 120), &[&f.depth], 160, 120, 8, nephele_wire::depth::DEPTH_LEVELS);
        let warped = warp(&f.rgba, 160, &grid, &moved, [255, 255, 255]).unwrap();
        let (warp_db, stale_db) = (psnr_rgb(&warped, &direct.rgba), psnr_rgb(&f.rgba, &direct.rgba));
        if let Ok(dir) = std::env::var("NEPHELE_GLASS_DUMP") {
            for (name, px) in [("src", &f.rgba), ("warped", &warped), ("direct", &direct.rgba)] {
                nephele_renderer::Frame { width: 160, height: 120, rgba: px.clone(), depth: vec![] }.save_png(&std::path::Path::new(&dir).join(format!("{name}.png"))).unwrap();
            }
        }
        eprintln!("moved camera: warp {warp_db:.2} dB, stale {stale_db:.2} dB");
        assert!(warp_db > stale_db + 6.0 && warp_db > 25.0, "warp {warp_db:.2} dB, stale {stale_db:.2} dB");
    }

    #[test]
    fn a_guard_band_crops_back_to_the_display() {
        let k = Intrinsics::from_fov_x(160, 120, 0.9);
        let o = overscanned(&k, 0.1);
        assert_eq!((o.width, o.height, o.fx), (192, 144, k.fx));
        assert_eq!((o.cx - k.cx, o.cy - k.cy), (16.0, 12.0));
        let frame: Vec<u8> = (0..192 * 144).flat_map(|i| [(i % 192) as u8, (i / 192) as u8, 0, 255]).collect();
        let c = crop(&frame, 192, 144, 160, 120);
        assert_eq!(&c[0..4], &[16, 12, 0, 255]);
    }

    fn turning(t_ms: f64, deg_per_s: f64, speed: f64) -> DMat4 {
        let t = t_ms / 1e3;
        DMat4::from_translation(DVec3::new(speed * t, 0.0, 1.0)) * DMat4::from_rotation_z((deg_per_s * t).to_radians()) * DMat4::from_rotation_x(0.3)
    }

    #[test]
    fn constant_velocity_is_predicted_exactly() {
        let mut p = PosePredictor::new();
        for i in 0..10 {
            p.observe(f64::from(i) * 20.0, turning(f64::from(i) * 20.0, 200.0, 0.5));
        }
        let predicted = p.predict(100.0).unwrap();
        let truth = turning(280.0, 200.0, 0.5);
        let err = (predicted - truth).to_cols_array().iter().map(|x| x.abs()).fold(0.0, f64::max);
        assert!(err < 1e-9, "{err}");
    }

    fn near(a: DMat4, b: DMat4) -> bool {
        (a - b).to_cols_array().iter().all(|x| x.abs() < 1e-9)
    }

    /// A minimum-jerk head turn (30° in 250 ms, 225 °/s peak) sampled every 20 ms and
    /// predicted 130 ms ahead: never past where it stops once it brakes (before its peak
    /// speed the stop cannot be seen: 4.3° over there, measured), and much nearer than the
    /// stale pose.
    #[test]
    fn a_head_turn_is_not_overshot() {
        let yaw = |t: f64| {
            let tau = (t / 0.25).clamp(0.0, 1.0);
            30.0 * tau * tau * tau * (10.0 - 15.0 * tau + 6.0 * tau * tau)
        };
        let mut p = PosePredictor::new();
        let (mut worst_over, mut err_sum, mut stale_sum) = (0.0f64, 0.0, 0.0);
        for i in 0..25 {
            let t = f64::from(i) * 0.02;
            p.observe(t * 1e3, DMat4::from_rotation_z(yaw(t).to_radians()));
            let predicted = p.predict(130.0).unwrap();
            let angle = DQuat::from_mat4(&predicted).to_axis_angle();
            let predicted_yaw = (angle.0.z.signum() * angle.1).to_degrees();
            // Once it brakes (after the peak at 125 ms), never past the stop; before, the stop
            // cannot be seen yet: a little, at most.
            let over = predicted_yaw - 30.0;
            worst_over = worst_over.max(if t > 0.13 { over } else { over - 4.5 });
            err_sum += (predicted_yaw - yaw(t + 0.13)).abs();
            stale_sum += (yaw(t) - yaw(t + 0.13)).abs();
        }
        assert!(worst_over < 1e-6, "overshoots the stop by {worst_over:.2}° (4.5° allowed before the peak)");
        assert!(err_sum < 0.5 * stale_sum, "mean error {:.2}° against stale {:.2}°", err_sum / 25.0, stale_sum / 25.0);
    }

    #[test]
    fn predictions_stop_where_the_motion_stops_and_never_cross_a_jump() {
        // Slowing down: 200 °/s over the first gap, 100 °/s over the second (their middles 20 ms
        // apart) is 5000 °/s²: 50 °/s at the last sample, stopping 0.25° further on; a 100 ms
        // constant-velocity guess would say 10°.
        let mut p = PosePredictor::new();
        let angle = |a: f64| DMat4::from_rotation_z(a.to_radians());
        p.observe(0.0, angle(0.0));
        p.observe(20.0, angle(4.0));
        p.observe(40.0, angle(6.0));
        let r = p.predict(100.0).unwrap();
        let turned = DQuat::from_mat4(&r).angle_between(DQuat::from_rotation_z(6f64.to_radians())).to_degrees();
        assert!((turned - 0.25).abs() < 0.01, "{turned}");
        // One sample: no velocity; NaN: ignored; a jump restarts.
        let mut p = PosePredictor::new();
        assert!(p.predict(50.0).is_none());
        p.observe(0.0, angle(10.0));
        assert!(near(p.predict(50.0).unwrap(), angle(10.0)));
        p.observe(20.0, DMat4::from_cols_array(&[f64::NAN; 16]));
        p.observe(f64::NAN, angle(11.0));
        assert!(near(p.predict(50.0).unwrap(), angle(10.0)));
        p.observe(20.0, angle(90.0)); // 4000 °/s: a teleport
        assert_eq!(p.jumps, 1);
        assert!(near(p.predict(50.0).unwrap(), angle(90.0)));
        // Horizons are clamped; NaN horizons predict nothing.
        p.observe(40.0, angle(92.0));
        let far = p.predict(1e9).unwrap();
        let at_max = p.predict(MAX_HORIZON_MS).unwrap();
        assert_eq!(far, at_max);
        assert!(near(p.predict(f64::NAN).unwrap(), angle(92.0)));
    }
}
