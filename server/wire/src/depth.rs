//! Depth with every frame (docs/architecture.md §5 "Depth"): for each view of an encoded
//! frame, the camera it was rendered with and a coarse grid of its depth, so a client can
//! reproject the picture to where the eye is when it is shown.
//!
//! The grid has a vertex every `stride` pixels of the view (pixel-corner coordinates
//! `0, s, 2s, …, w`) holding a camera-space depth `z` (distance along the view axis, scene
//! units): inside a surface (the four pixels at the vertex's corner all hit) the nearest of
//! those four, exact to half a pixel; elsewhere the **nearest** `z` of the pixels whose centres
//! lie within one stride of it, or "background" when none of them hit anything. The
//! nearest-of-the-neighbourhood rule at edges makes every grid cell that touches the object
//! move with the object's front; the only cells that stretch in a warp hold background pixels
//! (docs/architecture.md §5 "Reprojection").
//!
//! Depth is coded as inverse depth in `L` levels (10 bits, [`DEPTH_LEVELS`], by default),
//! linear between the view's own nearest and farthest vertex: code 0 is background, codes
//! 1..=L map `1/far ..= 1/near`. The quantisation error of a depth `z` is at most
//! `z² · (1/near − 1/far) / (2(L − 1))`: for lego at distance 4 (near 3, far 5) and 10 bits,
//! 0.0011 scene units; a warp moves a point by `f · t / z` pixels for a camera move `t`, so
//! that error shifts it by `f · t · δz / z²` — 0.002 px for a 10 cm step at f = 330 px.
//! Each view's codes go as a bit mask of the object vertices (row-major, least significant
//! bit first), then the object vertices' residuals row by row against the MED predictor of
//! LOCO-I (Weinberger et al., 2000: left, up, up-left; where a neighbour is background, the
//! left or upper one alone, else the previous code), zig-zag and LEB128 coded; all views'
//! streams together through raw deflate (RFC 1951, which browsers inflate with
//! `DecompressionStream("deflate-raw")`). Keeping background out of the prediction keeps the
//! object's edge from costing a jump of its whole depth twice per row.
//!
//! Master → client, one binary message on the pose channel after the frame's info, little
//! endian:
//!
//! | bytes       | field                                                              |
//! |-------------|--------------------------------------------------------------------|
//! | 0..4        | ASCII `NDP1`                                                       |
//! | 4..12       | `u64` frame number (as in the frame info)                          |
//! | 12..16      | `u32` pose sequence the frame answers                              |
//! | 16..20      | `u32` RTP ticks of the frame (as in the frame info)                |
//! | 20..24      | `u32` view count n, 1..=[`MAX_QUILT_VIEWS`]                        |
//! | per view    | `f32`×16 world_from_camera (column-major, OpenGL camera); `f32`×4 fx, fy, cx, cy (pixels, at the viewport's size); `u32`×4 viewport x, y, width, height (frame pixels); `u16` stride (pixels), `u16` levels L; `f32` near, far (scene units; 0, 0 when the view is all background) — 108 bytes |
//! | rest        | raw deflate of, view after view, the mask of its `(⌈w/s⌉+1)·(⌈h/s⌉+1)` vertices and the residuals of its object vertices |

use std::io::{Read, Write};

use glam::{DVec3, Mat4};
use nephele_limits::{MAX_DEPTH_STRIDE_PX, MAX_DEPTH_VERTICES, MAX_QUILT_VIEWS, DEPTH_STRIDE_PX};
use nephele_renderer::{Intrinsics, View};

use crate::Viewport;

/// Magic and version of a depth message.
pub const DEPTH_MAGIC: &[u8; 4] = b"NDP1";
const HEADER_LEN: usize = 24;
const VIEW_LEN: usize = 108;
/// Depth levels a view is coded with by default: 10 bits of inverse depth (see the module
/// notes for the error this gives).
pub const DEPTH_LEVELS: u16 = 1023;

/// One view's depth grid and the camera it was rendered with.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthView {
    pub world_from_camera: Mat4,
    /// At the viewport's size.
    pub intrinsics: Intrinsics,
    pub viewport: Viewport,
    /// Pixels between grid vertices.
    pub stride_px: u32,
    /// Codes run 1..=levels from the farthest vertex to the nearest.
    pub levels: u16,
    /// Nearest and farthest vertex depth, scene units along the view axis.
    pub near: f32,
    pub far: f32,
    /// `cols × rows` codes, row-major from the top-left: 0 background, else inverse depth.
    pub codes: Vec<u16>,
}

/// The depth of every view of one encoded frame.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthFrame {
    pub frame: u64,
    pub pose_seq: u32,
    pub rtp_ticks: u32,
    pub views: Vec<DepthView>,
}

/// Why a depth message was refused; the client then shows the frame unwarped.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DepthError {
    #[error("depth message is {len} bytes, shorter than its header")]
    Short { len: usize },
    #[error("depth message does not start with \"NDP1\"")]
    Magic,
    #[error("depth message has {count} views; 1..={MAX_QUILT_VIEWS} are allowed")]
    ViewCount { count: u32 },
    #[error("depth view {index}: {why}")]
    View { index: usize, why: String },
    #[error("depth message has {vertices} grid vertices; at most {MAX_DEPTH_VERTICES}")]
    TooManyVertices { vertices: usize },
    #[error("depth codes: {0}")]
    Codes(String),
}

/// Grid vertices across and down a `width`×`height` view at `stride` pixels.
pub fn grid_size(width: u32, height: u32, stride: u32) -> (usize, usize) {
    (width.div_ceil(stride) as usize + 1, height.div_ceil(stride) as usize + 1)
}

/// The grid step for a frame of these views: [`DEPTH_STRIDE_PX`], doubled until all
/// views together have at most [`MAX_DEPTH_VERTICES`] vertices.
pub fn stride_for(viewports: &[Viewport]) -> u32 {
    let mut stride = DEPTH_STRIDE_PX;
    while stride < MAX_DEPTH_STRIDE_PX
        && viewports.iter().map(|v| grid_size(v.width, v.height, stride)).map(|(c, r)| c * r).sum::<usize>() > MAX_DEPTH_VERTICES
    {
        stride *= 2;
    }
    stride
}

impl DepthView {
    /// Builds a view's grid from its rendered depth: `layers` are the per-object ray
    /// distances (scene units; ∞, NaN or ≤ 0 is no hit) of one render of `width`×`height`
    /// pixels, which may be smaller than the viewport (a render scale below 1); several
    /// layers (a composed scene) count their nearest hit.
    pub fn build(camera: &View, viewport: Viewport, layers: &[&[f32]], width: u32, height: u32, stride_px: u32, levels: u16) -> Self {
        let levels = levels.max(1);
        let k = camera.intrinsics;
        let (vw, vh) = (viewport.width, viewport.height);
        let (cols, rows) = grid_size(vw, vh, stride_px);
        // z of every render pixel (∞: no hit), and the nearest z per grid cell (every render
        // pixel falls in the cell under its centre).
        let (cells_x, cells_y) = (cols - 1, rows - 1);
        let mut pixel_z = vec![f64::INFINITY; (width * height) as usize];
        let mut cell_z = vec![f64::INFINITY; cells_x * cells_y];
        let (sx, sy) = (f64::from(vw) / f64::from(width.max(1)), f64::from(vh) / f64::from(height.max(1)));
        for y in 0..height as usize {
            let yv = (y as f64 + 0.5) * sy;
            let cy = ((yv / f64::from(stride_px)) as usize).min(cells_y - 1);
            let ny = (yv - f64::from(k.cy)) / f64::from(k.fy);
            for x in 0..width as usize {
                let i = y * width as usize + x;
                let t = layers.iter().filter_map(|l| l.get(i).copied()).filter(|t| t.is_finite() && *t > 0.0).fold(f32::INFINITY, f32::min);
                if !t.is_finite() {
                    continue;
                }
                let xv = (x as f64 + 0.5) * sx;
                let nx = (xv - f64::from(k.cx)) / f64::from(k.fx);
                // The ray's length per unit of view-axis depth is |(nx, ny, 1)|.
                let z = f64::from(t) / (nx * nx + ny * ny + 1.0).sqrt();
                pixel_z[i] = z;
                let cx = ((xv / f64::from(stride_px)) as usize).min(cells_x - 1);
                let c = &mut cell_z[cy * cells_x + cx];
                *c = c.min(z);
            }
        }
        // A vertex inside a surface (the four pixels at its corner all hit) takes their
        // nearest z: exact to half a pixel. Elsewhere — an edge — it takes the nearest of the
        // (up to four) cells around it, so the object's edge moves with the object.
        let (w, h) = (width as usize, height as usize);
        let mut z = vec![f64::INFINITY; cols * rows];
        for j in 0..rows {
            for i in 0..cols {
                let (xr, yr) = (f64::from((i as u32 * stride_px).min(vw)) / sx, f64::from((j as u32 * stride_px).min(vh)) / sy);
                let (x1, y1) = ((xr.round() as usize).clamp(1, w.max(2) - 1), (yr.round() as usize).clamp(1, h.max(2) - 1));
                let corner = if w >= 2 && h >= 2 {
                    [(x1 - 1, y1 - 1), (x1, y1 - 1), (x1 - 1, y1), (x1, y1)].iter().map(|&(x, y)| pixel_z[y * w + x]).fold(f64::NEG_INFINITY, f64::max)
                } else {
                    f64::INFINITY
                };
                z[j * cols + i] = if corner.is_finite() {
                    [(x1 - 1, y1 - 1), (x1, y1 - 1), (x1 - 1, y1), (x1, y1)].iter().map(|&(x, y)| pixel_z[y * w + x]).fold(f64::INFINITY, f64::min)
                } else {
                    let mut best = f64::INFINITY;
                    for cj in j.saturating_sub(1)..=j.min(cells_y - 1) {
                        for ci in i.saturating_sub(1)..=i.min(cells_x - 1) {
                            best = best.min(cell_z[cj * cells_x + ci]);
                        }
                    }
                    best
                };
            }
        }
        let hits = z.iter().copied().filter(|z| z.is_finite());
        let (near, far) = hits.fold((f64::INFINITY, 0.0f64), |(n, f), z| (n.min(z), f.max(z)));
        let (near, far) = if near.is_finite() { (near as f32, far as f32) } else { (0.0, 0.0) };
        let codes = z.iter().map(|&z| if z.is_finite() { encode_z(z, near, far, levels) } else { 0 }).collect();
        Self { world_from_camera: camera.world_from_camera.as_mat4(), intrinsics: k, viewport, stride_px, levels, near, far, codes }
    }

    /// `(cols, rows)` of the grid.
    pub fn grid(&self) -> (usize, usize) {
        grid_size(self.viewport.width, self.viewport.height, self.stride_px)
    }

    /// Depth along the view axis at vertex `(i, j)`, scene units; `None` for background.
    pub fn z_at(&self, i: usize, j: usize) -> Option<f32> {
        let (cols, _) = self.grid();
        decode_z(self.codes[j * cols + i], self.near, self.far, self.levels)
    }

    /// Where vertex `(i, j)` sits in the view, pixels (corner coordinates).
    pub fn vertex_px(&self, i: usize, j: usize) -> (f32, f32) {
        ((i as u32 * self.stride_px).min(self.viewport.width) as f32, (j as u32 * self.stride_px).min(self.viewport.height) as f32)
    }

    /// The view's camera as a [`View`] (f32 as sent).
    pub fn view(&self) -> View {
        View { world_from_camera: self.world_from_camera.as_dmat4(), intrinsics: self.intrinsics }
    }

    /// The largest depth error the 16-bit coding may add at depth `z`, scene units.
    pub fn max_coding_error(&self, z: f32) -> f32 {
        if self.far <= self.near { 0.0 } else { z * z * (1.0 / self.near - 1.0 / self.far) / (2.0 * (f32::from(self.levels) - 1.0).max(1.0)) }
    }

    /// A world-space point of vertex `(i, j)`, or `None` for background.
    pub fn world_point(&self, i: usize, j: usize) -> Option<DVec3> {
        let z = f64::from(self.z_at(i, j)?);
        let (x, y) = self.vertex_px(i, j);
        let k = &self.intrinsics;
        let p = DVec3::new((f64::from(x) - f64::from(k.cx)) / f64::from(k.fx) * z, -(f64::from(y) - f64::from(k.cy)) / f64::from(k.fy) * z, -z);
        Some(self.world_from_camera.as_dmat4().transform_point3(p))
    }
}

fn encode_z(z: f64, near: f32, far: f32, levels: u16) -> u16 {
    let (inv_near, inv_far) = (1.0 / f64::from(near), 1.0 / f64::from(far));
    if inv_near <= inv_far || levels == 1 {
        return levels;
    }
    let s = ((1.0 / z - inv_far) / (inv_near - inv_far)).clamp(0.0, 1.0);
    (1.0 + (s * f64::from(levels - 1)).round()) as u16
}

fn decode_z(code: u16, near: f32, far: f32, levels: u16) -> Option<f32> {
    if code == 0 {
        return None;
    }
    let (inv_near, inv_far) = (1.0 / f64::from(near), 1.0 / f64::from(far));
    if inv_near <= inv_far || levels == 1 {
        return Some(near);
    }
    let s = f64::from(code - 1) / f64::from(levels - 1);
    Some((1.0 / (inv_far + s * (inv_near - inv_far))) as f32)
}

/// LOCO-I's median edge detector: the prediction of a code from its left `a`, upper `b` and
/// upper-left `c` neighbours.
fn med(a: i32, b: i32, c: i32) -> i32 {
    if c >= a.max(b) {
        a.min(b)
    } else if c <= a.min(b) {
        a.max(b)
    } else {
        a + b - c
    }
}

/// The prediction of the object code at `at` from the codes before it (0 is background,
/// which predicts nothing): MED when the left, upper and upper-left vertices are all object,
/// else the left one, else the upper one, else `last`, the previous object code in scan order.
fn predicted(codes: &[u16], cols: usize, at: usize, last: u16) -> i32 {
    let (i, j) = (at % cols, at / cols);
    let known = |ok: bool, k: usize| if ok && codes[k] != 0 { Some(i32::from(codes[k])) } else { None };
    let a = known(i > 0, at.wrapping_sub(1));
    let b = known(j > 0, at.wrapping_sub(cols));
    let c = known(i > 0 && j > 0, at.wrapping_sub(cols + 1));
    match (a, b, c) {
        (Some(a), Some(b), Some(c)) => med(a, b, c),
        (Some(a), _, _) => a,
        (None, Some(b), _) => b,
        _ => i32::from(last),
    }
}

/// Stamps an encoded depth message with its frame's RTP ticks (known only when the frame is
/// handed to the track).
pub fn set_rtp_ticks(message: &mut [u8], rtp_ticks: u32) {
    if message.len() >= HEADER_LEN {
        message[16..20].copy_from_slice(&rtp_ticks.to_le_bytes());
    }
}

impl DepthFrame {
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER_LEN + VIEW_LEN * self.views.len() + 1024);
        out.extend_from_slice(DEPTH_MAGIC);
        out.extend_from_slice(&self.frame.to_le_bytes());
        for v in [self.pose_seq, self.rtp_ticks, self.views.len() as u32] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        let mut residuals = Vec::new();
        for v in &self.views {
            let k = &v.intrinsics;
            for x in v.world_from_camera.to_cols_array().into_iter().chain([k.fx, k.fy, k.cx, k.cy]) {
                out.extend_from_slice(&x.to_le_bytes());
            }
            for x in [v.viewport.x, v.viewport.y, v.viewport.width, v.viewport.height] {
                out.extend_from_slice(&x.to_le_bytes());
            }
            out.extend_from_slice(&(v.stride_px as u16).to_le_bytes());
            out.extend_from_slice(&v.levels.to_le_bytes());
            out.extend_from_slice(&v.near.to_le_bytes());
            out.extend_from_slice(&v.far.to_le_bytes());
            let (cols, _) = v.grid();
            // Which vertices are object, a bit each (row-major, least significant first) …
            let mut mask = vec![0u8; v.codes.len().div_ceil(8)];
            for (at, &code) in v.codes.iter().enumerate() {
                mask[at / 8] |= u8::from(code != 0) << (at % 8);
            }
            residuals.extend_from_slice(&mask);
            // … then the object vertices' residuals.
            let mut last = 0u16;
            for (at, &code) in v.codes.iter().enumerate().filter(|(_, c)| **c != 0) {
                // Residuals are taken modulo 2¹⁶ and zig-zagged: small either way.
                let r = (i32::from(code) - predicted(&v.codes, cols, at, last)) as i16;
                last = code;
                let mut z = ((r << 1) ^ (r >> 15)) as u16 as u32;
                while z >= 0x80 {
                    residuals.push((z as u8 & 0x7f) | 0x80);
                    z >>= 7;
                }
                residuals.push(z as u8);
            }
        }
        let mut deflate = flate2::write::DeflateEncoder::new(out, flate2::Compression::new(6));
        deflate.write_all(&residuals).expect("writing to a Vec cannot fail");
        deflate.finish().expect("writing to a Vec cannot fail")
    }

    /// Parses and checks a depth message: sizes against the limits, cameras finite, depth
    /// ranges positive and finite, exactly the codes the grids need.
    pub fn decode(bytes: &[u8]) -> Result<Self, DepthError> {
        if bytes.len() < HEADER_LEN {
            return Err(DepthError::Short { len: bytes.len() });
        }
        if &bytes[0..4] != DEPTH_MAGIC {
            return Err(DepthError::Magic);
        }
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let f32_at = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let count = u32_at(20);
        if count == 0 || count > MAX_QUILT_VIEWS {
            return Err(DepthError::ViewCount { count });
        }
        let n = count as usize;
        let body = HEADER_LEN + VIEW_LEN * n;
        if bytes.len() < body {
            return Err(DepthError::Short { len: bytes.len() });
        }
        let mut views = Vec::with_capacity(n);
        let mut vertices = 0usize;
        for index in 0..n {
            let o = HEADER_LEN + VIEW_LEN * index;
            let bad = |why: String| DepthError::View { index, why };
            let world_from_camera = Mat4::from_cols_array(&std::array::from_fn(|i| f32_at(o + 4 * i)));
            let (fx, fy, cx, cy) = (f32_at(o + 64), f32_at(o + 68), f32_at(o + 72), f32_at(o + 76));
            let viewport = Viewport { x: u32_at(o + 80), y: u32_at(o + 84), width: u32_at(o + 88), height: u32_at(o + 92) };
            let u16_at = |o: usize| u16::from_le_bytes(bytes[o..o + 2].try_into().expect("2 bytes"));
            let (stride_px, levels) = (u32::from(u16_at(o + 96)), u16_at(o + 98));
            if levels == 0 {
                return Err(bad("0 depth levels".into()));
            }
            let (near, far) = (f32_at(o + 100), f32_at(o + 104));
            if !world_from_camera.is_finite() || ![fx, fy, cx, cy].iter().all(|v| v.is_finite()) || fx <= 0.0 || fy <= 0.0 {
                return Err(bad("camera is not finite or its focal length is not positive".into()));
            }
            if viewport.width == 0 || viewport.height == 0 || viewport.width > nephele_limits::MAX_RENDER_EDGE_PX || viewport.height > nephele_limits::MAX_RENDER_EDGE_PX {
                return Err(bad(format!("viewport {}x{} is empty or too large", viewport.width, viewport.height)));
            }
            if !(1..=MAX_DEPTH_STRIDE_PX).contains(&stride_px) {
                return Err(bad(format!("stride {stride_px} is outside 1..={MAX_DEPTH_STRIDE_PX}")));
            }
            let all_background = near == 0.0 && far == 0.0;
            if !all_background && !(near.is_finite() && far.is_finite() && near > 0.0 && far >= near) {
                return Err(bad(format!("depth range {near}..{far} is not 0 < near ≤ far, finite")));
            }
            let (cols, rows) = grid_size(viewport.width, viewport.height, stride_px);
            vertices += cols * rows;
            if vertices > MAX_DEPTH_VERTICES {
                return Err(DepthError::TooManyVertices { vertices });
            }
            let intrinsics = Intrinsics { fx, fy, cx, cy, width: viewport.width, height: viewport.height };
            views.push(DepthView { world_from_camera, intrinsics, viewport, stride_px, levels, near, far, codes: Vec::new() });
        }
        // A mask byte per 8 vertices and at most 3 bytes a residual: a longer stream is refused
        // before it is inflated.
        let mut residuals = Vec::new();
        flate2::read::DeflateDecoder::new(&bytes[body..])
            .take(4 * vertices as u64 + n as u64 + 1)
            .read_to_end(&mut residuals)
            .map_err(|e| DepthError::Codes(format!("cannot inflate: {e}")))?;
        let mut at = 0usize;
        for (index, v) in views.iter_mut().enumerate() {
            let (cols, rows) = v.grid();
            let count = cols * rows;
            let Some(mask) = residuals.get(at..at + count.div_ceil(8)) else { return Err(DepthError::Codes(format!("view {index} ends in its mask"))) };
            let object: Vec<bool> = (0..count).map(|k| mask[k / 8] >> (k % 8) & 1 == 1).collect();
            at += count.div_ceil(8);
            if v.near == 0.0 && object.iter().any(|&o| o) {
                return Err(DepthError::Codes(format!("view {index} is all background yet has a depth code")));
            }
            v.codes.reserve(count);
            let mut last = 0u16;
            for (k, &is_object) in object.iter().enumerate() {
                if !is_object {
                    v.codes.push(0);
                    continue;
                }
                let mut z = 0u32;
                let mut shift = 0;
                loop {
                    let Some(&b) = residuals.get(at) else { return Err(DepthError::Codes(format!("view {index} ends after {k} of {} codes", cols * rows))) };
                    at += 1;
                    z |= u32::from(b & 0x7f) << shift;
                    if b & 0x80 == 0 {
                        break;
                    }
                    shift += 7;
                    if shift > 14 {
                        return Err(DepthError::Codes("a residual is longer than 16 bits".into()));
                    }
                }
                let r = ((z >> 1) as i32) ^ -((z & 1) as i32);
                let code = (predicted(&v.codes, cols, k, last) + r) as u16;
                if code == 0 || code > v.levels {
                    return Err(DepthError::Codes(format!("view {index} has code {code} outside its 1..={} levels", v.levels)));
                }
                last = code;
                v.codes.push(code);
            }
        }
        if at != residuals.len() {
            return Err(DepthError::Codes(format!("{} bytes after the last code", residuals.len() - at)));
        }
        Ok(Self { frame: u64::from_le_bytes(bytes[4..12].try_into().expect("8 bytes")), pose_seq: u32_at(12), rtp_ticks: u32_at(16), views })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sphere of radius 1 at the origin seen from distance 4: exact ray distances.
    fn sphere_depth(view: &View) -> Vec<f32> {
        let k = view.intrinsics;
        let mut out = Vec::with_capacity(k.pixel_count() as usize);
        for y in 0..k.height {
            for x in 0..k.width {
                let (o, d) = view.ray_in_world(f64::from(x) + 0.5, f64::from(y) + 0.5);
                let b = o.dot(d);
                let disc = b * b - (o.length_squared() - 1.0);
                out.push(if disc < 0.0 { f32::INFINITY } else { (-b - disc.sqrt()) as f32 });
            }
        }
        out
    }

    fn camera(w: u32, h: u32) -> View {
        View::orbit(DVec3::ZERO, 4.0, 30.0, 20.0, Intrinsics::from_fov_x(w, h, 0.8))
    }

    #[test]
    fn a_frame_round_trips_within_the_stated_error() {
        let view = camera(160, 120);
        let depth = sphere_depth(&view);
        let grid = DepthView::build(&view, Viewport::full(160, 120), &[&depth], 160, 120, 8, 65535);
        assert_eq!(grid.grid(), (21, 16));
        assert!((grid.near - 3.0).abs() < 0.05, "near {}", grid.near);
        let frame = DepthFrame { frame: 7, pose_seq: 9, rtp_ticks: 3000, views: vec![grid.clone()] };
        let bytes = frame.encode();
        let back = DepthFrame::decode(&bytes).unwrap();
        assert_eq!(back, frame);
        // Every vertex: its code decodes, within the coding bound, to the nearest z of the
        // four pixels at its corner when they all hit the sphere, else to the nearest z of
        // the pixels within one stride.
        let (cols, rows) = grid.grid();
        let k = view.intrinsics;
        let z_of = |px: u32, py: u32| {
            let t = depth[(py * 160 + px) as usize];
            let (nx, ny) = ((f64::from(px) + 0.5 - f64::from(k.cx)) / f64::from(k.fx), (f64::from(py) + 0.5 - f64::from(k.cy)) / f64::from(k.fy));
            if t.is_finite() { f64::from(t) / (nx * nx + ny * ny + 1.0).sqrt() } else { f64::INFINITY }
        };
        let mut worst = 0.0f32;
        let mut interior = 0;
        for j in 0..rows {
            for i in 0..cols {
                let (x, y) = grid.vertex_px(i, j);
                let (x1, y1) = ((x as u32).clamp(1, 159), (y as u32).clamp(1, 119));
                let corner = [(x1 - 1, y1 - 1), (x1, y1 - 1), (x1 - 1, y1), (x1, y1)].map(|(a, b)| z_of(a, b));
                let expected = if corner.iter().all(|z| z.is_finite()) {
                    interior += 1;
                    corner.into_iter().fold(f64::INFINITY, f64::min)
                } else {
                    let mut best = f64::INFINITY;
                    for py in 0..120u32 {
                        for px in 0..160u32 {
                            if (f64::from(px) + 0.5 - f64::from(x)).abs() < 8.0 && (f64::from(py) + 0.5 - f64::from(y)).abs() < 8.0 {
                                best = best.min(z_of(px, py));
                            }
                        }
                    }
                    best
                };
                match back.views[0].z_at(i, j) {
                    Some(z) => worst = worst.max((z - expected as f32).abs() / back.views[0].max_coding_error(z).max(1e-9)),
                    None => assert!(expected.is_infinite(), "vertex {i},{j} is background but should be {expected}"),
                }
            }
        }
        assert!(interior > 10, "{interior}");
        assert!(worst <= 1.01, "coding error {worst} × its bound");
        assert!(bytes.len() < 600, "{} bytes for a 21×16 grid", bytes.len());
        let centre = back.views[0].z_at(10, 8).unwrap();
        assert!((centre - 3.0).abs() < 0.01, "{centre}");
    }

    #[test]
    fn background_and_bad_depths_are_background() {
        let view = camera(64, 48);
        let mut depth = vec![f32::INFINITY; 64 * 48];
        depth[100] = f32::NAN;
        depth[101] = 0.0;
        depth[102] = -3.0;
        let grid = DepthView::build(&view, Viewport::full(64, 48), &[&depth], 64, 48, 8, DEPTH_LEVELS);
        assert!(grid.codes.iter().all(|&c| c == 0));
        assert_eq!((grid.near, grid.far), (0.0, 0.0));
        let bytes = DepthFrame { frame: 1, pose_seq: 1, rtp_ticks: 0, views: vec![grid] }.encode();
        assert!(DepthFrame::decode(&bytes).unwrap().views[0].codes.iter().all(|&c| c == 0));
    }

    #[test]
    fn a_smaller_render_and_composed_layers_count_their_nearest_hit() {
        let view = camera(64, 48);
        let half = View { intrinsics: view.intrinsics.scaled(0.5), ..view };
        let a = sphere_depth(&half);
        let b = vec![2.0f32; 32 * 24]; // a nearer plane-ish layer everywhere
        let grid = DepthView::build(&view, Viewport::full(64, 48), &[&a, &b], 32, 24, 8, DEPTH_LEVELS);
        assert!(grid.codes.iter().all(|&c| c != 0));
        assert!(grid.near < 2.0 && grid.near > 1.5, "{}", grid.near);
    }

    #[test]
    fn the_stride_grows_to_keep_a_4k_frame_in_one_message() {
        assert_eq!(stride_for(&[Viewport::full(640, 480)]), 16);
        let s = stride_for(&[Viewport::full(3840, 2160)]);
        let (c, r) = grid_size(3840, 2160, s);
        assert!(c * r <= MAX_DEPTH_VERTICES && s <= MAX_DEPTH_STRIDE_PX, "{s}");
        let eyes = [Viewport { x: 0, y: 0, width: 2064, height: 2208 }, Viewport { x: 2064, y: 0, width: 2064, height: 2208 }];
        let s = stride_for(&eyes);
        assert!(eyes.iter().map(|v| grid_size(v.width, v.height, s)).map(|(c, r)| c * r).sum::<usize>() <= MAX_DEPTH_VERTICES);
    }

    #[test]
    fn corrupt_messages_are_refused_in_words() {
        let view = camera(64, 48);
        let depth = sphere_depth(&view);
        let good = DepthFrame { frame: 1, pose_seq: 2, rtp_ticks: 3, views: vec![DepthView::build(&view, Viewport::full(64, 48), &[&depth], 64, 48, 8, DEPTH_LEVELS)] }.encode();
        for len in [0, 10, 23, 24, 100, good.len() - 1] {
            assert!(DepthFrame::decode(&good[..len]).is_err(), "{len}");
        }
        let mut b = good.clone();
        b[0] = b'X';
        assert_eq!(DepthFrame::decode(&b), Err(DepthError::Magic));
        let set = |offset: usize, v: [u8; 4]| {
            let mut b = good.clone();
            b[offset..offset + 4].copy_from_slice(&v);
            DepthFrame::decode(&b).unwrap_err().to_string()
        };
        assert!(set(20, 0u32.to_le_bytes()).contains("0 views"));
        assert!(set(20, 100_000u32.to_le_bytes()).contains("100000 views"));
        assert!(set(24, f32::NAN.to_le_bytes()).contains("not finite"));
        assert!(set(24 + 100, f32::INFINITY.to_le_bytes()).contains("depth range"));
        assert!(set(24 + 100, 0.0f32.to_le_bytes()).contains("depth range"));
        assert!(set(24 + 104, (-1.0f32).to_le_bytes()).contains("depth range"));
        assert!(set(24 + 96, [0, 0, 255, 3]).contains("stride 0"));
        assert!(set(24 + 96, [8, 0, 0, 0]).contains("0 depth levels"));
        let mut fine = DepthFrame::decode(&good).unwrap();
        fine.views[0].stride_px = 1;
        fine.views[0].codes = vec![1; 65 * 49];
        fine.views = vec![fine.views[0].clone(); 6];
        assert!(DepthFrame::decode(&fine.encode()).unwrap_err().to_string().contains("19110 grid vertices"));
        // Garbage instead of deflate, and a valid stream with a byte too many.
        let mut b = good[..HEADER_LEN + VIEW_LEN].to_vec();
        b.extend_from_slice(&[0xff; 40]);
        assert!(matches!(DepthFrame::decode(&b), Err(DepthError::Codes(_))));
        // Mask: no object vertex (a view that has a depth range may still be all background
        // after a corrupt mask: that is a valid message), then one stray byte.
        let mut residuals = vec![0u8; (9 * 7usize).div_ceil(8) + 1];
        residuals[8] = 2;
        let mut b = good[..HEADER_LEN + VIEW_LEN].to_vec();
        let mut d = flate2::write::DeflateEncoder::new(Vec::new(), flate2::Compression::fast());
        d.write_all(&residuals).unwrap();
        b.extend_from_slice(&d.finish().unwrap());
        assert!(DepthFrame::decode(&b).unwrap_err().to_string().contains("after the last code"));
    }
}
