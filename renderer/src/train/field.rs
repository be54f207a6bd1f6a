//! The i-NGP radiance field (Müller et al. 2022, §5.4 "Neural radiance and density fields"):
//!
//! ```text
//! position (unit cube) → hash grid (L·F) → density MLP (1 hidden layer of 64, ReLU) → 16 values
//!     o₀ = raw log-density, σ = exp(min(o₀, 15))   (truncated exp; ∂σ/∂o₀ = σ even when clamped)
//! [all 16 density outputs, SH degree 4 of the view direction] → colour MLP (2 × 64, ReLU) → 3
//!     rgb = sigmoid(·)
//! ```
//!
//! As in instant-ngp, the colour network sees all 16 density outputs (the raw log-density
//! included) as geometry features. The view encoding is [`crate::sh::sh4`], whose constants
//! match instant-ngp's. A [`FieldTape`] keeps what one batch's forward pass computed, so
//! [`Field::backward`] can return `∂loss/∂encoding` and the MLP gradients; the hash grid's own
//! gradient is scattered later, once for the whole batch ([`super::hash_grid::HashGrid::backward`]).

use glam::Vec3;
use rand::Rng;
use rayon::prelude::*;

use super::{
    hash_grid::{HashGrid, HashGridConfig},
    mlp::{Mlp, MlpTape, gather_rows},
};
use crate::sh::{SH_COEFFS, sh4};

/// Width of the density network's output: raw log-density plus 15 more geometry features.
pub const GEO_FEATURES: usize = 16;
/// Raw log-densities above this are clamped before `exp` (σ ≤ e¹⁵).
pub const MAX_LOG_DENSITY: f32 = 15.0;

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FieldConfig {
    pub grid: HashGridConfig,
    /// Hidden widths of the density MLP (instant-ngp: one layer of 64).
    pub density_hidden: Vec<usize>,
    /// Hidden widths of the colour MLP (instant-ngp: two layers of 64).
    pub colour_hidden: Vec<usize>,
}

/// `σ = exp(min(raw, 15))`, in 1/(scene unit).
#[inline]
pub fn density_from_raw(raw: f32) -> f32 {
    raw.min(MAX_LOG_DENSITY).exp()
}

#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// The trainable field.
#[derive(Debug, Clone, PartialEq)]
pub struct Field {
    pub grid: HashGrid,
    pub density_mlp: Mlp,
    pub colour_mlp: Mlp,
}

/// Gradients of every parameter group, laid out like the parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct FieldGradients {
    pub grid: Vec<f32>,
    pub density_mlp: Vec<f32>,
    pub colour_mlp: Vec<f32>,
}

/// What a forward pass over one batch of samples kept.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FieldTape {
    /// `samples × L·F`.
    pub encoded: Vec<f32>,
    pub density: MlpTape,
    /// σ per sample, 1/(scene unit).
    pub sigma: Vec<f32>,
    /// Samples the colour network was run on, in order (indices into the batch).
    pub coloured: Vec<u32>,
    /// `coloured × (16 + 16)`.
    pub colour_input: Vec<f32>,
    pub colour: MlpTape,
    /// `coloured × 3`, after the sigmoid.
    pub rgb: Vec<f32>,
}

impl Field {
    pub fn new(config: &FieldConfig, rng: &mut impl Rng) -> Self {
        let grid = HashGrid::new(config.grid, rng);
        let mut density_widths = vec![grid.output_width()];
        density_widths.extend(&config.density_hidden);
        density_widths.push(GEO_FEATURES);
        let mut colour_widths = vec![GEO_FEATURES + SH_COEFFS];
        colour_widths.extend(&config.colour_hidden);
        colour_widths.push(3);
        let density_mlp = Mlp::new(&density_widths, rng);
        let colour_mlp = Mlp::new(&colour_widths, rng);
        Self { grid, density_mlp, colour_mlp }
    }

    pub fn zero_gradients(&self) -> FieldGradients {
        FieldGradients {
            grid: vec![0.0; self.grid.params.len()],
            density_mlp: vec![0.0; self.density_mlp.params().len()],
            colour_mlp: vec![0.0; self.colour_mlp.params().len()],
        }
    }

    pub fn parameter_count(&self) -> usize {
        self.grid.params.len() + self.density_mlp.params().len() + self.colour_mlp.params().len()
    }

    /// Density pass: encodes `points01` and fills `tape.sigma`.
    pub fn forward_density(&self, points01: &[Vec3], tape: &mut FieldTape) {
        let width = self.grid.output_width();
        tape.encoded.clear();
        tape.encoded.resize(points01.len() * width, 0.0);
        self.grid.encode_batch(points01, &mut tape.encoded);
        self.density_mlp.forward(&tape.encoded, &mut tape.density);
        tape.sigma.clear();
        tape.sigma.extend(tape.density.output().chunks_exact(GEO_FEATURES).map(|o| density_from_raw(o[0])));
    }
}

impl FieldTape {
    /// Appends the rows of another density pass (its `encoded`, density-MLP tape and `σ`).
    pub fn append_density(&mut self, other: &FieldTape) {
        self.encoded.extend_from_slice(&other.encoded);
        self.density.append(&other.density);
        self.sigma.extend_from_slice(&other.sigma);
    }
}

impl Field {
    /// Colour pass over the samples `coloured` (after [`Self::forward_density`]);
    /// `view_sh[k]` is the SH encoding of sample `coloured[k]`'s view direction.
    pub fn forward_colour(&self, coloured: Vec<u32>, view_sh: &[[f32; SH_COEFFS]], tape: &mut FieldTape) {
        assert_eq!(coloured.len(), view_sh.len());
        let geo = tape.density.output();
        tape.colour_input.clear();
        for (&s, sh) in coloured.iter().zip(view_sh) {
            let s = s as usize;
            tape.colour_input.extend_from_slice(&geo[s * GEO_FEATURES..(s + 1) * GEO_FEATURES]);
            tape.colour_input.extend_from_slice(sh);
        }
        tape.coloured = coloured;
        self.colour_mlp.forward(&tape.colour_input, &mut tape.colour);
        tape.rgb.clear();
        tape.rgb.extend(tape.colour.output().iter().map(|&o| sigmoid(o)));
    }

    /// Backward pass of one tape, through the coloured samples only (the others had no
    /// effect on the loss). `d_sigma` (`coloured`) and `d_rgb` (`coloured × 3`) are
    /// `∂loss/∂σ` and `∂loss/∂rgb` of those samples. Adds the MLP gradients to `density_grad`
    /// and `colour_grad` and writes `∂loss/∂encoding` of the coloured samples
    /// (`coloured × L·F`, in the order of `tape.coloured`) into `d_encoded`.
    pub fn backward(
        &self,
        tape: &FieldTape,
        d_sigma: &[f32],
        d_rgb: &[f32],
        density_grad: &mut [f32],
        colour_grad: &mut [f32],
        d_encoded: &mut Vec<f32>,
    ) {
        let coloured = tape.coloured.len();
        assert_eq!(d_sigma.len(), coloured);
        assert_eq!(d_rgb.len(), coloured * 3);
        let d_colour_out: Vec<f32> = d_rgb.iter().zip(&tape.rgb).map(|(&d, &c)| d * c * (1.0 - c)).collect();
        let mut d_colour_in = vec![0.0; tape.colour_input.len()];
        self.colour_mlp.backward(&tape.colour_input, &tape.colour, &d_colour_out, colour_grad, Some(&mut d_colour_in));
        let mut d_geo = Vec::with_capacity(coloured * GEO_FEATURES);
        for ((&s, d_in), &d) in tape.coloured.iter().zip(d_colour_in.chunks_exact(GEO_FEATURES + SH_COEFFS)).zip(d_sigma) {
            d_geo.extend_from_slice(&d_in[..GEO_FEATURES]);
            // Truncated exp: ∂σ/∂raw = exp(min(raw, 15)) = σ.
            let raw_at = d_geo.len() - GEO_FEATURES;
            d_geo[raw_at] += d * tape.sigma[s as usize];
        }
        let encoded = gather_rows(&tape.encoded, self.grid.output_width(), &tape.coloured);
        let density_tape = tape.density.gather(&tape.coloured);
        d_encoded.clear();
        d_encoded.resize(encoded.len(), 0.0);
        self.density_mlp.backward(&encoded, &density_tape, &d_geo, density_grad, Some(d_encoded));
    }

    /// σ at many points of the unit cube (parallel; for occupancy updates).
    pub fn density(&self, points01: &[Vec3]) -> Vec<f32> {
        points01
            .par_chunks(4096)
            .flat_map_iter(|chunk| {
                let mut tape = FieldTape::default();
                self.forward_density(chunk, &mut tape);
                tape.sigma
            })
            .collect()
    }

    /// SH encoding of a view direction (unit, world space).
    pub fn view_encoding(dir: Vec3) -> [f32; SH_COEFFS] {
        sh4(dir)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{SeedableRng, rngs::SmallRng};

    fn tiny_field(seed: u64) -> Field {
        let config = FieldConfig {
            grid: HashGridConfig { levels: 4, log2_table_size: 10, base_resolution: 4, finest_resolution: 32 },
            density_hidden: vec![16],
            colour_hidden: vec![16, 16],
        };
        let mut rng = SmallRng::seed_from_u64(seed);
        let mut field = Field::new(&config, &mut rng);
        // Features large enough that the MLPs see them.
        field.grid.params.iter_mut().for_each(|v| *v = rng.random_range(-1.0..1.0));
        field
    }

    /// loss = Σ a_k σ_k + Σ b_k · rgb_k over the coloured samples k of a fixed batch, in f64.
    fn loss(field: &Field, points: &[Vec3], coloured: &[u32], sh: &[[f32; 16]], a: &[f32], b: &[f32]) -> f64 {
        let mut tape = FieldTape::default();
        field.forward_density(points, &mut tape);
        field.forward_colour(coloured.to_vec(), sh, &mut tape);
        let density: f64 = coloured.iter().zip(a).map(|(&s, &a)| tape.sigma[s as usize] as f64 * a as f64).sum();
        density + tape.rgb.iter().zip(b).map(|(&c, &b)| c as f64 * b as f64).sum::<f64>()
    }

    #[test]
    fn train_field_gradients_match_finite_differences() {
        let mut field = tiny_field(5);
        let mut rng = SmallRng::seed_from_u64(6);
        let points: Vec<Vec3> = (0..32).map(|_| Vec3::new(rng.random(), rng.random(), rng.random())).collect();
        let coloured: Vec<u32> = (0..32).filter(|s| s % 3 != 1).collect();
        let sh: Vec<[f32; 16]> = coloured.iter().map(|_| sh4(Vec3::new(rng.random(), rng.random(), 0.5).normalize())).collect();
        let a: Vec<f32> = (0..coloured.len()).map(|_| rng.random_range(-0.1..0.1)).collect();
        let b: Vec<f32> = (0..coloured.len() * 3).map(|_| rng.random_range(-1.0..1.0)).collect();

        let mut tape = FieldTape::default();
        field.forward_density(&points, &mut tape);
        field.forward_colour(coloured.clone(), &sh, &mut tape);
        let mut grads = field.zero_gradients();
        let mut d_encoded = Vec::new();
        field.backward(&tape, &a, &b, &mut grads.density_mlp, &mut grads.colour_mlp, &mut d_encoded);
        let coloured_points: Vec<Vec3> = coloured.iter().map(|&s| points[s as usize]).collect();
        field.grid.backward(&coloured_points, &d_encoded, &mut grads.grid);

        let eps = 1e-3f32;
        let check = |analytic: f32, up: f64, down: f64| {
            let fd = (up - down) / (2.0 * eps as f64);
            (analytic as f64 - fd).abs() / (analytic.abs() as f64).max(fd.abs()).max(1e-3) < 1e-2
        };
        // Grid: the 30 entries with the largest gradients, and MLP parameters at random.
        let mut order: Vec<usize> = (0..grads.grid.len()).collect();
        order.sort_by(|&i, &j| grads.grid[j].abs().total_cmp(&grads.grid[i].abs()));
        let (mut checked, mut agreed) = (0, 0);
        for &i in &order[..30] {
            let keep = field.grid.params[i];
            field.grid.params[i] = keep + eps;
            let up = loss(&field, &points, &coloured, &sh, &a, &b);
            field.grid.params[i] = keep - eps;
            let down = loss(&field, &points, &coloured, &sh, &a, &b);
            field.grid.params[i] = keep;
            checked += 1;
            agreed += check(grads.grid[i], up, down) as usize;
        }
        for which in 0..2 {
            for _ in 0..40 {
                let mlp = if which == 0 { &field.density_mlp } else { &field.colour_mlp };
                let i = rng.random_range(0..mlp.params().len());
                let keep = mlp.params()[i];
                let set = |field: &mut Field, v: f32| {
                    let mlp = if which == 0 { &mut field.density_mlp } else { &mut field.colour_mlp };
                    mlp.update(|p| p[i] = v);
                };
                set(&mut field, keep + eps);
                let up = loss(&field, &points, &coloured, &sh, &a, &b);
                set(&mut field, keep - eps);
                let down = loss(&field, &points, &coloured, &sh, &a, &b);
                set(&mut field, keep);
                let analytic = if which == 0 { grads.density_mlp[i] } else { grads.colour_mlp[i] };
                checked += 1;
                agreed += check(analytic, up, down) as usize;
            }
        }
        // A few ReLU kinks may be crossed by ±eps; a wrong backward fails most checks.
        assert!(agreed * 100 >= checked * 95, "{agreed} of {checked} gradients agree");
    }

    #[test]
    fn train_field_density_is_a_truncated_exp() {
        assert_eq!(density_from_raw(0.0), 1.0);
        assert_eq!(density_from_raw(100.0), MAX_LOG_DENSITY.exp());
        assert!(density_from_raw(-100.0) >= 0.0);
    }
}
