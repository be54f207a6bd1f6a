//! The vector kernels, compiled for AVX-512 and AVX2 + FMA and picked at run time (the
//! release build targets baseline x86-64).

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
