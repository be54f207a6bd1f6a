//! The specular network F_s (NEPHELE §4.2): `[E_s, E_v, α_c] → 64 → 64 (ReLU) → 4`, giving
//! `c_s = sigmoid(o₀₋₂)` and `α = sigmoid(o₃)`. Plain f32, row-major weights.

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

    /// The same network laid out for the CPU's vector units; see [`MlpKernel`].
    pub fn kernel(&self) -> MlpKernel {
        let transpose = |w: &[f32], rows: usize, cols: usize| {
            let mut t = vec![0.0; rows * cols];
            for r in 0..rows {
                for c in 0..cols {
                    t[c * rows + r] = w[r * cols + c];
                }
            }
            t
        };
        MlpKernel {
            input: self.input,
            w0t: transpose(&self.w0, HIDDEN, self.input),
            b0: self.b0.clone().try_into().expect("checked shape"),
            w1t: transpose(&self.w1, HIDDEN, HIDDEN),
            b1: self.b1.clone().try_into().expect("checked shape"),
            w2t: transpose(&self.w2, 4, HIDDEN),
            b2: self.b2.clone().try_into().expect("checked shape"),
        }
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

/// [`SpecularMlp`] with transposed weights, so each layer is a sequence of
/// "output vector += weight column × one input" steps that the compiler turns into SIMD
/// over the 64 outputs. Every output accumulates its products in the same order as
/// [`SpecularMlp::forward`], so the results are bit-identical (tested), only faster.
#[derive(Debug, Clone, PartialEq)]
pub struct MlpKernel {
    input: usize,
    /// `input × HIDDEN`: column i of `w0` is row i here.
    w0t: Vec<f32>,
    b0: [f32; HIDDEN],
    w1t: Vec<f32>,
    b1: [f32; HIDDEN],
    /// `HIDDEN × 4`.
    w2t: Vec<f32>,
    b2: [f32; 4],
}

impl MlpKernel {
    /// Raw outputs `o`, bit-identical to [`SpecularMlp::forward`].
    pub fn forward(&self, x: &[f32]) -> [f32; 4] {
        debug_assert_eq!(x.len(), self.input);
        let h0 = layer::<HIDDEN>(&self.w0t, &self.b0, x, true);
        let h1 = layer::<HIDDEN>(&self.w1t, &self.b1, &h0, true);
        layer::<4>(&self.w2t, &self.b2, &h1, false)
    }
}

/// `out = b + Σ_i wt[i]·x[i]` (then ReLU), summing from −0.0 in input order as
/// `Iterator::sum` does.
#[inline(always)]
fn layer<const N: usize>(wt: &[f32], b: &[f32; N], x: &[f32], relu: bool) -> [f32; N] {
    let mut acc = [-0.0f32; N];
    for (col, &xi) in wt.chunks_exact(N).zip(x) {
        let col: &[f32; N] = col.try_into().expect("chunks_exact");
        for j in 0..N {
            acc[j] += col[j] * xi;
        }
    }
    for j in 0..N {
        acc[j] += b[j];
        if relu {
            acc[j] = acc[j].max(0.0);
        }
    }
    acc
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    #[test]
    fn kernel_is_bit_identical_to_the_reference() {
        let mut rng = SmallRng::seed_from_u64(7);
        for input in [1, 5, 21, 64] {
            let mut m = SpecularMlp::zeros(input);
            for w in [&mut m.w0, &mut m.b0, &mut m.w1, &mut m.b1, &mut m.w2, &mut m.b2] {
                w.iter_mut().for_each(|v| *v = rng.random_range(-1.0..1.0));
            }
            let k = m.kernel();
            for _ in 0..200 {
                let x: Vec<f32> = (0..input).map(|_| rng.random_range(-3.0..3.0)).collect();
                let (a, b) = (m.forward(&x), k.forward(&x));
                assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits), "input {input}: {a:?} vs {b:?}");
            }
        }
    }
}
