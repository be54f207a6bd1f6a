//! The wavefront march's steps in AVX-512 registers: the same lanes, state and rule as
//! [`v3`], taken as four groups of 16 lanes with mask registers in place of blends (half
//! the instructions per lane of the groups of 8), and the density's f16 pairs split
//! by a 32→16-bit narrowing. The same operations in the same order on every lane, so the
//! same frames to the bit (tested against the AVX2 and per-ray marches).

use super::avx2::{Closed, LANES, Rule, Runs, Wave};
use super::*;
use std::arch::x86_64::*;

/// [`Footprints::band_bounds`] with each row of a rectangle as a masked 16-lane min and
/// max per 16 pixels (`_mm512_min_ps(r, b)` is `r < b ? r : b`: the scalar rule to the
/// bit).
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
pub(super) fn band_bounds(fp: &Footprints, width: u32, y0: u32, n: usize) -> RayBounds {
    fp.band_bounds_with(width, y0, n, |lo, hi, r| {
        let (r_lo, r_hi) = (_mm512_set1_ps(r.t_lo), _mm512_set1_ps(r.t_hi));
        for (lo, hi) in lo.chunks_mut(16).zip(hi.chunks_mut(16)) {
            let mask = (u32::MAX >> (32 - lo.len())) as __mmask16;
            // SAFETY: the mask covers `lo.len() == hi.len()` lanes, all inside the slices.
            unsafe {
                let (l, h) = (lo.as_mut_ptr(), hi.as_mut_ptr());
                _mm512_mask_storeu_ps(l, mask, _mm512_min_ps(r_lo, _mm512_maskz_loadu_ps(mask, l)));
                _mm512_mask_storeu_ps(h, mask, _mm512_max_ps(r_hi, _mm512_maskz_loadu_ps(mask, h)));
            }
        }
    })
}

/// [`avx2::march_wave`] with its steps in AVX-512 registers ([`steps`]).
#[inline]
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq,avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
pub(super) fn march_wave<const MULTI: bool, F: FnMut(usize, Vec3, Vec3, MarchHit, &mut Segments, Option<(Segment, bool)>)>(
    p: &FastPrepared,
    f: &RayFrame,
    s: &RenderSettings,
    step: f32,
    gap_t: f32,
    y0: u32,
    bounds: Option<&RayBounds>,
    n: usize,
    finish: F,
) {
    // SAFETY: the CPU has AVX-512 F/VL/BW/DQ and x86-64-v3 (this function's features).
    unsafe { avx2::march_wave_in::<MULTI, true, F>(p, f, s, step, gap_t, y0, bounds, n, finish) }
}

/// One step of every lane, four groups of 16 stage by stage (every group's cell gathers,
/// then every group's corner gathers and exps, then the rules); lanes set in `finished`
/// are frozen. Returns the lanes that stopped or have no sample left.
///
/// # Safety
/// As [`avx2::march_wave`]'s step: `cells` fits `density` (asserted by the caller), whose
/// live index entries are negative or bricks' first corners; the CPU has AVX-512.
#[inline]
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq,avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
pub(super) unsafe fn steps<const MULTI: bool>(
    density: &TextureCubes,
    cells: &LiveCells,
    rule: &Rule<'_>,
    wave: &mut Wave,
    runs: &mut Runs,
    segments: &mut Closed,
    finished: u64,
    step: f32,
) -> u64 {
    const { assert!(LANES == 64, "four groups of 16 lanes") };
    let frozen = [finished as u16, (finished >> 16) as u16, (finished >> 32) as u16, (finished >> 48) as u16];
    // SAFETY: as the caller guarantees; lanes `at..at + 16` of `LANES`-lane arrays.
    unsafe {
        // Written out: as `map`s over the groups, 11% slower per frame.
        let at = [locate16(density, cells, wave, 0, step), locate16(density, cells, wave, 16, step), locate16(density, cells, wave, 32, step), locate16(density, cells, wave, 48, step)];
        let sampled = [
            sigma16(density, cells, &at[0], frozen[0], step),
            sigma16(density, cells, &at[1], frozen[1], step),
            sigma16(density, cells, &at[2], frozen[2], step),
            sigma16(density, cells, &at[3], frozen[3], step),
        ];
        rule16::<MULTI>(rule, wave, runs, segments, 0, &at[0], sampled[0], frozen[0])
            | rule16::<MULTI>(rule, wave, runs, segments, 16, &at[1], sampled[1], frozen[1])
            | rule16::<MULTI>(rule, wave, runs, segments, 32, &at[2], sampled[2], frozen[2])
            | rule16::<MULTI>(rule, wave, runs, segments, 48, &at[3], sampled[3], frozen[3])
    }
}

/// [`avx2`]'s `Located` for 16 lanes.
struct Located {
    k: __m512i,
    t0: __m512,
    t: __m512,
    g: [__m512; 3],
    c: [__m512; 3],
    brick: __m512i,
}

/// The next samples of lanes `at..at + 16` (as `avx2::locate8`).
///
/// # Safety
/// `cells.index` has `grid³` entries; `at + 16 ≤ LANES`.
#[inline]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq,avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
unsafe fn locate16(density: &TextureCubes, cells: &LiveCells, wave: &Wave, at: usize, step: f32) -> Located {
    // SAFETY: 16-lane loads at `at ≤ LANES − 16`; the gather as `cells16`.
    unsafe {
        let ld = |a: &[f32; LANES]| _mm512_loadu_ps(a.as_ptr().add(at));
        let k = _mm512_loadu_si512(wave.k.as_ptr().add(at).cast());
        let t0 = ld(&wave.t0);
        let t = _mm512_add_ps(t0, _mm512_mul_ps(_mm512_add_ps(_mm512_cvtepi32_ps(k), _mm512_set1_ps(0.5)), _mm512_set1_ps(step)));
        // g = (o + t·d − min) · (res / size), as `TextureCubes::to_fine`.
        let (min, scale) = (density.bounds.min, density.fine_per_unit());
        let fine = |a: usize| {
            let p = _mm512_add_ps(ld(&wave.o[a]), _mm512_mul_ps(t, ld(&wave.d[a])));
            _mm512_mul_ps(_mm512_sub_ps(p, _mm512_set1_ps(min[a])), _mm512_set1_ps(scale[a]))
        };
        let g = [fine(0), fine(1), fine(2)];
        // cell = clamp(trunc(g / r), 0, b − 1) (g · 1/r is g / r to the bit for r a power
        // of two).
        let (b, r) = (density.grid as i32, density.brick as f32);
        let over_r = |g: __m512| if density.brick.is_power_of_two() { _mm512_mul_ps(g, _mm512_set1_ps(1.0 / r)) } else { _mm512_div_ps(g, _mm512_set1_ps(r)) };
        let cell = |g: __m512| _mm512_min_ps(_mm512_max_ps(_mm512_cvtepi32_ps(_mm512_cvttps_epi32(over_r(g))), _mm512_setzero_ps()), _mm512_set1_ps((b - 1) as f32));
        let c = [cell(g[0]), cell(g[1]), cell(g[2])];
        // As `avx2::cells8`.
        let cell_at = if cells.cell_numbers_in_f32 {
            let bf = _mm512_set1_ps(b as f32);
            _mm512_cvttps_epi32(_mm512_fmadd_ps(_mm512_fmadd_ps(c[2], bf, c[1]), bf, c[0]))
        } else {
            let bi = _mm512_set1_epi32(b);
            _mm512_add_epi32(_mm512_cvttps_epi32(c[0]), _mm512_mullo_epi32(bi, _mm512_add_epi32(_mm512_cvttps_epi32(c[1]), _mm512_mullo_epi32(bi, _mm512_cvttps_epi32(c[2])))))
        };
        // Each coordinate is clamped to 0..b, so `cell_at < b³ = cells.index.len()`.
        let brick = _mm512_i32gather_epi32::<4>(cell_at, cells.index.as_ptr());
        Located { k, t0, t, g, c, brick }
    }
}

/// σ and e = e^(−σδ) of located samples (σ = 0, e = 1 in dead cells and frozen lanes),
/// and which lanes read a live brick (as `avx2::sigma8`).
///
/// # Safety
/// Every non-negative lane of `at.brick` is a brick of `density`.
#[inline]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq,avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
unsafe fn sigma16(density: &TextureCubes, cells: &LiveCells, at: &Located, frozen: __mmask16, step: f32) -> (__mmask16, __m512, __m512) {
    let is_live = !frozen & _mm512_cmpgt_epi32_mask(at.brick, _mm512_set1_epi32(-1));
    // SAFETY: a dead cell (negative) is read as brick 0 and masked out below.
    let acc = unsafe { density16(density, cells, at.g, at.c, _mm512_max_epi32(at.brick, _mm512_setzero_si512())) };
    let sigma = _mm512_maskz_mov_ps(is_live, acc);
    let ex = _mm512_mask_blend_ps(is_live, _mm512_set1_ps(1.0), exp_neg16(_mm512_mul_ps(sigma, _mm512_set1_ps(step))));
    (is_live, sigma, ex)
}

/// σ at fine-grid points `g` of cells `c` from their bricks: `avx2::density8` on 16 lanes
/// (the same corner order and operations, so the same bits).
///
/// # Safety
/// Every lane of `first` is the first corner of a brick of `density` (`values` below
/// 2³¹ entries).
#[inline]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq,avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
unsafe fn density16(density: &TextureCubes, cells: &LiveCells, g: [__m512; 3], c: [__m512; 3], first: __m512i) -> __m512 {
    let r = density.brick as f32;
    let e = density.brick as i32 + 1;
    let zero = _mm512_setzero_ps();
    // u = clamp(g − cell·r, 0, r), base = min(trunc u, r − 1), f = u − base.
    let split = |a: usize| {
        let u = _mm512_min_ps(_mm512_max_ps(_mm512_sub_ps(g[a], _mm512_mul_ps(c[a], _mm512_set1_ps(r))), zero), _mm512_set1_ps(r));
        let base = _mm512_min_ps(_mm512_cvtepi32_ps(_mm512_cvttps_epi32(u)), _mm512_set1_ps(r - 1.0));
        (_mm512_sub_ps(u, base), base)
    };
    let (fx, bx) = split(0);
    let (fy, by) = split(1);
    let (fz, bz) = split(2);
    let ef = _mm512_set1_ps(e as f32);
    let idx0 = _mm512_add_epi32(first, _mm512_cvttps_epi32(_mm512_fmadd_ps(_mm512_fmadd_ps(bz, ef, by), ef, bx)));
    let one = _mm512_set1_ps(1.0);
    let (hx, hy, hz) = (_mm512_sub_ps(one, fx), _mm512_sub_ps(one, fy), _mm512_sub_ps(one, fz));
    let mut acc = zero;
    // SAFETY (the gathers): `idx0 + corner offset` lies in the brick's corners (each
    // coordinate of `base + corner` in 0..=r); in the paired reads x ≤ r − 1, so both
    // u16s lie in the brick's row.
    if let Some(h) = &cells.values_f16 {
        for pair in 0..4i32 {
            let (dy, dz) = (pair & 1, pair >> 1);
            let bits = unsafe { _mm512_i32gather_epi32::<2>(_mm512_add_epi32(idx0, _mm512_set1_epi32(e * (dy + e * dz))), h.as_ptr().cast()) };
            // The low and high f16 of each 32-bit lane, narrowed to 16 bits and widened to f32.
            let v0 = _mm512_cvtph_ps(_mm512_cvtepi32_epi16(bits));
            let v1 = _mm512_cvtph_ps(_mm512_cvtepi32_epi16(_mm512_srli_epi32::<16>(bits)));
            let wyz = |w: __m512| _mm512_mul_ps(_mm512_mul_ps(w, if dy == 1 { fy } else { hy }), if dz == 1 { fz } else { hz });
            acc = _mm512_add_ps(acc, _mm512_mul_ps(wyz(hx), v0));
            acc = _mm512_add_ps(acc, _mm512_mul_ps(wyz(fx), v1));
        }
    } else {
        for corner in 0..8i32 {
            let (dx, dy, dz) = (corner & 1, (corner >> 1) & 1, corner >> 2);
            let w = _mm512_mul_ps(_mm512_mul_ps(if dx == 1 { fx } else { hx }, if dy == 1 { fy } else { hy }), if dz == 1 { fz } else { hz });
            let v = unsafe { _mm512_i32gather_ps::<4>(_mm512_add_epi32(idx0, _mm512_set1_epi32(dx + e * (dy + e * dz))), density.values.as_ptr()) };
            acc = _mm512_add_ps(acc, _mm512_mul_ps(w, v));
        }
    }
    acc
}

/// Files the open runs of lanes `closing` (bits of lanes `at..at + 16`) among their rays'
/// closed segments as [`Closed::push`] does one lane at a time (by [`closed_slot`]), and clears their runs'
/// primary flags. (0.96–0.99 of the time per lego frame of the loop over the closing lanes;
/// on AVX2 the same in 8 lanes was 3–7% slower than the loop, which `v3` keeps.)
///
/// # Safety
/// `at + 16 ≤ LANES`.
#[inline]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq,avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
pub(super) unsafe fn close16(runs: &mut Runs, closed: &mut Closed, at: usize, closing: __mmask16) {
    // SAFETY: 16-lane loads and stores at `at ≤ LANES − 16` of `LANES`-lane arrays.
    unsafe {
        let ld = |a: &[f32; LANES]| _mm512_loadu_ps(a.as_ptr().add(at));
        let ldi = |a: &[i32; LANES]| _mm512_loadu_si512(a.as_ptr().add(at).cast());
        let set = _mm512_set1_epi32;
        let is_primary = closing & _mm512_test_epi32_mask(ldi(&runs.primary), ldi(&runs.primary));
        let primary = _mm512_mask_mov_epi32(ldi(&closed.primary), is_primary, set(-1));
        let count = ldi(&closed.count);
        let append = closing & _mm512_cmplt_epi32_mask(count, set(MAX_SEGMENTS as i32));
        let (mut lightest_w, mut lightest) = (_mm512_set1_ps(f32::INFINITY), _mm512_setzero_si512());
        for s in 0..MAX_SEGMENTS {
            let w = ld(&closed.weight[s]);
            let lighter = _mm512_cmpneq_epi32_mask(primary, set(s as i32)) & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(w, lightest_w);
            lightest_w = _mm512_mask_mov_ps(lightest_w, lighter, w);
            lightest = _mm512_mask_mov_epi32(lightest, lighter, set(s as i32));
        }
        let weight = ld(&runs.weight);
        let replace = closing & !append & (is_primary | _mm512_cmp_ps_mask::<_CMP_LT_OQ>(lightest_w, weight));
        let filed = append | replace;
        let slot = _mm512_mask_mov_epi32(lightest, append, count);
        let run = [weight, ld(&runs.peak_w), ld(&runs.peak_t), ld(&runs.first_t), ld(&runs.last_t)];
        for s in 0..MAX_SEGMENTS {
            let here = filed & _mm512_cmpeq_epi32_mask(slot, set(s as i32));
            for (field, v) in [&mut closed.weight, &mut closed.peak_w, &mut closed.peak_t, &mut closed.first_t, &mut closed.last_t].into_iter().zip(run) {
                _mm512_mask_storeu_ps(field[s].as_mut_ptr().add(at), here, v);
            }
        }
        _mm512_storeu_si512(closed.primary.as_mut_ptr().add(at).cast(), _mm512_mask_mov_epi32(primary, is_primary & filed, slot));
        _mm512_storeu_si512(closed.count.as_mut_ptr().add(at).cast(), _mm512_mask_add_epi32(count, append, count, set(1)));
        _mm512_storeu_si512(runs.primary.as_mut_ptr().add(at).cast(), _mm512_maskz_mov_epi32(!closing, ldi(&runs.primary)));
    }
}

/// The rule on lanes `at..at + 16` (as `avx2::rule8`, with masks for blends). Returns the
/// lanes (bits `at..at + 16`) that stopped or have no sample left.
#[inline]
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq,avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
fn rule16<const MULTI: bool>(rule: &Rule<'_>, wave: &mut Wave, runs: &mut Runs, segments: &mut Closed, at: usize, l: &Located, (is_live, sigma, ex): (__mmask16, __m512, __m512), frozen: __mmask16) -> u64 {
    let s = rule.s;
    let (one, zero) = (_mm512_set1_ps(1.0), _mm512_setzero_ps());
    // SAFETY: 16-lane loads and stores at `at ≤ LANES − 16` of `LANES`-lane arrays.
    unsafe {
        let ld = |a: &[f32; LANES]| _mm512_loadu_ps(a.as_ptr().add(at));
        let ldi = |a: &[i32; LANES]| _mm512_loadu_si512(a.as_ptr().add(at).cast());
        let st = |a: &mut [f32; LANES], v: __m512| _mm512_storeu_ps(a.as_mut_ptr().add(at), v);
        let nonzero = _mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(sigma, zero);
        let alpha = _mm512_sub_ps(one, ex);
        let transmittance = ld(&wave.transmittance);
        let w = _mm512_mul_ps(transmittance, alpha);
        let w_max = ld(&wave.w_max);
        let new_max = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(w, w_max);
        let w_max = _mm512_mask_blend_ps(new_max, w_max, w);
        st(&mut wave.w_max, w_max);
        let t_hit = _mm512_mask_blend_ps(new_max, ld(&wave.t_hit), l.t);
        st(&mut wave.t_hit, t_hit);
        let transmittance = _mm512_mul_ps(transmittance, _mm512_sub_ps(one, alpha));
        st(&mut wave.transmittance, transmittance);
        let stop = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(transmittance, _mm512_mul_ps(_mm512_set1_ps(s.stop_ratio), w_max))
            | _mm512_cmp_ps_mask::<_CMP_LT_OQ>(transmittance, _mm512_set1_ps(s.stop_below()));
        let samples = _mm512_loadu_si512(wave.samples.as_ptr().add(at).cast());
        _mm512_storeu_si512(wave.samples.as_mut_ptr().add(at).cast(), _mm512_mask_add_epi32(samples, nonzero, samples, _mm512_set1_epi32(1)));
        if MULTI {
            // `Segments::sample` on each lane with w > 0 (not NaN), as `avx2::rule8`.
            let t = l.t;
            let valid = !frozen & _mm512_cmp_ps_mask::<_CMP_GT_OQ>(w, zero);
            let open = _mm512_test_epi32_mask(ldi(&runs.open), ldi(&runs.open));
            let past_gap = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(_mm512_sub_ps(t, ld(&runs.peak_t)), _mm512_set1_ps(rule.gap_t));
            let closing = valid & open & past_gap;
            if closing != 0 {
                close16(runs, segments, at, closing);
            }
            let open = open & !closing;
            let start = valid & !open;
            let weight = _mm512_mask_blend_ps(start, ld(&runs.weight), zero);
            let peak_w = _mm512_mask_blend_ps(start, ld(&runs.peak_w), zero);
            let peak_t = _mm512_mask_blend_ps(start, ld(&runs.peak_t), t);
            let first_t = _mm512_mask_blend_ps(start, ld(&runs.first_t), t);
            st(&mut runs.first_t, first_t);
            _mm512_storeu_si512(runs.open.as_mut_ptr().add(at).cast(), _mm512_movm_epi32(open | valid));
            st(&mut runs.weight, _mm512_mask_blend_ps(valid, weight, _mm512_add_ps(weight, w)));
            let last_t = _mm512_mask_blend_ps(valid, ld(&runs.last_t), t);
            st(&mut runs.last_t, last_t);
            let heavier = valid & _mm512_cmp_ps_mask::<_CMP_GT_OQ>(w, peak_w);
            st(&mut runs.peak_w, _mm512_mask_blend_ps(heavier, peak_w, w));
            st(&mut runs.peak_t, _mm512_mask_blend_ps(heavier, peak_t, t));
            let primary = _mm512_test_epi32_mask(ldi(&runs.primary), ldi(&runs.primary)) | (valid & new_max);
            _mm512_storeu_si512(runs.primary.as_mut_ptr().add(at).cast(), _mm512_movm_epi32(primary));
        }
        let k1 = _mm512_add_epi32(l.k, _mm512_set1_epi32(1));
        // The dead box's radius for the ray's octant (as `avx2::rule8`).
        let radii = _mm512_max_epi32(_mm512_sub_epi32(_mm512_set1_epi32(-1), l.brick), _mm512_setzero_si512());
        let radius = _mm512_cvtepi32_ps(_mm512_and_si512(_mm512_srlv_epi32(radii, ldi(&wave.octant_shift)), _mm512_set1_epi32(7)));
        const CEIL: i32 = _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC;
        let exit = |a: usize| {
            let t_per = ld(&wave.t_per_fine[a]);
            let up = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(t_per, zero);
            let face = _mm512_mask_blend_ps(up, _mm512_sub_ps(zero, radius), _mm512_add_ps(radius, one));
            let bound = _mm512_mul_ps(_mm512_add_ps(l.c[a], face), _mm512_set1_ps(rule.r));
            // ≥ 0, or NaN for a parallel ray (0·∞), which `min_ps` drops for its second operand.
            _mm512_mul_ps(_mm512_sub_ps(bound, l.g[a]), t_per)
        };
        let dt = _mm512_min_ps(exit(2), _mm512_min_ps(exit(1), exit(0)));
        let ks = _mm512_roundscale_ps::<CEIL>(_mm512_sub_ps(
            _mm512_mul_ps(_mm512_sub_ps(_mm512_sub_ps(_mm512_add_ps(l.t, dt), _mm512_set1_ps(rule.margin)), l.t0), _mm512_set1_ps(1.0 / rule.step)),
            _mm512_set1_ps(0.5),
        ));
        // min(k_end, ks) keeps a NaN (its second operand); max(·, k + 1) then takes k + 1.
        let k_end = ldi(&wave.k_end);
        let ks = _mm512_max_ps(_mm512_min_ps(_mm512_cvtepi32_ps(k_end), ks), _mm512_cvtepi32_ps(k1));
        let k_next = _mm512_mask_blend_epi32(frozen, _mm512_mask_blend_epi32(is_live, _mm512_cvttps_epi32(ks), k1), l.k);
        _mm512_storeu_si512(wave.k.as_mut_ptr().add(at).cast(), k_next);
        let past_end = !_mm512_cmpgt_epi32_mask(k_end, k_next);
        (((stop & nonzero) | past_end) as u64) << at
    }
}

/// [`exp_neg`] on 16 lanes, the same operations in the same order as `avx2::exp_neg8`.
#[inline]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq,avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
fn exp_neg16(x: __m512) -> __m512 {
    let x = _mm512_sub_ps(_mm512_setzero_ps(), x);
    let underflow = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(x, _mm512_set1_ps(-87.0));
    let nan = _mm512_cmp_ps_mask::<_CMP_UNORD_Q>(x, x);
    let xc = _mm512_min_ps(x, _mm512_set1_ps(88.0));
    let magic = _mm512_set1_ps(12_582_912.0);
    let n = _mm512_sub_ps(_mm512_fmadd_ps(xc, _mm512_set1_ps(std::f32::consts::LOG2_E), magic), magic);
    let r = _mm512_fnmadd_ps(n, _mm512_set1_ps(-2.121_944_4e-4), _mm512_fnmadd_ps(n, _mm512_set1_ps(0.693_359_4), xc));
    let mut p = _mm512_set1_ps(1.987_569_2e-4);
    for c in [1.398_199_9e-3, 8.333_452e-3, 4.166_579_6e-2, 1.666_666_5e-1, 0.5] {
        p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(c));
    }
    let y = _mm512_add_ps(_mm512_fmadd_ps(_mm512_mul_ps(p, r), r, r), _mm512_set1_ps(1.0));
    let scale = _mm512_castsi512_ps(_mm512_slli_epi32::<23>(_mm512_add_epi32(_mm512_cvtps_epi32(n), _mm512_set1_epi32(127))));
    _mm512_mask_blend_ps(nan, _mm512_maskz_mov_ps(!underflow, _mm512_mul_ps(y, scale)), x)
}
