//! One training step of the i-NGP field (Müller et al. 2022; volume rendering as in NeRF,
//! Mildenhall et al. 2020):
//!
//! 1. draw `rays_per_batch` pixels uniformly over all images and pixels of the dataset, each
//!    with a random background colour: target `= rgb·a + bg·(1 − a)`;
//! 2. the forward pass of [`NgpModel::forward_chunk`] (in the renderer crate): march each ray
//!    through the scene box with a random offset within the first step, samples kept only in
//!    occupied cells of the [`OccupancyGrid`], σ front to back until
//!    `T < early_stop_transmittance`, colour only for the samples used, composited over the
//!    ray's background: `C = Σ T_i α_i c_i + T_end · bg`;
//! 3. loss `= mean over rays and channels of (C − target)²`;
//! 4. reverse accumulation: `∂C/∂c_i = T_i α_i`, and
//!    `∂C/∂σ_i = δ · (T_{i+1} c_i − Σ_{j>i} T_j α_j c_j − T_end bg)`, where the sum is
//!    `C − (everything up to i)`; then back through the field to the MLPs and hash grid;
//! 5. Adam on each parameter group (L2 on MLP weights only, zero-gradient grid entries skipped).
//!
//! Rays are processed in chunks in parallel (rayon); each chunk returns its own MLP gradients
//! and per-sample encoding gradients, summed in chunk order, so a step is deterministic for
//! a given seed whatever the thread count. The occupancy grid is refreshed every
//! `update_every` steps after a warm-up.

use std::time::Instant;

use glam::Vec3;
use nephele_renderer::{
    cubes::Aabb,
    ngp::{Field, FieldConfig, HashGridConfig, NgpModel, NgpRay, OccupancyGrid},
};
use rand::{Rng, SeedableRng, rngs::SmallRng};
use rayon::prelude::*;

use crate::{
    adam::{Adam, AdamConfig, add_l2},
    dataset::Dataset,
    field::{FieldBackward, FieldGradients},
    hash_grid::HashGridBackward,
};

#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OccupancyConfig {
    /// Cells per axis.
    pub resolution: u32,
    /// Steps between updates.
    pub update_every: u32,
    /// Steps before the first update (the grid is fully occupied until then).
    pub warmup_steps: u32,
    /// Per-update decay of the density estimates.
    pub decay: f32,
    /// Cells evaluated per update after the first (which evaluates all), as a fraction of all.
    pub fraction_per_update: f32,
    /// A cell is occupied if one step through it is at least this opaque (`σ·δ`), or its
    /// estimate is above the mean.
    pub min_optical_thickness: f32,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrainConfig {
    pub field: FieldConfig,
    /// Scene box, world space; positions are mapped from it to the unit cube.
    pub bounds: Aabb,
    /// Ray-marching step `δ = bounds diagonal / steps_per_diagonal`.
    pub steps_per_diagonal: u32,
    /// Early ray termination; 0 disables it.
    pub early_stop_transmittance: f32,
    pub rays_per_batch: usize,
    /// Rays per parallel work item.
    pub rays_per_chunk: usize,
    pub adam: AdamConfig,
    /// L2 weight on MLP weights (added to their gradients).
    pub l2_mlp_weights: f32,
    pub occupancy: OccupancyConfig,
    pub seed: u64,
    /// Learning-rate multipliers: `(from step, factor)`, ascending; 1 before the first.
    #[serde(default)]
    pub learning_rate_schedule: Vec<(u64, f32)>,
}

impl TrainConfig {
    /// instant-ngp's NeRF setup on NeRF-synthetic's [-1.5, 1.5]³: L = 16, T = 2¹⁹,
    /// resolutions 16…2048, 64-wide MLPs, 128³ occupancy, 1024 steps per diagonal. The
    /// occupancy grid is first estimated (all cells) after 16 steps, then 1/8 of the cells
    /// every 16 steps: marching the full box is the most expensive part of early training.
    pub fn full() -> Self {
        Self {
            field: FieldConfig {
                grid: HashGridConfig { levels: 16, log2_table_size: 19, base_resolution: 16, finest_resolution: 2048 },
                density_hidden: vec![64],
                colour_hidden: vec![64, 64],
            },
            bounds: Aabb::cube(1.5),
            steps_per_diagonal: 1024,
            early_stop_transmittance: 1e-4,
            rays_per_batch: 4096,
            rays_per_chunk: 32,
            adam: AdamConfig::default(),
            l2_mlp_weights: 1e-6,
            occupancy: OccupancyConfig {
                resolution: 128,
                update_every: 16,
                warmup_steps: 16,
                decay: 0.95,
                fraction_per_update: 0.125,
                min_optical_thickness: 0.01,
            },
            seed: 0,
            learning_rate_schedule: Vec::new(),
        }
    }

    /// Small and fast, for tests: L = 8, T = 2¹⁴, resolutions 16…256, 1024 rays per batch,
    /// 32³ occupancy (every cell re-evaluated each update), 256 steps per diagonal.
    pub fn tiny() -> Self {
        let full = Self::full();
        Self {
            field: FieldConfig {
                grid: HashGridConfig { levels: 8, log2_table_size: 14, base_resolution: 16, finest_resolution: 256 },
                ..full.field
            },
            steps_per_diagonal: 256,
            rays_per_batch: 1024,
            occupancy: OccupancyConfig { resolution: 32, fraction_per_update: 1.0, ..full.occupancy },
            ..full
        }
    }
}

impl TrainConfig {
    /// Between [`Self::tiny`] and [`Self::full`], for CPU runs on real scenes in minutes
    /// rather than hours: L = 16, T = 2¹⁷, resolutions 16…1024, 2048 rays per batch, 64³
    /// occupancy (¼ of the cells per update), 512 steps per diagonal.
    pub fn fast() -> Self {
        let full = Self::full();
        Self {
            field: FieldConfig {
                grid: HashGridConfig { levels: 16, log2_table_size: 17, base_resolution: 16, finest_resolution: 1024 },
                ..full.field
            },
            steps_per_diagonal: 512,
            rays_per_batch: 2048,
            occupancy: OccupancyConfig { resolution: 64, fraction_per_update: 0.25, ..full.occupancy },
            ..full
        }
    }

    /// Names accepted by [`Self::preset`].
    pub const PRESETS: [&'static str; 4] = ["tiny", "fast", "default", "quality"];

    /// `tiny`, `fast`, or `default` and `quality` (both [`Self::full`]; they differ in steps).
    pub fn preset(name: &str) -> Option<Self> {
        match name {
            "tiny" => Some(Self::tiny()),
            "fast" => Some(Self::fast()),
            "default" | "quality" | "full" => Some(Self::full()),
            _ => None,
        }
    }

    /// Range checks on everything that sizes an allocation or a loop, so a configuration
    /// read from a file cannot ask for absurd memory or panic in [`Trainer::new`].
    pub fn validate(&self) -> Result<(), String> {
        self.field.grid.validate()?;
        let widths_ok = |w: &[usize]| w.len() <= 8 && w.iter().all(|&n| (1..=1024).contains(&n));
        if !widths_ok(&self.field.density_hidden) || !widths_ok(&self.field.colour_hidden) {
            return Err(format!("MLP hidden widths out of range: {:?} / {:?}", self.field.density_hidden, self.field.colour_hidden));
        }
        if !self.bounds.is_valid() {
            return Err(format!("invalid scene bounds {:?}", self.bounds));
        }
        if !(1..=1 << 16).contains(&self.steps_per_diagonal) {
            return Err(format!("steps_per_diagonal {} out of range", self.steps_per_diagonal));
        }
        if !(1..=1 << 24).contains(&self.rays_per_batch) || !(1..=1 << 16).contains(&self.rays_per_chunk) {
            return Err(format!("rays per batch / chunk {} / {} out of range", self.rays_per_batch, self.rays_per_chunk));
        }
        if !(1..=512).contains(&self.occupancy.resolution) {
            return Err(format!("occupancy resolution {} out of range", self.occupancy.resolution));
        }
        let finite = [self.early_stop_transmittance, self.l2_mlp_weights, self.adam.learning_rate, self.adam.beta1, self.adam.beta2, self.adam.epsilon]
            .iter()
            .chain(&[self.occupancy.decay, self.occupancy.fraction_per_update, self.occupancy.min_optical_thickness])
            .all(|v| v.is_finite());
        if !finite || !self.learning_rate_schedule.iter().all(|(_, f)| f.is_finite() && *f > 0.0) {
            return Err("non-finite optimiser or occupancy setting".into());
        }
        Ok(())
    }
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self::full()
    }
}

/// One training ray, world space.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrainRay {
    pub origin: Vec3,
    /// Unit direction.
    pub dir: Vec3,
    /// Pixel colour over `background`.
    pub target: Vec3,
    pub background: Vec3,
    /// Sample offset within a step, in [0, 1).
    pub jitter: f32,
}

/// What one batch cost and gave.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct BatchStats {
    /// Mean squared error over rays and channels.
    pub loss: f64,
    pub rays: usize,
    /// Samples whose density was evaluated.
    pub samples: usize,
    /// Samples whose colour was evaluated (before early termination).
    pub coloured_samples: usize,
}

impl BatchStats {
    /// `−10·log10(loss)`, in dB.
    pub fn psnr(&self) -> f64 {
        -10.0 * self.loss.max(1e-12).log10()
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StepStats {
    pub step: u64,
    pub batch: BatchStats,
    pub occupancy_ms: f64,
    pub total_ms: f64,
}

/// The field, its occupancy grid and optimiser state.
#[derive(Debug, Clone)]
pub struct Trainer {
    pub config: TrainConfig,
    pub field: Field,
    pub occupancy: OccupancyGrid,
    /// Steps taken.
    pub step: u64,
    grads: FieldGradients,
    adam_grid: Adam,
    adam_density: Adam,
    adam_colour: Adam,
}

/// Result of one chunk of rays.
#[derive(Debug, Default)]
struct ChunkOutput {
    squared_error: f64,
    samples: usize,
    coloured_samples: usize,
    /// Backward only: positions and ∂loss/∂encoding of the coloured samples, MLP gradients.
    points01: Vec<Vec3>,
    d_encoded: Vec<f32>,
    density_grad: Vec<f32>,
    colour_grad: Vec<f32>,
}

/// A well-mixed 64-bit value from a seed and two counters (splitmix64 finaliser).
pub(crate) fn mix(seed: u64, a: u64, b: u64) -> u64 {
    let mut x = seed ^ a.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ b.wrapping_mul(0xc2b2_ae3d_27d4_eb4f);
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

impl Trainer {
    pub fn new(config: TrainConfig) -> Self {
        assert!(config.bounds.is_valid() && config.steps_per_diagonal > 0 && config.rays_per_chunk > 0);
        let mut rng = SmallRng::seed_from_u64(mix(config.seed, 0, 0));
        let field = Field::new(&config.field, &mut rng);
        let occupancy = OccupancyGrid::new(config.bounds, config.occupancy.resolution);
        let grads = field.zero_gradients();
        let adam_grid = Adam::new(config.adam, field.grid.params.len());
        let adam_density = Adam::new(config.adam, field.density_mlp.params().len());
        let adam_colour = Adam::new(config.adam, field.colour_mlp.params().len());
        Self { config, field, occupancy, step: 0, grads, adam_grid, adam_density, adam_colour }
    }

    /// The field, its occupancy grid and the march settings of the configuration, as the
    /// renderer evaluates them.
    pub fn model(&self) -> NgpModel<'_> {
        NgpModel {
            field: &self.field,
            occupancy: &self.occupancy,
            bounds: self.config.bounds,
            steps_per_diagonal: self.config.steps_per_diagonal,
            early_stop_transmittance: self.config.early_stop_transmittance,
            rays_per_chunk: self.config.rays_per_chunk,
        }
    }

    /// Ray-marching step δ, scene units.
    pub fn step_size(&self) -> f32 {
        self.model().step_size()
    }

    /// Scene point → unit cube of the hash grid.
    pub fn to_unit(&self, p_in_world: Vec3) -> Vec3 {
        self.model().to_unit(p_in_world)
    }

    /// Appends the unit-cube positions of the samples along one ray (occupied cells only).
    pub fn march(&self, origin: Vec3, dir: Vec3, jitter: f32, points01: &mut Vec<Vec3>) {
        self.model().march(origin, dir, jitter, points01)
    }

    /// Random rays of the next batch (deterministic in seed and step).
    pub fn sample_batch(&self, data: &Dataset) -> Vec<TrainRay> {
        assert!(!data.images.is_empty());
        let mut rng = SmallRng::seed_from_u64(mix(self.config.seed, self.step, 1));
        (0..self.config.rays_per_batch)
            .map(|_| {
                let image = &data.images[rng.random_range(0..data.images.len())];
                let (x, y) = (rng.random_range(0..image.width), rng.random_range(0..image.height));
                let (origin, dir) = image.ray(x, y);
                let [r, g, b, a] = image.pixel(x, y);
                let background = Vec3::new(rng.random(), rng.random(), rng.random());
                let target = Vec3::new(r, g, b) * a + background * (1.0 - a);
                TrainRay { origin, dir, target, background, jitter: rng.random() }
            })
            .collect()
    }

    /// Forward (and with `loss_scale`, backward) over one chunk. `loss_scale` multiplies the
    /// summed squared error to give the batch loss.
    fn run_chunk(&self, rays: &[TrainRay], loss_scale: Option<f32>) -> ChunkOutput {
        let model = self.model();
        let delta = model.step_size();
        let marched: Vec<NgpRay> =
            rays.iter().map(|r| NgpRay { origin: r.origin, dir: r.dir, background: r.background, jitter: r.jitter }).collect();
        let forward = model.forward_chunk(&marched);
        let (tape, used) = (&forward.tape, &forward.used);

        let mut out = ChunkOutput { samples: forward.points01.len(), coloured_samples: tape.coloured.len(), ..ChunkOutput::default() };
        let mut d_sigma = vec![0.0f32; if loss_scale.is_some() { tape.coloured.len() } else { 0 }];
        let mut d_rgb = vec![0.0f32; if loss_scale.is_some() { tape.rgb.len() } else { 0 }];
        let mut k0 = 0;
        for ((ray, rows), &c) in rays.iter().zip(used).zip(&forward.rgb) {
            let n = rows.len();
            let colour = |i: usize| Vec3::from_slice(&tape.rgb[3 * (k0 + i)..3 * (k0 + i) + 3]);
            let alpha = |i: usize| -(-tape.sigma[rows[i] as usize] * delta).exp_m1();
            let error = c - ray.target;
            out.squared_error += error.length_squared() as f64;
            if let Some(scale) = loss_scale {
                let d_c = 2.0 * scale * error;
                let mut transmittance = 1.0f32;
                let mut so_far = Vec3::ZERO;
                for i in 0..n {
                    let (a, ci) = (alpha(i), colour(i));
                    let w = transmittance * a;
                    so_far += w * ci;
                    let after = transmittance * (1.0 - a);
                    d_sigma[k0 + i] = delta * d_c.dot(after * ci - (c - so_far));
                    d_rgb[3 * (k0 + i)..3 * (k0 + i) + 3].copy_from_slice(&(w * d_c).to_array());
                    transmittance = after;
                }
            }
            k0 += n;
        }
        if loss_scale.is_some() {
            out.density_grad = vec![0.0; self.field.density_mlp.params().len()];
            out.colour_grad = vec![0.0; self.field.colour_mlp.params().len()];
            self.field.backward(tape, &d_sigma, &d_rgb, &mut out.density_grad, &mut out.colour_grad, &mut out.d_encoded);
            out.points01 = tape.coloured.iter().map(|&s| forward.points01[s as usize]).collect();
        }
        out
    }

    /// Loss of a batch and its gradients, added to `grads`.
    pub fn gradients(&self, rays: &[TrainRay], grads: &mut FieldGradients) -> BatchStats {
        let scale = 1.0 / (3 * rays.len().max(1)) as f32;
        let outputs: Vec<ChunkOutput> = rays.par_chunks(self.config.rays_per_chunk).map(|c| self.run_chunk(c, Some(scale))).collect();
        let mut stats = BatchStats { rays: rays.len(), ..BatchStats::default() };
        let mut squared_error = 0.0;
        for o in &outputs {
            squared_error += o.squared_error;
            stats.samples += o.samples;
            stats.coloured_samples += o.coloured_samples;
            grads.density_mlp.iter_mut().zip(&o.density_grad).for_each(|(g, d)| *g += d);
            grads.colour_mlp.iter_mut().zip(&o.colour_grad).for_each(|(g, d)| *g += d);
        }
        stats.loss = squared_error * scale as f64;
        let points01: Vec<Vec3> = outputs.iter().flat_map(|o| o.points01.iter().copied()).collect();
        let d_encoded: Vec<f32> = outputs.iter().flat_map(|o| o.d_encoded.iter().copied()).collect();
        self.field.grid.backward(&points01, &d_encoded, &mut grads.grid);
        stats
    }

    /// Loss of a batch without gradients.
    pub fn loss(&self, rays: &[TrainRay]) -> f64 {
        let squared_error: f64 = rays.par_chunks(self.config.rays_per_chunk).map(|c| self.run_chunk(c, None).squared_error).sum();
        squared_error / (3 * rays.len().max(1)) as f64
    }

    /// Renders rays (origin, unit direction) over `background`: (rgb, opacity) per ray
    /// ([`NgpModel::render`]).
    pub fn render(&self, rays: &[(Vec3, Vec3)], background: Vec3) -> Vec<(Vec3, f32)> {
        self.model().render(rays, background)
    }

    /// Mean over images of the PSNR (dB) of the rendered image against the ground truth, both
    /// over `background`.
    pub fn psnr(&self, data: &Dataset, background: Vec3) -> f64 {
        let total: f64 = data
            .images
            .iter()
            .map(|image| {
                let rays: Vec<(Vec3, Vec3)> = image.rays().collect();
                let rendered = self.render(&rays, background);
                let truth = image.composite_over(background);
                let squared_error: f64 =
                    rendered.iter().zip(truth.chunks_exact(3)).map(|((c, _), t)| (*c - Vec3::from_slice(t)).length_squared() as f64).sum();
                -10.0 * (squared_error / truth.len() as f64).max(1e-12).log10()
            })
            .sum();
        total / data.images.len().max(1) as f64
    }

    /// Re-estimates the occupancy grid: every cell when `all_cells`, else a random
    /// `fraction_per_update` of them.
    pub fn update_occupancy(&mut self, all_cells: bool) {
        let cfg = self.config.occupancy;
        let mut rng = SmallRng::seed_from_u64(mix(self.config.seed, self.step, 2));
        let n = self.occupancy.cell_count();
        let cells: Vec<usize> = if all_cells || cfg.fraction_per_update >= 1.0 {
            (0..n).collect()
        } else {
            let count = ((n as f32 * cfg.fraction_per_update) as usize).max(1);
            (0..count).map(|_| rng.random_range(0..n)).collect()
        };
        let points01: Vec<Vec3> = cells.iter().map(|&c| self.to_unit(self.occupancy.random_point_in(c, &mut rng))).collect();
        let sigma = self.field.density(&points01);
        let threshold = cfg.min_optical_thickness / self.step_size();
        self.occupancy.update(&cells, &sigma, cfg.decay, threshold);
    }

    /// The learning rate of the next step.
    pub fn learning_rate(&self) -> f32 {
        let factor = self.config.learning_rate_schedule.iter().rev().find(|(from, _)| self.step >= *from).map_or(1.0, |(_, f)| *f);
        self.config.adam.learning_rate * factor
    }

    /// One optimisation step on a random batch of `data`.
    pub fn train_step(&mut self, data: &Dataset) -> StepStats {
        let start = Instant::now();
        let lr = self.learning_rate();
        for adam in [&mut self.adam_grid, &mut self.adam_density, &mut self.adam_colour] {
            adam.config.learning_rate = lr;
        }
        let cfg = self.config.occupancy;
        let since_warmup = self.step.checked_sub(cfg.warmup_steps as u64);
        if let Some(k) = since_warmup.filter(|k| k % cfg.update_every.max(1) as u64 == 0) {
            self.update_occupancy(k == 0);
        }
        let occupancy_ms = start.elapsed().as_secs_f64() * 1e3;
        let rays = self.sample_batch(data);
        let mut grads = std::mem::replace(&mut self.grads, FieldGradients { grid: vec![], density_mlp: vec![], colour_mlp: vec![] });
        let batch = self.gradients(&rays, &mut grads);
        let l2 = self.config.l2_mlp_weights;
        add_l2(self.field.density_mlp.params(), &mut grads.density_mlp, &self.field.density_mlp.weight_ranges(), l2);
        add_l2(self.field.colour_mlp.params(), &mut grads.colour_mlp, &self.field.colour_mlp.weight_ranges(), l2);
        self.adam_grid.step(&mut self.field.grid.params, &mut grads.grid, true);
        let adam_density = &mut self.adam_density;
        self.field.density_mlp.update(|p| adam_density.step(p, &mut grads.density_mlp, false));
        let adam_colour = &mut self.adam_colour;
        self.field.colour_mlp.update(|p| adam_colour.step(p, &mut grads.colour_mlp, false));
        self.grads = grads;
        self.step += 1;
        StepStats { step: self.step, batch, occupancy_ms, total_ms: start.elapsed().as_secs_f64() * 1e3 }
    }
}

/// What the renderer needs to draw the trainer's field (e.g. `GpuNgp::new(ctx, &trainer)`).
impl<'a> From<&'a Trainer> for NgpModel<'a> {
    fn from(trainer: &'a Trainer) -> Self {
        trainer.model()
    }
}

pub mod checkpoint;
pub mod eval;

#[cfg(test)]
mod gpu_tests;
#[cfg(test)]
mod tests;

