//! Volume rendering of the i-NGP field (as in NeRF, Mildenhall et al. 2020), the forward half
//! of a training step:
//!
//! 1. march each ray through the scene box with the fixed step `δ = box diagonal /
//!    steps_per_diagonal`, samples at `t₀ + (k + u)δ` (`u` the ray's jitter: uniform when
//!    training, ½ when rendering, the renderer's rule of docs/architecture.md §3), kept only in occupied
//!    cells of the [`OccupancyGrid`];
//! 2. σ front to back, `α_i = 1 − exp(−σ_i δ)`, `T_{i+1} = T_i (1 − α_i)`, stopping once
//!    `T < early_stop_transmittance` (σ is evaluated a window of samples at a time, so the
//!    samples behind that point cost nothing); colour only for the samples used;
//!    `C = Σ T_i α_i c_i + T_end · bg`.
//!
//! Rays are processed in chunks; [`NgpModel::render`] runs the chunks in parallel (rayon).

use glam::Vec3;
use rayon::prelude::*;

use super::{
    field::{Field, FieldTape},
    occupancy::OccupancyGrid,
};
use crate::{
    cubes::Aabb,
    model::clip_ray,
    sh::{SH_COEFFS, sh4},
};

/// Samples per ray and round of density evaluation in a chunk.
pub const DENSITY_WINDOW: usize = 32;

/// An i-NGP field with its occupancy grid and march settings, borrowed from whoever owns them
/// (the trainer).
#[derive(Debug, Clone, Copy)]
pub struct NgpModel<'a> {
    pub field: &'a Field,
    pub occupancy: &'a OccupancyGrid,
    /// Scene box, world space; positions are mapped from it to the unit cube.
    pub bounds: Aabb,
    /// Ray-marching step `δ = bounds diagonal / steps_per_diagonal`.
    pub steps_per_diagonal: u32,
    /// Early ray termination; 0 disables it.
    pub early_stop_transmittance: f32,
    /// Rays per chunk in [`Self::render`]. The last bits of a ray's colour depend on its row
    /// in the chunk's matrix products, so renders that must agree use the same value.
    pub rays_per_chunk: usize,
}

/// One ray of a chunk, world space.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NgpRay {
    pub origin: Vec3,
    /// Unit direction.
    pub dir: Vec3,
    pub background: Vec3,
    /// Sample offset within a step, in [0, 1).
    pub jitter: f32,
}

/// What the forward pass over one chunk of rays computed; the trainer's backward pass reads
/// the tape.
#[derive(Debug, Clone, Default)]
pub struct NgpChunk {
    /// One row per evaluated sample, in evaluation order; the colour pass ran on the rows of
    /// `used`, concatenated.
    pub tape: FieldTape,
    /// Unit-cube position of each row.
    pub points01: Vec<Vec3>,
    /// Per ray, its rows front to back, up to and including the one that stopped it.
    pub used: Vec<Vec<u32>>,
    /// Per ray, the colour composited over its background, and its opacity.
    pub rgb: Vec<Vec3>,
    pub opacity: Vec<f32>,
}

impl NgpModel<'_> {
    /// Ray-marching step δ, scene units.
    pub fn step_size(&self) -> f32 {
        self.bounds.size().length() / self.steps_per_diagonal as f32
    }

    /// Scene point → unit cube of the hash grid.
    pub fn to_unit(&self, p_in_world: Vec3) -> Vec3 {
        (p_in_world - self.bounds.min) / self.bounds.size()
    }

    /// Appends the unit-cube positions of the samples along one ray (occupied cells only).
    pub fn march(&self, origin: Vec3, dir: Vec3, jitter: f32, points01: &mut Vec<Vec3>) {
        let Some((t0, t1)) = clip_ray(&self.bounds, origin, dir) else { return };
        let delta = self.step_size();
        for k in 0..=self.steps_per_diagonal {
            let t = t0 + (k as f32 + jitter) * delta;
            if t >= t1 {
                break;
            }
            let p = origin + t * dir;
            if self.occupancy.is_occupied(p) {
                points01.push(self.to_unit(p).clamp(Vec3::ZERO, Vec3::ONE));
            }
        }
    }

    /// Forward pass over one chunk of rays.
    pub fn forward_chunk(&self, rays: &[NgpRay]) -> NgpChunk {
        let delta = self.step_size();
        let early_stop = self.early_stop_transmittance;
        let mut marched = Vec::new();
        let mut ranges = Vec::with_capacity(rays.len());
        for ray in rays {
            let start = marched.len();
            self.march(ray.origin, ray.dir, ray.jitter, &mut marched);
            ranges.push(start..marched.len());
        }
        // σ front to back in rounds of `DENSITY_WINDOW` samples per ray still transparent: a
        // ray's samples behind the one that makes `T < early_stop` are never evaluated (early
        // in training, before the occupancy grid has emptied the box, that is most of them).
        let mut tape = FieldTape::default();
        let mut round = FieldTape::default();
        let mut points01: Vec<Vec3> = Vec::new();
        let mut used: Vec<Vec<u32>> = vec![Vec::new(); rays.len()];
        let mut next: Vec<usize> = ranges.iter().map(|r| r.start).collect();
        let mut transmittance = vec![1.0f32; rays.len()];
        let mut owners = Vec::new();
        loop {
            let first_row = points01.len();
            owners.clear();
            for (r, range) in ranges.iter().enumerate() {
                if transmittance[r] >= early_stop {
                    let end = (next[r] + DENSITY_WINDOW).min(range.end);
                    points01.extend_from_slice(&marched[next[r]..end]);
                    owners.extend(std::iter::repeat_n(r, end - next[r]));
                    next[r] = end;
                }
            }
            if owners.is_empty() {
                break;
            }
            self.field.forward_density(&points01[first_row..], &mut round);
            tape.append_density(&round);
            for (k, &r) in owners.iter().enumerate() {
                if transmittance[r] >= early_stop {
                    used[r].push((first_row + k) as u32);
                    transmittance[r] *= (-round.sigma[k] * delta).exp();
                }
            }
        }
        // Only the used samples need a colour.
        let view_sh: Vec<[f32; SH_COEFFS]> = rays.iter().zip(&used).flat_map(|(ray, u)| std::iter::repeat_n(sh4(ray.dir), u.len())).collect();
        self.field.forward_colour(used.concat(), &view_sh, &mut tape);

        let mut rgb = Vec::with_capacity(rays.len());
        let mut opacity = Vec::with_capacity(rays.len());
        let mut k0 = 0;
        for (ray, rows) in rays.iter().zip(&used) {
            let n = rows.len();
            let colour = |i: usize| Vec3::from_slice(&tape.rgb[3 * (k0 + i)..3 * (k0 + i) + 3]);
            let alpha = |i: usize| -(-tape.sigma[rows[i] as usize] * delta).exp_m1();
            let mut transmittance = 1.0f32;
            let mut c = Vec3::ZERO;
            for i in 0..n {
                let a = alpha(i);
                c += transmittance * a * colour(i);
                transmittance *= 1.0 - a;
            }
            c += transmittance * ray.background;
            rgb.push(c);
            opacity.push(1.0 - transmittance);
            k0 += n;
        }
        NgpChunk { tape, points01, used, rgb, opacity }
    }

    /// Renders rays (origin, unit direction) over `background`: (rgb, opacity) per ray.
    pub fn render(&self, rays: &[(Vec3, Vec3)], background: Vec3) -> Vec<(Vec3, f32)> {
        let rays: Vec<NgpRay> = rays.iter().map(|&(origin, dir)| NgpRay { origin, dir, background, jitter: 0.5 }).collect();
        rays.par_chunks(self.rays_per_chunk)
            .flat_map_iter(|c| {
                let out = self.forward_chunk(c);
                out.rgb.into_iter().zip(out.opacity)
            })
            .collect()
    }
}
