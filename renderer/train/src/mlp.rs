//! Backward pass of the i-NGP tiny MLP ([`nephele_renderer::ngp::mlp`]), layer by layer from
//! the last: `δ = ∂loss/∂pre-activation`, `∂b += Σ_rows δ`, `∂W += δᵀ·X`, `∂X = δ·W`, and
//! through the ReLU `δ_prev = ∂X ⊙ [X > 0]`. Callers split big batches into chunks and run
//! them in parallel, each chunk with its own gradient buffer, then sum the buffers in chunk
//! order.

use nephele_renderer::ngp::mlp::{Mlp, MlpTape, gemm, gemm_tn};

/// The gradient of [`Mlp::forward`].
pub trait MlpBackward {
    /// Backward pass: adds `∂loss/∂params` to `grad` (layout of [`Mlp::params`]) given
    /// `d_output` (`rows × output width`, ∂loss/∂raw output) and the tape of the forward pass
    /// of `input`. Writes `∂loss/∂input` into `d_input` when given (`rows × input width`).
    fn backward(&self, input: &[f32], tape: &MlpTape, d_output: &[f32], grad: &mut [f32], d_input: Option<&mut [f32]>);
}

impl MlpBackward for Mlp {
    fn backward(&self, input: &[f32], tape: &MlpTape, d_output: &[f32], grad: &mut [f32], mut d_input: Option<&mut [f32]>) {
        let rows = tape.rows;
        if rows == 0 && input.is_empty() && d_output.is_empty() {
            // No rows (e.g. a chunk whose samples all fell in empty space, whose tape was
            // never filled): nothing to add, nothing to pass back.
            return;
        }
        let layers = self.widths().len() - 1;
        assert_eq!(grad.len(), self.params().len());
        assert_eq!(input.len(), rows * self.input_width());
        assert_eq!(d_output.len(), rows * self.output_width());
        let mut offsets = Vec::with_capacity(layers);
        let mut at = 0;
        for w in self.widths().windows(2) {
            offsets.push(at);
            at += w[0] * w[1] + w[1];
        }
        let mut delta = d_output.to_vec();
        let mut d_x = Vec::new();
        for l in (0..layers).rev() {
            let (inputs, outputs) = (self.widths()[l], self.widths()[l + 1]);
            let x = if l == 0 { input } else { &tape.layers[l - 1][..] };
            let weights = &self.params()[offsets[l]..offsets[l] + inputs * outputs];
            let (g_weights, g_bias) = grad[offsets[l]..offsets[l] + inputs * outputs + outputs].split_at_mut(inputs * outputs);
            for d in delta.chunks_exact(outputs) {
                for (g, &v) in g_bias.iter_mut().zip(d) {
                    *g += v;
                }
            }
            gemm_tn(&delta, x, g_weights, rows, outputs, inputs);
            let out: &mut Vec<f32> = match (l, d_input.as_deref_mut()) {
                (0, Some(d)) => {
                    assert_eq!(d.len(), input.len());
                    d.fill(0.0);
                    gemm(&delta, weights, d, outputs, inputs);
                    break;
                }
                (0, None) => break,
                _ => &mut d_x,
            };
            out.clear();
            out.resize(rows * inputs, 0.0);
            gemm(&delta, weights, out, outputs, inputs);
            // Through the ReLU of the previous layer: its output x is 0 where it was cut.
            for (d, &xi) in out.iter_mut().zip(x) {
                if xi <= 0.0 {
                    *d = 0.0;
                }
            }
            std::mem::swap(&mut delta, &mut d_x);
        }
    }
}

#[cfg(test)]
mod tests {
    use nephele_renderer::ngp::mlp::gather_rows;
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    use super::*;

    /// A chunk whose samples all fell in empty space has nothing to colour: its colour tape
    /// was never filled (no layers). Found by training on the synthetic `mixed` scene.
    #[test]
    fn backward_with_no_rows_is_a_no_op() {
        let mlp = Mlp::new(&[5, 8, 3], &mut SmallRng::seed_from_u64(1));
        let mut grad = vec![0.0; mlp.params().len()];
        let mut d_input: Vec<f32> = Vec::new();
        mlp.backward(&[], &MlpTape::default(), &[], &mut grad, Some(&mut d_input));
        assert!(grad.iter().all(|g| *g == 0.0));
        let mut tape = MlpTape::default();
        mlp.forward(&[], &mut tape);
        mlp.backward(&[], &tape, &[], &mut grad, None);
        assert!(grad.iter().all(|g| *g == 0.0));
    }

    fn setup(widths: &[usize], rows: usize, seed: u64) -> (Mlp, Vec<f32>, Vec<f32>) {
        let mut rng = SmallRng::seed_from_u64(seed);
        let mut mlp = Mlp::new(widths, &mut rng);
        // Non-zero biases so the check covers them.
        mlp.update(|p| p.iter_mut().for_each(|v| *v += rng.random_range(-0.1..0.1)));
        let x: Vec<f32> = (0..rows * widths[0]).map(|_| rng.random_range(-1.0..1.0)).collect();
        let r: Vec<f32> = (0..rows * widths[widths.len() - 1]).map(|_| rng.random_range(-1.0..1.0)).collect();
        (mlp, x, r)
    }

    /// loss = Σ r · output, in f64 over the f32 forward pass.
    fn loss(mlp: &Mlp, x: &[f32], r: &[f32]) -> f64 {
        let mut tape = MlpTape::default();
        mlp.forward(x, &mut tape);
        tape.output().iter().zip(r).map(|(&o, &r)| o as f64 * r as f64).sum()
    }

    fn relative_error(analytic: f64, numeric: f64) -> f64 {
        (analytic - numeric).abs() / analytic.abs().max(numeric.abs()).max(1e-3)
    }

    #[test]
    fn train_mlp_gradients_match_finite_differences() {
        let widths = [6, 32, 32, 4];
        let (mut mlp, x, r) = setup(&widths, 8, 2);
        let mut tape = MlpTape::default();
        mlp.forward(&x, &mut tape);
        let mut grad = vec![0.0; mlp.params().len()];
        let mut d_x = vec![0.0; x.len()];
        mlp.backward(&x, &tape, &r, &mut grad, Some(&mut d_x));
        // ReLU kinks make a few finite differences meaningless; demand 95 % agreement
        // (a wrong backward fails nearly all of them).
        let eps = 1e-3f32;
        let (mut checked, mut agreed) = (0, 0);
        let mut rng = SmallRng::seed_from_u64(9);
        for _ in 0..200 {
            let i = rng.random_range(0..grad.len());
            let keep = mlp.params()[i];
            mlp.update(|p| p[i] = keep + eps);
            let up = loss(&mlp, &x, &r);
            mlp.update(|p| p[i] = keep - eps);
            let down = loss(&mlp, &x, &r);
            mlp.update(|p| p[i] = keep);
            let fd = (up - down) / (2.0 * eps as f64);
            checked += 1;
            agreed += (relative_error(grad[i] as f64, fd) < 1e-2) as usize;
        }
        assert!(agreed * 100 >= checked * 95, "params: {agreed} of {checked} agree");
        let (mut checked, mut agreed) = (0, 0);
        let mut x_moved = x.clone();
        for i in 0..x.len() {
            x_moved[i] = x[i] + eps;
            let up = loss(&mlp, &x_moved, &r);
            x_moved[i] = x[i] - eps;
            let down = loss(&mlp, &x_moved, &r);
            x_moved[i] = x[i];
            let fd = (up - down) / (2.0 * eps as f64);
            checked += 1;
            agreed += (relative_error(d_x[i] as f64, fd) < 1e-2) as usize;
        }
        assert!(agreed * 100 >= checked * 95, "inputs: {agreed} of {checked} agree");
    }

    #[test]
    fn train_mlp_backward_accumulates_and_gathers() {
        let (mlp, x, mut r) = setup(&[5, 8, 2], 4, 3);
        r[2..4].fill(0.0); // row 1 has no gradient
        let mut tape = MlpTape::default();
        mlp.forward(&x, &mut tape);
        let mut once = vec![0.0; mlp.params().len()];
        let mut d_x = vec![1.0; x.len()];
        mlp.backward(&x, &tape, &r, &mut once, Some(&mut d_x));
        assert!(d_x[5..10].iter().all(|&v| v == 0.0));
        let mut twice = once.clone();
        mlp.backward(&x, &tape, &r, &mut twice, None);
        for (a, b) in once.iter().zip(&twice) {
            assert!((2.0 * a - b).abs() <= 1e-6 * a.abs().max(1.0));
        }
        // A gathered tape backpropagates like the rows it came from.
        let rows = [3u32, 2, 0];
        let (x_sub, r_sub) = (gather_rows(&x, 5, &rows), gather_rows(&r, 2, &rows));
        let mut sub = vec![0.0; mlp.params().len()];
        mlp.backward(&x_sub, &tape.gather(&rows), &r_sub, &mut sub, None);
        for (a, b) in once.iter().zip(&sub) {
            assert!((a - b).abs() <= 1e-5 * a.abs().max(1.0), "{a} vs {b}");
        }
        let weight_count: usize = mlp.weight_ranges().iter().map(|r| r.len()).sum();
        assert_eq!(weight_count, 5 * 8 + 8 * 2);
    }
}
