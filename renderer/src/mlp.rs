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
            hidden8: None,
        }
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

/// The vector kernels, compiled for AVX-512 and AVX2 + FMA and picked at run time (the
/// release build targets baseline x86-64).
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
pub mod simd {
    use super::{HIDDEN, MlpKernel, TILE, TileInput};

    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub enum Level {
        Avx512,
        Avx2,
        Portable,
    }

    /// The widest vector unit this CPU has (detected once). `NEPHELE_SIMD=avx2|portable`
    /// caps it, for comparisons.
    pub fn level() -> Level {
        static LEVEL: std::sync::OnceLock<Level> = std::sync::OnceLock::new();
        *LEVEL.get_or_init(|| {
            let cap = std::env::var("NEPHELE_SIMD").unwrap_or_default();
            if cap != "avx2" && cap != "portable" && std::arch::is_x86_feature_detected!("avx512f") {
                Level::Avx512
            } else if cap != "portable" && std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                Level::Avx2
            } else {
                Level::Portable
            }
        })
    }

    use std::{arch::x86_64::*, mem::MaybeUninit};

    /// A layer's outputs before it writes them: no zeroing, which took ~2% of a lego frame
    /// (128 vector stores per tile), for rows that the layer overwrites every one of.
    type Rows<const N: usize> = [MaybeUninit<[f32; TILE]>; N];

    /// Rows that a layer has written, every one ([`dense512`] and [`dense_int8`] do).
    ///
    /// # Safety
    /// Every row of `rows` is initialized.
    unsafe fn written<const N: usize>(rows: &Rows<N>) -> &[[f32; TILE]; N] {
        // SAFETY: `MaybeUninit<T>` has `T`'s layout, and every row is initialized (the
        // caller's guarantee).
        unsafe { &*rows.as_ptr().cast::<[[f32; TILE]; N]>() }
    }

    /// Inputs of a layer that are not zero for every ray of the tile, in order: the others
    /// (ReLU outputs that are 0 for all 16 rays: ~30% of the hidden units' rows on lego,
    /// neighbouring pixels' queries being alike) add only w·0 = +0, which changes no sum
    /// (short of the sign of a zero sum, which the ReLU or sigmoid after it makes moot), so
    /// they are skipped.
    struct Active {
        rows: [u8; HIDDEN],
        n: usize,
    }

    impl Active {
        /// The first `n` rows.
        fn all(n: usize) -> Self {
            Self { rows: std::array::from_fn(|i| i as u8), n }
        }
        fn rows(&self) -> &[u8] {
            &self.rows[..self.n]
        }
    }

    /// [`super::dense_tile`] in AVX-512 registers: `BLOCK` accumulators of 16 rays each,
    /// over the input rows `active`; writes every row of `y` and returns the outputs that are
    /// not zero for every ray.
    #[target_feature(enable = "avx512f")]
    fn dense512<const OUT: usize, const BLOCK: usize>(wt: &[f32], b: &[f32; OUT], x: &[[f32; TILE]], active: &Active, y: &mut Rows<OUT>, relu: bool) -> Active {
        const { assert!(OUT % BLOCK == 0 && OUT <= HIDDEN, "blocks must tile the outputs") };
        let mut out = Active { rows: [0; HIDDEN], n: 0 };
        for o0 in (0..OUT).step_by(BLOCK) {
            let mut acc = [_mm512_setzero_ps(); BLOCK];
            for (j, a) in acc.iter_mut().enumerate() {
                *a = _mm512_set1_ps(b[o0 + j]);
            }
            // No bounds check (and so no panic path) inside the loop: with one, the
            // accumulators went to the stack after every product.
            assert!(active.rows().iter().all(|&i| (i as usize) < x.len()) && wt.len() >= x.len() * OUT, "rows inside the weights");
            for &i in active.rows() {
                // SAFETY: `i < x.len()` and `(i + 1) · OUT ≤ wt.len()` (asserted above);
                // `x[i]` is 16 f32 and `o0 + BLOCK ≤ OUT`.
                unsafe {
                    let xv = _mm512_loadu_ps(x.get_unchecked(i as usize).as_ptr());
                    let w = wt.as_ptr().add(i as usize * OUT + o0);
                    for (j, a) in acc.iter_mut().enumerate() {
                        *a = _mm512_fmadd_ps(_mm512_set1_ps(*w.add(j)), xv, *a);
                    }
                }
            }
            for (j, a) in acc.iter().enumerate() {
                let v = if relu { _mm512_max_ps(*a, _mm512_setzero_ps()) } else { *a };
                // SAFETY: `y[o0 + j]` is 16 f32.
                unsafe { _mm512_storeu_ps(y[o0 + j].as_mut_ptr().cast(), v) };
                out.rows[out.n] = (o0 + j) as u8;
                out.n += usize::from(_mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(v, _mm512_setzero_ps()) != 0);
            }
        }
        out
    }

    /// [`super::dense_tile`] in AVX2 registers: `BLOCK` outputs × two 8-ray halves at a
    /// time (the last `OUT % BLOCK`, a multiple of 4, four at a time), over the input rows
    /// `active`; returns the outputs that are not zero for every ray.
    #[target_feature(enable = "avx2,fma")]
    fn dense256<const OUT: usize, const BLOCK: usize>(wt: &[f32], b: &[f32; OUT], x: &[[f32; TILE]], active: &Active, y: &mut [[f32; TILE]; OUT], relu: bool) -> Active {
        const { assert!(OUT % BLOCK % 4 == 0 && OUT <= HIDDEN, "blocks must tile the outputs") };
        let mut out = Active { rows: [0; HIDDEN], n: 0 };
        let mut o0 = 0;
        while o0 + BLOCK <= OUT {
            block256::<OUT, BLOCK>(o0, wt, b, x, active, y, relu, &mut out);
            o0 += BLOCK;
        }
        while o0 < OUT {
            block256::<OUT, 4>(o0, wt, b, x, active, y, relu, &mut out);
            o0 += 4;
        }
        out
    }

    /// Outputs `o0..o0 + BLOCK` of [`dense256`], appending the ones not zero for every ray
    /// to `out`.
    #[inline]
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx2,fma")]
    fn block256<const OUT: usize, const BLOCK: usize>(o0: usize, wt: &[f32], b: &[f32; OUT], x: &[[f32; TILE]], active: &Active, y: &mut [[f32; TILE]; OUT], relu: bool, out: &mut Active) {
        let mut acc = [[_mm256_setzero_ps(); 2]; BLOCK];
        for (j, a) in acc.iter_mut().enumerate() {
            *a = [_mm256_set1_ps(b[o0 + j]); 2];
        }
        for &i in active.rows() {
            let (xi, w_row) = (&x[i as usize], &wt[i as usize * OUT..(i as usize + 1) * OUT]);
            // SAFETY: `xi` is 16 f32: two 8-wide loads.
            let (x0, x1) = unsafe { (_mm256_loadu_ps(xi.as_ptr()), _mm256_loadu_ps(xi.as_ptr().add(8))) };
            let w: &[f32; BLOCK] = w_row[o0..o0 + BLOCK].try_into().expect("block inside the row");
            for j in 0..BLOCK {
                let wv = _mm256_set1_ps(w[j]);
                acc[j][0] = _mm256_fmadd_ps(wv, x0, acc[j][0]);
                acc[j][1] = _mm256_fmadd_ps(wv, x1, acc[j][1]);
            }
        }
        for (j, a) in acc.iter().enumerate() {
            let (v0, v1) = if relu { (_mm256_max_ps(a[0], _mm256_setzero_ps()), _mm256_max_ps(a[1], _mm256_setzero_ps())) } else { (a[0], a[1]) };
            // SAFETY: `y[o0 + j]` is 16 f32.
            unsafe {
                _mm256_storeu_ps(y[o0 + j].as_mut_ptr(), v0);
                _mm256_storeu_ps(y[o0 + j].as_mut_ptr().add(8), v1);
            }
            let zero = |v: __m256| _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_NEQ_UQ>(v, _mm256_setzero_ps())) == 0;
            out.rows[out.n] = (o0 + j) as u8;
            out.n += usize::from(!(zero(v0) && zero(v1)));
        }
    }

    #[target_feature(enable = "avx512f")]
    fn avx512(k: &MlpKernel, x: &TileInput) -> [[f32; TILE]; 4] {
        let mut h0: Rows<HIDDEN> = [MaybeUninit::uninit(); HIDDEN];
        let active = dense512::<HIDDEN, 16>(&k.w0t, &k.b0, &x[..k.input], &Active::all(k.input), &mut h0, true);
        let mut h1: Rows<HIDDEN> = [MaybeUninit::uninit(); HIDDEN];
        // SAFETY (`written`, three times): each layer wrote every row.
        let active = dense512::<HIDDEN, 16>(&k.w1t, &k.b1, unsafe { written(&h0) }, &active, &mut h1, true);
        let mut o: Rows<4> = [MaybeUninit::uninit(); 4];
        dense512::<4, 4>(&k.w2t, &k.b2, unsafe { written(&h1) }, &active, &mut o, false);
        *unsafe { written(&o) }
    }

    /// Whether the CPU has AVX-512 VNNI for [`super::MlpKernel::with_int8_hidden`] (within
    /// the cap of `NEPHELE_SIMD`).
    pub fn vnni() -> bool {
        level() == Level::Avx512 && std::arch::is_x86_feature_detected!("avx512bw") && std::arch::is_x86_feature_detected!("avx512vnni")
    }

    /// The hidden layer in 8 bits (see [`super::MlpKernel::with_int8_hidden`]): rows of
    /// `h0` quantised per query (lane), four rows packed per i32 lane; `vpdpbusd` into 16
    /// accumulators per block of 16 outputs; then `max(0, Σ · lane scale · row scale + b)`.
    /// Like [`dense512`], skips groups of 4 inputs that are zero for the whole tile and
    /// returns the outputs that are not.
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    fn dense_int8(q: &super::Int8Hidden, b: &[f32; HIDDEN], h0: &[[f32; TILE]; HIDDEN], active: &Active, y: &mut Rows<HIDDEN>) -> Active {
        let zero = _mm512_setzero_ps();
        let mut largest = zero;
        let mut groups = 0u32;
        for &i in active.rows() {
            // SAFETY: a row is 16 f32.
            largest = _mm512_max_ps(largest, unsafe { _mm512_loadu_ps(h0[i as usize].as_ptr()) });
            groups |= 1 << (i / 4);
        }
        // Per lane: bytes = h · 255 / largest (0 where the query's hidden vector is all 0).
        let to_byte = _mm512_maskz_div_ps(_mm512_cmp_ps_mask::<_CMP_GT_OQ>(largest, zero), _mm512_set1_ps(255.0), largest);
        let lane_scale = _mm512_mul_ps(largest, _mm512_set1_ps(1.0 / 255.0));
        let mut packed = [_mm512_setzero_si512(); HIDDEN / 4];
        let mut which = [0u8; HIDDEN / 4];
        let mut n = 0;
        while groups != 0 {
            let g = groups.trailing_zeros() as usize;
            groups &= groups - 1;
            let mut p = _mm512_setzero_si512();
            for (byte, row) in h0[4 * g..4 * g + 4].iter().enumerate() {
                // SAFETY: a row is 16 f32. 0 ≤ h ≤ largest, so the rounded byte is 0..=255.
                let v = _mm512_cvtps_epi32(_mm512_mul_ps(unsafe { _mm512_loadu_ps(row.as_ptr()) }, to_byte));
                p = _mm512_or_si512(p, _mm512_sllv_epi32(v, _mm512_set1_epi32(8 * byte as i32)));
            }
            (packed[n], which[n]) = (p, g as u8);
            n += 1;
        }
        let mut out = Active { rows: [0; HIDDEN], n: 0 };
        for block in 0..HIDDEN / 16 {
            let w: &[i32; 256] = q.w[256 * block..256 * (block + 1)].try_into().expect("a block of weights");
            let mut acc = [_mm512_setzero_si512(); 16];
            for (p, &g) in packed[..n].iter().zip(&which[..n]) {
                let wg: &[i32; 16] = w[16 * (g as usize % 16)..16 * (g as usize % 16) + 16].try_into().expect("a group of weights");
                for (a, &wj) in acc.iter_mut().zip(wg) {
                    *a = _mm512_dpbusd_epi32(*a, *p, _mm512_set1_epi32(wj));
                }
            }
            for (jj, a) in acc.iter().enumerate() {
                let j = 16 * block + jj;
                let v = _mm512_fmadd_ps(_mm512_mul_ps(_mm512_cvtepi32_ps(*a), lane_scale), _mm512_set1_ps(q.scale[j]), _mm512_set1_ps(b[j]));
                let v = _mm512_max_ps(v, zero);
                // SAFETY: `y[j]` is 16 f32.
                unsafe { _mm512_storeu_ps(y[j].as_mut_ptr().cast(), v) };
                out.rows[out.n] = j as u8;
                out.n += usize::from(_mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(v, zero) != 0);
            }
        }
        out
    }

    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    fn avx512_int8(k: &MlpKernel, x: &TileInput) -> [[f32; TILE]; 4] {
        let q = k.hidden8.as_ref().expect("checked by the caller");
        let mut h0: Rows<HIDDEN> = [MaybeUninit::uninit(); HIDDEN];
        let active = dense512::<HIDDEN, 16>(&k.w0t, &k.b0, &x[..k.input], &Active::all(k.input), &mut h0, true);
        let mut h1: Rows<HIDDEN> = [MaybeUninit::uninit(); HIDDEN];
        // SAFETY (`written`, three times): each layer wrote every row.
        let active = dense_int8(q, &k.b1, unsafe { written(&h0) }, &active, &mut h1);
        let mut o: Rows<4> = [MaybeUninit::uninit(); 4];
        dense512::<4, 4>(&k.w2t, &k.b2, unsafe { written(&h1) }, &active, &mut o, false);
        *unsafe { written(&o) }
    }

    pub fn tile_avx512_int8(k: &MlpKernel, x: &TileInput) -> [[f32; TILE]; 4] {
        assert!(vnni() && k.hidden8.is_some());
        // SAFETY: the CPU has AVX-512 F/BW/VNNI (checked above); the body is safe code.
        unsafe { avx512_int8(k, x) }
    }

    #[target_feature(enable = "avx2,fma")]
    fn avx2(k: &MlpKernel, x: &TileInput) -> [[f32; TILE]; 4] {
        let mut h0 = [[0.0f32; TILE]; HIDDEN];
        // Blocks of 6 outputs: 12 accumulators cover the FMA latency that 8 (blocks of 4) left
        // exposed (0.975–0.985 of the time per lego frame on Zen 3; the same frames).
        let active = dense256::<HIDDEN, 6>(&k.w0t, &k.b0, &x[..k.input], &Active::all(k.input), &mut h0, true);
        let mut h1 = [[0.0f32; TILE]; HIDDEN];
        let active = dense256::<HIDDEN, 6>(&k.w1t, &k.b1, &h0, &active, &mut h1, true);
        let mut o = [[0.0f32; TILE]; 4];
        dense256::<4, 4>(&k.w2t, &k.b2, &h1, &active, &mut o, false);
        o
    }

    /// [`dense_int8`] for AVX2: the products by `vpmaddubsw` (pairs of u8 × i8 summed into
    /// i16; weights in −64..=64 so that no sum saturates) and `vpmaddwd` by ones (pairs of
    /// those into i32), 8 queries per register, blocks of 4 outputs × both halves of the
    /// tile in 8 accumulators.
    #[target_feature(enable = "avx2,fma")]
    fn dense_int8_avx2(q: &super::Int8Hidden, b: &[f32; HIDDEN], h0: &[[f32; TILE]; HIDDEN], active: &Active, y: &mut [[f32; TILE]; HIDDEN]) -> Active {
        const BLOCK: usize = 4;
        let zero = _mm256_setzero_ps();
        let half = |row: &[f32; TILE], h: usize| unsafe { _mm256_loadu_ps(row.as_ptr().add(8 * h)) };
        let mut largest = [zero; 2];
        let mut groups = 0u32;
        for &i in active.rows() {
            let row = &h0[i as usize];
            largest = [_mm256_max_ps(largest[0], half(row, 0)), _mm256_max_ps(largest[1], half(row, 1))];
            groups |= 1 << (i / 4);
        }
        // Per lane: bytes = h · 255 / largest (0 where the query's hidden vector is all 0).
        let to_byte = largest.map(|l| _mm256_and_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(l, zero), _mm256_div_ps(_mm256_set1_ps(255.0), l)));
        let lane_scale = largest.map(|l| _mm256_mul_ps(l, _mm256_set1_ps(1.0 / 255.0)));
        let mut packed = [[_mm256_setzero_si256(); 2]; HIDDEN / 4];
        let mut which = [0u8; HIDDEN / 4];
        let mut n = 0;
        while groups != 0 {
            let g = groups.trailing_zeros() as usize;
            groups &= groups - 1;
            let mut p = [_mm256_setzero_si256(); 2];
            for (byte, row) in h0[4 * g..4 * g + 4].iter().enumerate() {
                for (h, p) in p.iter_mut().enumerate() {
                    // 0 ≤ h ≤ largest, so the rounded byte is 0..=255.
                    let v = _mm256_cvtps_epi32(_mm256_mul_ps(half(row, h), to_byte[h]));
                    *p = _mm256_or_si256(*p, _mm256_sllv_epi32(v, _mm256_set1_epi32(8 * byte as i32)));
                }
            }
            (packed[n], which[n]) = (p, g as u8);
            n += 1;
        }
        let ones = _mm256_set1_epi16(1);
        let mut out = Active { rows: [0; HIDDEN], n: 0 };
        for o0 in (0..HIDDEN).step_by(BLOCK) {
            let w: &[i32; 256] = q.w[256 * (o0 / 16)..256 * (o0 / 16 + 1)].try_into().expect("a block of weights");
            let mut acc = [[_mm256_setzero_si256(); 2]; BLOCK];
            for (p, &g) in packed[..n].iter().zip(&which[..n]) {
                let at = 16 * (g as usize % 16) + o0 % 16;
                let wg: &[i32; BLOCK] = w[at..at + BLOCK].try_into().expect("a group of weights");
                for (a, &wj) in acc.iter_mut().zip(wg) {
                    let wv = _mm256_set1_epi32(wj);
                    a[0] = _mm256_add_epi32(a[0], _mm256_madd_epi16(_mm256_maddubs_epi16(p[0], wv), ones));
                    a[1] = _mm256_add_epi32(a[1], _mm256_madd_epi16(_mm256_maddubs_epi16(p[1], wv), ones));
                }
            }
            for (jj, a) in acc.iter().enumerate() {
                let j = o0 + jj;
                let v = |h: usize| _mm256_max_ps(_mm256_fmadd_ps(_mm256_mul_ps(_mm256_cvtepi32_ps(a[h]), lane_scale[h]), _mm256_set1_ps(q.scale[j]), _mm256_set1_ps(b[j])), zero);
                let (v0, v1) = (v(0), v(1));
                // SAFETY: `y[j]` is 16 f32.
                unsafe {
                    _mm256_storeu_ps(y[j].as_mut_ptr(), v0);
                    _mm256_storeu_ps(y[j].as_mut_ptr().add(8), v1);
                }
                let nonzero = |v: __m256| _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_NEQ_UQ>(v, zero)) != 0;
                out.rows[out.n] = j as u8;
                out.n += usize::from(nonzero(v0) || nonzero(v1));
            }
        }
        out
    }

    #[target_feature(enable = "avx2,fma")]
    fn avx2_int8(k: &MlpKernel, x: &TileInput) -> [[f32; TILE]; 4] {
        let q = k.hidden8.as_ref().expect("checked by the caller");
        let mut h0 = [[0.0f32; TILE]; HIDDEN];
        let active = dense256::<HIDDEN, 6>(&k.w0t, &k.b0, &x[..k.input], &Active::all(k.input), &mut h0, true);
        let mut h1 = [[0.0f32; TILE]; HIDDEN];
        let active = dense_int8_avx2(q, &k.b1, &h0, &active, &mut h1);
        let mut o = [[0.0f32; TILE]; 4];
        dense256::<4, 4>(&k.w2t, &k.b2, &h1, &active, &mut o, false);
        o
    }

    pub fn tile_avx2_int8(k: &MlpKernel, x: &TileInput) -> [[f32; TILE]; 4] {
        assert!(matches!(level(), Level::Avx2 | Level::Avx512) && k.hidden8.as_ref().is_some_and(|q| q.weight_levels <= 64.0));
        // SAFETY: the CPU has AVX2 and FMA (checked above); the body is safe code.
        unsafe { avx2_int8(k, x) }
    }

    pub fn tile_avx512(k: &MlpKernel, x: &TileInput) -> [[f32; TILE]; 4] {
        assert_eq!(level(), Level::Avx512);
        // SAFETY: the CPU has AVX-512F and FMA (checked by `level`); the body is safe code.
        unsafe { avx512(k, x) }
    }

    /// Peak fused multiply-add rate of one thread, GFLOP/s (2 per lane per FMA): twelve
    /// independent chains of vector FMAs at the widest level, `iterations` rounds.
    pub fn fma_peak_gflops(iterations: u64) -> f64 {
        #[target_feature(enable = "avx512f")]
        fn run512(n: u64) -> f32 {
            let mut acc = [_mm512_set1_ps(1.0); 12];
            let (m, c) = (_mm512_set1_ps(std::hint::black_box(0.999_999)), _mm512_set1_ps(std::hint::black_box(1e-7)));
            for _ in 0..n {
                for a in acc.iter_mut() {
                    *a = _mm512_fmadd_ps(*a, m, c);
                }
            }
            acc.iter().map(|a| _mm512_reduce_add_ps(*a)).sum()
        }
        #[target_feature(enable = "avx2,fma")]
        fn run256(n: u64) -> f32 {
            let mut acc = [_mm256_set1_ps(1.0); 12];
            let (m, c) = (_mm256_set1_ps(std::hint::black_box(0.999_999)), _mm256_set1_ps(std::hint::black_box(1e-7)));
            for _ in 0..n {
                for a in acc.iter_mut() {
                    *a = _mm256_fmadd_ps(*a, m, c);
                }
            }
            let mut lanes = [0.0f32; 8];
            for a in acc {
                let mut v = [0.0f32; 8];
                // SAFETY: `v` is 8 f32.
                unsafe { _mm256_storeu_ps(v.as_mut_ptr(), a) };
                lanes.iter_mut().zip(v).for_each(|(l, x)| *l += x);
            }
            lanes.iter().sum()
        }
        let start = std::time::Instant::now();
        let lanes = match level() {
            Level::Avx512 => {
                // SAFETY: the CPU has AVX-512F (checked by `level`).
                std::hint::black_box(unsafe { run512(iterations) });
                16
            }
            Level::Avx2 => {
                // SAFETY: the CPU has AVX2 and FMA (checked by `level`).
                std::hint::black_box(unsafe { run256(iterations) });
                8
            }
            Level::Portable => return 0.0,
        };
        2.0 * 12.0 * lanes as f64 * iterations as f64 / start.elapsed().as_secs_f64() / 1e9
    }

    pub fn tile_avx2(k: &MlpKernel, x: &TileInput) -> [[f32; TILE]; 4] {
        assert!(matches!(level(), Level::Avx2 | Level::Avx512));
        // SAFETY: the CPU has AVX2 and FMA (checked by `level`); the body is safe code.
        unsafe { avx2(k, x) }
    }
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

    /// The vector kernels skip the inputs that are zero for the whole tile (dead ReLUs): the
    /// same bits as the fused portable body, which takes every input in the same order.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn skipping_zero_rows_changes_no_bit() {
        if simd::level() == simd::Level::Portable {
            eprintln!("no AVX2 on this CPU: only the portable path exists");
            return;
        }
        let mut rng = SmallRng::seed_from_u64(12);
        for input in [5, 25, 64] {
            let mut m = SpecularMlp::zeros(input);
            for w in [&mut m.w0, &mut m.b0, &mut m.w1, &mut m.b1, &mut m.w2, &mut m.b2] {
                w.iter_mut().for_each(|v| *v = rng.random_range(-0.5..0.5));
            }
            // A third of each hidden layer is off for every input, as dead ReLUs are; the
            // rest is on for some rays of a tile and off for others.
            for j in (0..HIDDEN).step_by(3) {
                (m.b0[j], m.b1[(j + 1) % HIDDEN]) = (-100.0, -100.0);
            }
            let k = m.kernel();
            for _ in 0..50 {
                let mut x = [[0.0f32; TILE]; MAX_INPUT];
                for row in x.iter_mut().take(input) {
                    row.iter_mut().for_each(|v| *v = rng.random_range(-3.0..3.0));
                }
                let fused = tile_body::<8, true>(&k, &x);
                let bits = |o: [[f32; TILE]; 4]| o.map(|r| r.map(f32::to_bits));
                assert_eq!(bits(simd::tile_avx2(&k, &x)), bits(fused), "AVX2, input {input}");
                if simd::level() == simd::Level::Avx512 {
                    assert_eq!(bits(simd::tile_avx512(&k, &x)), bits(fused), "AVX-512, input {input}");
                }
            }
        }
    }

    #[test]
    fn tile_kernel_agrees_with_the_reference() {
        let mut rng = SmallRng::seed_from_u64(9);
        for input in [1, 21, 37, 64] {
            let mut m = SpecularMlp::zeros(input);
            for w in [&mut m.w0, &mut m.b0, &mut m.w1, &mut m.b1, &mut m.w2, &mut m.b2] {
                w.iter_mut().for_each(|v| *v = rng.random_range(-0.5..0.5));
            }
            let k = m.kernel();
            let mut x = [[0.0f32; TILE]; MAX_INPUT];
            for row in x.iter_mut().take(input) {
                row.iter_mut().for_each(|v| *v = rng.random_range(-3.0..3.0));
            }
            let got = k.forward_tile(&x);
            let portable = tile_body::<8, false>(&k, &x);
            // Every vector level this CPU has, not only the widest.
            #[cfg(target_arch = "x86_64")]
            let avx2 = (simd::level() != simd::Level::Portable).then(|| simd::tile_avx2(&k, &x));
            #[cfg(not(target_arch = "x86_64"))]
            let avx2: Option<[[f32; TILE]; 4]> = None;
            for l in 0..TILE {
                let xs: Vec<f32> = (0..input).map(|i| x[i][l]).collect();
                let want = m.forward(&xs);
                for j in 0..4 {
                    // Sums of ≤ 64 products of size ≲ 10: f32 rounding differences ≲ 1e-5.
                    let tol = 1e-5 * (1.0 + want[j].abs());
                    assert!((got[j][l] - want[j]).abs() <= tol, "input {input} lane {l} out {j}: {} vs {}", got[j][l], want[j]);
                    assert!((portable[j][l] - want[j]).abs() <= tol);
                    assert!(avx2.is_none_or(|a| (a[j][l] - want[j]).abs() <= tol), "AVX2, input {input}");
                }
            }
        }
    }

    /// The 8-bit hidden layer errs as its rounding predicts. Per product w·h the rounding
    /// adds at most |w|·λ/2 + h·s/2 + s·λ/4 (λ = the query's largest hidden value / 255,
    /// s = the row's largest |w| / 127), carried through layer 2 by |w2|: a hard bound on
    /// every output. Treating the roundings as independent and uniform, the error's standard
    /// deviation is the root of Σ w²λ²/12 + h²s²/12 (through |w2|²): the errors' RMS over
    /// the tiles must be within 1.5 of it and none beyond 6 (a kernel that mixed up its
    /// bytes would be off by the outputs' own size). Extremes: a query whose hidden vector
    /// is all zero (then the f32 kernel's bits), one with a single tiny input, inputs
    /// scaled by 10⁻⁴ and 10³.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn int8_hidden_layer_errs_within_its_rounding_bound() {
        if !simd::vnni() && simd::level() != simd::Level::Avx2 {
            eprintln!("this CPU has neither AVX-512 VNNI nor AVX2 without AVX-512: the 8-bit hidden layer is never used here (the f32 kernel is)");
            assert!(!SpecularMlp::zeros(4).kernel().with_int8_hidden().int8_hidden());
            return;
        }
        let mut rng = SmallRng::seed_from_u64(21);
        let (mut z_sq, mut z_max, mut count) = (0.0f64, 0.0f64, 0usize);
        for (input, scale) in [(25, 1.0f32), (25, 1e-4), (25, 1e3), (64, 1.0), (7, 1.0)] {
            let mut m = SpecularMlp::zeros(input);
            for w in [&mut m.w0, &mut m.b0, &mut m.w1, &mut m.b1, &mut m.w2, &mut m.b2] {
                w.iter_mut().for_each(|v| *v = rng.random_range(-0.5..0.5));
            }
            if input == 7 {
                m.b0.iter_mut().for_each(|b| *b = -b.abs() - 0.01);
            }
            let k = m.kernel().with_int8_hidden();
            assert!(k.int8_hidden());
            let weight_levels = k.hidden8.as_ref().map_or(0.0, |q| q.weight_levels);
            let mut x = [[0.0f32; TILE]; MAX_INPUT];
            for row in x.iter_mut().take(input) {
                row.iter_mut().for_each(|v| *v = scale * rng.random_range(-3.0..3.0));
            }
            // Lane 0 without input (with negative biases: every hidden unit off); lane 1 with
            // one tiny input.
            let all_off = input == 7;
            x.iter_mut().take(input).for_each(|row| (row[0], row[1]) = (0.0, 0.0));
            x[0][1] = 1e-6;
            let got = k.forward_tile(&x);
            let f32_tile = m.kernel().forward_tile(&x);
            for l in 0..TILE {
                let xs: Vec<f32> = (0..input).map(|i| x[i][l]).collect();
                let h0: Vec<f32> = (0..HIDDEN).map(|j| (m.b0[j] + (0..input).map(|i| m.w0[j * input + i] * xs[i]).sum::<f32>()).max(0.0)).collect();
                let lambda = h0.iter().fold(0.0f32, |a, &v| a.max(v)) / 255.0;
                let (bound1, var1): (Vec<f32>, Vec<f64>) = (0..HIDDEN)
                    .map(|j| {
                        let row = &m.w1[j * HIDDEN..(j + 1) * HIDDEN];
                        let s = row.iter().fold(0.0f32, |a, v| a.max(v.abs())) / weight_levels;
                        let size: f32 = m.b1[j].abs() + row.iter().zip(&h0).map(|(w, h)| (w * h).abs()).sum::<f32>();
                        let bound = row.iter().zip(&h0).map(|(w, h)| w.abs() * lambda / 2.0 + h * s / 2.0 + s * lambda / 4.0).sum::<f32>() + 1e-5 * size;
                        let var = row.iter().zip(&h0).map(|(&w, &h)| ((w * lambda).powi(2) + (h * s).powi(2)) as f64 / 12.0).sum::<f64>();
                        (bound, var)
                    })
                    .unzip();
                let want = m.forward(&xs);
                for (o, (got_o, want_o)) in got.iter().zip(want).enumerate() {
                    let bound = (0..HIDDEN).map(|j| m.w2[o * HIDDEN + j].abs() * bound1[j]).sum::<f32>() + 1e-5 * (1.0 + want_o.abs());
                    let err = (got_o[l] - want_o).abs();
                    assert!(err <= bound, "input {input} ×{scale} lane {l} out {o}: {} vs {want_o} (bound {bound})", got_o[l]);
                    if l == 0 && all_off {
                        assert_eq!(got_o[l], f32_tile[o][l], "no hidden value: the f32 kernel's bits");
                        continue;
                    }
                    let std = (0..HIDDEN).map(|j| (m.w2[o * HIDDEN + j] as f64).powi(2) * var1[j]).sum::<f64>().sqrt();
                    let z = err as f64 / (std + 1e-6 * (1.0 + want_o.abs() as f64));
                    (z_sq, z_max, count) = (z_sq + z * z, z_max.max(z), count + 1);
                }
            }
        }
        let z_rms = (z_sq / count as f64).sqrt();
        eprintln!("errors in predicted standard deviations: RMS {z_rms:.2}, largest {z_max:.2} over {count} outputs");
        assert!(z_rms <= 1.5 && z_max <= 6.0, "RMS {z_rms}, largest {z_max}");
    }
}
