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
//! match instant-ngp's. A [`FieldTape`] keeps what one batch's forward pass computed, for the
//! backward pass in the `nephele-train` crate.

use glam::Vec3;
use rand::Rng;
use rayon::prelude::*;

use super::{
    hash_grid::{HashGrid, HashGridConfig},
    mlp::{Mlp, MlpTape},
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

/// The i-NGP field: hash grid and both MLPs.
#[derive(Debug, Clone, PartialEq)]
pub struct Field {
    pub grid: HashGrid,
    pub density_mlp: Mlp,
    pub colour_mlp: Mlp,
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

    #[test]
    fn train_field_density_is_a_truncated_exp() {
        assert_eq!(density_from_raw(0.0), 1.0);
        assert_eq!(density_from_raw(100.0), MAX_LOG_DENSITY.exp());
        assert!(density_from_raw(-100.0) >= 0.0);
    }
}
