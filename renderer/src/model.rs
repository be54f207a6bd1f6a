//! The i-NOLF per-ray maths of DESIGN §3, written once in plain Rust. The CPU reference
//! renders with it directly; the WGSL kernels (`shaders/*.wgsl`) transcribe the same steps
//! and are tested against it.
//!
//! 1. clip the object-space ray to the box → `[t0, t1]`;
//! 2. DDA over the density index grid (Amanatides & Woo), fixed samples `t_k = t0 + (k+½)δ`
//!    only in occupied cells, each read from the brick of the cell the DDA is in; `α_k = 1 − exp(−σ_k δ)`, `w_k = T_k α_k`; the hit is the sample
//!    of largest weight, `α_c = 1 − T`; stop once `T < early_stop` (`α_c` then within
//!    `early_stop` of `1 − T_end`) or, if enabled, `T < stop_ratio·w_max` (the hit stays exact:
//!    no later weight can exceed `T`; `α_c` may fall short);
//! 3. at the hit: diffuse cubes → `c_d`, tint; PSH → E_s; SH4(dir) → E_v; MLP → `c_s`, α;
//!    `c = clamp(c_d + t·c_s, 0, 1)`, pixel `= α c + (1 − α) bg`.

use glam::{IVec3, Vec3};

use crate::{asset::Asset, cubes::Aabb, cubes::TextureCubes, mlp::sigmoid, sh::sh4};

/// Stand-in for infinity that survives GPU fast-math (WGSL does not promise IEEE infinities).
pub const BIG: f32 = 1e30;
/// Direction components smaller than this count as zero.
pub const TINY_DIR: f32 = 1e-12;

/// Runtime knobs users trade speed against accuracy with.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RenderSettings {
    /// Multiplies the asset's step δ.
    pub step_scale: f32,
    /// Also stop marching when `T < stop_ratio · w_max`: any value ≤ 1 keeps the hit point
    /// exact (no later weight can exceed `T`) but leaves `α_c` short by up to `T`; 0 disables it.
    pub stop_ratio: f32,
    /// Stop marching when `T < early_stop` (bounds the error of `α_c`).
    pub early_stop: f32,
    /// Miss threshold on `α_c`; `None` uses the asset's.
    pub alpha_min: Option<f32>,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self { step_scale: 1.0, stop_ratio: 0.0, early_stop: 1e-3, alpha_min: None }
    }
}

impl RenderSettings {
    pub fn validate(&self) -> Result<(), String> {
        let ok = self.step_scale.is_finite()
            && (0.05..=20.0).contains(&self.step_scale)
            && (0.0..=1.0).contains(&self.stop_ratio)
            && (0.0..1.0).contains(&self.early_stop)
            && self.alpha_min.is_none_or(|a| (0.0..1.0).contains(&a));
        if ok { Ok(()) } else { Err(format!("render settings out of range: {self:?}")) }
    }
}

/// Ray/box intersection `[t_near, t_far]`, or `None`. Zero direction components are handled
/// without infinities or NaN.
pub fn clip_ray(bounds: &Aabb, o: Vec3, d: Vec3) -> Option<(f32, f32)> {
    let (mut t_near, mut t_far) = (-BIG, BIG);
    for a in 0..3 {
        if d[a].abs() < TINY_DIR {
            if o[a] < bounds.min[a] || o[a] > bounds.max[a] {
                return None;
            }
        } else {
            let ta = (bounds.min[a] - o[a]) / d[a];
            let tb = (bounds.max[a] - o[a]) / d[a];
            t_near = t_near.max(ta.min(tb));
            t_far = t_far.min(ta.max(tb));
        }
    }
    let t0 = t_near.max(0.0);
    (t_far > t0).then_some((t0, t_far))
}

/// Result of marching one ray through the density cubes.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct MarchHit {
    /// Object-space ray parameter of the max-weight sample.
    pub t_hit: f32,
    /// Coarse opacity `1 − T` where marching stopped.
    pub alpha_c: f32,
    pub w_max: f32,
    /// Density samples taken (for the benchmark).
    pub samples: u32,
}

/// Marches the density cubes along `o + t·d` with step `step`.
pub fn march(density: &TextureCubes, o: Vec3, d: Vec3, step: f32, s: &RenderSettings) -> MarchHit {
    let mut out = MarchHit::default();
    let Some((t0, t1)) = clip_ray(&density.bounds, o, d) else { return out };
    let b = density.grid as i32;
    let cell_size = density.bounds.size() / b as f32;
    let p0 = o + t0 * d;
    let g = (p0 - density.bounds.min) / cell_size;
    let mut cell = g.floor().as_ivec3().clamp(IVec3::ZERO, IVec3::splat(b - 1));
    let mut dir_step = IVec3::ZERO;
    let mut t_max = Vec3::splat(BIG);
    let mut t_delta = Vec3::splat(BIG);
    for a in 0..3 {
        if d[a].abs() >= TINY_DIR {
            dir_step[a] = if d[a] > 0.0 { 1 } else { -1 };
            let boundary = density.bounds.min[a] + (cell[a] + (d[a] > 0.0) as i32) as f32 * cell_size[a];
            t_max[a] = t0 + (boundary - p0[a]) / d[a];
            t_delta[a] = cell_size[a] / d[a].abs();
        }
    }
    let (mut transmittance, mut w_max, mut t_hit) = (1.0f32, 0.0f32, 0.0f32);
    let mut t_enter = t0;
    let mut k_next = 0i32;
    let mut samples = 0u32;
    'cells: for _ in 0..3 * b + 3 {
        if t_enter >= t1 {
            break;
        }
        let t_exit = t_max.min_element().min(t1);
        let brick = density.brick_at(cell.as_uvec3());
        if brick >= 0 {
            // Samples in this cell read its brick (the DDA's cell, not a re-derived one).
            let cell_f = cell.as_vec3();
            let k_a = k_next.max(((t_enter - t0) / step - 0.5).ceil() as i32);
            let k_b = ((t_exit - t0) / step - 0.5).ceil() as i32;
            for k in k_a..k_b {
                let t = t0 + (k as f32 + 0.5) * step;
                let sigma = density.sample_in_brick::<1>(brick as usize, cell_f, density.to_fine(o + t * d))[0];
                let alpha = 1.0 - (-sigma * step).exp();
                let w = transmittance * alpha;
                if w > w_max {
                    w_max = w;
                    t_hit = t;
                }
                transmittance *= 1.0 - alpha;
                samples += 1;
                if transmittance < s.stop_ratio * w_max || transmittance < s.early_stop {
                    break 'cells;
                }
            }
            k_next = k_next.max(k_b);
        }
        let axis = if t_max.x <= t_max.y && t_max.x <= t_max.z { 0 } else if t_max.y <= t_max.z { 1 } else { 2 };
        cell[axis] += dir_step[axis];
        if cell[axis] < 0 || cell[axis] >= b {
            break;
        }
        t_enter = t_exit;
        t_max[axis] += t_delta[axis];
    }
    out.t_hit = t_hit;
    out.alpha_c = 1.0 - transmittance;
    out.w_max = w_max;
    out.samples = samples;
    out
}

/// Shades a hit: returns `(rgb over bg, α)`.
pub fn shade(asset: &Asset, net: &crate::mlp::MlpKernel, p_hit: Vec3, d: Vec3, alpha_c: f32, bg: Vec3) -> (Vec3, f32) {
    let [r, g, b, tint] = asset.diffuse.sample::<4>(p_hit);
    let features = asset.psh.features as usize;
    let mut x = [0.0f32; crate::mlp::MAX_INPUT];
    asset.psh.encode(p_hit, &mut x[..features]);
    x[features..features + 16].copy_from_slice(&sh4(d));
    x[features + 16] = alpha_c;
    let o = net.forward(&x[..features + 17]);
    let c_s = Vec3::new(sigmoid(o[0]), sigmoid(o[1]), sigmoid(o[2]));
    let alpha = sigmoid(o[3]);
    let c = (Vec3::new(r, g, b) + tint * c_s).clamp(Vec3::ZERO, Vec3::ONE);
    (alpha * c + (1.0 - alpha) * bg, alpha)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clipping_handles_axis_parallel_and_inside_rays() {
        let b = Aabb::cube(1.0);
        assert_eq!(clip_ray(&b, Vec3::new(0.0, 0.0, 5.0), Vec3::new(0.0, 0.0, -1.0)), Some((4.0, 6.0)));
        // Inside the box: starts at 0.
        assert_eq!(clip_ray(&b, Vec3::ZERO, Vec3::X), Some((0.0, 1.0)));
        // Parallel to a face, outside it: miss; on the face plane: hit.
        assert_eq!(clip_ray(&b, Vec3::new(0.0, 2.0, 5.0), Vec3::new(0.0, 0.0, -1.0)), None);
        assert!(clip_ray(&b, Vec3::new(0.0, 1.0, 5.0), Vec3::new(0.0, 0.0, -1.0)).is_some());
        // Pointing away.
        assert_eq!(clip_ray(&b, Vec3::new(0.0, 0.0, 5.0), Vec3::Z), None);
        // Grazing an edge exactly gives an empty or tiny interval, never NaN.
        if let Some((t0, t1)) = clip_ray(&b, Vec3::new(1.0, 1.0, 5.0), Vec3::new(0.0, 0.0, -1.0)) {
            assert!(t0.is_finite() && t1.is_finite());
        }
    }
}
