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

mod geometry;
mod student;

pub use self::geometry::*;
pub use self::student::*;

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
