//! Adam (Kingma & Ba, ICLR 2015) with bias correction, in f32, with instant-ngp's settings
//! as defaults: β₁ = 0.9, β₂ = 0.99, ε = 1e-15, learning rate 1e-2.
//!
//! For the hash-grid table, [`Adam::step`] can skip entries whose gradient is exactly zero
//! (their moments are neither decayed nor used), as instant-ngp does: most table entries
//! are untouched by a batch and should not drift. L2 regularisation of MLP weights is
//! added to the gradient by the caller ([`add_l2`]), so biases and the grid stay free.
//! Gradients are consumed: the step leaves them zeroed for the next batch.

use rayon::prelude::*;

#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AdamConfig {
    pub learning_rate: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub epsilon: f32,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self { learning_rate: 1e-2, beta1: 0.9, beta2: 0.99, epsilon: 1e-15 }
    }
}

/// Moments of one parameter group.
#[derive(Debug, Clone, PartialEq)]
pub struct Adam {
    pub config: AdamConfig,
    first_moment: Vec<f32>,
    second_moment: Vec<f32>,
    /// Steps taken (for the bias correction).
    steps: u32,
}

/// Parameters per parallel work item.
const CHUNK: usize = 1 << 14;

impl Adam {
    pub fn new(config: AdamConfig, params: usize) -> Self {
        Self { config, first_moment: vec![0.0; params], second_moment: vec![0.0; params], steps: 0 }
    }

    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// First and second moment estimates, laid out like the parameters (for checkpoints).
    pub fn moments(&self) -> (&[f32], &[f32]) {
        (&self.first_moment, &self.second_moment)
    }

    /// Restores a state saved from [`Self::moments`] and [`Self::steps`].
    pub fn from_state(config: AdamConfig, first_moment: Vec<f32>, second_moment: Vec<f32>, steps: u32) -> Self {
        assert_eq!(first_moment.len(), second_moment.len());
        Self { config, first_moment, second_moment, steps }
    }

    /// One update of `params` from `grads`, which are zeroed afterwards. With `skip_zero`,
    /// entries whose gradient is exactly 0 are left alone.
    pub fn step(&mut self, params: &mut [f32], grads: &mut [f32], skip_zero: bool) {
        assert_eq!(params.len(), self.first_moment.len());
        assert_eq!(grads.len(), params.len());
        self.steps += 1;
        let AdamConfig { learning_rate, beta1, beta2, epsilon } = self.config;
        let t = self.steps as i32;
        // Bias corrections folded into the step size: lr·√(1−β₂ᵗ)/(1−β₁ᵗ).
        let step_size = learning_rate * (1.0 - beta2.powi(t)).sqrt() / (1.0 - beta1.powi(t));
        let eps_hat = epsilon * (1.0 - beta2.powi(t)).sqrt();
        params
            .par_chunks_mut(CHUNK)
            .zip(grads.par_chunks_mut(CHUNK))
            .zip(self.first_moment.par_chunks_mut(CHUNK).zip(self.second_moment.par_chunks_mut(CHUNK)))
            .for_each(|((p, g), (m, v))| {
                for i in 0..p.len() {
                    let gi = g[i];
                    if skip_zero && gi == 0.0 {
                        continue;
                    }
                    m[i] = beta1 * m[i] + (1.0 - beta1) * gi;
                    v[i] = beta2 * v[i] + (1.0 - beta2) * gi * gi;
                    p[i] -= step_size * m[i] / (v[i].sqrt() + eps_hat);
                    g[i] = 0.0;
                }
            });
    }
}

/// `grads[r] += weight · params[r]` over the given ranges (∂ of `½·weight·‖w‖²`).
pub fn add_l2(params: &[f32], grads: &mut [f32], ranges: &[std::ops::Range<usize>], weight: f32) {
    if weight == 0.0 {
        return;
    }
    for r in ranges {
        for (g, &p) in grads[r.clone()].iter_mut().zip(&params[r.clone()]) {
            *g += weight * p;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn train_adam_minimises_a_quadratic_and_skips_zero_gradients() {
        // f(p) = Σ (p_i − i)², except p_3 which never receives a gradient.
        let mut params = vec![0.0f32; 6];
        let mut adam = Adam::new(AdamConfig { learning_rate: 0.05, ..AdamConfig::default() }, params.len());
        for _ in 0..2000 {
            let mut grads: Vec<f32> = params.iter().enumerate().map(|(i, &p)| 2.0 * (p - i as f32)).collect();
            grads[3] = 0.0;
            adam.step(&mut params, &mut grads, true);
            assert!(grads.iter().all(|&g| g == 0.0), "gradients are consumed");
        }
        for (i, &p) in params.iter().enumerate() {
            let want = if i == 3 { 0.0 } else { i as f32 };
            assert!((p - want).abs() < 1e-2, "p[{i}] = {p}");
        }
        // The first step moves every touched parameter by about the learning rate.
        let mut p = vec![1.0f32, 1.0];
        let mut adam = Adam::new(AdamConfig::default(), 2);
        adam.step(&mut p, &mut [3.0, -1e-3], false);
        assert!((p[0] - 0.99).abs() < 1e-5 && (p[1] - 1.01).abs() < 1e-5, "{p:?}");
    }
}
