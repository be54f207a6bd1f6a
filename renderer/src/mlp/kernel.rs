//! The specular network arranged for the machine: [`MlpKernel`] holds the weights
//! transposed (and, if chosen, the hidden layer in 8 bits), runs one query bit-identically to
//! [`SpecularMlp::forward`], or a tile of [`TILE`] queries as register-blocked matrix
//! products in [`simd`] (AVX-512, AVX2 + FMA, picked at run time). Also the machine's FMA
//! peak, which `bench render` measures every frame against.

use super::{HIDDEN, MAX_INPUT, SpecularMlp};

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
pub mod simd;
#[cfg(test)]
mod tests;

impl SpecularMlp {
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
            hidden8: None,
        }
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
    /// The hidden layer in 8 bits, if chosen ([`Self::with_int8_hidden`]).
    hidden8: Option<Int8Hidden>,
}

/// The 64 → 64 hidden layer in 8 bits: for AVX-512 VNNI (`vpdpbusd`: 64 products of
/// u8 × i8 summed into 16 i32 per instruction, four times an f32 FMA's count), or for AVX2
/// (`vpmaddubsw` then `vpmaddwd`: 32 products into 8 i32 in two instructions).
#[derive(Debug, Clone, PartialEq)]
struct Int8Hidden {
    /// `w1` per output row rounded to −W..=W of `scale[j]` (W: [`Self::weight_levels`]),
    /// four inputs per i32, laid out `[block of 16 outputs][group of 4 inputs][output in
    /// the block]`.
    w: Vec<i32>,
    /// Output row j's weights are `scale[j] ×` its bytes.
    scale: [f32; HIDDEN],
    /// The byte a row's largest weight maps to: 127 with VNNI; 64 with AVX2, whose
    /// `vpmaddubsw` sums two u8 × i8 products in an i16 that must not saturate
    /// (2 · 255 · 64 < 2¹⁵ ≤ 2 · 255 · 127).
    weight_levels: f32,
}

impl Int8Hidden {
    fn new(w1t: &[f32], weight_levels: f32) -> Self {
        let wlev = weight_levels;
        let w1 = |j: usize, i: usize| w1t[i * HIDDEN + j];
        let scale: [f32; HIDDEN] = std::array::from_fn(|j| (0..HIDDEN).fold(0.0f32, |m, i| m.max(w1(j, i).abs())) / wlev);
        let w = (0..HIDDEN * HIDDEN / 4)
            .map(|k| {
                let (block, group, jj) = (k / 256, (k / 16) % 16, k % 16);
                let j = 16 * block + jj;
                let byte = |b: usize| {
                    if scale[j] > 0.0 { (w1(j, 4 * group + b) / scale[j]).round().clamp(-wlev, wlev) as i8 } else { 0 }
                };
                i32::from_le_bytes([byte(0) as u8, byte(1) as u8, byte(2) as u8, byte(3) as u8])
            })
            .collect();
        Self { w, scale, weight_levels }
    }
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

/// Rays per batched network call ([`MlpKernel::forward_tile`]): one 512-bit vector of f32.
pub const TILE: usize = 16;

/// Inputs of one tile, feature-major: `x[i][lane]` is input `i` of ray `lane`, so every
/// input is one vector over the tile's rays.
pub type TileInput = [[f32; TILE]; MAX_INPUT];

impl MlpKernel {
    pub fn input(&self) -> usize {
        self.input
    }

    /// This kernel with its hidden layer (two thirds of the multiply-adds) in 8 bits in
    /// [`Self::forward_tile`], if the CPU has AVX-512 VNNI or, without AVX-512, AVX2 (else
    /// unchanged): each query's hidden vector is scaled to 0..=255 by its own largest value,
    /// each output's weights to −W..=W by their largest magnitude (W = 127 with VNNI, 64 with
    /// AVX2), and the products summed exactly in i32. The rounding errs by at most half a
    /// step of each (1/510 of a query's largest hidden value, 1/(2W) of a row's largest
    /// weight). On lego the frame is within 2 of 255 of the f32 kernel's with VNNI (65.6 dB)
    /// and within 4 with AVX2 (64.9 dB; `nephele bench render --networks f32,int8`).
    pub fn with_int8_hidden(mut self) -> Self {
        #[cfg(target_arch = "x86_64")]
        if simd::vnni() {
            self.hidden8 = Some(Int8Hidden::new(&self.w1t, 127.0));
        } else if simd::level() == simd::Level::Avx2 {
            self.hidden8 = Some(Int8Hidden::new(&self.w1t, 64.0));
        }
        self
    }

    /// Whether [`Self::forward_tile`] runs the hidden layer in 8 bits.
    pub fn int8_hidden(&self) -> bool {
        self.hidden8.is_some()
    }

    /// Raw outputs `o[j][lane]` for the [`TILE`] rays of `x` (only the first `input` rows
    /// are read): each layer is a small matrix product over the tile, blocked so that its
    /// accumulators stay in vector registers, with fused multiply-adds; the vector kernels
    /// skip hidden units that are zero for every ray of the tile (0.940–0.960 of the time per
    /// lego 640×480 frame, the same bits). The kernel is chosen
    /// at run time (AVX-512, AVX2 + FMA, or portable); all agree with [`Self::forward`] to
    /// within f32 rounding of the sums (fused vs separate multiply-add; tested).
    pub fn forward_tile(&self, x: &TileInput) -> [[f32; TILE]; 4] {
        #[cfg(target_arch = "x86_64")]
        match simd::level() {
            simd::Level::Avx512 if self.hidden8.is_some() => {
                return simd::tile_avx512_int8(self, x);
            }
            simd::Level::Avx512 => return simd::tile_avx512(self, x),
            simd::Level::Avx2 if self.hidden8.is_some() => return simd::tile_avx2_int8(self, x),
            simd::Level::Avx2 => return simd::tile_avx2(self, x),
            simd::Level::Portable => {}
        }
        tile_body::<8, false>(self, x)
    }
}

/// One dense layer over a tile: `y[o] = b[o] + Σ_i w[i][o]·x[i]` (then ReLU), computed in
/// blocks of `BLOCK` outputs whose `BLOCK × TILE` accumulators live in registers.
#[inline(always)]
fn dense_tile<const OUT: usize, const BLOCK: usize, const FUSED: bool>(
    wt: &[f32],
    b: &[f32; OUT],
    x: &[[f32; TILE]],
    y: &mut [[f32; TILE]; OUT],
    relu: bool,
) {
    const { assert!(OUT % BLOCK == 0, "blocks must tile the outputs") };
    for o0 in (0..OUT).step_by(BLOCK) {
        let mut acc = [[0.0f32; TILE]; BLOCK];
        for (j, a) in acc.iter_mut().enumerate() {
            *a = [b[o0 + j]; TILE];
        }
        for (xi, w_row) in x.iter().zip(wt.chunks_exact(OUT)) {
            let w: &[f32; BLOCK] = w_row[o0..o0 + BLOCK].try_into().expect("block inside the row");
            for j in 0..BLOCK {
                for l in 0..TILE {
                    acc[j][l] = if FUSED { w[j].mul_add(xi[l], acc[j][l]) } else { acc[j][l] + w[j] * xi[l] };
                }
            }
        }
        for (j, a) in acc.iter().enumerate() {
            y[o0 + j] = if relu { a.map(|v| v.max(0.0)) } else { *a };
        }
    }
}

#[inline(always)]
fn tile_body<const BLOCK: usize, const FUSED: bool>(k: &MlpKernel, x: &TileInput) -> [[f32; TILE]; 4] {
    let mut h0 = [[0.0f32; TILE]; HIDDEN];
    dense_tile::<HIDDEN, BLOCK, FUSED>(&k.w0t, &k.b0, &x[..k.input], &mut h0, true);
    let mut h1 = [[0.0f32; TILE]; HIDDEN];
    dense_tile::<HIDDEN, BLOCK, FUSED>(&k.w1t, &k.b1, &h0, &mut h1, true);
    let mut o = [[0.0f32; TILE]; 4];
    dense_tile::<4, 4, FUSED>(&k.w2t, &k.b2, &h1, &mut o, false);
    o
}

/// The machine's FMA peak right now: GFLOP/s over all rayon threads (the best of five
/// rounds of ~40 ms, so that one moment of a shared host's contention does not pass for the
/// peak: a single round once read 180 against 353 GFLOP/s a minute later), how many
/// threads, and the vector level; `None` without vector FMA.
pub fn peak_fma_gflops() -> Option<(f64, usize, String)> {
    #[cfg(target_arch = "x86_64")]
    {
        use rayon::prelude::*;
        let threads = rayon::current_num_threads();
        let round = || -> f64 { (0..threads).into_par_iter().map(|_| simd::fma_peak_gflops(20_000_000)).sum() };
        let total = (0..5).map(|_| round()).fold(0.0, f64::max);
        (total > 0.0).then(|| (total, threads, format!("{:?}", simd::level())))
    }
    #[cfg(not(target_arch = "x86_64"))]
    None
}

/// Whether the 8-bit hidden layer would use AVX-512 VNNI (false off x86-64).
pub fn simd_vnni() -> bool {
    #[cfg(target_arch = "x86_64")]
    return simd::vnni();
    #[cfg(not(target_arch = "x86_64"))]
    false
}

