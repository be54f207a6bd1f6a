//! The i-NGP tiny MLP: fully connected layers, ReLU on hidden layers, a linear output (the
//! caller applies its own output activation), in f32. Separate from the inference
//! [`crate::mlp::SpecularMlp`] because the i-NGP field runs batches and keeps every
//! activation (an [`MlpTape`]) for the backward pass, which is in the `nephele-train` crate.
//!
//! Batches are row-major (one sample per row) and every layer is a small matrix product,
//! done by [`gemm`]: register tiles of 4 rows × 8 columns whose inner loop the compiler turns
//! into SIMD, so weights and activations are loaded once per tile rather than once per
//! multiply-add. Forward: `Y = X·Wᵀ + b` (a transposed copy of each weight matrix is kept for
//! it), ReLU on hidden layers. [`gemm_tn`] (`δᵀ·X`, the weight gradient) sits beside it so
//! both kernels share one run-time choice of vector width.

use rand::Rng;

/// Parameter layout: for each layer `l`, `W_l` (`out × in`, row-major) then `b_l` (`out`).
#[derive(Debug, Clone, PartialEq)]
pub struct Mlp {
    /// `[input, hidden…, output]`.
    widths: Vec<usize>,
    params: Vec<f32>,
    /// Per layer `W_lᵀ` (`in × out`), rebuilt from `params` after every change.
    transposed: Vec<f32>,
}

/// Activations of one batch, kept for the backward pass: `layers[l]` is the output of layer
/// `l` (`rows × widths[l+1]`), after ReLU for hidden layers, raw for the last.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MlpTape {
    pub rows: usize,
    pub layers: Vec<Vec<f32>>,
}

impl MlpTape {
    /// The network's raw output, `rows × output width`.
    pub fn output(&self) -> &[f32] {
        self.layers.last().map(Vec::as_slice).unwrap_or(&[])
    }

    /// Appends another tape's rows (same network).
    pub fn append(&mut self, other: &MlpTape) {
        if self.layers.is_empty() {
            self.layers = other.layers.clone();
        } else {
            assert_eq!(self.layers.len(), other.layers.len(), "tapes of different networks");
            for (mine, theirs) in self.layers.iter_mut().zip(&other.layers) {
                mine.extend_from_slice(theirs);
            }
        }
        self.rows += other.rows;
    }

    /// The tape of the given rows only, in that order.
    pub fn gather(&self, rows: &[u32]) -> MlpTape {
        let layers = self.layers.iter().map(|l| gather_rows(l, l.len() / self.rows.max(1), rows)).collect();
        MlpTape { rows: rows.len(), layers }
    }
}

/// Rows `rows` of a row-major matrix of the given width, in that order.
pub fn gather_rows(data: &[f32], width: usize, rows: &[u32]) -> Vec<f32> {
    let mut out = Vec::with_capacity(rows.len() * width);
    for &r in rows {
        out.extend_from_slice(&data[r as usize * width..(r as usize + 1) * width]);
    }
    out
}

impl Mlp {
    /// He-uniform weights (`±√(6/fan_in)`) for ReLU layers, Glorot-uniform for the output
    /// layer, zero biases.
    pub fn new(widths: &[usize], rng: &mut impl Rng) -> Self {
        assert!(widths.len() >= 2 && widths.iter().all(|&w| w > 0), "bad MLP widths {widths:?}");
        let mut params = Vec::with_capacity(Self::count(widths));
        let layers = widths.len() - 1;
        for l in 0..layers {
            let (fan_in, fan_out) = (widths[l], widths[l + 1]);
            let limit = if l + 1 < layers { (6.0 / fan_in as f32).sqrt() } else { (6.0 / (fan_in + fan_out) as f32).sqrt() };
            params.extend((0..fan_in * fan_out).map(|_| rng.random_range(-limit..limit)));
            params.extend(std::iter::repeat_n(0.0, fan_out));
        }
        let mut mlp = Self { widths: widths.to_vec(), params, transposed: Vec::new() };
        mlp.rebuild();
        mlp
    }

    /// Parameters of an MLP with these widths (`[input, hidden…, output]`).
    pub fn count(widths: &[usize]) -> usize {
        widths.windows(2).map(|w| w[0] * w[1] + w[1]).sum()
    }

    pub fn widths(&self) -> &[usize] {
        &self.widths
    }
    pub fn input_width(&self) -> usize {
        self.widths[0]
    }
    pub fn output_width(&self) -> usize {
        *self.widths.last().expect("at least two widths")
    }
    pub fn params(&self) -> &[f32] {
        &self.params
    }

    /// Changes the parameters (e.g. an optimiser step) and refreshes the transposed copy.
    pub fn update(&mut self, f: impl FnOnce(&mut [f32])) {
        f(&mut self.params);
        self.rebuild();
    }

    /// Index ranges of the weight matrices (not biases), for L2 regularisation.
    pub fn weight_ranges(&self) -> Vec<std::ops::Range<usize>> {
        let mut at = 0;
        self.widths
            .windows(2)
            .map(|w| {
                let range = at..at + w[0] * w[1];
                at += w[0] * w[1] + w[1];
                range
            })
            .collect()
    }

    fn rebuild(&mut self) {
        self.transposed.clear();
        let mut at = 0;
        for w in self.widths.windows(2) {
            let (inputs, outputs) = (w[0], w[1]);
            let weights = &self.params[at..at + inputs * outputs];
            for i in 0..inputs {
                self.transposed.extend((0..outputs).map(|j| weights[j * inputs + i]));
            }
            at += inputs * outputs + outputs;
        }
    }

    /// Forward pass of `input` (`rows × input width`), filling `tape`.
    pub fn forward(&self, input: &[f32], tape: &mut MlpTape) {
        let rows = input.len() / self.input_width();
        assert_eq!(input.len(), rows * self.input_width());
        let layers = self.widths.len() - 1;
        tape.rows = rows;
        tape.layers.resize_with(layers, Vec::new);
        let (mut at_params, mut at_transposed) = (0, 0);
        for l in 0..layers {
            let (inputs, outputs) = (self.widths[l], self.widths[l + 1]);
            let wt = &self.transposed[at_transposed..at_transposed + inputs * outputs];
            let bias = &self.params[at_params + inputs * outputs..at_params + inputs * outputs + outputs];
            let (before, after) = tape.layers.split_at_mut(l);
            let x_all: &[f32] = if l == 0 { input } else { &before[l - 1] };
            let y_all = &mut after[0];
            y_all.clear();
            y_all.resize(rows * outputs, 0.0);
            for y in y_all.chunks_exact_mut(outputs) {
                y.copy_from_slice(bias);
            }
            gemm(x_all, wt, y_all, inputs, outputs);
            if l + 1 < layers {
                y_all.iter_mut().for_each(|v| *v = v.max(0.0));
            }
            at_params += inputs * outputs + outputs;
            at_transposed += inputs * outputs;
        }
    }
}

/// Rows of a register tile.
const TILE_ROWS: usize = 4;
/// Columns of a register tile (two 4-wide or one 8-wide vector).
const TILE_COLS: usize = 8;

/// `c += a·b` with `a` = `rows × k`, `b` = `k × n`, `c` = `rows × n`, all row-major.
pub fn gemm(a: &[f32], b: &[f32], c: &mut [f32], k: usize, n: usize) {
    #[cfg(target_arch = "x86_64")]
    if wide::available() {
        return wide::gemm(a, b, c, k, n);
    }
    gemm_body(a, b, c, k, n)
}

/// `c += aᵀ·b` with `a` = `rows × m`, `b` = `rows × n`, `c` = `m × n`, all row-major
/// (the weight gradient `δᵀ·X`).
pub fn gemm_tn(a: &[f32], b: &[f32], c: &mut [f32], rows: usize, m: usize, n: usize) {
    #[cfg(target_arch = "x86_64")]
    if wide::available() {
        return wide::gemm_tn(a, b, c, rows, m, n);
    }
    gemm_tn_body(a, b, c, rows, m, n)
}

/// The same kernels compiled for 256-bit AVX2 vectors, chosen at run time on CPUs that have
/// them (the release build targets baseline x86-64, i.e. 128-bit SSE2). Rust never contracts
/// `a * b + c` into a fused multiply-add, so both versions do the same f32 operations in the
/// same order per output element and give bit-identical results; only the vector width differs.
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod wide {
    pub fn available() -> bool {
        std::arch::is_x86_feature_detected!("avx2")
    }

    #[target_feature(enable = "avx2")]
    fn gemm_avx2(a: &[f32], b: &[f32], c: &mut [f32], k: usize, n: usize) {
        super::gemm_body(a, b, c, k, n)
    }

    #[target_feature(enable = "avx2")]
    fn gemm_tn_avx2(a: &[f32], b: &[f32], c: &mut [f32], rows: usize, m: usize, n: usize) {
        super::gemm_tn_body(a, b, c, rows, m, n)
    }

    pub fn gemm(a: &[f32], b: &[f32], c: &mut [f32], k: usize, n: usize) {
        assert!(available());
        // SAFETY: the CPU supports AVX2 (checked just above); the function is otherwise safe.
        unsafe { gemm_avx2(a, b, c, k, n) }
    }

    pub fn gemm_tn(a: &[f32], b: &[f32], c: &mut [f32], rows: usize, m: usize, n: usize) {
        assert!(available());
        // SAFETY: as in `gemm`.
        unsafe { gemm_tn_avx2(a, b, c, rows, m, n) }
    }
}

#[inline(always)]
fn gemm_body(a: &[f32], b: &[f32], c: &mut [f32], k: usize, n: usize) {
    let rows = c.len() / n.max(1);
    assert!(a.len() == rows * k && b.len() == k * n && c.len() == rows * n);
    let full_cols = n - n % TILE_COLS;
    let mut r0 = 0;
    while r0 < rows {
        let tile_rows = (rows - r0).min(TILE_ROWS);
        let a_rows = &a[r0 * k..(r0 + tile_rows) * k];
        let c_rows = &mut c[r0 * n..(r0 + tile_rows) * n];
        if tile_rows == TILE_ROWS {
            for c0 in (0..full_cols).step_by(TILE_COLS) {
                let mut acc = [[0f32; TILE_COLS]; TILE_ROWS];
                let (a0, a1, a2, a3) = (&a_rows[..k], &a_rows[k..2 * k], &a_rows[2 * k..3 * k], &a_rows[3 * k..4 * k]);
                for (kk, b_row) in b.chunks_exact(n).enumerate() {
                    let b_tile: &[f32; TILE_COLS] = b_row[c0..c0 + TILE_COLS].try_into().expect("tile");
                    let a_col = [a0[kk], a1[kk], a2[kk], a3[kk]];
                    for rr in 0..TILE_ROWS {
                        for cc in 0..TILE_COLS {
                            acc[rr][cc] += a_col[rr] * b_tile[cc];
                        }
                    }
                }
                for rr in 0..TILE_ROWS {
                    for (out, v) in c_rows[rr * n + c0..rr * n + c0 + TILE_COLS].iter_mut().zip(acc[rr]) {
                        *out += v;
                    }
                }
            }
        }
        // Leftover rows and columns, plainly.
        let first_plain_col = if tile_rows == TILE_ROWS { full_cols } else { 0 };
        if first_plain_col < n {
            for rr in 0..tile_rows {
                let a_row = &a_rows[rr * k..(rr + 1) * k];
                let c_row = &mut c_rows[rr * n + first_plain_col..(rr + 1) * n];
                for (&av, b_row) in a_row.iter().zip(b.chunks_exact(n)) {
                    for (out, &bv) in c_row.iter_mut().zip(&b_row[first_plain_col..]) {
                        *out += av * bv;
                    }
                }
            }
        }
        r0 += tile_rows;
    }
}

#[inline(always)]
fn gemm_tn_body(a: &[f32], b: &[f32], c: &mut [f32], rows: usize, m: usize, n: usize) {
    assert!(a.len() == rows * m && b.len() == rows * n && c.len() == m * n);
    let full_m = m - m % TILE_ROWS;
    let full_n = n - n % TILE_COLS;
    for j0 in (0..full_m).step_by(TILE_ROWS) {
        for i0 in (0..full_n).step_by(TILE_COLS) {
            let mut acc = [[0f32; TILE_COLS]; TILE_ROWS];
            for (a_row, b_row) in a.chunks_exact(m).zip(b.chunks_exact(n)) {
                let a_tile: &[f32; TILE_ROWS] = a_row[j0..j0 + TILE_ROWS].try_into().expect("tile");
                let b_tile: &[f32; TILE_COLS] = b_row[i0..i0 + TILE_COLS].try_into().expect("tile");
                for jj in 0..TILE_ROWS {
                    for ii in 0..TILE_COLS {
                        acc[jj][ii] += a_tile[jj] * b_tile[ii];
                    }
                }
            }
            for jj in 0..TILE_ROWS {
                for (out, v) in c[(j0 + jj) * n + i0..(j0 + jj) * n + i0 + TILE_COLS].iter_mut().zip(acc[jj]) {
                    *out += v;
                }
            }
        }
    }
    // Leftover rows of c (j ≥ full_m) over all columns, and leftover columns (i ≥ full_n).
    for (a_row, b_row) in a.chunks_exact(m).zip(b.chunks_exact(n)) {
        for j in 0..m {
            let av = a_row[j];
            let cols = if j < full_m { full_n..n } else { 0..n };
            if cols.is_empty() || av == 0.0 {
                continue;
            }
            for (out, &bv) in c[j * n + cols.start..j * n + cols.end].iter_mut().zip(&b_row[cols]) {
                *out += av * bv;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{SeedableRng, rngs::SmallRng};

    /// Plain per-sample reference forward, written directly from the definition.
    fn reference_forward(mlp: &Mlp, x: &[f32]) -> Vec<f32> {
        let mut v = x.to_vec();
        let mut at = 0;
        let layers = mlp.widths.len() - 1;
        for l in 0..layers {
            let (inputs, outputs) = (mlp.widths[l], mlp.widths[l + 1]);
            let w = &mlp.params[at..at + inputs * outputs];
            let b = &mlp.params[at + inputs * outputs..at + inputs * outputs + outputs];
            v = (0..outputs)
                .map(|j| {
                    let s = b[j] + (0..inputs).map(|i| w[j * inputs + i] * v[i]).sum::<f32>();
                    if l + 1 < layers { s.max(0.0) } else { s }
                })
                .collect();
            at += inputs * outputs + outputs;
        }
        v
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

    #[test]
    fn train_mlp_forward_matches_the_definition() {
        let (mlp, x, _) = setup(&[7, 16, 9, 3], 20, 1);
        let mut tape = MlpTape::default();
        mlp.forward(&x, &mut tape);
        for (row, out) in x.chunks_exact(7).zip(tape.output().chunks_exact(3)) {
            let want = reference_forward(&mlp, row);
            for (a, b) in out.iter().zip(&want) {
                assert!((a - b).abs() < 1e-5, "{out:?} vs {want:?}");
            }
        }
    }

    #[test]
    fn train_mlp_gemm_matches_plain_products() {
        let mut rng = SmallRng::seed_from_u64(4);
        for (rows, k, n) in [(1, 1, 1), (4, 8, 8), (9, 5, 16), (7, 64, 3), (13, 16, 64), (3, 7, 9)] {
            let a: Vec<f32> = (0..rows * k).map(|_| rng.random_range(-1.0..1.0)).collect();
            let b: Vec<f32> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
            let mut c: Vec<f32> = (0..rows * n).map(|_| rng.random_range(-1.0..1.0)).collect();
            let want: Vec<f32> =
                (0..rows * n).map(|i| c[i] + (0..k).map(|kk| a[i / n * k + kk] * b[kk * n + i % n]).sum::<f32>()).collect();
            gemm(&a, &b, &mut c, k, n);
            assert!(c.iter().zip(&want).all(|(x, y)| (x - y).abs() < 1e-4), "gemm {rows}x{k}x{n}");
            // aᵀ·b with a = rows × k and b = rows × n.
            let b2: Vec<f32> = (0..rows * n).map(|_| rng.random_range(-1.0..1.0)).collect();
            let mut c2 = vec![0.5f32; k * n];
            let want: Vec<f32> = (0..k * n).map(|i| 0.5 + (0..rows).map(|r| a[r * k + i / n] * b2[r * n + i % n]).sum::<f32>()).collect();
            gemm_tn(&a, &b2, &mut c2, rows, k, n);
            assert!(c2.iter().zip(&want).all(|(x, y)| (x - y).abs() < 1e-4), "gemm_tn {rows}x{k}x{n}");
            // The run-time-chosen wide kernels equal the baseline ones bit for bit.
            let (mut plain, mut plain_tn) = (vec![0.25f32; rows * n], vec![0.25f32; k * n]);
            let (mut chosen, mut chosen_tn) = (plain.clone(), plain_tn.clone());
            gemm_body(&a, &b, &mut plain, k, n);
            gemm(&a, &b, &mut chosen, k, n);
            gemm_tn_body(&a, &b2, &mut plain_tn, rows, k, n);
            gemm_tn(&a, &b2, &mut chosen_tn, rows, k, n);
            assert_eq!((plain, plain_tn), (chosen, chosen_tn), "{rows}x{k}x{n}");
        }
    }
}
