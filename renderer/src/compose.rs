//! Depth composition of several objects' renders into one frame (NEPHELE §5.1, §6.1):
//! per pixel, the layers are ordered by depth, nearest first, and blended front to back —
//! the nearest hit wins and its alpha lets what lies behind show through — then the
//! background fills what is left. This is the CPU reference; `gpu::compose` is the same
//! rule in a wgpu kernel, tested against it.
//!
//! Each layer is an object rendered over black, so its RGB is premultiplied by its alpha
//! (`rgb = α·c`): exactly what the renderer writes with a black background. Per pixel, with
//! layers `i` sorted by depth (misses, depth ∞, last; ties keep the layers' order):
//! `C = Σ_i T_i·rgb_i`, `T_{i+1} = T_i·(1 − α_i)`, `T_0 = 1`; output
//! `rgb = C + T_end·background`, `α = 1 − T_end`, depth = the nearest hit's.

use glam::Vec3;

use crate::render::{Frame, to_unorm8};

/// Most layers (objects) composed into one frame.
pub const MAX_LAYERS: usize = 16;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ComposeError {
    #[error("no layers to compose")]
    NoLayers,
    #[error("{0} layers; at most {MAX_LAYERS} objects are composed into one frame")]
    TooManyLayers(usize),
    #[error("layer {index} is {width}x{height}; the first is {first_width}x{first_height}")]
    SizeMismatch { index: usize, width: u32, height: u32, first_width: u32, first_height: u32 },
    #[error("layer {0} has buffers that do not match its size")]
    Malformed(usize),
    #[error("background is not finite")]
    Background,
}

/// Checks the layers and returns their common size.
pub fn check_layers(layers: &[&Frame], background: Vec3) -> Result<(u32, u32), ComposeError> {
    let first = layers.first().ok_or(ComposeError::NoLayers)?;
    if layers.len() > MAX_LAYERS {
        return Err(ComposeError::TooManyLayers(layers.len()));
    }
    if !background.is_finite() {
        return Err(ComposeError::Background);
    }
    for (index, l) in layers.iter().enumerate() {
        if (l.width, l.height) != (first.width, first.height) {
            return Err(ComposeError::SizeMismatch { index, width: l.width, height: l.height, first_width: first.width, first_height: first.height });
        }
        let n = l.width as usize * l.height as usize;
        if l.rgba.len() != 4 * n || l.depth.len() != n {
            return Err(ComposeError::Malformed(index));
        }
    }
    Ok((first.width, first.height))
}

/// Composes premultiplied layers over `background` (linear RGB in [0, 1]). One plain
/// loop (a few ms at 640×480): it runs beside the renderer, so it takes no threads from it.
pub fn compose(layers: &[&Frame], background: Vec3) -> Result<Frame, ComposeError> {
    let (width, height) = check_layers(layers, background)?;
    let n = width as usize * height as usize;
    let k = layers.len();
    let mut rgba = vec![0u8; 4 * n];
    let mut depth = vec![f32::INFINITY; n];
    if k == 2 {
        compose_two(layers[0], layers[1], background, &mut rgba, &mut depth);
        return Ok(Frame { width, height, rgba, depth });
    }
    let mut order = [0usize; MAX_LAYERS];
    let mut keys = [0f32; MAX_LAYERS];
    for p in 0..n {
        // Insertion sort by depth: stable (equal depths keep the layers' order), K ≤ 16.
        for i in 0..k {
            let d = key(layers[i].depth[p]);
            let mut j = i;
            while j > 0 && keys[j - 1] > d {
                order[j] = order[j - 1];
                keys[j] = keys[j - 1];
                j -= 1;
            }
            order[j] = i;
            keys[j] = d;
        }
        let (mut r, mut g, mut b, mut t) = (0.0f32, 0.0f32, 0.0f32, 1.0f32);
        for &i in &order[..k] {
            let px = &layers[i].rgba[4 * p..4 * p + 4];
            r += t * f32::from(px[0]) * INV;
            g += t * f32::from(px[1]) * INV;
            b += t * f32::from(px[2]) * INV;
            t *= 1.0 - f32::from(px[3]) * INV;
        }
        let out = Vec3::new(r, g, b) + t * background;
        rgba[4 * p..4 * p + 4].copy_from_slice(&[to_unorm8(out.x), to_unorm8(out.y), to_unorm8(out.z), to_unorm8(1.0 - t)]);
        depth[p] = layers[order[0]].depth[p];
    }
    Ok(Frame { width, height, rgba, depth })
}

const INV: f32 = 1.0 / 255.0;

/// The common case, two objects: the same rule without the general sort.
fn compose_two(a: &Frame, b: &Frame, background: Vec3, rgba: &mut [u8], depth: &mut [f32]) {
    let pixels = a.rgba.chunks_exact(4).zip(&a.depth).zip(b.rgba.chunks_exact(4).zip(&b.depth));
    for ((out, d), ((pa, &da), (pb, &db))) in rgba.chunks_exact_mut(4).zip(depth.iter_mut()).zip(pixels) {
        // Stable: b goes first only when strictly nearer.
        let ((front, df), back) = if key(db) < key(da) { ((pb, db), pa) } else { ((pa, da), pb) };
        let t0 = 1.0 - f32::from(front[3]) * INV;
        let t1 = t0 * (1.0 - f32::from(back[3]) * INV);
        let mix = |c: usize, bg: f32| (f32::from(front[c]) * INV + t0 * f32::from(back[c]) * INV + t1 * bg).clamp(0.0, 1.0);
        out.copy_from_slice(&[unorm(mix(0, background.x)), unorm(mix(1, background.y)), unorm(mix(2, background.z)), unorm((1.0 - t1).clamp(0.0, 1.0))]);
        *d = df;
    }
}

/// [`to_unorm8`] for a value already in [0, 1] (adding ½ and truncating rounds halves away
/// from zero, as `round` does, without its libm call).
fn unorm(x: f32) -> u8 {
    (x * 255.0 + 0.5) as u8
}

/// Sort key of a depth: misses (∞) and NaN last.
fn key(d: f32) -> f32 {
    if d.is_nan() { f32::INFINITY } else { d }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layer(w: u32, h: u32, f: impl Fn(u32) -> ([u8; 4], f32)) -> Frame {
        let (mut rgba, mut depth) = (Vec::new(), Vec::new());
        for i in 0..w * h {
            let (px, d) = f(i);
            rgba.extend_from_slice(&px);
            depth.push(d);
        }
        Frame { width: w, height: h, rgba, depth }
    }

    #[test]
    fn nearest_wins_and_alpha_shows_what_lies_behind() {
        let bg = Vec3::new(0.0, 0.0, 1.0);
        // Opaque red at depth 2, half-transparent green (premultiplied) at depth 1.
        let red = layer(1, 1, |_| ([255, 0, 0, 255], 2.0));
        let green = layer(1, 1, |_| ([0, 128, 0, 128], 1.0));
        let out = compose(&[&red, &green], bg).unwrap();
        // 0.502 green + (1 − 0.502)·red, opaque, depth of the green.
        assert_eq!(out.rgba, vec![127, 128, 0, 255]);
        assert_eq!(out.depth, vec![1.0]);
        // Order of the layers does not matter, only their depths.
        assert_eq!(compose(&[&green, &red], bg).unwrap(), out);
        // Green behind red: the opaque red hides it.
        let far_green = layer(1, 1, |_| ([0, 128, 0, 128], 3.0));
        assert_eq!(compose(&[&far_green, &red], bg).unwrap().rgba, vec![255, 0, 0, 255]);
        // Nothing hit: the background, alpha 0, depth ∞.
        let miss = layer(1, 1, |_| ([0, 0, 0, 0], f32::INFINITY));
        let out = compose(&[&miss, &miss], bg).unwrap();
        assert_eq!((out.rgba.clone(), out.depth[0]), (vec![0, 0, 255, 0], f32::INFINITY));
    }

    #[test]
    fn one_layer_equals_rendering_over_the_background() {
        // α·c premultiplied then over bg: c = 200/255·(1/α)… at α = 1 and 0 exactly, and within
        // one level in between (8-bit premultiplied colour).
        let bg = Vec3::new(1.0, 1.0, 1.0);
        let l = layer(4, 1, |i| match i {
            0 => ([200, 100, 50, 255], 1.0),
            1 => ([0, 0, 0, 0], f32::INFINITY),
            2 => ([100, 50, 25, 128], 1.0),
            _ => ([10, 20, 30, 40], 1.0),
        });
        let out = compose(&[&l], bg).unwrap();
        assert_eq!(&out.rgba[0..8], &[200, 100, 50, 255, 255, 255, 255, 0]);
        assert_eq!(&out.rgba[8..12], &[227, 177, 152, 128]);
    }

    #[test]
    fn bad_layers_are_errors() {
        let a = layer(2, 2, |_| ([0, 0, 0, 0], 1.0));
        let b = layer(2, 3, |_| ([0, 0, 0, 0], 1.0));
        assert_eq!(compose(&[], Vec3::ONE), Err(ComposeError::NoLayers));
        assert!(matches!(compose(&[&a, &b], Vec3::ONE), Err(ComposeError::SizeMismatch { index: 1, .. })));
        let many: Vec<&Frame> = (0..MAX_LAYERS + 1).map(|_| &a).collect();
        assert_eq!(compose(&many, Vec3::ONE), Err(ComposeError::TooManyLayers(MAX_LAYERS + 1)));
        assert_eq!(compose(&[&a], Vec3::NAN), Err(ComposeError::Background));
        let mut broken = a.clone();
        broken.depth.pop();
        assert_eq!(compose(&[&broken], Vec3::ONE), Err(ComposeError::Malformed(0)));
    }
}

#[cfg(test)]
mod speed {
    /// Prints the compose time at 640×480, two layers (not asserted: a benchmark note).
    #[test]
    fn compose_time_at_640x480() {
        use super::*;
        let layer = |d: f32| Frame { width: 640, height: 480, rgba: vec![100; 640 * 480 * 4], depth: vec![d; 640 * 480] };
        let (a, b) = (layer(1.0), layer(2.0));
        let t = std::time::Instant::now();
        for _ in 0..5 {
            compose(&[&a, &b], Vec3::ONE).unwrap();
        }
        eprintln!("compose 640x480, 2 layers: {:.2} ms", t.elapsed().as_secs_f64() * 1e3 / 5.0);
    }
}
