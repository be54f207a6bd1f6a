//! Backward pass of the multi-resolution hash encoding
//! ([`nephele_renderer::ngp::hash_grid`]). The encoding is linear in its parameters, so the
//! gradient just goes back to the 8 corners with the same trilinear weights. It runs in
//! parallel over levels: each level owns a disjoint slice of the table, so threads never
//! share a write and the summation order (point order) is fixed, whatever the thread count.

use glam::Vec3;
use nephele_renderer::ngp::hash_grid::{FEATURES_PER_LEVEL, HashGrid};
use rayon::prelude::*;

/// The gradient of [`HashGrid::encode_batch`] with respect to the table.
pub trait HashGridBackward {
    /// Adds `∂loss/∂params` to `grad` (same layout as `params`) given `d_encoded`
    /// (`points.len() × L·F`, `∂loss/∂encoding`). Rows that are all zero are skipped.
    /// Parallel over levels; the result does not depend on the thread count.
    fn backward(&self, points01: &[Vec3], d_encoded: &[f32], grad: &mut [f32]);
}

impl HashGridBackward for HashGrid {
    fn backward(&self, points01: &[Vec3], d_encoded: &[f32], grad: &mut [f32]) {
        assert_eq!(grad.len(), self.params.len());
        let width = self.output_width();
        assert_eq!(d_encoded.len(), points01.len() * width);
        // One disjoint slice of the gradient per level.
        let mut slices = Vec::with_capacity(self.levels.len());
        let mut rest = grad;
        for level in &self.levels {
            let (head, tail) = rest.split_at_mut(level.entries * FEATURES_PER_LEVEL);
            slices.push(head);
            rest = tail;
        }
        self.levels.par_iter().zip(slices).enumerate().for_each(|(l, (level, g))| {
            let column = l * FEATURES_PER_LEVEL;
            for (p, d_row) in points01.iter().zip(d_encoded.chunks_exact(width)) {
                let d = &d_row[column..column + FEATURES_PER_LEVEL];
                if d.iter().all(|&v| v == 0.0) {
                    continue;
                }
                let (entries, weights) = self.corners(level, *p);
                for (e, w) in entries.iter().zip(weights) {
                    let local = (e - level.first_entry) * FEATURES_PER_LEVEL;
                    for k in 0..FEATURES_PER_LEVEL {
                        g[local + k] += w * d[k];
                    }
                }
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use nephele_renderer::ngp::hash_grid::HashGridConfig;
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    use super::*;

    fn config() -> HashGridConfig {
        HashGridConfig { levels: 8, log2_table_size: 12, base_resolution: 4, finest_resolution: 128 }
    }

    #[test]
    fn train_hash_grid_backward_matches_finite_differences() {
        let mut rng = SmallRng::seed_from_u64(4);
        let mut grid = HashGrid::new(config(), &mut rng);
        grid.params.iter_mut().for_each(|v| *v = rng.random_range(-1.0..1.0));
        let width = grid.output_width();
        let points: Vec<Vec3> = (0..64).map(|_| Vec3::new(rng.random(), rng.random(), rng.random())).collect();
        let r: Vec<f32> = (0..points.len() * width).map(|_| rng.random_range(-1.0..1.0)).collect();
        // loss = Σ r · encode(points), accumulated in f64.
        let loss = |g: &HashGrid| -> f64 {
            let mut enc = vec![0.0; points.len() * width];
            g.encode_batch(&points, &mut enc);
            enc.iter().zip(&r).map(|(&e, &r)| e as f64 * r as f64).sum()
        };
        let mut grad = vec![0.0; grid.params.len()];
        grid.backward(&points, &r, &mut grad);
        let touched: Vec<usize> = (0..grad.len()).filter(|&i| grad[i] != 0.0).collect();
        assert!(touched.len() > 500);
        let eps = 1e-2;
        for k in 0..40 {
            let i = touched[(k * 7919) % touched.len()];
            let keep = grid.params[i];
            grid.params[i] = keep + eps;
            let up = loss(&grid);
            grid.params[i] = keep - eps;
            let down = loss(&grid);
            grid.params[i] = keep;
            let fd = (up - down) / (2.0 * eps as f64);
            let rel = (fd - grad[i] as f64).abs() / fd.abs().max(grad[i].abs() as f64).max(1e-3);
            assert!(rel < 1e-2, "param {i}: analytic {} vs finite difference {fd}", grad[i]);
        }
        // Untouched entries have no gradient: a point moves only its own 8 corners.
        assert!(touched.len() <= points.len() * grid.levels.len() * 8 * FEATURES_PER_LEVEL);
    }
}
