//! The specular network F_s (NEPHELE §4.2): `[E_s, E_v, α_c] → 64 → 64 (ReLU) → 4`, giving
//! `c_s = sigmoid(o₀₋₂)` and `α = sigmoid(o₃)`, in plain f32 with row-major weights: the
//! reference every kernel is tested against. The fast kernels (transposed weights, tiles of
//! queries in SIMD, the 8-bit hidden layer) are in [`kernel`].

mod kernel;

#[cfg(target_arch = "x86_64")]
pub use kernel::simd;
pub use kernel::{MlpKernel, TILE, TileInput, peak_fma_gflops, simd_vnni};

/// Hidden width; fixed because the WGSL kernel sizes its private arrays with it.
pub const HIDDEN: usize = 64;
/// Largest accepted input width (features + 16 SH + 1).
pub const MAX_INPUT: usize = 64;

#[derive(Debug, Clone, PartialEq)]
pub struct SpecularMlp {
    pub input: usize,
    /// `HIDDEN × input`, row-major (one row per hidden unit).
    pub w0: Vec<f32>,
    pub b0: Vec<f32>,
    /// `HIDDEN × HIDDEN`.
    pub w1: Vec<f32>,
    pub b1: Vec<f32>,
    /// `4 × HIDDEN`.
    pub w2: Vec<f32>,
    pub b2: Vec<f32>,
}

pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

impl SpecularMlp {
    pub fn zeros(input: usize) -> Self {
        Self {
            input,
            w0: vec![0.0; HIDDEN * input],
            b0: vec![0.0; HIDDEN],
            w1: vec![0.0; HIDDEN * HIDDEN],
            b1: vec![0.0; HIDDEN],
            w2: vec![0.0; 4 * HIDDEN],
            b2: vec![0.0; 4],
        }
    }

    /// Raw outputs `o` (before the sigmoids).
    pub fn forward(&self, x: &[f32]) -> [f32; 4] {
        debug_assert_eq!(x.len(), self.input);
        let mut h0 = [0.0f32; HIDDEN];
        for (j, h) in h0.iter_mut().enumerate() {
            let row = &self.w0[j * self.input..(j + 1) * self.input];
            *h = (self.b0[j] + row.iter().zip(x).map(|(w, v)| w * v).sum::<f32>()).max(0.0);
        }
        let mut h1 = [0.0f32; HIDDEN];
        for (j, h) in h1.iter_mut().enumerate() {
            let row = &self.w1[j * HIDDEN..(j + 1) * HIDDEN];
            *h = (self.b1[j] + row.iter().zip(&h0).map(|(w, v)| w * v).sum::<f32>()).max(0.0);
        }
        let mut o = [0.0f32; 4];
        for (j, out) in o.iter_mut().enumerate() {
            let row = &self.w2[j * HIDDEN..(j + 1) * HIDDEN];
            *out = self.b2[j] + row.iter().zip(&h1).map(|(w, v)| w * v).sum::<f32>();
        }
        o
    }

    /// Multiply-adds of one forward pass.
    pub fn macs(&self) -> u64 {
        (HIDDEN * self.input + HIDDEN * HIDDEN + 4 * HIDDEN) as u64
    }

    pub fn parameter_count(&self) -> usize {
        self.w0.len() + self.b0.len() + self.w1.len() + self.b1.len() + self.w2.len() + self.b2.len()
    }

    /// Shapes agree with `input` and every weight is finite.
    pub fn check(&self) -> Result<(), String> {
        let shapes = [
            (self.w0.len(), HIDDEN * self.input, "w0"),
            (self.b0.len(), HIDDEN, "b0"),
            (self.w1.len(), HIDDEN * HIDDEN, "w1"),
            (self.b1.len(), HIDDEN, "b1"),
            (self.w2.len(), 4 * HIDDEN, "w2"),
            (self.b2.len(), 4, "b2"),
        ];
        if self.input == 0 || self.input > MAX_INPUT {
            return Err(format!("input width {} outside 1..={MAX_INPUT}", self.input));
        }
        for (got, want, name) in shapes {
            if got != want {
                return Err(format!("{name} has {got} values, expected {want}"));
            }
        }
        let all = [&self.w0, &self.b0, &self.w1, &self.b1, &self.w2, &self.b2];
        if all.iter().any(|t| t.iter().any(|v| !v.is_finite())) {
            return Err("non-finite weight".into());
        }
        Ok(())
    }
}
