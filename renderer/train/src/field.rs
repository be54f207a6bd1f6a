//! Backward pass of the i-NGP field ([`nephele_renderer::ngp::field`]): from `∂loss/∂σ` and
//! `∂loss/∂rgb` of the coloured samples of a [`FieldTape`] to the MLP gradients and
//! `∂loss/∂encoding`; the hash grid's own gradient is scattered later, once for the whole
//! batch ([`crate::hash_grid::HashGridBackward`]).

use nephele_renderer::{
    ngp::{
        field::{Field, FieldTape, GEO_FEATURES},
        mlp::gather_rows,
    },
    sh::SH_COEFFS,
};

use crate::mlp::MlpBackward;

/// Gradients of every parameter group, laid out like the parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct FieldGradients {
    pub grid: Vec<f32>,
    pub density_mlp: Vec<f32>,
    pub colour_mlp: Vec<f32>,
}

/// Gradients of a [`Field`].
pub trait FieldBackward {
    /// Zeroed gradients of every parameter group.
    fn zero_gradients(&self) -> FieldGradients;

    /// Backward pass of one tape, through the coloured samples only (the others had no
    /// effect on the loss). `d_sigma` (`coloured`) and `d_rgb` (`coloured × 3`) are
    /// `∂loss/∂σ` and `∂loss/∂rgb` of those samples. Adds the MLP gradients to `density_grad`
    /// and `colour_grad` and writes `∂loss/∂encoding` of the coloured samples
    /// (`coloured × L·F`, in the order of `tape.coloured`) into `d_encoded`.
    fn backward(
        &self,
        tape: &FieldTape,
        d_sigma: &[f32],
        d_rgb: &[f32],
        density_grad: &mut [f32],
        colour_grad: &mut [f32],
        d_encoded: &mut Vec<f32>,
    );
}

impl FieldBackward for Field {
    fn zero_gradients(&self) -> FieldGradients {
        FieldGradients {
            grid: vec![0.0; self.grid.params.len()],
            density_mlp: vec![0.0; self.density_mlp.params().len()],
            colour_mlp: vec![0.0; self.colour_mlp.params().len()],
        }
    }

    fn backward(
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
}

#[cfg(test)]
mod tests {
    use glam::Vec3;
    use nephele_renderer::{
        ngp::{field::FieldConfig, hash_grid::HashGridConfig},
        sh::sh4,
    };
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    use super::*;
    use crate::hash_grid::HashGridBackward;

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
}
