//! The i-NOLF stages of training (NEPHELE §4; docs/architecture.md §4 stages 2–4): distil a trained i-NGP
//! field (the teacher) into an i-NOLF asset.
//!
//! 2. **Geometry.** Bake density texture cubes from the teacher's σ over a box fitted to its
//!    occupancy grid, keeping only bricks where a step is visibly opaque; then march every
//!    training ray through the cubes with exactly the renderer's rule ([`model::march`]) to get
//!    its hit point `P_h` and coarse opacity `α_c`. Rays below the asset's `alpha_min` are
//!    misses, as they will be at render time.
//! 3. **Appearance.** Build the perfect spatial hash over the vertices of the cells that hold
//!    hit points, dilated by `psh_dilation` vertices for views the cameras did not see. Train
//!    together, on `‖c − c_gt‖² + ‖α − α_gt‖²` with a random background per ray:
//!    - the diffuse net: multi-resolution hash grid `E_d(P_h)` → MLP (64) → `c_d` (sigmoid RGB)
//!      and specular tint `t` (sigmoid);
//!    - the specular net: PSH features `E_s(P_h)` (trilinear, trainable) with SH4 of the view
//!      direction and `α_c` → MLP (64, 64) → `c_s`, `α` (sigmoids);
//!    - `c = clamp(c_d + t·c_s, 0, 1)`, pixel `= α c + (1 − α) bg`, exactly [`model::shade`];
//!    - optionally (`teacher_query_weight` λ > 0), `+ λ Σ_q w_q β_q ‖c_q − c̄_q‖²`: each
//!      query's colour toward the teacher's colour averaged by weight `w_q` near it
//!      ([`teacher_query_targets`]).
//!
//!    Rays are drawn half uniformly over all hits and half from an error map: per image tile
//!    of `error_tile` pixels, a running mean of the loss of the rays drawn there, so training
//!    spends its rays where the asset is worst.
//! 4. **Bake.** Evaluate the diffuse net at the corners of diffuse bricks around the cells that
//!    hold hit points (dilated by one cell) and assemble the [`Asset`].
//!
//! All gradients are hand-derived (checked against finite differences in the tests); batches
//! are split into chunks processed in parallel and summed in chunk order, so a run is
//! deterministic for a seed whatever the thread count.

use std::time::Instant;

use glam::{UVec3, Vec3};
use nephele_renderer::{
    View,
    asset::{Asset, MarchMeta},
    container::{self, Reader, Tensor, Verify},
    cubes::{Aabb, CubeStorage, TextureCubes},
    mlp::{HIDDEN, SpecularMlp},
    model::{self, RenderSettings},
    ngp::{
        NgpRay,
        hash_grid::{HashGrid, HashGridConfig},
        mlp::{Mlp, MlpTape},
    },
    psh::{PshError, SpatialHash},
    sh::{SH_COEFFS, sh4},
};
use rand::{Rng, SeedableRng, rngs::SmallRng};
use rayon::prelude::*;
use safetensors::Dtype;
use serde::{Deserialize, Serialize};

use crate::{
    adam::{Adam, AdamConfig, add_l2},
    dataset::{Dataset, DatasetImage},
    hash_grid::HashGridBackward,
    mlp::MlpBackward,
    trainer::{Trainer, mix},
};

/// Settings of the i-NOLF stages.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DistillConfig {
    /// Density index grid `b` and brick edge `r` (fine resolution `b·r` over the fitted box).
    pub density_grid: u32,
    pub density_brick: u32,
    /// A density brick is kept if its largest σ makes one march step at least this opaque,
    /// and it lies within `density_dilation` cells of a cell holding a training hit (the
    /// inside of solid objects is never reached).
    pub min_step_opacity: f32,
    pub density_dilation: u32,
    /// March samples per fine density cell (along the box's longest axis); below 1, a step
    /// spans several cells (½: one sample per two cells).
    pub samples_per_cell: f32,
    pub diffuse_grid: u32,
    pub diffuse_brick: u32,
    /// Diffuse bricks go in cells holding training hits and this many cells around them.
    pub diffuse_dilation: u32,
    /// How the baked diffuse colour and tint are stored (all in [0, 1]: 8-bit unorm halves
    /// the bytes at ≤ 1/510 error).
    #[serde(default)]
    pub diffuse_storage: CubeStorage,
    /// Train the diffuse net through the trilinear lattice of its bake (see
    /// [`Student::diffuse_lattice`]).
    #[serde(default)]
    pub train_on_bake_lattice: bool,
    /// PSH grid `N` and features per vertex.
    pub psh_grid: u32,
    pub psh_features: u32,
    /// Vertices within this many grid steps of a hit cell are stored too, where a density
    /// brick could put a hit (see [`psh_vertex_set`]).
    pub psh_dilation: u32,
    /// Diffuse encoding E_d over the fitted box.
    pub diffuse_encoding: HashGridConfig,
    /// Ablation (Table 5): without a diffuse net the specular net's colour is the whole
    /// colour (NEPHELE's "base"); and E_s from a multi-resolution hash grid instead of the
    /// PSH (every row before "+ PSH"). Such students are not baked into assets.
    #[serde(default = "yes")]
    pub diffuse_net: bool,
    #[serde(default)]
    pub specular_hash_grid: Option<HashGridConfig>,
    /// Coarse opacity below which a ray is a miss.
    pub alpha_min: f32,
    /// The multi-hit rule the student is trained for and the asset renders with
    /// ([`model::HitRule`]; absent in older checkpoints: one hit).
    #[serde(default)]
    pub hits: model::HitRule,
    /// The march's stop on transmittance the student is trained with and the asset renders
    /// with ([`nephele_renderer::asset::MarchMeta::early_stop`]; absent in older checkpoints:
    /// [`model::DEFAULT_EARLY_STOP`]).
    #[serde(default = "default_early_stop")]
    pub early_stop: f32,
    /// Views rendered by the teacher from new camera positions, added to the training images
    /// for stages 2–4 ([`with_teacher_views`]); 0: the captured images only.
    #[serde(default)]
    pub teacher_views: u32,
    /// Weight λ of a second loss on each query's own colour: toward the teacher's colour
    /// averaged by weight over its samples near the query ([`teacher_query_targets`]), so
    /// each hit learns its surface's colour and not only the blend the pixel sees (0: off).
    #[serde(default)]
    pub teacher_query_weight: f32,
    pub steps: u64,
    pub rays_per_batch: usize,
    pub rays_per_chunk: usize,
    pub adam: AdamConfig,
    pub l2_mlp_weights: f32,
    /// Learning-rate multipliers `(from step, factor)`.
    pub learning_rate_schedule: Vec<(u64, f32)>,
    /// Error-map tile edge in pixels, and the share of each batch drawn from it.
    pub error_tile: u32,
    pub error_fraction: f32,
    pub seed: u64,
}

impl DistillConfig {
    /// For real scenes: density cubes 128×4 (512³ fine over the fitted cube, one march sample
    /// per two fine cells) and diffuse cubes 64×4 (256³, 8-bit) in the cells holding training
    /// hits, PSH 128 with 8 features on those cells' vertices, dilated by one vertex where a
    /// hit can land; adaptive multi-hit with τ = 0.1. Measured on lego (held-out PSNR, asset
    /// size):
    /// - density at 512³ instead of 256³: +1.81 dB (31.33 → 33.14, +24 MB). The density sets
    ///   each query's blend weight; with the teacher's own colours at the asset's queries, 256³
    ///   caps near 31.8 dB and 512³ near 33.1 (`nephele eval --teacher`). The march step does
    ///   not matter (two samples per 256³ cell: −0.01 dB), so it stays that of 256³: the
    ///   frame costs more only for the larger cubes. 8³ bricks under a 64³ index instead:
    ///   −4 MB and a faster march (fewer index reads), but −0.18 dB for the student;
    /// - against 128³ f16 diffuse with every part dilated by one cell (at 256³ density): 256³
    ///   diffuse +0.54 dB (+12.9 MB as f16, +4.8 MB as 8-bit); no dilation of density −0.06 dB
    ///   (−1.9 MB); PSH dilation kept only where a hit can land −0.7 MB; PSH 256 instead of
    ///   128 +0.39 dB (+12.4 MB).
    pub fn default_for(steps: u64) -> Self {
        Self {
            density_grid: 128,
            density_brick: 4,
            min_step_opacity: 0.01,
            density_dilation: 0,
            samples_per_cell: 0.5,
            diffuse_grid: 64,
            diffuse_brick: 4,
            diffuse_dilation: 0,
            diffuse_storage: CubeStorage::Unorm8,
            train_on_bake_lattice: true,
            psh_grid: 128,
            // 8 features: +0.29 dB over 4 on lego (τ = 0.1 students, 19.5 against 17.9 MB).
            psh_features: 8,
            psh_dilation: 1,
            // No finer than the cubes it is baked into, so the specular net learns to make up
            // for what the baked diffuse lacks (measured on lego with 128³ cubes: +0.8 dB over
            // an encoding twice as fine).
            diffuse_encoding: HashGridConfig { levels: 12, log2_table_size: 18, base_resolution: 16, finest_resolution: 256 },
            diffuse_net: true,
            specular_hash_grid: None,
            alpha_min: 0.02,
            // Adaptive multi-hit: a second (third) query where ≥ 10% of a ray's weight lies
            // in another segment: +0.83 dB on lego at 1.29 queries per hit ray.
            hits: model::HitRule { tau: 0.1, max_hits: 3, gap_steps: 3.0 },
            early_stop: model::DEFAULT_EARLY_STOP,
            teacher_views: 0,
            teacher_query_weight: 0.0,
            steps,
            rays_per_batch: 8192,
            rays_per_chunk: 128,
            adam: AdamConfig::default(),
            l2_mlp_weights: 1e-6,
            learning_rate_schedule: vec![(steps * 6 / 10, 1.0 / 3.0), (steps * 85 / 100, 0.1)],
            error_tile: 16,
            error_fraction: 0.5,
            seed: 0,
        }
    }

    /// Higher resolution, larger asset, more margin for views far from the captured ones: PSH
    /// 256, f16 diffuse, and density and diffuse dilated by a cell around the hit cells.
    pub fn quality(steps: u64) -> Self {
        Self { density_dilation: 1, diffuse_dilation: 1, diffuse_storage: CubeStorage::F16, psh_grid: 256, ..Self::default_for(steps) }
    }

    /// Small, for tests.
    pub fn tiny(steps: u64) -> Self {
        Self {
            density_grid: 16,
            density_brick: 4,
            diffuse_grid: 16,
            diffuse_brick: 4,
            diffuse_dilation: 1,
            samples_per_cell: 1.0,
            psh_grid: 32,
            psh_features: 4,
            hits: model::HitRule::default(),
            diffuse_encoding: HashGridConfig { levels: 4, log2_table_size: 14, base_resolution: 4, finest_resolution: 32 },
            rays_per_batch: 2048,
            error_tile: 8,
            ..Self::default_for(steps)
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        self.diffuse_encoding.validate()?;
        if let Some(grid) = &self.specular_hash_grid {
            grid.validate()?;
        }
        let cube_ok = |g: u32, r: u32| (1..=512).contains(&g) && (1..=32).contains(&r) && g * r <= 4096;
        if !cube_ok(self.density_grid, self.density_brick) || !cube_ok(self.diffuse_grid, self.diffuse_brick) {
            return Err("texture cube sizes out of range".into());
        }
        if !(0.25..=8.0).contains(&self.samples_per_cell) || self.density_dilation > 4 || self.diffuse_dilation > 4 {
            return Err("samples per cell or dilations out of range".into());
        }
        if !(2..=nephele_renderer::psh::MAX_COORD).contains(&self.psh_grid) || !(1..=32).contains(&self.psh_features) || self.psh_dilation > 4 {
            return Err(format!("PSH grid {} / features {} / dilation {} out of range", self.psh_grid, self.psh_features, self.psh_dilation));
        }
        self.hits.validate()?;
        if !(0.0..1.0).contains(&self.alpha_min) || !(0.0..1.0).contains(&self.min_step_opacity) || !(0.0..1.0).contains(&self.early_stop) {
            return Err("alpha_min, min_step_opacity and early_stop must be in [0, 1)".into());
        }
        if !(1..=1 << 22).contains(&self.rays_per_batch) || !(1..=1 << 16).contains(&self.rays_per_chunk) || self.error_tile == 0 {
            return Err("batch, chunk or tile size out of range".into());
        }
        if !(self.teacher_query_weight.is_finite() && self.teacher_query_weight >= 0.0) {
            return Err("teacher_query_weight must be finite and ≥ 0".into());
        }
        if !(0.0..=1.0).contains(&self.error_fraction) || !self.learning_rate_schedule.iter().all(|(_, f)| f.is_finite() && *f > 0.0) {
            return Err("error fraction or learning-rate schedule out of range".into());
        }
        Ok(())
    }

    /// The early stop of the marches that choose the box and the bricks to keep: never later
    /// than the renderer's default, so a larger [`Self::early_stop`] changes what the
    /// student learns, not which surfaces the asset holds (new views may reach surfaces
    /// that the training rays stopped short of).
    pub fn geometry_early_stop(&self) -> f32 {
        self.early_stop.min(model::DEFAULT_EARLY_STOP)
    }

    /// The multi-hit rule the student is trained for.
    pub fn hit_rule(&self) -> model::HitRule {
        self.hits
    }

    /// March step δ for cubes over `bounds`: a fine density cell along the longest axis over
    /// `samples_per_cell`.
    pub fn step(&self, bounds: &Aabb) -> f32 {
        bounds.size().max_element() / ((self.density_grid * self.density_brick) as f32 * self.samples_per_cell)
    }
}

fn yes() -> bool {
    true
}

fn default_early_stop() -> f32 {
    model::DEFAULT_EARLY_STOP
}

/// The box to model: the object as the training images show it. Density cubes over the
/// teacher's whole box are marched with every training ray; the box of the hits whose pixel
/// is at least half opaque in the ground truth (its 0.05–99.95% quantiles per axis), grown by
/// one coarse cell and made a cube inside the teacher's box, is kept. Faint haze the field
/// left where no image shows anything (common in corners) stays outside.
/// Images without transparency count every hit.
pub fn fit_bounds(teacher: &Trainer, data: &Dataset, cfg: &DistillConfig) -> Option<Aabb> {
    let whole = teacher.config.bounds;
    let coarse = bake_density(teacher, whole, cfg);
    let hits = march_rays(&coarse, cfg.step(&whole), cfg.alpha_min, cfg.geometry_early_stop(), &model::HitRule::default(), data, cfg.error_tile);
    let has_alpha = data.images.iter().any(|im| im.rgba.chunks_exact(4).any(|p| p[3] < 0.5));
    let points: Vec<Vec3> = hits
        .rays
        .iter()
        .filter(|h| !has_alpha || data.images[h.image as usize].pixel(h.x_px as u32, h.y_px as u32)[3] >= 0.5)
        .map(|h| h.p_hit)
        .collect();
    if points.is_empty() {
        return None;
    }
    // Robust extent: the 0.05% and 99.95% quantiles per axis, so a few hits on faint haze
    // (an edge pixel's ray passing the object) do not stretch the box.
    let quantile = |axis: usize, q: f64| {
        let mut v: Vec<f32> = points.iter().map(|p| p[axis]).collect();
        let k = ((v.len() - 1) as f64 * q).round() as usize;
        *v.select_nth_unstable_by(k, f32::total_cmp).1
    };
    let lo = Vec3::new(quantile(0, 0.0005), quantile(1, 0.0005), quantile(2, 0.0005));
    let hi = Vec3::new(quantile(0, 0.9995), quantile(1, 0.9995), quantile(2, 0.9995));
    // A cube, so cells are cubes: one grid size serves all axes, and a flat object does not
    // get finer cells (and more bricks) along its short axes than along its long one.
    let margin = whole.size().max_element() / cfg.density_grid as f32;
    let half = (0.5 * (hi - lo).max_element() + margin).min(0.5 * whole.size().min_element());
    let centre = (0.5 * (lo + hi)).clamp(whole.min + half, whole.max - half);
    let fitted = Aabb { min: centre - half, max: centre + half };
    fitted.is_valid().then_some(fitted)
}

/// Teacher σ at object-space points (batched).
fn teacher_sigma(teacher: &Trainer, points: &[Vec3]) -> Vec<f32> {
    let points01: Vec<Vec3> = points.iter().map(|&p| teacher.to_unit(p).clamp(Vec3::ZERO, Vec3::ONE)).collect();
    teacher.field.density(&points01)
}

/// Stage 2a: density cubes from the teacher over `bounds`; a cell gets a brick if the teacher's
/// occupancy grid marks any point of it (corners and centre) and its largest σ makes a step
/// of `δ` at least `min_step_opacity` opaque.
pub fn bake_density(teacher: &Trainer, bounds: Aabb, cfg: &DistillConfig) -> TextureCubes {
    let b = cfg.density_grid;
    let cell_size = bounds.size() / b as f32;
    let occupied = |c: UVec3| {
        let lo = bounds.min + c.as_vec3() * cell_size;
        (0..9u32).any(|k| {
            let f = if k == 8 { Vec3::splat(0.5) } else { Vec3::new((k & 1) as f32, (k >> 1 & 1) as f32, (k >> 2) as f32) * 0.98 + 0.01 };
            teacher.occupancy.is_occupied(lo + f * cell_size)
        })
    };
    // Every candidate brick with the teacher's σ evaluated in one batch, then drop the ones
    // that stay transparent.
    let candidates = TextureCubes::bake_batched(bounds, b, cfg.density_brick, 1, occupied, |points| {
        teacher_sigma(teacher, points).into_iter().map(|s| s.min(65504.0)).collect()
    });
    let sigma_min = -(1.0 - cfg.min_step_opacity).ln() / cfg.step(&bounds);
    candidates.retain(|_, sigma| sigma.iter().any(|&s| s >= sigma_min))
}

/// One training ray that hits the density cubes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HitRay {
    pub image: u32,
    pub x_px: u16,
    pub y_px: u16,
    pub p_hit: Vec3,
    pub alpha_c: f32,
    pub more: MoreHits,
}

impl HitRay {
    /// Every point this ray queries the network at.
    pub fn points(&self) -> impl Iterator<Item = Vec3> + '_ {
        self.more.queries(self.p_hit).map(|(p, _)| p)
    }
}

/// A ray's queries beyond its primary hit `p_hit` (the multi-hit rule, [`model::MultiHit`]),
/// and the blend weights of all of them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MoreHits {
    pub p: [Vec3; model::MAX_HITS - 1],
    /// Blend weights, primary first; sum to 1.
    pub beta: [f32; model::MAX_HITS],
    pub count: u8,
}

impl Default for MoreHits {
    /// One hit.
    fn default() -> Self {
        let mut beta = [0.0; model::MAX_HITS];
        beta[0] = 1.0;
        Self { p: [Vec3::ZERO; model::MAX_HITS - 1], beta, count: 1 }
    }
}

impl MoreHits {
    /// From a march result along `o + t·d`.
    pub fn of(m: &model::MultiHit, o: Vec3, d: Vec3) -> Self {
        let mut out = Self { beta: m.beta, count: m.count.max(1) as u8, ..Self::default() };
        for i in 1..m.count as usize {
            out.p[i - 1] = o + m.t[i] * d;
        }
        out
    }

    /// `(point, blend weight)` of every query, primary first.
    pub fn queries(&self, p_hit: Vec3) -> impl Iterator<Item = (Vec3, f32)> + '_ {
        std::iter::once(p_hit).chain(self.p.iter().copied()).zip(self.beta).take(self.count as usize)
    }
}

/// Most degrees a teacher view's camera is turned from the training camera it starts from.
pub const TEACHER_VIEW_TURN_DEG: f64 = 20.0;

/// The images plus `count` views rendered by the teacher (RGB and α, straight) from cameras
/// the images do not have: each is a random training camera turned about the point the
/// training cameras look at (their least-squares meeting point) by up to
/// [`TEACHER_VIEW_TURN_DEG`] about a random axis, so it sees the object from between and
/// around the captured views, with the same intrinsics and up vector as the camera it came
/// from. The student then learns the teacher's appearance there too, instead of only at the
/// captured pixels (at 400×400 on lego, a student fitted to 70 views alone overfits: finer
/// diffuse cubes raise its training PSNR and lower its held-out PSNR).
pub fn with_teacher_views(teacher: &Trainer, data: &Dataset, count: usize, seed: u64, progress: &(dyn Fn(usize) + Sync)) -> Dataset {
    let mut out = data.clone();
    if count == 0 || data.images.is_empty() {
        return out;
    }
    // Where the training cameras look: the point nearest to all their optical axes.
    let (mut a, mut b) = (glam::DMat3::ZERO, glam::DVec3::ZERO);
    for im in &data.images {
        let m = im.view.world_from_camera;
        let (o, d) = (m.w_axis.truncate(), -m.z_axis.truncate().normalize());
        let p = glam::DMat3::IDENTITY - glam::DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += p;
        b += p * o;
    }
    let centre = if a.determinant().abs() > 1e-9 { a.inverse() * b } else { glam::DVec3::ZERO };
    let mut rng = SmallRng::seed_from_u64(seed ^ 0x0074_6561_6368_6572);
    let views: Vec<(usize, glam::DMat4)> = (0..count)
        .map(|_| {
            let j = rng.random_range(0..data.images.len());
            let axis = glam::DVec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)).normalize_or(glam::DVec3::Z);
            let angle = rng.random_range(0.0..TEACHER_VIEW_TURN_DEG).to_radians();
            let turn = glam::DMat4::from_translation(centre) * glam::DMat4::from_axis_angle(axis, angle) * glam::DMat4::from_translation(-centre);
            (j, turn * data.images[j].view.world_from_camera)
        })
        .collect();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let rendered: Vec<DatasetImage> = views
        .iter()
        .enumerate()
        .map(|(i, &(j, world_from_camera))| {
            let like = &data.images[j];
            let mut image = DatasetImage { view: View { world_from_camera, intrinsics: like.view.intrinsics }, width: like.width, height: like.height, rgba: Vec::new(), path: format!("teacher view {i} (from {})", like.path.display()).into() };
            let rays: Vec<(Vec3, Vec3)> = image.rays().collect();
            // Over black the colour is premultiplied by α.
            image.rgba = teacher
                .render(&rays, Vec3::ZERO)
                .into_iter()
                .flat_map(|(premultiplied, alpha)| {
                    let rgb = if alpha > 1e-4 { (premultiplied / alpha).clamp(Vec3::ZERO, Vec3::ONE) } else { Vec3::ZERO };
                    [rgb.x, rgb.y, rgb.z, alpha.clamp(0.0, 1.0)]
                })
                .collect();
            progress(done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1);
            image
        })
        .collect();
    out.images.extend(rendered);
    out
}

/// The per-query colour targets of [`DistillConfig::teacher_query_weight`]: per hit ray and
/// query, the teacher's colour averaged by weight over its own march samples within `window`
/// (ray-parameter units; the multi-hit rule's segment gap) of the query, and that weight
/// (≤ 1; 0 where the teacher has less than 10⁻³ of its weight there: no target). On the
/// oracle rows of `bench tradeoff`, such averaged colours are the ones that come within
/// 0.1 dB of the teacher on lego.
pub fn teacher_query_targets(teacher: &Trainer, data: &Dataset, hits: &Hits, window: f32) -> Vec<[[f32; 4]; model::MAX_HITS]> {
    hits.rays
        .par_chunks(teacher.model().rays_per_chunk.max(1))
        .flat_map_iter(|chunk| {
            let rays: Vec<NgpRay> = chunk
                .iter()
                .map(|h| {
                    let (origin, dir) = data.images[h.image as usize].ray(h.x_px as u32, h.y_px as u32);
                    NgpRay { origin, dir, background: Vec3::ZERO, jitter: 0.5 }
                })
                .collect();
            let samples = teacher_samples(teacher, &rays);
            chunk.iter().zip(rays).zip(samples).map(move |((h, ray), (samples, _))| {
                let mut acc = [[0.0f32; 4]; model::MAX_HITS];
                for (a, p) in acc.iter_mut().zip(h.points()) {
                    if let Some((c, w)) = teacher_colour_near(&samples, ray.dir.dot(p - ray.origin), window) {
                        *a = [c.x, c.y, c.z, w.min(1.0)];
                    }
                }
                acc
            })
        })
        .collect()
}

/// The teacher's colour averaged by weight over its samples within `window` of `t_q` along
/// the ray, and that weight; `None` where the weight there is below 10⁻³.
pub fn teacher_colour_near(samples: &[(f32, f32, Vec3)], t_q: f32, window: f32) -> Option<(Vec3, f32)> {
    let (sum, w) = samples.iter().filter(|s| (s.0 - t_q).abs() <= window).fold((Vec3::ZERO, 0.0f32), |(c, w), s| (c + s.1 * s.2, w + s.1));
    (w > 1e-3).then(|| (sum / w, w))
}

/// One ray's march by the teacher: its samples `(t, weight, colour)` front to back, and the
/// transmittance left at the end.
pub type TeacherMarch = (Vec<(f32, f32, Vec3)>, f32);

/// The teacher's march along `rays` (one chunk): per ray, its samples front to back as
/// `(t, weight, colour)`, with `t` along the ray's direction and weight `T·α`, and the
/// transmittance left at the end (α = 1 − that).
pub fn teacher_samples(teacher: &Trainer, rays: &[NgpRay]) -> Vec<TeacherMarch> {
    let m = teacher.model();
    let delta = m.step_size();
    let out = m.forward_chunk(rays);
    let mut k0 = 0;
    rays.iter()
        .zip(&out.used)
        .map(|(ray, rows)| {
            let mut transmittance = 1.0f32;
            let samples = rows
                .iter()
                .enumerate()
                .map(|(i, &row)| {
                    let p = m.bounds.min + out.points01[row as usize] * m.bounds.size();
                    let alpha = -(-out.tape.sigma[row as usize] * delta).exp_m1();
                    let w = transmittance * alpha;
                    transmittance *= 1.0 - alpha;
                    (ray.dir.dot(p - ray.origin), w, Vec3::from_slice(&out.tape.rgb[3 * (k0 + i)..3 * (k0 + i) + 3]))
                })
                .collect();
            k0 += rows.len();
            (samples, transmittance)
        })
        .collect()
}

/// Stage 2b output: hits grouped by error-map tile.
#[derive(Debug, Clone)]
pub struct Hits {
    pub rays: Vec<HitRay>,
    /// `tile_start[t]..tile_start[t + 1]` are the hits of tile `t` (tiles are numbered image
    /// by image, row-major within an image).
    pub tile_start: Vec<usize>,
    pub tiles_x: u32,
    pub tiles_y: u32,
    pub total_rays: usize,
    /// Missed rays whose ground truth is at least half opaque (what the cubes lose).
    pub missed_opaque: usize,
}

/// Stage 2b: marches every pixel of every image through `density`.
pub fn march_rays(density: &TextureCubes, step: f32, alpha_min: f32, early_stop: f32, rule: &model::HitRule, data: &Dataset, tile: u32) -> Hits {
    let settings = RenderSettings { early_stop: Some(early_stop), ..Default::default() };
    let (w, h) = data.images.first().map_or((0, 0), |im| (im.width, im.height));
    let (tiles_x, tiles_y) = (w.div_ceil(tile), h.div_ceil(tile));
    let per_image: Vec<(Vec<HitRay>, Vec<usize>, usize)> = data
        .images
        .par_iter()
        .enumerate()
        .map(|(i, image)| {
            let mut rays = Vec::new();
            let mut counts = Vec::with_capacity((tiles_x * tiles_y) as usize);
            let mut missed = 0;
            for ty in 0..tiles_y {
                for tx in 0..tiles_x {
                    let before = rays.len();
                    for y in ty * tile..((ty + 1) * tile).min(image.height) {
                        for x in tx * tile..((tx + 1) * tile).min(image.width) {
                            let (o, d) = image.ray(x, y);
                            let hit = model::march_multi(density, o, d, step, &settings, rule);
                            if hit.march.alpha_c >= alpha_min {
                                let (p_hit, more) = (o + hit.march.t_hit * d, MoreHits::of(&hit, o, d));
                                rays.push(HitRay { image: i as u32, x_px: x as u16, y_px: y as u16, p_hit, alpha_c: hit.march.alpha_c, more });
                            } else if image.pixel(x, y)[3] >= 0.5 {
                                missed += 1;
                            }
                        }
                    }
                    counts.push(rays.len() - before);
                }
            }
            (rays, counts, missed)
        })
        .collect();
    let mut hits = Hits {
        rays: Vec::new(),
        tile_start: vec![0],
        tiles_x,
        tiles_y,
        total_rays: data.images.iter().map(|im| (im.width * im.height) as usize).sum(),
        missed_opaque: 0,
    };
    for (rays, counts, missed) in per_image {
        hits.rays.extend(rays);
        for c in counts {
            let last = *hits.tile_start.last().expect("starts with 0");
            hits.tile_start.push(last + c);
        }
        hits.missed_opaque += missed;
    }
    hits
}

/// Sets bit `i`.
fn set_bit(bits: &mut [u64], i: usize) {
    bits[i / 64] |= 1 << (i % 64);
}
fn get_bit(bits: &[u64], i: usize) -> bool {
    bits[i / 64] >> (i % 64) & 1 == 1
}

/// Cells of an `n³` grid over `bounds` holding any of `points`, dilated by `dilation` cells
/// (as sorted coordinates of an `(n + extra)³` lattice when `extra` is 1: grid vertices).
fn marked_cells(bounds: &Aabb, n: u32, extra: u32, points: impl Iterator<Item = Vec3>, dilation: u32) -> Vec<UVec3> {
    let side = (n + extra) as usize;
    let index = |v: UVec3| v.x as usize + side * (v.y as usize + side * v.z as usize);
    let mut bits = vec![0u64; (side * side * side).div_ceil(64)];
    for p in points {
        let g = ((p - bounds.min) / bounds.size() * n as f32).clamp(Vec3::ZERO, Vec3::splat(n as f32 - 1.0)).as_uvec3();
        // The cell's own corners (vertex lattice) or the cell itself.
        for c in 0..if extra == 1 { 8 } else { 1 } {
            set_bit(&mut bits, index(g + UVec3::new(c & 1, c >> 1 & 1, c >> 2)));
        }
    }
    let d = dilation as i32;
    let mut out = Vec::new();
    let mut dilated = bits.clone();
    for i in 0..side * side * side {
        if !get_bit(&bits, i) {
            continue;
        }
        let v = UVec3::new((i % side) as u32, (i / side % side) as u32, (i / (side * side)) as u32).as_ivec3();
        for dz in -d..=d {
            for dy in -d..=d {
                for dx in -d..=d {
                    let u = v + glam::IVec3::new(dx, dy, dz);
                    if u.min_element() >= 0 && u.max_element() < side as i32 {
                        set_bit(&mut dilated, index(u.as_uvec3()));
                    }
                }
            }
        }
    }
    for i in 0..side * side * side {
        if get_bit(&dilated, i) {
            out.push(UVec3::new((i % side) as u32, (i / side % side) as u32, (i / (side * side)) as u32));
        }
    }
    out
}

/// The PSH's vertices (of an `n³` grid over `bounds`): the corners of the cells holding hit
/// points, dilated by `dilation` vertices for views the cameras did not see, less those of no
/// cell that overlaps a density brick. A ray hits only inside density bricks, so a vertex
/// outside them is never read and the dilation costs only where a view can land.
fn psh_vertex_set(bounds: &Aabb, n: u32, density: &TextureCubes, hits: &Hits, dilation: u32) -> Vec<UVec3> {
    let near = marked_cells(bounds, n, 1, hits.rays.iter().flat_map(HitRay::points), dilation);
    if dilation == 0 {
        return near;
    }
    let side = n as usize + 1;
    let mut reachable = vec![0u64; (side * side * side).div_ceil(64)];
    let b = density.grid as usize;
    let n = n as usize;
    for (i, _) in density.index.iter().enumerate().filter(|(_, brick)| **brick >= 0) {
        let cell = [i % b, i / b % b, i / (b * b)];
        // PSH cells overlapping index cell `cell`, then their corners.
        let lo = cell.map(|c| c * n / b);
        let hi = cell.map(|c| ((c + 1) * n).div_ceil(b).min(n));
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    set_bit(&mut reachable, x + side * (y + side * z));
                }
            }
        }
    }
    near.into_iter().filter(|v| get_bit(&reachable, v.x as usize + side * (v.y as usize + side * v.z as usize))).collect()
}

/// `cells` of `cubes`' index grid as a mask over its cell indices.
fn cell_mask(cubes: &TextureCubes, cells: &[UVec3]) -> Vec<bool> {
    let mut mask = vec![false; cubes.index.len()];
    for &c in cells.iter().filter(|c| c.max_element() < cubes.grid) {
        mask[cubes.cell_index(c)] = true;
    }
    mask
}

/// The diffuse net: `E_d(P_h)` (multi-resolution hash grid over the box) → 64 → 4 (c_d, tint).
#[derive(Debug, Clone)]
pub struct DiffuseNet {
    pub grid: HashGrid,
    pub mlp: Mlp,
}

/// The specular net's position encoding `E_s`.
#[derive(Debug, Clone)]
pub enum SpecularEncoding {
    /// A single-resolution grid stored in a perfect spatial hash: what an asset holds.
    /// Its values are the trainable features (f32 while training).
    Psh(SpatialHash),
    /// A multi-resolution hash grid over the box: the ablation rows of NEPHELE's Table 5
    /// before "+ PSH". Such a student renders only through [`super::variants`].
    HashGrid(HashGrid),
}

impl SpecularEncoding {
    /// Values per point.
    pub fn width(&self) -> usize {
        match self {
            Self::Psh(psh) => psh.features as usize,
            Self::HashGrid(grid) => grid.output_width(),
        }
    }

    pub fn params(&self) -> &[f32] {
        match self {
            Self::Psh(psh) => &psh.values,
            Self::HashGrid(grid) => &grid.params,
        }
    }

    pub fn params_mut(&mut self) -> &mut Vec<f32> {
        match self {
            Self::Psh(psh) => &mut psh.values,
            Self::HashGrid(grid) => &mut grid.params,
        }
    }

    /// Bytes stored: PSH keys, offsets and f16 features, or the f32 hash table.
    pub fn stored_bytes(&self) -> u64 {
        match self {
            Self::Psh(psh) => psh.stored_bytes(),
            Self::HashGrid(grid) => 4 * grid.params.len() as u64,
        }
    }

    /// `E_s` at object-space `p` (`p01` is the same point in the unit cube of the box).
    fn encode(&self, p: Vec3, p01: Vec3, out: &mut [f32]) {
        match self {
            Self::Psh(psh) => psh.encode(p, out),
            Self::HashGrid(grid) => grid.encode(p01, out),
        }
    }

    /// Adds `∂loss/∂params` given `∂loss/∂E_s` per point (`points × width`).
    fn backward(&self, points: &[Vec3], points01: &[Vec3], d_encoded: &[f32], grad: &mut [f32]) {
        match self {
            Self::Psh(psh) => {
                let f = psh.features as usize;
                for (&p, d) in points.iter().zip(d_encoded.chunks_exact(f)) {
                    for (slot, w) in psh.corner_slots(p) {
                        for (g, v) in grad[slot * f..(slot + 1) * f].iter_mut().zip(d) {
                            *g += w * v;
                        }
                    }
                }
            }
            Self::HashGrid(grid) => grid.backward(points01, d_encoded, grad),
        }
    }
}

/// The nets of stage 3.
#[derive(Debug, Clone)]
pub struct Student {
    pub bounds: Aabb,
    /// `None` in the "base" ablation rows: no diffuse/specular split, the specular net's
    /// colour is the whole colour (`c_d = 0`, tint 1).
    pub diffuse: Option<DiffuseNet>,
    /// When set, the diffuse net is read as the renderer reads the baked cubes: evaluated at
    /// the 8 corners of the cell of this fine lattice (cells per axis over `bounds`) around
    /// the hit, outputs blended trilinearly. Training then optimises what is baked.
    pub diffuse_lattice: Option<u32>,
    pub encoding: SpecularEncoding,
    /// `[E_s, SH4, α_c] → 64 → 64 → 4` (c_s, α).
    pub specular_mlp: Mlp,
}

/// Gradients of every [`Student`] parameter group (empty for a group the student lacks).
#[derive(Debug, Clone, Default)]
pub struct StudentGradients {
    pub diffuse_grid: Vec<f32>,
    pub diffuse_mlp: Vec<f32>,
    pub encoding: Vec<f32>,
    pub specular_mlp: Vec<f32>,
}

/// One ray of a batch: its hit and target.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StudentRay {
    /// The primary hit; `more` holds the others and every query's blend weight.
    pub p_hit: Vec3,
    pub more: MoreHits,
    pub dir: Vec3,
    pub alpha_c: f32,
    /// Straight RGB and alpha of the pixel.
    pub rgb: Vec3,
    pub alpha: f32,
    pub background: Vec3,
    /// Per query (primary first): a straight RGB target and its loss weight (0: none).
    pub query_targets: [[f32; 4]; model::MAX_HITS],
}

/// Forward results of one ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StudentOutput {
    /// Pixel over the ray's background, and α.
    pub pixel: Vec3,
    pub alpha: f32,
    /// `‖pixel − target‖²` and `(α − α_gt)²`.
    pub rgb_error: f32,
    pub alpha_error: f32,
    /// `Σ_q w_q β_q ‖c_q − c_q,target‖²` over the queries' colours and targets.
    pub target_error: f32,
}

/// Where a chunk's diffuse colour and tint come from.
#[derive(Clone, Copy)]
enum DiffuseSource<'a> {
    /// The student's own net (or constant `c_d = 0`, tint 1 without one).
    Own,
    /// Read from baked cubes (`[r, g, b, tint]`) at each query.
    Cubes(&'a TextureCubes),
}

#[derive(Default)]
struct ChunkGradients {
    /// Where the diffuse net was evaluated (rows of `d_diffuse_encoded`).
    diffuse_points01: Vec<Vec3>,
    diffuse_mlp: Vec<f32>,
    specular_mlp: Vec<f32>,
    d_diffuse_encoded: Vec<f32>,
    d_specular_encoded: Vec<f32>,
    /// Where the specular encoding was read (rows of `d_specular_encoded`).
    specular_points: Vec<Vec3>,
    outputs: Vec<StudentOutput>,
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

impl Student {
    /// The student `cfg` describes: E_s from `psh`, or from `cfg.specular_hash_grid` when
    /// set; a diffuse net when `cfg.diffuse_net`.
    pub fn new(bounds: Aabb, psh: SpatialHash, cfg: &DistillConfig, rng: &mut impl Rng) -> Self {
        let diffuse = cfg.diffuse_net.then(|| {
            let grid = HashGrid::new(cfg.diffuse_encoding, rng);
            let mut mlp = Mlp::new(&[grid.output_width(), HIDDEN, 4], rng);
            // The specular term starts off (tint ≈ 0.02) and earns its place, so noise in the
            // per-vertex features is not mixed into every colour from the first step.
            let tint_bias = mlp.params().len() - 1;
            mlp.update(|p| p[tint_bias] = -4.0);
            DiffuseNet { grid, mlp }
        });
        let encoding = match cfg.specular_hash_grid {
            Some(grid) => SpecularEncoding::HashGrid(HashGrid::new(grid, rng)),
            None => SpecularEncoding::Psh(psh),
        };
        let specular_mlp = Mlp::new(&[encoding.width() + SH_COEFFS + 1, HIDDEN, HIDDEN, 4], rng);
        let diffuse_lattice = (cfg.diffuse_net && cfg.train_on_bake_lattice).then_some(cfg.diffuse_grid * cfg.diffuse_brick);
        Self { bounds, diffuse, diffuse_lattice, encoding, specular_mlp }
    }

    pub fn to_unit(&self, p: Vec3) -> Vec3 {
        ((p - self.bounds.min) / self.bounds.size()).clamp(Vec3::ZERO, Vec3::ONE)
    }

    pub fn zero_gradients(&self) -> StudentGradients {
        let (grid, mlp) = self.diffuse.as_ref().map_or((0, 0), |d| (d.grid.params.len(), d.mlp.params().len()));
        StudentGradients {
            diffuse_grid: vec![0.0; grid],
            diffuse_mlp: vec![0.0; mlp],
            encoding: vec![0.0; self.encoding.params().len()],
            specular_mlp: vec![0.0; self.specular_mlp.params().len()],
        }
    }

    /// Bytes of every trained parameter as stored for rendering (f32 nets and hash tables,
    /// the PSH as an asset stores it).
    pub fn stored_bytes(&self) -> u64 {
        let diffuse = self.diffuse.as_ref().map_or(0, |d| d.grid.params.len() + d.mlp.params().len());
        4 * (diffuse + self.specular_mlp.params().len()) as u64 + self.encoding.stored_bytes()
    }

    /// Diffuse colour and tint at object-space points: `points × 4` (`c_d = 0`, tint 1
    /// without a diffuse net).
    pub fn diffuse(&self, points: &[Vec3]) -> Vec<f32> {
        let Some(net) = &self.diffuse else {
            return points.iter().flat_map(|_| [0.0, 0.0, 0.0, 1.0]).collect();
        };
        points
            .par_chunks(1024)
            .flat_map_iter(|chunk| {
                let points01: Vec<Vec3> = chunk.iter().map(|&p| self.to_unit(p)).collect();
                let mut enc = vec![0.0; points01.len() * net.grid.output_width()];
                net.grid.encode_batch(&points01, &mut enc);
                let mut tape = MlpTape::default();
                net.mlp.forward(&enc, &mut tape);
                tape.output().iter().map(|&o| sigmoid(o)).collect::<Vec<_>>()
            })
            .collect()
    }

    /// Where the diffuse net is evaluated for a hit and with what weights: the hit itself, or
    /// the 8 lattice corners around it (the trilinear rule of [`TextureCubes::sample`]).
    fn diffuse_taps(&self, p: Vec3, points01: &mut Vec<Vec3>, weights: &mut Vec<f32>) {
        let Some(res) = self.diffuse_lattice else {
            points01.push(self.to_unit(p));
            weights.push(1.0);
            return;
        };
        let n = res as f32;
        let g = ((p - self.bounds.min) * (n / self.bounds.size())).clamp(Vec3::ZERO, Vec3::splat(n));
        let base = g.as_uvec3().as_vec3().min(Vec3::splat(n - 1.0));
        let f = g - base;
        for corner in 0..8u32 {
            let d = Vec3::new((corner & 1) as f32, (corner >> 1 & 1) as f32, (corner >> 2) as f32);
            let w = Vec3::select(d.cmpeq(Vec3::ONE), f, Vec3::ONE - f);
            points01.push((base + d) / n);
            weights.push(w.x * w.y * w.z);
        }
    }

    /// Forward, and with `loss_scale` the backward pass of
    /// `loss_scale · Σ (‖e_rgb‖² + e_α² + target error)`.
    /// A ray's queries (one per hit, [`MoreHits`]) are shaded each as [`model::shade`] does
    /// and blended by their weights `β`: pixel `= Σ β_q pixel_q`, α `= Σ β_q α_q`.
    fn run_chunk(&self, rays: &[StudentRay], diffuse_source: DiffuseSource<'_>, loss_scale: Option<f32>) -> ChunkGradients {
        // Every query of the chunk: (ray, point, β).
        let queries: Vec<(usize, Vec3, f32)> = rays.iter().enumerate().flat_map(|(i, r)| r.more.queries(r.p_hit).map(move |(p, b)| (i, p, b))).collect();
        // Each query's place in its ray (for its target).
        let slots: Vec<usize> = rays.iter().flat_map(|r| 0..r.more.queries(r.p_hit).count()).collect();
        let nq = queries.len();
        let net = match diffuse_source {
            DiffuseSource::Own => self.diffuse.as_ref(),
            DiffuseSource::Cubes(_) => None,
        };
        // Diffuse colour and tint per query: the net's taps, blended, or given.
        let taps = if self.diffuse_lattice.is_some() { 8 } else { 1 };
        let (mut tap_points01, mut tap_weights) = (Vec::new(), Vec::new());
        let mut enc = Vec::new();
        let mut tape_d = MlpTape::default();
        let mut diffuse_out = Vec::new();
        let blended: Vec<[f32; 4]> = match (net, diffuse_source) {
            (_, DiffuseSource::Cubes(cubes)) => queries.iter().map(|q| cubes.sample::<4>(q.1)).collect(),
            (None, _) => vec![[0.0, 0.0, 0.0, 1.0]; nq],
            (Some(net), _) => {
                for &(_, p, _) in &queries {
                    self.diffuse_taps(p, &mut tap_points01, &mut tap_weights);
                }
                enc = vec![0.0; nq * taps * net.grid.output_width()];
                net.grid.encode_batch(&tap_points01, &mut enc);
                net.mlp.forward(&enc, &mut tape_d);
                diffuse_out = tape_d.output().iter().map(|&o| sigmoid(o)).collect();
                (0..nq)
                    .map(|q| {
                        let mut b = [0.0f32; 4];
                        for t in q * taps..(q + 1) * taps {
                            for (b, v) in b.iter_mut().zip(&diffuse_out[4 * t..4 * t + 4]) {
                                *b += tap_weights[t] * v;
                            }
                        }
                        b
                    })
                    .collect()
            }
        };
        // The specular net, once per query.
        let f = self.encoding.width();
        let ws = f + SH_COEFFS + 1;
        let mut xs = vec![0.0; nq * ws];
        let points: Vec<Vec3> = queries.iter().map(|q| q.1).collect();
        let points01: Vec<Vec3> = points.iter().map(|&p| self.to_unit(p)).collect();
        for ((&(i, p, _), &p01), x) in queries.iter().zip(&points01).zip(xs.chunks_exact_mut(ws)) {
            self.encoding.encode(p, p01, &mut x[..f]);
            x[f..f + SH_COEFFS].copy_from_slice(&sh4(rays[i].dir));
            x[f + SH_COEFFS] = rays[i].alpha_c;
        }
        let mut tape_s = MlpTape::default();
        self.specular_mlp.forward(&xs, &mut tape_s);
        // Each query's colour (before and after the clamp), specular colour and α.
        struct Shaded {
            u: Vec3,
            c: Vec3,
            c_s: Vec3,
            alpha: f32,
        }
        let shaded: Vec<Shaded> = (0..nq)
            .map(|q| {
                let os = &tape_s.output()[4 * q..4 * q + 4];
                let [r, g, b, tint] = blended[q];
                let c_s = Vec3::new(sigmoid(os[0]), sigmoid(os[1]), sigmoid(os[2]));
                let u = Vec3::new(r, g, b) + tint * c_s;
                Shaded { u, c: u.clamp(Vec3::ZERO, Vec3::ONE), c_s, alpha: sigmoid(os[3]) }
            })
            .collect();
        // Per ray: the blend, its errors, and d(loss)/d(pixel), d(loss)/d(α).
        let mut out = ChunkGradients::default();
        let (mut pixel, mut alpha, mut target_error) = (vec![Vec3::ZERO; rays.len()], vec![0.0f32; rays.len()], vec![0.0f32; rays.len()]);
        for ((&(i, _, beta), sh), &slot) in queries.iter().zip(&shaded).zip(&slots) {
            let bg = rays[i].background;
            pixel[i] += beta * (sh.alpha * sh.c + (1.0 - sh.alpha) * bg);
            alpha[i] += beta * sh.alpha;
            let [r, g, b, w] = rays[i].query_targets[slot];
            target_error[i] += w * beta * (sh.c - Vec3::new(r, g, b)).length_squared();
        }
        let mut d_ray = Vec::with_capacity(rays.len());
        for (i, ray) in rays.iter().enumerate() {
            let target = ray.alpha * ray.rgb + (1.0 - ray.alpha) * ray.background;
            let e = pixel[i] - target;
            let ea = alpha[i] - ray.alpha;
            out.outputs.push(StudentOutput { pixel: pixel[i], alpha: alpha[i], rgb_error: e.length_squared(), alpha_error: ea * ea, target_error: target_error[i] });
            if let Some(s) = loss_scale {
                d_ray.push((2.0 * s * e, 2.0 * s * ea));
            }
        }
        if loss_scale.is_none() {
            return out;
        }
        // Per query: the chain through the blend (× β) and [`model::shade`].
        let sig_d = |y: f32| y * (1.0 - y);
        let (mut d_od, mut d_os) = (vec![0.0; diffuse_out.len()], vec![0.0; nq * 4]);
        for (q, (&(i, _, beta), sh)) in queries.iter().zip(&shaded).enumerate() {
            let (d_pixel, d_alpha_loss) = d_ray[i];
            let tint = blended[q][3];
            let d_pixel = beta * d_pixel;
            let d_alpha = d_pixel.dot(sh.c - rays[i].background) + beta * d_alpha_loss;
            let inside = Vec3::select(sh.u.cmpgt(Vec3::ZERO) & sh.u.cmplt(Vec3::ONE), Vec3::ONE, Vec3::ZERO);
            let [r, g, b, w] = rays[i].query_targets[slots[q]];
            let d_target = 2.0 * loss_scale.unwrap_or(0.0) * w * beta * (sh.c - Vec3::new(r, g, b));
            let d_c = (sh.alpha * d_pixel + d_target) * inside;
            let d_cs = tint * d_c;
            if net.is_some() {
                let d_blended = [d_c.x, d_c.y, d_c.z, d_c.dot(sh.c_s)];
                for t in q * taps..(q + 1) * taps {
                    for ch in 0..4 {
                        d_od[4 * t + ch] = tap_weights[t] * d_blended[ch] * sig_d(diffuse_out[4 * t + ch]);
                    }
                }
            }
            let c_s = sh.c_s;
            d_os[4 * q..4 * q + 4].copy_from_slice(&[d_cs.x * sig_d(c_s.x), d_cs.y * sig_d(c_s.y), d_cs.z * sig_d(c_s.z), d_alpha * sig_d(sh.alpha)]);
        }
        if let Some(net) = net {
            out.diffuse_mlp = vec![0.0; net.mlp.params().len()];
            out.d_diffuse_encoded = vec![0.0; enc.len()];
            net.mlp.backward(&enc, &tape_d, &d_od, &mut out.diffuse_mlp, Some(&mut out.d_diffuse_encoded));
            out.diffuse_points01 = tap_points01;
        }
        out.specular_mlp = vec![0.0; self.specular_mlp.params().len()];
        let mut d_xs = vec![0.0; nq * ws];
        self.specular_mlp.backward(&xs, &tape_s, &d_os, &mut out.specular_mlp, Some(&mut d_xs));
        out.d_specular_encoded = d_xs.chunks_exact(ws).flat_map(|row| row[..f].iter().copied()).collect();
        out.specular_points = points;
        out
    }

    /// Per-ray results without gradients.
    pub fn forward(&self, rays: &[StudentRay], rays_per_chunk: usize) -> Vec<StudentOutput> {
        rays.par_chunks(rays_per_chunk.max(1)).flat_map_iter(|c| self.run_chunk(c, DiffuseSource::Own, None).outputs).collect()
    }

    /// Per-ray results with the diffuse colour and tint given per ray (read from baked
    /// cubes) instead of the diffuse net.
    pub fn forward_with_diffuse(&self, rays: &[StudentRay], diffuse: &TextureCubes, rays_per_chunk: usize) -> Vec<StudentOutput> {
        rays.par_chunks(rays_per_chunk.max(1)).flat_map_iter(|c| self.run_chunk(c, DiffuseSource::Cubes(diffuse), None).outputs).collect()
    }

    /// Adds the gradients of the batch loss `mean over rays of (‖e_rgb‖² + e_α² + target
    /// error) / 4` to `grads`; returns the per-ray results.
    pub fn gradients(&self, rays: &[StudentRay], rays_per_chunk: usize, grads: &mut StudentGradients) -> Vec<StudentOutput> {
        let scale = 1.0 / (4 * rays.len().max(1)) as f32;
        let chunks: Vec<ChunkGradients> = rays.par_chunks(rays_per_chunk.max(1)).map(|c| self.run_chunk(c, DiffuseSource::Own, Some(scale))).collect();
        let mut outputs = Vec::with_capacity(rays.len());
        let (mut d_diffuse, mut d_specular, mut diffuse_points01, mut points) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for c in chunks {
            diffuse_points01.extend(c.diffuse_points01);
            points.extend(c.specular_points);
            grads.diffuse_mlp.iter_mut().zip(&c.diffuse_mlp).for_each(|(g, d)| *g += d);
            grads.specular_mlp.iter_mut().zip(&c.specular_mlp).for_each(|(g, d)| *g += d);
            d_diffuse.extend(c.d_diffuse_encoded);
            d_specular.extend(c.d_specular_encoded);
            outputs.extend(c.outputs);
        }
        if let Some(net) = &self.diffuse {
            net.grid.backward(&diffuse_points01, &d_diffuse, &mut grads.diffuse_grid);
        }
        let points01: Vec<Vec3> = points.iter().map(|&p| self.to_unit(p)).collect();
        self.encoding.backward(&points, &points01, &d_specular, &mut grads.encoding);
        outputs
    }

    /// The specular MLP in the asset's layout.
    pub fn specular_for_asset(&self) -> SpecularMlp {
        let p = self.specular_mlp.params();
        let input = self.specular_mlp.input_width();
        let (l0, l1) = (input * HIDDEN + HIDDEN, HIDDEN * HIDDEN + HIDDEN);
        SpecularMlp {
            input,
            w0: p[..input * HIDDEN].to_vec(),
            b0: p[input * HIDDEN..l0].to_vec(),
            w1: p[l0..l0 + HIDDEN * HIDDEN].to_vec(),
            b1: p[l0 + HIDDEN * HIDDEN..l0 + l1].to_vec(),
            w2: p[l0 + l1..l0 + l1 + 4 * HIDDEN].to_vec(),
            b2: p[l0 + l1 + 4 * HIDDEN..].to_vec(),
        }
    }
}

/// Stage 3 state: the student, its optimisers and the error map.
#[derive(Debug, Clone)]
pub struct Distiller {
    pub config: DistillConfig,
    pub student: Student,
    pub hits: Hits,
    /// Per hit ray, [`teacher_query_targets`] (empty: none).
    pub query_targets: Vec<[[f32; 4]; model::MAX_HITS]>,
    pub step: u64,
    /// Running mean loss per tile (0 for tiles without hits).
    pub error_map: Vec<f32>,
    adam: [Adam; 4],
    grads: StudentGradients,
    /// Cumulative error over tiles, rebuilt every 16 steps.
    cdf: Vec<f64>,
}

/// What one distillation step gave.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct DistillStats {
    pub step: u64,
    /// Mean over rays and channels of the squared RGB error (over random backgrounds).
    pub rgb_mse: f64,
    pub alpha_mse: f64,
    pub ms: f64,
}

impl DistillStats {
    pub fn psnr(&self) -> f64 {
        -10.0 * self.rgb_mse.max(1e-12).log10()
    }
}

/// What the geometry stage made, with counts for the log.
#[derive(Debug, Clone)]
pub struct Geometry {
    pub bounds: Aabb,
    pub step: f32,
    pub density: TextureCubes,
    pub hits: Hits,
    pub psh_vertices: Vec<UVec3>,
}

/// Stage 2: fitted box, density cubes, hits of every training ray, PSH vertex set.
pub fn geometry(teacher: &Trainer, data: &Dataset, cfg: &DistillConfig) -> Result<Geometry, String> {
    cfg.validate()?;
    if data.images.iter().any(|im| im.width > u16::MAX as u32 + 1 || im.height > u16::MAX as u32 + 1) {
        return Err("images wider or taller than 65536 pixels are not supported; use --downscale".into());
    }
    let bounds = fit_bounds(teacher, data, cfg).ok_or("no training ray hits the field's density: nothing to model")?;
    let step = cfg.step(&bounds);
    let baked = bake_density(teacher, bounds, cfg);
    let first = march_rays(&baked, step, cfg.alpha_min, cfg.geometry_early_stop(), &cfg.hits, data, cfg.error_tile);
    // Keep only bricks near surfaces the cameras reach, then march again with exactly the
    // cubes (and the early stop) that will be stored.
    let near = cell_mask(&baked, &marked_cells(&bounds, cfg.density_grid, 0, first.rays.iter().flat_map(HitRay::points), cfg.density_dilation));
    let density = baked.retain(|i, _| near[i]);
    let hits = march_rays(&density, step, cfg.alpha_min, cfg.early_stop, &cfg.hits, data, cfg.error_tile);
    if hits.rays.is_empty() {
        return Err("no training ray hits the baked density: nothing to model".into());
    }
    let psh_vertices = psh_vertex_set(&bounds, cfg.psh_grid, &density, &hits, cfg.psh_dilation);
    Ok(Geometry { bounds, step, density, hits, psh_vertices })
}

impl Geometry {
    /// The same geometry with the PSH vertex set for another grid `N` (for the PSH variants).
    pub fn with_psh_grid(&self, psh_grid: u32, dilation: u32) -> Self {
        let psh_vertices = psh_vertex_set(&self.bounds, psh_grid, &self.density, &self.hits, dilation);
        Self { psh_vertices, ..self.clone() }
    }
}

impl Distiller {
    pub fn new(geometry: Geometry, cfg: DistillConfig) -> Result<Self, PshError> {
        let mut rng = SmallRng::seed_from_u64(mix(cfg.seed, 0, 10));
        let f = cfg.psh_features;
        let psh = SpatialHash::build(
            geometry.bounds,
            cfg.psh_grid,
            f,
            &geometry.psh_vertices,
            |_, out| out.iter_mut().for_each(|v| *v = 0.0),
            mix(cfg.seed, 0, 11),
        )?;
        let mut student = Student::new(geometry.bounds, psh, &cfg, &mut rng);
        // Stored entries start small and random (as hash-grid entries do); free slots stay 0.
        if let SpecularEncoding::Psh(psh) = &mut student.encoding {
            let keys = psh.keys.clone();
            for (slot, values) in psh.values.chunks_exact_mut(f as usize).enumerate() {
                if keys[slot] != nephele_renderer::psh::EMPTY_KEY {
                    values.iter_mut().for_each(|v| *v = rng.random_range(-1e-4..1e-4));
                }
            }
        }
        let grads = student.zero_gradients();
        let adam = [
            Adam::new(cfg.adam, grads.diffuse_grid.len()),
            Adam::new(cfg.adam, grads.diffuse_mlp.len()),
            Adam::new(cfg.adam, grads.encoding.len()),
            Adam::new(cfg.adam, grads.specular_mlp.len()),
        ];
        let tiles = geometry.hits.tile_start.len() - 1;
        let error_map = (0..tiles).map(|t| if geometry.hits.tile_start[t + 1] > geometry.hits.tile_start[t] { 1.0 } else { 0.0 }).collect();
        let mut d = Self { config: cfg, student, hits: geometry.hits, query_targets: Vec::new(), step: 0, error_map, adam, grads, cdf: Vec::new() };
        d.rebuild_cdf();
        Ok(d)
    }

    fn rebuild_cdf(&mut self) {
        let mut total = 0.0f64;
        self.cdf = self.error_map.iter().map(|&e| {
            total += e as f64;
            total
        }).collect();
    }

    /// The next batch: indices into `hits.rays` and their tiles.
    fn sample(&self) -> Vec<(usize, usize)> {
        let mut rng = SmallRng::seed_from_u64(mix(self.config.seed, self.step, 12));
        let n = self.config.rays_per_batch;
        let from_map = (n as f32 * self.config.error_fraction) as usize;
        let total = self.cdf.last().copied().unwrap_or(0.0);
        let starts = &self.hits.tile_start;
        (0..n)
            .map(|k| {
                if k < from_map && total > 0.0 {
                    let u = rng.random::<f64>() * total;
                    let tile = self.cdf.partition_point(|&c| c <= u).min(self.cdf.len() - 1);
                    let (a, b) = (starts[tile], starts[tile + 1]);
                    if b > a {
                        return (rng.random_range(a..b), tile);
                    }
                }
                let i = rng.random_range(0..self.hits.rays.len());
                (i, starts.partition_point(|&s| s <= i) - 1)
            })
            .collect()
    }

    /// One Adam step on a batch drawn from `data` (the dataset the hits came from).
    pub fn train_step(&mut self, data: &Dataset) -> DistillStats {
        let start = Instant::now();
        let picks = self.sample();
        let mut rng = SmallRng::seed_from_u64(mix(self.config.seed, self.step, 13));
        let rays: Vec<StudentRay> = picks
            .iter()
            .map(|&(i, _)| {
                let h = self.hits.rays[i];
                let image = &data.images[h.image as usize];
                let (_, dir) = image.ray(h.x_px as u32, h.y_px as u32);
                let [r, g, b, a] = image.pixel(h.x_px as u32, h.y_px as u32);
                let background = Vec3::new(rng.random(), rng.random(), rng.random());
                let query_targets = self.query_targets.get(i).map_or([[0.0; 4]; model::MAX_HITS], |t| t.map(|q| [q[0], q[1], q[2], q[3] * self.config.teacher_query_weight]));
                StudentRay { p_hit: h.p_hit, more: h.more, dir, alpha_c: h.alpha_c, rgb: Vec3::new(r, g, b), alpha: a, background, query_targets }
            })
            .collect();
        let mut grads = std::mem::take(&mut self.grads);
        let outputs = self.student.gradients(&rays, self.config.rays_per_chunk, &mut grads);
        let l2 = self.config.l2_mlp_weights;
        if let Some(net) = &self.student.diffuse {
            add_l2(net.mlp.params(), &mut grads.diffuse_mlp, &net.mlp.weight_ranges(), l2);
        }
        add_l2(self.student.specular_mlp.params(), &mut grads.specular_mlp, &self.student.specular_mlp.weight_ranges(), l2);
        let factor = self.config.learning_rate_schedule.iter().rev().find(|(from, _)| self.step >= *from).map_or(1.0, |(_, f)| *f);
        for adam in &mut self.adam {
            adam.config.learning_rate = self.config.adam.learning_rate * factor;
        }
        let [a_grid, a_dmlp, a_enc, a_smlp] = &mut self.adam;
        if let Some(net) = &mut self.student.diffuse {
            a_grid.step(&mut net.grid.params, &mut grads.diffuse_grid, true);
            net.mlp.update(|p| a_dmlp.step(p, &mut grads.diffuse_mlp, false));
        }
        a_enc.step(self.student.encoding.params_mut(), &mut grads.encoding, true);
        self.student.specular_mlp.update(|p| a_smlp.step(p, &mut grads.specular_mlp, false));
        self.grads = grads;
        // Error map: running mean of the loss of the rays drawn in each tile.
        for (&(_, tile), o) in picks.iter().zip(&outputs) {
            let e = &mut self.error_map[tile];
            *e = 0.9 * *e + 0.1 * (o.rgb_error + o.alpha_error).max(1e-6);
        }
        self.step += 1;
        if self.step.is_multiple_of(16) {
            self.rebuild_cdf();
        }
        let n = outputs.len().max(1) as f64;
        DistillStats {
            step: self.step,
            rgb_mse: outputs.iter().map(|o| o.rgb_error as f64).sum::<f64>() / (3.0 * n),
            alpha_mse: outputs.iter().map(|o| o.alpha_error as f64).sum::<f64>() / n,
            ms: start.elapsed().as_secs_f64() * 1e3,
        }
    }

    /// The diffuse net baked into cubes in the cells holding hits (and `diffuse_dilation`
    /// cells around them).
    pub fn bake_diffuse(&self) -> TextureCubes {
        let cfg = &self.config;
        let s = &self.student;
        let bounds = s.bounds;
        let cells = marked_cells(&bounds, cfg.diffuse_grid, 0, self.hits.rays.iter().flat_map(HitRay::points), cfg.diffuse_dilation);
        let g = cfg.diffuse_grid as usize;
        let mut wanted = vec![false; g * g * g];
        for c in &cells {
            wanted[c.x as usize + g * (c.y as usize + g * c.z as usize)] = true;
        }
        // The diffuse net, evaluated once for all corners of all wanted bricks.
        let occupied = |c: UVec3| wanted[c.x as usize + g * (c.y as usize + g * c.z as usize)];
        TextureCubes::bake_batched(bounds, cfg.diffuse_grid, cfg.diffuse_brick, 4, occupied, |points| s.diffuse(points)).stored_as(cfg.diffuse_storage)
    }

    /// Stage 4: bake the diffuse cubes and assemble the asset. Only students with a diffuse
    /// net and a PSH make assets.
    pub fn bake(&self, density: TextureCubes, step: f32, name: &str, provenance: serde_json::Value) -> Result<Asset, String> {
        let SpecularEncoding::Psh(psh) = &self.student.encoding else {
            return Err("a student with a hash-grid E_s has no asset form (it is a Table 5 ablation)".into());
        };
        if self.student.diffuse.is_none() {
            return Err("a student without a diffuse net has no asset form (it is a Table 5 ablation)".into());
        }
        let mut psh = psh.clone();
        psh.values.iter_mut().for_each(|v| *v = half::f16::from_f32(*v).to_f32());
        Ok(Asset {
            name: name.to_string(),
            bounds: self.student.bounds,
            march: MarchMeta { step, alpha_min: self.config.alpha_min, hits: self.config.hit_rule(), early_stop: self.config.early_stop },
            density,
            diffuse: self.bake_diffuse(),
            psh,
            mlp: self.student.specular_for_asset(),
            provenance,
        })
    }
}

pub const STUDENT_FORMAT: &str = "nephele-nolf-student";
/// The `__metadata__` key of the student's JSON.
const STUDENT_KEY: &str = "nolf_student";

fn encoding_tensor(e: &SpecularEncoding) -> &'static str {
    match e {
        SpecularEncoding::Psh(_) => "psh_values",
        SpecularEncoding::HashGrid(_) => "specular_grid",
    }
}

impl Distiller {
    /// The trained nets in a [`container`] file (f32 tensors `diffuse_grid`, `diffuse_mlp`,
    /// `psh_values` or `specular_grid`, `specular_mlp`; JSON metadata `nolf_student` with the
    /// step and configuration). The geometry is not stored: it is recomputed,
    /// deterministically, from the teacher. Written at the end of the stage, so a resumed run
    /// skips a finished stage. `teacher_step` names the i-NGP state the geometry came from.
    pub fn student_bytes(&self, teacher_step: u64) -> Result<Vec<u8>, String> {
        let s = &self.student;
        let bytes = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        let mut data = Vec::new();
        if let Some(net) = &s.diffuse {
            data.push(("diffuse_grid", bytes(&net.grid.params)));
            data.push(("diffuse_mlp", bytes(net.mlp.params())));
        }
        data.push((encoding_tensor(&s.encoding), bytes(s.encoding.params())));
        data.push(("specular_mlp", bytes(s.specular_mlp.params())));
        let tensors: Vec<Tensor<'_>> = data.iter().map(|(name, b)| Tensor { name, dtype: Dtype::F32, shape: vec![b.len() / 4], data: b }).collect();
        let meta = serde_json::json!({ "format": STUDENT_FORMAT, "version": 1, "step": self.step, "teacher_step": teacher_step, "config": self.config, "encoding_values": s.encoding.params().len() });
        container::write(STUDENT_KEY, &meta, &tensors).map_err(|e| e.to_string())
    }

    /// Loads nets written by [`Self::student_bytes`] into this distiller (same configuration
    /// and geometry). Every mismatch is an error naming what differs. Files written before
    /// student checkpoints had checksums still load.
    pub fn load_student(&mut self, bytes: &[u8], teacher_step: u64) -> Result<(), String> {
        let file = Reader::new(bytes, STUDENT_KEY, Verify::WhenPresent).map_err(|e| format!("not a student checkpoint: {e}"))?;
        let meta: serde_json::Value = file.meta().map_err(|e| format!("not a student checkpoint: {e}"))?;
        if meta["format"] != STUDENT_FORMAT || meta["version"] != 1 {
            return Err(format!("unsupported student checkpoint {} v{}", meta["format"], meta["version"]));
        }
        if meta["teacher_step"] != teacher_step {
            return Err(format!("student checkpoint was distilled from the i-NGP field at step {}, not {teacher_step}; start afresh", meta["teacher_step"]));
        }
        let config: DistillConfig = serde_json::from_value(meta["config"].clone()).map_err(|e| format!("student checkpoint config: {e}"))?;
        if config != self.config {
            return Err("student checkpoint was trained with a different configuration; start afresh".into());
        }
        let read = |name: &'static str, want: usize| -> Result<Vec<f32>, String> {
            let data = file.tensor(name, Dtype::F32, &[want]).map_err(|e| format!("student checkpoint: {e}"))?;
            let v: Vec<f32> = data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
            if v.iter().any(|x| !x.is_finite()) {
                return Err(format!("student checkpoint tensor {name} has non-finite values"));
            }
            Ok(v)
        };
        let s = &mut self.student;
        let diffuse = match &s.diffuse {
            Some(net) => Some((read("diffuse_grid", net.grid.params.len())?, read("diffuse_mlp", net.mlp.params().len())?)),
            None => None,
        };
        let encoding = read(encoding_tensor(&s.encoding), s.encoding.params().len())?;
        let smlp = read("specular_mlp", s.specular_mlp.params().len())?;
        if let (Some(net), Some((grid, mlp))) = (&mut s.diffuse, diffuse) {
            net.grid.params = grid;
            net.mlp.update(|p| p.copy_from_slice(&mlp));
        }
        *s.encoding.params_mut() = encoding;
        s.specular_mlp.update(|p| p.copy_from_slice(&smlp));
        self.step = meta["step"].as_u64().unwrap_or(0);
        Ok(())
    }
}

/// Renders every pixel of a dataset view with the asset (the CPU reference maths of
/// [`model::march`] and [`model::shade`], unquantised) over `background`: interleaved RGB,
/// row-major, the layout of [`crate::dataset::DatasetImage::composite_over`].
pub fn render_image(asset: &Asset, image: &crate::dataset::DatasetImage, background: Vec3) -> Vec<f32> {
    render_image_with(asset, image, background, &RenderSettings::default())
}

/// [`render_image`] with render knobs (step scale, hit rule, early stop).
pub fn render_image_with(asset: &Asset, image: &crate::dataset::DatasetImage, background: Vec3, settings: &RenderSettings) -> Vec<f32> {
    let net = asset.mlp.kernel();
    let settings = &settings.for_asset(&asset.march);
    let rule = settings.hit_rule(&asset.march.hits);
    let step = asset.march.step * settings.step_scale;
    let rays: Vec<(Vec3, Vec3)> = image.rays().collect();
    rays.par_iter()
        .flat_map_iter(|&(o, d)| {
            let m = model::march_multi(&asset.density, o, d, step, settings, &rule);
            let rgb = if m.march.alpha_c < settings.alpha_min.unwrap_or(asset.march.alpha_min) { background } else { model::shade_multi(asset, &net, &m, o, d, background).0 };
            rgb.to_array()
        })
        .collect()
}

#[cfg(test)]
mod tests;
