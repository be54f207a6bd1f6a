//! The wavefront march in AVX2 registers: 32 rays, four groups of 8 lanes interleaved stage
//! by stage (see the notes of [`super`]), and the tile inputs' gathers for CPUs without
//! AVX-512. Compiled for AVX2 + FMA and entered only when the CPU has them.

use super::*;
use std::arch::x86_64::*;

#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
#[allow(clippy::too_many_arguments)]
fn band_v3(p: &FastPrepared, f: &RayFrame, req: &ViewRequest, settings: &RenderSettings, rule: &HitRule, y0: u32, bounds: Option<&RayBounds>, rgba: &mut [u8], depth: &mut [f32]) -> BandStats {
    p.band::<true>(f, req, settings, rule, y0, bounds, rgba, depth)
}

#[allow(clippy::too_many_arguments)]
pub(super) fn band(p: &FastPrepared, f: &RayFrame, req: &ViewRequest, settings: &RenderSettings, rule: &HitRule, y0: u32, bounds: Option<&RayBounds>, rgba: &mut [u8], depth: &mut [f32]) -> BandStats {
    assert_ne!(crate::mlp::simd::level(), crate::mlp::simd::Level::Portable);
    // SAFETY: the CPU has AVX2 and FMA (checked by `level`; every x86-64 CPU with them
    // has the rest of x86-64-v3); the body is safe code.
    unsafe { band_v3(p, f, req, settings, rule, y0, bounds, rgba, depth) }
}

/// [`FastPrepared::sigmas`] in AVX2 registers, 8 samples at a time: the same f32
/// operations in the same order as the scalar path (no fused multiply-adds), so
/// bit-identical, with the cell's brick and the 8 trilinear corners gathered.
#[inline]
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
pub(super) fn sigmas(density: &TextureCubes, cells: &LiveCells, k0: i32, n: usize, o: Vec3, d: Vec3, t0: f32, step: f32) -> ([f32; BATCH], [f32; BATCH], u32) {
    cells.assert_fits(density);
    let mut sigma = [0.0f32; BATCH];
    let mut out = [1.0f32; BATCH];
    let mut nonzero = 0u32;
    for half in 0..n.div_ceil(8) {
        let at = 8 * half;
        // SAFETY: register arithmetic; `cells8` on the live index (b³ entries, asserted),
        // `density8` on its bricks with negative entries replaced by 0 (as in
        // `march_wave`); stores into `[f32; BATCH]` at `at ≤ BATCH − 8`.
        unsafe {
            let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
            let k = _mm256_add_epi32(_mm256_set1_epi32(k0 + at as i32), lane);
            // t = t0 + (k + ½)·δ, p = o + t·d, g = (p − min) · (res / size).
            let t = _mm256_add_ps(_mm256_set1_ps(t0), _mm256_mul_ps(_mm256_add_ps(_mm256_cvtepi32_ps(k), _mm256_set1_ps(0.5)), _mm256_set1_ps(step)));
            let g = fine8(density, [_mm256_set1_ps(o.x), _mm256_set1_ps(o.y), _mm256_set1_ps(o.z)], [_mm256_set1_ps(d.x), _mm256_set1_ps(d.y), _mm256_set1_ps(d.z)], t);
            let (c, brick) = cells8(density, cells, g);
            let is_live = _mm256_cmpgt_epi32(brick, _mm256_set1_epi32(-1));
            if _mm256_movemask_epi8(is_live) == 0 {
                continue;
            }
            let acc = density8(density, cells, g, c, _mm256_max_epi32(brick, _mm256_setzero_si256()));
            let one = _mm256_set1_ps(1.0);
            let acc = _mm256_and_ps(acc, _mm256_castsi256_ps(is_live));
            nonzero |= (_mm256_movemask_ps(_mm256_cmp_ps::<_CMP_NEQ_UQ>(acc, _mm256_setzero_ps())) as u32) << at;
            _mm256_storeu_ps(sigma.as_mut_ptr().add(at), acc);
            let ex = _mm256_blendv_ps(one, exp_neg8(_mm256_mul_ps(acc, _mm256_set1_ps(step))), _mm256_castsi256_ps(is_live));
            _mm256_storeu_ps(out.as_mut_ptr().add(at), ex);
        }
    }
    (sigma, out, nonzero)
}

/// The `i32`s at `base[at[lane]]`, read one lane at a time: on Zen 3, 8 loads and inserts
/// take ~0.6 of a `vpgatherdd`'s time (microbenchmark).
///
/// # Safety
/// Every lane of `at` indexes the slice `base` points into.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
unsafe fn read8(base: *const i32, at: __m256i) -> __m256i {
    let mut lanes = [0i32; 8];
    unsafe { _mm256_storeu_si256(lanes.as_mut_ptr().cast(), at) };
    // SAFETY: the caller's guarantee.
    let rd = |l: usize| unsafe { *base.add(lanes[l] as usize) };
    let low = _mm_insert_epi32::<3>(_mm_insert_epi32::<2>(_mm_insert_epi32::<1>(_mm_cvtsi32_si128(rd(0)), rd(1)), rd(2)), rd(3));
    let high = _mm_insert_epi32::<3>(_mm_insert_epi32::<2>(_mm_insert_epi32::<1>(_mm_cvtsi32_si128(rd(4)), rd(5)), rd(6)), rd(7));
    _mm256_set_m128i(high, low)
}

/// [`FastPrepared::tile_inputs_scalar`] for a whole tile in AVX2 registers, 8 queries at
/// a time, from the query points `p[axis][lane]`: each query's 8 hash corners (brick
/// table reads gathered; an absent corner reads the zero row) and its features summed in
/// the scalar path's order (the same sums), and the 8-bit diffuse corners gathered and
/// weighted as bytes, scaled by 1/255 once (within an ulp of the scalar path's per-corner
/// division). Needs `features` a multiple of 8. `lane_reads`: read the index entries and
/// corners lane by lane instead of gathering them (for CPUs whose gathers are slow; the
/// same values).
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
#[allow(clippy::too_many_arguments)]
pub(super) fn tile_inputs(hash: &PshBricks, psh: &SpatialHash, bytes: &DiffuseBytes, cubes: &TextureCubes, p: &[[f32; TILE]; 3], x: &mut TileInput, diffuse: &mut [[f32; TILE]; 4], lane_reads: bool) {
    use std::arch::x86_64::*;
    let nf = psh.features as usize;
    let zero_id = hash.zero_id(nf);
    assert!(
        nf.is_multiple_of(8)
            && nf + 17 <= MAX_INPUT
            && hash.index.len() == hash.grid.pow(3)
            && hash.tables.len() < i32::MAX as usize
            && zero_id < i32::MAX as usize
            && cubes.channels == 4
            && bytes.corners.len() == cubes.values.len() / 4
            && cubes.index.len() == (cubes.grid as usize).pow(3)
    );
    const EDGE: i32 = PshBricks::EDGE as i32;
    // Lane reads also read the masked-off lanes (at brick 0), so they need a brick.
    let lane_reads = lane_reads && hash.tables.len() >= (EDGE * EDGE * EDGE) as usize && !bytes.corners.is_empty();
    // Unmasked reads. SAFETY (callers): every lane of `at` indexes `base`'s slice.
    let read = |base: *const i32, at: __m256i| unsafe { if lane_reads { read8(base, at) } else { _mm256_i32gather_epi32::<4>(base, at) } };
    let mut ids = [[0u32; 8]; 8];
    let mut weights = [[0.0f32; 8]; 8];
    for half in 0..TILE / 8 {
        let at = 8 * half;
        // SAFETY: register arithmetic; loads of `p[axis][at..at + 8]` and stores into
        // `ids`/`weights`/`diffuse[c][at..at + 8]` (all in bounds: `at + 8 ≤ TILE`);
        // gathers of `hash.index` at brick coordinates each below `grid` (the cell's
        // coordinate is clamped to `0..n` and `grid = ⌈n / BRICK⌉`), of `hash.tables` at
        // `brick · EDGE³ + (l + corner) ` with `0 ≤ brick` < tables (masked where −1) and
        // each of `l + corner` in `0..EDGE`, of `cubes.index` at cell coordinates clamped
        // into `0..grid`, and of `bytes.corners` at `brick · corners + (base + corner)`
        // with `0 ≤ brick < brick_count` (checked in `DiffuseBytes::new`; masked where
        // −1) and each coordinate of `base + corner` in `0..=r`.
        unsafe {
            let load = |a: usize| _mm256_loadu_ps(p[a].as_ptr().add(at));
            let (px, py, pz) = (load(0), load(1), load(2));
            let one = _mm256_set1_ps(1.0);
            let zero = _mm256_setzero_ps();
            let weights8 = |fx: __m256, fy: __m256, fz: __m256, out: &mut [__m256; 8]| {
                let (hx, hy, hz) = (_mm256_sub_ps(one, fx), _mm256_sub_ps(one, fy), _mm256_sub_ps(one, fz));
                for (corner, w) in out.iter_mut().enumerate() {
                    let (dx, dy, dz) = (corner & 1, (corner >> 1) & 1, corner >> 2);
                    *w = _mm256_mul_ps(_mm256_mul_ps(if dx == 1 { fx } else { hx }, if dy == 1 { fy } else { hy }), if dz == 1 { fz } else { hz });
                }
            };
            let mut w = [zero; 8];

            // The hash: g = (p − min) / size · n, base = clamp(⌊g⌋, 0, n − 1),
            // f = clamp(g − base, 0, 1), as `PshBricks::corners`.
            let n = psh.grid as f32;
            let (min, size) = (psh.bounds.min, psh.bounds.size());
            let grid_f = |v: __m256, a: usize| _mm256_mul_ps(_mm256_div_ps(_mm256_sub_ps(v, _mm256_set1_ps(min[a])), _mm256_set1_ps(size[a])), _mm256_set1_ps(n));
            let split = |g: __m256| {
                let base = _mm256_min_ps(_mm256_max_ps(_mm256_floor_ps(g), zero), _mm256_set1_ps(n - 1.0));
                (_mm256_min_ps(_mm256_max_ps(_mm256_sub_ps(g, base), zero), one), _mm256_cvttps_epi32(base))
            };
            let (fx, bx) = split(grid_f(px, 0));
            let (fy, by) = split(grid_f(py, 1));
            let (fz, bz) = split(grid_f(pz, 2));
            weights8(fx, fy, fz, &mut w);
            const { assert!(PshBricks::BRICK == 4, "the brick of a vertex is `>> 2`") };
            let low = _mm256_set1_epi32(PshBricks::BRICK as i32 - 1);
            let g = _mm256_set1_epi32(hash.grid as i32);
            let brick_of = |b: __m256i| _mm256_srli_epi32::<2>(b);
            let brick_at = _mm256_add_epi32(brick_of(bx), _mm256_mullo_epi32(g, _mm256_add_epi32(brick_of(by), _mm256_mullo_epi32(g, brick_of(bz)))));
            let brick = read(hash.index.as_ptr(), brick_at);
            let live = _mm256_cmpgt_epi32(brick, _mm256_set1_epi32(-1));
            let e = _mm256_set1_epi32(EDGE);
            let (lx, ly, lz) = (_mm256_and_si256(bx, low), _mm256_and_si256(by, low), _mm256_and_si256(bz, low));
            let table0 = _mm256_add_epi32(
                _mm256_mullo_epi32(_mm256_max_epi32(brick, _mm256_setzero_si256()), _mm256_set1_epi32(EDGE * EDGE * EDGE)),
                _mm256_add_epi32(lx, _mm256_mullo_epi32(e, _mm256_add_epi32(ly, _mm256_mullo_epi32(e, lz)))),
            );
            let absent = _mm256_set1_epi32(PshBricks::ABSENT as i32);
            let zero_row = _mm256_set1_epi32(zero_id as i32);
            for corner in 0..8i32 {
                let (dx, dy, dz) = (corner & 1, (corner >> 1) & 1, corner >> 2);
                let at = _mm256_add_epi32(table0, _mm256_set1_epi32(dx + EDGE * (dy + EDGE * dz)));
                let id = if lane_reads { _mm256_blendv_epi8(absent, read8(hash.tables.as_ptr().cast(), at), live) } else { _mm256_mask_i32gather_epi32::<4>(absent, hash.tables.as_ptr().cast(), at, live) };
                let id = _mm256_blendv_epi8(id, zero_row, _mm256_cmpeq_epi32(id, absent));
                _mm256_storeu_si256(ids[corner as usize].as_mut_ptr().cast(), id);
                _mm256_storeu_ps(weights[corner as usize].as_mut_ptr(), w[corner as usize]);
            }

            // The diffuse cubes, as `TextureCubes::sample_with`: g = to_fine(p),
            // cell = clamp(trunc(g / r), 0, grid − 1), u = clamp(g − cell·r, 0, r),
            // base = min(trunc u, r − 1), f = u − base.
            let r = cubes.brick as f32;
            let (min, scale) = (cubes.bounds.min, cubes.fine_per_unit());
            let fine = |v: __m256, a: usize| _mm256_mul_ps(_mm256_sub_ps(v, _mm256_set1_ps(min[a])), _mm256_set1_ps(scale[a]));
            let cell = |g: __m256| _mm256_floor_ps(_mm256_min_ps(_mm256_max_ps(_mm256_div_ps(g, _mm256_set1_ps(r)), zero), _mm256_set1_ps(cubes.grid as f32 - 1.0)));
            let inside = |g: __m256, c: __m256| {
                let u = _mm256_min_ps(_mm256_max_ps(_mm256_sub_ps(g, _mm256_mul_ps(c, _mm256_set1_ps(r))), zero), _mm256_set1_ps(r));
                let base = _mm256_min_ps(_mm256_floor_ps(u), _mm256_set1_ps(r - 1.0));
                (_mm256_sub_ps(u, base), _mm256_cvttps_epi32(base))
            };
            let (gx, gy, gz) = (fine(px, 0), fine(py, 1), fine(pz, 2));
            let (cx, cy, cz) = (cell(gx), cell(gy), cell(gz));
            let (fx, bx) = inside(gx, cx);
            let (fy, by) = inside(gy, cy);
            let (fz, bz) = inside(gz, cz);
            weights8(fx, fy, fz, &mut w);
            let g = _mm256_set1_epi32(cubes.grid as i32);
            let cell_at = _mm256_add_epi32(_mm256_cvttps_epi32(cx), _mm256_mullo_epi32(g, _mm256_add_epi32(_mm256_cvttps_epi32(cy), _mm256_mullo_epi32(g, _mm256_cvttps_epi32(cz)))));
            let brick = read(cubes.index.as_ptr(), cell_at);
            let live = _mm256_cmpgt_epi32(brick, _mm256_set1_epi32(-1));
            let e = cubes.brick as i32 + 1;
            let ei = _mm256_set1_epi32(e);
            let start = _mm256_add_epi32(
                _mm256_mullo_epi32(_mm256_max_epi32(brick, _mm256_setzero_si256()), _mm256_set1_epi32(cubes.brick_corners() as i32)),
                _mm256_add_epi32(bx, _mm256_mullo_epi32(ei, _mm256_add_epi32(by, _mm256_mullo_epi32(ei, bz)))),
            );
            let byte = _mm256_set1_epi32(0xff);
            let mut acc = [zero; 4];
            for corner in 0..8i32 {
                let (dx, dy, dz) = (corner & 1, (corner >> 1) & 1, corner >> 2);
                let at = _mm256_add_epi32(start, _mm256_set1_epi32(dx + e * (dy + e * dz)));
                let v = if lane_reads { _mm256_and_si256(live, read8(bytes.corners.as_ptr().cast(), at)) } else { _mm256_mask_i32gather_epi32::<4>(_mm256_setzero_si256(), bytes.corners.as_ptr().cast(), at, live) };
                let wc = w[corner as usize];
                acc[0] = _mm256_fmadd_ps(wc, _mm256_cvtepi32_ps(_mm256_and_si256(v, byte)), acc[0]);
                acc[1] = _mm256_fmadd_ps(wc, _mm256_cvtepi32_ps(_mm256_and_si256(_mm256_srli_epi32::<8>(v), byte)), acc[1]);
                acc[2] = _mm256_fmadd_ps(wc, _mm256_cvtepi32_ps(_mm256_and_si256(_mm256_srli_epi32::<16>(v), byte)), acc[2]);
                acc[3] = _mm256_fmadd_ps(wc, _mm256_cvtepi32_ps(_mm256_srli_epi32::<24>(v)), acc[3]);
            }
            for (c, a) in diffuse.iter_mut().zip(acc) {
                _mm256_storeu_ps(c.as_mut_ptr().add(at), _mm256_mul_ps(a, _mm256_set1_ps(1.0 / 255.0)));
            }
        }
        // Features, one query at a time, 8 at once: Σ over corners of weight × row, in
        // corner order (separate multiply and add, as `PshBricks::encode`).
        for lane in 0..8 {
            for chunk in (0..nf).step_by(8) {
                // SAFETY: register arithmetic on 8-float loads from bounds-checked slices.
                unsafe {
                    let mut acc = _mm256_setzero_ps();
                    for corner in 0..8 {
                        let row = &hash.values[ids[corner][lane] as usize * nf + chunk..][..8];
                        acc = _mm256_add_ps(acc, _mm256_mul_ps(_mm256_set1_ps(weights[corner][lane]), _mm256_loadu_ps(row.as_ptr())));
                    }
                    let mut out = [0.0f32; 8];
                    _mm256_storeu_ps(out.as_mut_ptr(), acc);
                    for (row, v) in x[chunk..chunk + 8].iter_mut().zip(out) {
                        row[at + lane] = v;
                    }
                }
            }
        }
    }
}

/// The lanes of [`march_wave`]: each one's ray, lattice and scan state.
pub(super) struct Wave {
    pub(super) o: [[f32; LANES]; 3],
    pub(super) d: [[f32; LANES]; 3],
    /// Per axis, `(size[a] / res) / d[a]`: ray parameter per fine-grid unit (+∞
    /// where the ray is parallel to the axis).
    pub(super) t_per_fine: [[f32; LANES]; 3],
    /// Where the ray's octant keeps its dead-box radius in a dead cell's index entry:
    /// 3·oct, oct's bit a set where the ray rises along axis a (`t_per_fine[a] > 0`;
    /// [`dead_radii`]).
    pub(super) octant_shift: [i32; LANES],
    /// The ray parameter where it enters the box (the lattice's origin).
    pub(super) t0: [f32; LANES],
    /// The next lattice sample, and the end of the ray's samples.
    pub(super) k: [i32; LANES],
    pub(super) k_end: [i32; LANES],
    pub(super) transmittance: [f32; LANES],
    pub(super) w_max: [f32; LANES],
    pub(super) t_hit: [f32; LANES],
    pub(super) samples: [u32; LANES],
}

/// The open segment of each lane's ray ([`Segments`]' open run, kept in vectors).
pub(super) struct Runs {
    /// All ones where the lane has an open run, and where it holds the heaviest sample.
    pub(super) open: [i32; LANES],
    pub(super) primary: [i32; LANES],
    pub(super) weight: [f32; LANES],
    pub(super) peak_w: [f32; LANES],
    pub(super) peak_t: [f32; LANES],
    pub(super) first_t: [f32; LANES],
    pub(super) last_t: [f32; LANES],
}

impl Default for Wave {
    fn default() -> Self {
        // SAFETY: every field is an array of f32, i32 or u32, for which zero bits are valid.
        unsafe { std::mem::zeroed() }
    }
}

impl Default for Runs {
    fn default() -> Self {
        // SAFETY: as for `Wave`.
        unsafe { std::mem::zeroed() }
    }
}

impl Runs {
    pub(super) fn segment(&self, l: usize) -> Segment {
        Segment { weight: self.weight[l], peak_w: self.peak_w[l], peak_t: self.peak_t[l], first_t: self.first_t[l], last_t: self.last_t[l] }
    }
}

/// The closed segments of each lane's ray ([`Segments`]' closed list, kept in vectors so
/// that the runs a step closes are filed without a loop over lanes: 212k per lego
/// 640×480 frame): slot `s` of lane `l` is `weight[s][l]` etc., `count[l]` slots are
/// used, and `primary[l]` is the slot holding the ray's heaviest sample (−1: none).
pub(super) struct Closed {
    pub(super) weight: [[f32; LANES]; MAX_SEGMENTS],
    pub(super) peak_w: [[f32; LANES]; MAX_SEGMENTS],
    pub(super) peak_t: [[f32; LANES]; MAX_SEGMENTS],
    pub(super) first_t: [[f32; LANES]; MAX_SEGMENTS],
    pub(super) last_t: [[f32; LANES]; MAX_SEGMENTS],
    pub(super) count: [i32; LANES],
    pub(super) primary: [i32; LANES],
}

impl Default for Closed {
    fn default() -> Self {
        let slots = [[0.0; LANES]; MAX_SEGMENTS];
        Self { weight: slots, peak_w: slots, peak_t: slots, first_t: slots, last_t: slots, count: [0; LANES], primary: [-1; LANES] }
    }
}

impl Closed {
    /// Files `run` among lane `l`'s closed segments as [`Segments::close_run`] does (by
    /// [`closed_slot`]); `avx512::close16` does the same on 16 lanes.
    pub(super) fn push(&mut self, l: usize, run: Segment, is_primary: bool) {
        if is_primary {
            self.primary[l] = -1;
        }
        let n = self.count[l] as usize;
        if let Some(s) = closed_slot(n, usize::try_from(self.primary[l]).ok(), is_primary, run.weight, |s| self.weight[s][l]) {
            self.count[l] = self.count[l].max(s as i32 + 1);
            (self.weight[s][l], self.peak_w[s][l], self.peak_t[s][l], self.first_t[s][l], self.last_t[s][l]) = (run.weight, run.peak_w, run.peak_t, run.first_t, run.last_t);
            if is_primary {
                self.primary[l] = s as i32;
            }
        }
    }

    /// Moves lane `l`'s closed segments into `tracker` (empty, for [`Segments::finish`]),
    /// leaving the lane empty for its next ray.
    pub(super) fn take(&mut self, l: usize, tracker: &mut Segments) {
        let n = std::mem::take(&mut self.count[l]) as usize;
        let primary = std::mem::replace(&mut self.primary[l], -1);
        if n > 0 {
            let slot = |s: usize| Segment { weight: self.weight[s][l], peak_w: self.peak_w[s][l], peak_t: self.peak_t[s][l], first_t: self.first_t[s][l], last_t: self.last_t[s][l] };
            let closed: [Segment; MAX_SEGMENTS] = std::array::from_fn(slot);
            tracker.set_closed(&closed, n, usize::try_from(primary).ok());
        }
    }
}

/// Rays in flight in [`march_wave`]: four groups of 8 lanes, whose steps are interleaved
/// stage by stage so that the groups' reads overlap (2% faster per lego frame than two
/// groups; 16 rays were 13% faster than 8). With AVX-512, four groups of 16 (0.977–0.984
/// of the time per lego frame of two groups; on AVX2, 64 lanes as two rounds of four
/// groups of 8 were 3% slower than 32).
pub(super) const LANES: usize = 64;
/// Lanes of the AVX2 march, the first of the [`LANES`].
const LANES_AVX2: usize = 32;

/// Steps of [`march_wave`] between looks at which lanes have finished. A finished lane
/// idles until then: with 4, 8% of lane-steps on lego were idle, and 2 is 2% faster
/// per frame (1 is about the same as 2).
const STEPS: usize = 2;

/// The band's rays marched 32 at a time, one per lane ("wavefront"; four groups of 8
/// lanes, interleaved stage by stage; 64 in groups of 16 on AVX-512): each step evaluates one lattice sample of every
/// lane's ray, so the lanes' dependent reads (cell, then corners) overlap instead of
/// queueing along one ray, and no sample past a ray's stop is evaluated. A lane whose
/// sample lies in a dead cell jumps to the first lattice sample at or after where its ray
/// leaves the cell's dead box for its octant ([`dead_radii`]), less a margin of δ/16 (far
/// above the rounding of the sample positions and of the jump), so every skipped sample
/// lies in the dead box: σ = 0, which changes nothing. Each lane takes its samples in order by the
/// reference's rule, so every ray's result is [`FastPrepared::march`]'s. The steps have no
/// branch on the data: lanes that finish are frozen, and every [`STEPS`] steps they take
/// the band's next pixels. `finish(pixel, o, d, hit, tracker, run)` gets every pixel of
/// the band once, with the ray's closed segments and its open run (multi-hit), for
/// [`Segments::finish`].
#[inline]
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
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
    // SAFETY: the CPU has x86-64-v3 (this function's features).
    unsafe { march_wave_in::<MULTI, false, F>(p, f, s, step, gap_t, y0, bounds, n, finish) }
}

/// [`march_wave`]'s body; `WIDE`: its steps in AVX-512 registers, four groups of 16 lanes
/// ([`super::avx512::steps`]), else four groups of 8 in AVX2 registers (the first
/// [`LANES_AVX2`] lanes).
///
/// # Safety
/// The CPU has x86-64-v3, and AVX-512 (F, VL, BW, DQ) if `WIDE`; inlined only into
/// functions compiled for those features.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(super) unsafe fn march_wave_in<const MULTI: bool, const WIDE: bool, F: FnMut(usize, Vec3, Vec3, MarchHit, &mut Segments, Option<(Segment, bool)>)>(
    p: &FastPrepared,
    f: &RayFrame,
    s: &RenderSettings,
    step: f32,
    gap_t: f32,
    y0: u32,
    bounds: Option<&RayBounds>,
    n: usize,
    mut finish: F,
) {
    let density = &p.asset.density;
    let cells = &p.live;
    cells.assert_fits(density);
    let r = density.brick as f32;
    let mut wave = Wave::default();
    // Each lane's pixel and closed segments (multi-hit; a finished lane's move to
    // `tracker` for `finish`, which leaves it empty), and the open segments.
    let mut pixel = [0usize; LANES];
    let mut segments = Closed::default();
    // A finished ray's segments for `finish`, which leaves it empty.
    let mut tracker = Segments::new(gap_t);
    let mut runs = Runs::default();
    // The band's rays, made and clipped 8 at a time before the march ([`rays8`]); pixels
    // without samples are finished here.
    let mut starts = Vec::with_capacity(n);
    // In blocks of `RAY_BLOCK_COLUMNS` columns by the band's rows, each row of a block 8
    // pixels at a time: the rays in flight together are neighbours in two directions,
    // not along one row.
    let width = f.intrinsics.width as usize;
    debug_assert!(n.is_multiple_of(width), "bands are whole rows");
    let rows = n / width;
    let pieces = (0..width).step_by(RAY_BLOCK_COLUMNS).flat_map(|x0| {
        let x1 = (x0 + RAY_BLOCK_COLUMNS).min(width);
        (0..rows).flat_map(move |row| (x0..x1).step_by(8).map(move |x| (row * width + x, 8.min(x1 - x))))
    });
    for (i0, lanes) in pieces {
        // SAFETY: the CPU has x86-64-v3 (the caller's guarantee).
        let c = unsafe { rays8(f, density, bounds, y0, i0, lanes, step) };
        for l in 0..lanes {
            let (o, d) = (Vec3::new(c.o[0][l], c.o[1][l], c.o[2][l]), Vec3::new(c.d[0][l], c.d[1][l], c.d[2][l]));
            if c.start >> l & 1 != 0 {
                let t_per_fine = [c.t_per_fine[0][l], c.t_per_fine[1][l], c.t_per_fine[2][l]];
                starts.push(Start { pixel: i0 + l, o, d, t_per_fine, t0: c.t0[l], k_first: c.k_first[l], k_end: c.k_end[l] });
            } else if c.made >> l & 1 != 0 {
                finish(i0 + l, o, d, MarchHit::default(), &mut tracker, None);
            } else {
                // No live cell's footprint covers the pixel: the ray is not even made.
                finish(i0 + l, Vec3::ZERO, Vec3::ZERO, MarchHit::default(), &mut tracker, None);
            }
        }
    }
    let mut starts = starts.into_iter();
    // Gives `lane` the band's next ray; false when there is none left.
    let mut refill = |lane: usize, wave: &mut Wave, runs: &mut Runs, pixel: &mut [usize; LANES]| -> bool {
        let Some(Start { pixel: i, o, d, t_per_fine, t0, k_first, k_end }) = starts.next() else { return false };
        for a in 0..3 {
            (wave.o[a][lane], wave.d[a][lane], wave.t_per_fine[a][lane]) = (o[a], d[a], t_per_fine[a]);
        }
        wave.octant_shift[lane] = (0..3).filter(|&a| t_per_fine[a] > 0.0).map(|a| 3 << a).sum();
        (wave.t0[lane], wave.k[lane], wave.k_end[lane]) = (t0, k_first, k_end);
        (wave.transmittance[lane], wave.w_max[lane], wave.t_hit[lane], wave.samples[lane]) = (1.0, 0.0, 0.0, 0);
        (runs.open[lane], runs.primary[lane]) = (0, 0);
        pixel[lane] = i;
        true
    };
    let mut active = 0u64;
    let lanes = if WIDE { LANES } else { LANES_AVX2 };
    for lane in 0..lanes {
        if refill(lane, &mut wave, &mut runs, &mut pixel) {
            active |= 1 << lane;
        }
    }
    let rule = Rule { s, step, gap_t, margin: step / 16.0, r };
    // The f16 copy that `fetch8` reads the corners' rows from (bricks up to 5³ cells).
    let rows_f16 = cells.values_f16.as_deref().filter(|_| density.brick <= 5);
    while active != 0 {
        // Lanes that have finished (or are idle): frozen until the refill below.
        let mut finished = !active & (u64::MAX >> (64 - lanes));
        for _ in 0..STEPS {
            if WIDE {
                // SAFETY: the CPU has AVX-512 (the caller's guarantee); as below.
                finished |= unsafe { super::avx512::steps::<MULTI>(density, cells, &rule, &mut wave, &mut runs, &mut segments, finished, step) };
                continue;
            }
            // SAFETY: `locate8` on the live index (b³ entries, asserted); `sigma8` on its
            // bricks (every entry is negative or a brick's first corner, by
            // `LiveCells::new`); lanes `at..at + 8` of the `LANES`-lane arrays.
            let stopped = unsafe {
                let frozen = |at: usize| _mm256_cmpgt_epi32(_mm256_and_si256(_mm256_set1_epi32((finished >> at) as i32), _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128)), _mm256_setzero_si256());
                let frozen = [frozen(0), frozen(8), frozen(16), frozen(24)];
                // The four groups stage by stage, written out: every group's cell gathers,
                // then every group's corner reads, then their sums and exps, then the
                // rules (as a loop over the groups it ran 5% slower). With the f16 row
                // reads, all four groups' loads are issued before any sum waits on one
                // (0.983–0.991 of the time per lego frame at 640×480 and 1280×720 on Zen 3
                // against reading and summing a group at a time; the same frames).
                let at = [
                    locate8(density, cells, &wave, 0, step),
                    locate8(density, cells, &wave, 8, step),
                    locate8(density, cells, &wave, 16, step),
                    locate8(density, cells, &wave, 24, step),
                ];
                let sampled = if let Some(h) = rows_f16 {
                    let fetch = |l: &Located| fetch8(density, h, l.g, l.c, _mm256_max_epi32(l.brick, _mm256_setzero_si256()));
                    let rows = [fetch(&at[0]), fetch(&at[1]), fetch(&at[2]), fetch(&at[3])];
                    [
                        sigma_of8(&at[0], sum_rows8(&rows[0]), frozen[0], step),
                        sigma_of8(&at[1], sum_rows8(&rows[1]), frozen[1], step),
                        sigma_of8(&at[2], sum_rows8(&rows[2]), frozen[2], step),
                        sigma_of8(&at[3], sum_rows8(&rows[3]), frozen[3], step),
                    ]
                } else {
                    [
                        sigma8(density, cells, &at[0], frozen[0], step),
                        sigma8(density, cells, &at[1], frozen[1], step),
                        sigma8(density, cells, &at[2], frozen[2], step),
                        sigma8(density, cells, &at[3], frozen[3], step),
                    ]
                };
                rule8::<MULTI>(&rule, &mut wave, &mut runs, &mut segments, 0, &at[0], sampled[0], frozen[0])
                    | rule8::<MULTI>(&rule, &mut wave, &mut runs, &mut segments, 8, &at[1], sampled[1], frozen[1])
                    | rule8::<MULTI>(&rule, &mut wave, &mut runs, &mut segments, 16, &at[2], sampled[2], frozen[2])
                    | rule8::<MULTI>(&rule, &mut wave, &mut runs, &mut segments, 24, &at[3], sampled[3], frozen[3])
            };
            finished |= stopped;
        }
        let mut bits = finished & active;
        while bits != 0 {
            let l = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let hit = MarchHit { t_hit: wave.t_hit[l], alpha_c: 1.0 - wave.transmittance[l], w_max: wave.w_max[l], samples: wave.samples[l] };
            // The open run, which `Segments::finish` closes.
            let run = (MULTI && runs.open[l] != 0).then(|| (runs.segment(l), runs.primary[l] != 0));
            let (o, d) = (Vec3::new(wave.o[0][l], wave.o[1][l], wave.o[2][l]), Vec3::new(wave.d[0][l], wave.d[1][l], wave.d[2][l]));
            if MULTI {
                segments.take(l, &mut tracker);
            }
            finish(pixel[l], o, d, hit, &mut tracker, run);
            if !refill(l, &mut wave, &mut runs, &mut pixel) {
                active &= !(1 << l);
            }
        }
    }
}

/// A ray of [`march_wave`] that takes samples: its pixel in the band, origin and
/// direction, ray parameter per fine-grid unit along each axis (+∞ where it is parallel
/// to the axis; for the dead-cell jumps), and its lattice ([`lattice`]).
struct Start {
    pixel: usize,
    o: Vec3,
    d: Vec3,
    t_per_fine: [f32; 3],
    t0: f32,
    k_first: i32,
    k_end: i32,
}

/// Pixels `i0..i0 + 8` of a band (lanes past `n` are ignored): their rays as
/// [`RayFrame::ray`] makes them, clipped to the box and cut to the pixel's bounds as
/// [`lattice`] does — the same operations in the same order, so the same bits — 8 at a
/// time, so that their divisions and square roots overlap.
struct Rays8 {
    o: [[f32; 8]; 3],
    d: [[f32; 8]; 3],
    t_per_fine: [[f32; 8]; 3],
    t0: [f32; 8],
    k_first: [i32; 8],
    k_end: [i32; 8],
    /// Lanes (bits) whose ray was made: some footprint covers the pixel.
    made: u32,
    /// Lanes whose ray takes samples: it was made, meets the box and has lattice samples
    /// inside its bounds (the others are finished without a march).
    start: u32,
}

/// See [`Rays8`].
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
fn rays8(f: &RayFrame, density: &TextureCubes, bounds: Option<&RayBounds>, y0: u32, i0: usize, lanes: usize, step: f32) -> Rays8 {
    let width = f.intrinsics.width as usize;
    let (mut x_px, mut y_px, mut t_lo, mut t_hi) = ([0.0f32; 8], [0.0f32; 8], [f32::NEG_INFINITY; 8], [f32::INFINITY; 8]);
    for l in 0..lanes {
        let i = i0 + l;
        (x_px[l], y_px[l]) = ((i % width) as f32, (y0 as usize + i / width) as f32);
        if let Some(b) = bounds {
            (t_lo[l], t_hi[l]) = (b.t_lo[i], b.t_hi[i]);
        }
    }
    // No footprint covers any of the 8 pixels (common: a third of a lego 640×480 frame's
    // pixels are uncovered): no ray is made (0.987–0.989 of the time per frame).
    if (0..lanes).all(|l| t_lo[l] > t_hi[l]) {
        return Rays8 { o: [[0.0; 8]; 3], d: [[0.0; 8]; 3], t_per_fine: [[0.0; 8]; 3], t0: [0.0; 8], k_first: [0; 8], k_end: [0; 8], made: 0, start: 0 };
    }
    let set = _mm256_set1_ps;
    let ld = |a: &[f32; 8]| {
        // SAFETY: 8 f32.
        unsafe { _mm256_loadu_ps(a.as_ptr()) }
    };
    let st = |v: __m256| {
        let mut a = [0.0f32; 8];
        // SAFETY: 8 f32.
        unsafe { _mm256_storeu_ps(a.as_mut_ptr(), v) };
        a
    };
    let k = &f.intrinsics;
    // `RayFrame::ray`.
    let x = _mm256_div_ps(_mm256_sub_ps(_mm256_add_ps(ld(&x_px), set(0.5)), set(k.cx)), set(k.fx));
    let y = _mm256_div_ps(_mm256_xor_ps(_mm256_sub_ps(_mm256_add_ps(ld(&y_px), set(0.5)), set(k.cy)), set(-0.0)), set(k.fy));
    let r2 = _mm256_add_ps(_mm256_mul_ps(x, x), _mm256_mul_ps(y, y));
    let len = _mm256_sqrt_ps(_mm256_add_ps(set(1.0), r2));
    let (x_len, y_len) = (_mm256_div_ps(x, len), _mm256_div_ps(y, len));
    let z_dir = _mm256_div_ps(set(-1.0), len);
    let z_off = _mm256_div_ps(r2, _mm256_mul_ps(len, _mm256_add_ps(len, set(1.0))));
    let [c0, c1, c2] = f.object_from_camera;
    let rotate = |a: usize, v: [__m256; 3]| _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(set(c0[a]), v[0]), _mm256_mul_ps(set(c1[a]), v[1])), _mm256_mul_ps(set(c2[a]), v[2]));
    let d = [0, 1, 2].map(|a| rotate(a, [x_len, y_len, z_dir]));
    let o = [0, 1, 2].map(|a| _mm256_add_ps(set(f.origin_near_in_object[a]), _mm256_mul_ps(set(f.t_shift), rotate(a, [x_len, y_len, z_off]))));
    // `clip_ray`.
    let (lo, hi) = (density.bounds.min, density.bounds.max);
    let (mut t_near, mut t_far, mut outside) = (set(-crate::model::BIG), set(crate::model::BIG), _mm256_setzero_ps());
    for a in 0..3 {
        let abs = _mm256_andnot_ps(set(-0.0), d[a]);
        let tiny = _mm256_cmp_ps::<_CMP_LT_OQ>(abs, set(crate::model::TINY_DIR));
        let out = _mm256_or_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(o[a], set(lo[a])), _mm256_cmp_ps::<_CMP_GT_OQ>(o[a], set(hi[a])));
        outside = _mm256_or_ps(outside, _mm256_and_ps(tiny, out));
        let ta = _mm256_div_ps(_mm256_sub_ps(set(lo[a]), o[a]), d[a]);
        let tb = _mm256_div_ps(_mm256_sub_ps(set(hi[a]), o[a]), d[a]);
        t_near = _mm256_blendv_ps(_mm256_max_ps(t_near, _mm256_min_ps(ta, tb)), t_near, tiny);
        t_far = _mm256_blendv_ps(_mm256_min_ps(t_far, _mm256_max_ps(ta, tb)), t_far, tiny);
    }
    let t0 = _mm256_max_ps(t_near, _mm256_setzero_ps());
    let clipped = _mm256_andnot_ps(outside, _mm256_cmp_ps::<_CMP_GT_OQ>(t_far, t0));
    // `lattice`.
    let (t_lo, t_hi) = (ld(&t_lo), ld(&t_hi));
    let made = _mm256_cmp_ps::<_CMP_LE_OQ>(t_lo, t_hi);
    let (t_begin, t_end) = (_mm256_max_ps(t0, t_lo), _mm256_min_ps(t_far, t_hi));
    let lattice_k = |t: __m256| _mm256_ceil_ps(_mm256_sub_ps(_mm256_div_ps(_mm256_sub_ps(t, t0), set(step)), set(0.5)));
    // (Clamped below 2³⁰ before the integer conversion, as `as i32` saturates.)
    let to_i32 = |v: __m256| _mm256_cvttps_epi32(_mm256_min_ps(v, set(1073741824.0)));
    let k_first = to_i32(_mm256_max_ps(lattice_k(t_begin), _mm256_setzero_ps()));
    let k_end = to_i32(lattice_k(t_end));
    let samples = _mm256_and_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(t_begin, t_end), _mm256_castsi256_ps(_mm256_cmpgt_epi32(k_end, k_first)));
    let lane_mask = (1u32 << lanes) - 1;
    let made_bits = _mm256_movemask_ps(made) as u32 & lane_mask;
    let start_bits = _mm256_movemask_ps(_mm256_and_ps(_mm256_and_ps(made, clipped), samples)) as u32 & lane_mask;
    // Ray parameter per fine-grid unit, (size / res) / d (+∞ where d = 0).
    let (size, res) = (density.bounds.size(), density.fine_res() as f32);
    let t_per_fine = [0, 1, 2].map(|a| {
        let per = _mm256_div_ps(set(size[a] / res), d[a]);
        st(_mm256_blendv_ps(per, set(f32::INFINITY), _mm256_cmp_ps::<_CMP_EQ_OQ>(d[a], _mm256_setzero_ps())))
    });
    let ki = |v: __m256i| {
        let mut a = [0i32; 8];
        // SAFETY: 8 i32.
        unsafe { _mm256_storeu_si256(a.as_mut_ptr().cast(), v) };
        a
    };
    Rays8 { o: o.map(st), d: d.map(st), t_per_fine, t0: st(t0), k_first: ki(k_first), k_end: ki(k_end), made: made_bits, start: start_bits }
}

/// A group's samples of one step: where they are and in which cell (`brick` < 0 where
/// the cell is not live).
struct Located {
    k: __m256i,
    t0: __m256,
    t: __m256,
    g: [__m256; 3],
    c: [__m256; 3],
    brick: __m256i,
}

/// The next samples of lanes `at..at + 8`: t = t0 + (k + ½)·δ, their fine-grid position
/// (as `sigmas`) and cell.
///
/// # Safety
/// As [`cells8`]; `at + 8 ≤ LANES`.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
unsafe fn locate8(density: &TextureCubes, cells: &LiveCells, wave: &Wave, at: usize, step: f32) -> Located {
    // SAFETY: 8-lane loads at `at ≤ LANES − 8`; `cells8` as the caller guarantees.
    unsafe {
        let ld = |a: &[f32; LANES]| _mm256_loadu_ps(a.as_ptr().add(at));
        let k = _mm256_loadu_si256(wave.k.as_ptr().add(at).cast());
        let t0 = ld(&wave.t0);
        let t = _mm256_add_ps(t0, _mm256_mul_ps(_mm256_add_ps(_mm256_cvtepi32_ps(k), _mm256_set1_ps(0.5)), _mm256_set1_ps(step)));
        let g = fine8(density, [ld(&wave.o[0]), ld(&wave.o[1]), ld(&wave.o[2])], [ld(&wave.d[0]), ld(&wave.d[1]), ld(&wave.d[2])], t);
        let (c, brick) = cells8(density, cells, g);
        Located { k, t0, t, g, c, brick }
    }
}

/// σ and e = e^(−σδ) of located samples (σ = 0, e = 1 in dead cells and frozen lanes),
/// and which lanes read a live brick.
///
/// # Safety
/// As [`density8`] for the non-negative bricks of `at`.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
unsafe fn sigma8(density: &TextureCubes, cells: &LiveCells, at: &Located, frozen: __m256i, step: f32) -> (__m256i, __m256, __m256) {
    // SAFETY: a dead cell (negative) is read as brick 0 and masked out below.
    let acc = unsafe { density8(density, cells, at.g, at.c, _mm256_max_epi32(at.brick, _mm256_setzero_si256())) };
    sigma_of8(at, acc, frozen, step)
}

/// [`sigma8`] from the trilinear sums `acc` of its samples.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
fn sigma_of8(at: &Located, acc: __m256, frozen: __m256i, step: f32) -> (__m256i, __m256, __m256) {
    let is_live = _mm256_andnot_si256(frozen, _mm256_cmpgt_epi32(at.brick, _mm256_set1_epi32(-1)));
    let sigma = _mm256_and_ps(acc, _mm256_castsi256_ps(is_live));
    let ex = _mm256_blendv_ps(_mm256_set1_ps(1.0), exp_neg8(_mm256_mul_ps(sigma, _mm256_set1_ps(step))), _mm256_castsi256_ps(is_live));
    (is_live, sigma, ex)
}

/// `_mm256_blendv_ps(a, b, mask)` as one instruction that the compiler cannot see
/// through: a blend of a loaded value stored back to where it came from would otherwise
/// become a masked store (`vmaskmovps`), which is slow on AMD's cores.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
fn blend_opaque(a: __m256, b: __m256, mask: __m256) -> __m256 {
    let out: __m256;
    // SAFETY: a register-only blend (AVX, which the function's features include).
    unsafe { std::arch::asm!("vblendvps {o}, {a}, {b}, {m}", o = lateout(ymm_reg) out, a = in(ymm_reg) a, b = in(ymm_reg) b, m = in(ymm_reg) mask, options(pure, nomem, nostack, preserves_flags)) };
    out
}

/// The march's constants for [`rule8`].
pub(super) struct Rule<'a> {
    pub(super) s: &'a RenderSettings,
    pub(super) step: f32,
    pub(super) gap_t: f32,
    pub(super) margin: f32,
    /// Fine cells per index cell.
    pub(super) r: f32,
}

/// The rule on lanes `at..at + 8` for their samples `(is_live, σ, e)`, as `Scan::take`
/// on each lane: α = 1 − e, w = T·α, the heaviest sample, T ·= 1 − α, then the stopping
/// tests. With σ = 0 (dead cells and frozen lanes), α = 0 and nothing changes, so every
/// lane runs it; only σ ≠ 0 samples count and can stop. Then each lane's next sample:
/// k + 1 in a live cell; in a dead one, the first lattice sample at or after
/// t_exit − margin (t_exit: where the ray leaves the cell's dead box), if that is
/// further; a frozen lane stays. Returns the lanes (bits `at..at + 8`) that stopped or
/// have no sample left.
#[inline]
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
fn rule8<const MULTI: bool>(rule: &Rule<'_>, wave: &mut Wave, runs: &mut Runs, segments: &mut Closed, at: usize, l: &Located, (is_live, sigma, ex): (__m256i, __m256, __m256), frozen: __m256i) -> u64 {
    let s = rule.s;
    let (one, zero) = (_mm256_set1_ps(1.0), _mm256_setzero_ps());
    // SAFETY: 8-lane loads and stores at `at ≤ LANES − 8` of `LANES`-lane arrays.
    unsafe {
        let ld = |a: &[f32; LANES]| _mm256_loadu_ps(a.as_ptr().add(at));
        let ldi = |a: &[i32; LANES]| _mm256_loadu_si256(a.as_ptr().add(at).cast());
        let nonzero = _mm256_cmp_ps::<_CMP_NEQ_UQ>(sigma, zero);
        let alpha = _mm256_sub_ps(one, ex);
        let transmittance = ld(&wave.transmittance);
        let w = _mm256_mul_ps(transmittance, alpha);
        let w_max = ld(&wave.w_max);
        let new_max = _mm256_cmp_ps::<_CMP_GT_OQ>(w, w_max);
        let w_max = blend_opaque(w_max, w, new_max);
        _mm256_storeu_ps(wave.w_max.as_mut_ptr().add(at), w_max);
        _mm256_storeu_ps(wave.t_hit.as_mut_ptr().add(at), blend_opaque(ld(&wave.t_hit), l.t, new_max));
        let transmittance = _mm256_mul_ps(transmittance, _mm256_sub_ps(one, alpha));
        _mm256_storeu_ps(wave.transmittance.as_mut_ptr().add(at), transmittance);
        let stop = _mm256_or_ps(
            _mm256_cmp_ps::<_CMP_LT_OQ>(transmittance, _mm256_mul_ps(_mm256_set1_ps(s.stop_ratio), w_max)),
            _mm256_cmp_ps::<_CMP_LT_OQ>(transmittance, _mm256_set1_ps(s.stop_below())),
        );
        let samples = _mm256_sub_epi32(_mm256_loadu_si256(wave.samples.as_ptr().add(at).cast()), _mm256_castps_si256(nonzero));
        _mm256_storeu_si256(wave.samples.as_mut_ptr().add(at).cast(), samples);
        if MULTI {
            // `Segments::sample` on each lane with w > 0 (not NaN): a sample past the gap
            // after the open run's peak closes the run (scalar: the closed runs'
            // bookkeeping), then the open run takes the sample.
            let t = l.t;
            let valid = _mm256_andnot_ps(_mm256_castsi256_ps(frozen), _mm256_cmp_ps::<_CMP_GT_OQ>(w, zero));
            let open = _mm256_castsi256_ps(ldi(&runs.open));
            let past_gap = _mm256_cmp_ps::<_CMP_GT_OQ>(_mm256_sub_ps(t, ld(&runs.peak_t)), _mm256_set1_ps(rule.gap_t));
            let mut closing = _mm256_movemask_ps(_mm256_and_ps(_mm256_and_ps(valid, open), past_gap)) as u32;
            while closing != 0 {
                let lane = at + closing.trailing_zeros() as usize;
                closing &= closing - 1;
                segments.push(lane, runs.segment(lane), runs.primary[lane] != 0);
                (runs.open[lane], runs.primary[lane]) = (0, 0);
            }
            let open = _mm256_castsi256_ps(ldi(&runs.open));
            let start = _mm256_andnot_ps(open, valid);
            let weight = _mm256_blendv_ps(ld(&runs.weight), zero, start);
            let peak_w = _mm256_blendv_ps(ld(&runs.peak_w), zero, start);
            let peak_t = _mm256_blendv_ps(ld(&runs.peak_t), t, start);
            _mm256_storeu_ps(runs.first_t.as_mut_ptr().add(at), blend_opaque(ld(&runs.first_t), t, start));
            _mm256_storeu_si256(runs.open.as_mut_ptr().add(at).cast(), _mm256_castps_si256(_mm256_or_ps(open, valid)));
            _mm256_storeu_ps(runs.weight.as_mut_ptr().add(at), blend_opaque(weight, _mm256_add_ps(weight, w), valid));
            _mm256_storeu_ps(runs.last_t.as_mut_ptr().add(at), blend_opaque(ld(&runs.last_t), t, valid));
            let heavier = _mm256_and_ps(valid, _mm256_cmp_ps::<_CMP_GT_OQ>(w, peak_w));
            _mm256_storeu_ps(runs.peak_w.as_mut_ptr().add(at), blend_opaque(peak_w, w, heavier));
            _mm256_storeu_ps(runs.peak_t.as_mut_ptr().add(at), blend_opaque(peak_t, t, heavier));
            let primary = _mm256_or_ps(_mm256_castsi256_ps(ldi(&runs.primary)), _mm256_and_ps(valid, new_max));
            _mm256_storeu_si256(runs.primary.as_mut_ptr().add(at).cast(), _mm256_castps_si256(primary));
        }
        let k1 = _mm256_add_epi32(l.k, _mm256_set1_epi32(1));
        // The dead box's radius R in cells for the ray's octant, from its 3 bits at 3·oct
        // (0 in live cells, whose jump is not taken).
        let radii = _mm256_max_epi32(_mm256_sub_epi32(_mm256_set1_epi32(-1), l.brick), _mm256_setzero_si256());
        let radius = _mm256_cvtepi32_ps(_mm256_and_si256(_mm256_srlv_epi32(radii, ldi(&wave.octant_shift)), _mm256_set1_epi32(7)));
        let exit = |a: usize| {
            let t_per = ld(&wave.t_per_fine[a]);
            let up = _mm256_cmp_ps::<_CMP_GT_OQ>(t_per, zero);
            // The face the ray leaves the box by, c + R + 1 or c − R cells, in fine-grid units.
            let face = _mm256_blendv_ps(_mm256_sub_ps(zero, radius), _mm256_add_ps(radius, _mm256_set1_ps(1.0)), up);
            let bound = _mm256_mul_ps(_mm256_add_ps(l.c[a], face), _mm256_set1_ps(rule.r));
            // (bound − g)·t_per: ≥ 0, or NaN for a parallel ray (0·∞), which `min_ps`
            // drops in favour of its second operand.
            _mm256_mul_ps(_mm256_sub_ps(bound, l.g[a]), t_per)
        };
        let dt = _mm256_min_ps(exit(2), _mm256_min_ps(exit(1), exit(0)));
        let ks = _mm256_ceil_ps(_mm256_sub_ps(_mm256_mul_ps(_mm256_sub_ps(_mm256_sub_ps(_mm256_add_ps(l.t, dt), _mm256_set1_ps(rule.margin)), l.t0), _mm256_set1_ps(1.0 / rule.step)), _mm256_set1_ps(0.5)));
        // min(k_end, ks) keeps a NaN (its second operand); max(·, k + 1) then takes k + 1.
        let k_end = ldi(&wave.k_end);
        let ks = _mm256_max_ps(_mm256_min_ps(_mm256_cvtepi32_ps(k_end), ks), _mm256_cvtepi32_ps(k1));
        let k_next = _mm256_blendv_epi8(_mm256_blendv_epi8(_mm256_cvttps_epi32(ks), k1, is_live), l.k, frozen);
        _mm256_storeu_si256(wave.k.as_mut_ptr().add(at).cast(), k_next);
        let past_end = !(_mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpgt_epi32(k_end, k_next))) as u32) & 0xff;
        (((_mm256_movemask_ps(_mm256_and_ps(stop, nonzero)) as u32) | past_end) as u64) << at
    }
}

/// The fine-grid coordinates `g = (o + t·d − min) · (res / size)` of 8 samples, as
/// [`TextureCubes::to_fine`] computes them (the same operations, so the same bits).
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
fn fine8(density: &TextureCubes, o: [__m256; 3], d: [__m256; 3], t: __m256) -> [__m256; 3] {
    let (min, scale) = (density.bounds.min, density.fine_per_unit());
    let axis = |a: usize| {
        let p = _mm256_add_ps(o[a], _mm256_mul_ps(t, d[a]));
        _mm256_mul_ps(_mm256_sub_ps(p, _mm256_set1_ps(min[a])), _mm256_set1_ps(scale[a]))
    };
    [axis(0), axis(1), axis(2)]
}

/// The index cells of fine-grid points `g` — trunc(g / r) clamped to the grid, as
/// `TextureCubes::sample` — and their live bricks (negative where the cell is not live).
///
/// # Safety
/// `cells.index` has `grid³` entries; the CPU has x86-64-v3.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
unsafe fn cells8(density: &TextureCubes, cells: &LiveCells, g: [__m256; 3]) -> ([__m256; 3], __m256i) {
    let (b, r) = (density.grid as i32, density.brick as f32);
    // (g · 1/r is g / r to the bit when r is a power of two.)
    let over_r = |g: __m256| if density.brick.is_power_of_two() { _mm256_mul_ps(g, _mm256_set1_ps(1.0 / r)) } else { _mm256_div_ps(g, _mm256_set1_ps(r)) };
    let cell = |g: __m256| _mm256_min_ps(_mm256_max_ps(_mm256_cvtepi32_ps(_mm256_cvttps_epi32(over_r(g))), _mm256_setzero_ps()), _mm256_set1_ps((b - 1) as f32));
    let c = [cell(g[0]), cell(g[1]), cell(g[2])];
    let cell_at = if cells.cell_numbers_in_f32 {
        // In f32 (exact: integers below 2²⁴), shorter than two integer multiplies.
        let bf = _mm256_set1_ps(b as f32);
        _mm256_cvttps_epi32(_mm256_fmadd_ps(_mm256_fmadd_ps(c[2], bf, c[1]), bf, c[0]))
    } else {
        let bi = _mm256_set1_epi32(b);
        _mm256_add_epi32(_mm256_cvttps_epi32(c[0]), _mm256_mullo_epi32(bi, _mm256_add_epi32(_mm256_cvttps_epi32(c[1]), _mm256_mullo_epi32(bi, _mm256_cvttps_epi32(c[2])))))
    };
    // SAFETY: each coordinate is clamped to 0..b, so `cell_at < b³ = cells.index.len()`.
    (c, unsafe { _mm256_i32gather_epi32::<4>(cells.index.as_ptr(), cell_at) })
}

/// σ at fine-grid points `g` of cells `c` from their bricks (`first`: each brick's first
/// corner, as the live index holds it): the trilinear sum of the brick's corners in
/// `TextureCubes::sample`'s order (the same bits) — where the cubes have f16 values, a z
/// plane's four corners in one row read per lane (bricks up to 5³ cells), else two
/// corners (x, x + 1) per 32-bit element gathered.
///
/// # Safety
/// Every lane of `first` is the first corner of a brick of `density` (`values` below
/// 2³¹ entries); the CPU has x86-64-v3.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
unsafe fn density8(density: &TextureCubes, cells: &LiveCells, g: [__m256; 3], c: [__m256; 3], first: __m256i) -> __m256 {
    let e = density.brick as i32 + 1;
    let zero = _mm256_setzero_ps();
    let ([fx, fy, fz], idx0) = split8(density, g, c, first);
    let one = _mm256_set1_ps(1.0);
    let (hx, hy, hz) = (_mm256_sub_ps(one, fx), _mm256_sub_ps(one, fy), _mm256_sub_ps(one, fz));
    let mut acc = zero;
    // SAFETY (the reads): `idx0 + corner offset` lies in the brick's corners (each
    // coordinate of `base + corner` in 0..=r); in the paired reads x ≤ r − 1, so both
    // u16s lie in the brick's row; a row load's 8 u16s end at most 5 − e past the brick
    // (x, y ≤ r − 1), inside the f16 copy's 8 u16s of padding.
    if let Some(h) = &cells.values_f16 {
        if e <= 6 {
            // SAFETY: as above (the caller's guarantee).
            return sum_rows8(&unsafe { rows8(h, e, [fx, fy, fz], idx0) });
        }
        // Corners (0, y, z) and (1, y, z) as one 32-bit read of two f16s: split,
        // convert, and add in the same corner order as below.
        for pair in 0..4i32 {
            let (dy, dz) = (pair & 1, pair >> 1);
            let bits = unsafe { _mm256_i32gather_epi32::<2>(h.as_ptr().cast(), _mm256_add_epi32(idx0, _mm256_set1_epi32(e * (dy + e * dz)))) };
            let (v0, v1) = f16_pairs(bits);
            let wyz = |w: __m256| _mm256_mul_ps(_mm256_mul_ps(w, if dy == 1 { fy } else { hy }), if dz == 1 { fz } else { hz });
            acc = _mm256_add_ps(acc, _mm256_mul_ps(wyz(hx), v0));
            acc = _mm256_add_ps(acc, _mm256_mul_ps(wyz(fx), v1));
        }
    } else {
        for corner in 0..8i32 {
            let (dx, dy, dz) = (corner & 1, (corner >> 1) & 1, corner >> 2);
            let w = _mm256_mul_ps(_mm256_mul_ps(if dx == 1 { fx } else { hx }, if dy == 1 { fy } else { hy }), if dz == 1 { fz } else { hz });
            let v = unsafe { _mm256_i32gather_ps::<4>(density.values.as_ptr(), _mm256_add_epi32(idx0, _mm256_set1_epi32(dx + e * (dy + e * dz)))) };
            acc = _mm256_add_ps(acc, _mm256_mul_ps(w, v));
        }
    }
    acc
}

/// A group's trilinear fractions and its corner rows, loaded: the first half of
/// [`density8`]'s row reads (bricks up to 5³ cells), split off so that a step can issue
/// every group's loads before it waits for any ([`sum_rows8`] is the second half).
pub(super) struct Rows8 {
    f: [__m256; 3],
    /// Per z plane, lanes l and l + 4 in one register: their 4 corners' f16s in the low
    /// 8 bytes of each 128-bit half.
    lanes: [[__m256i; 4]; 2],
}

/// The trilinear fractions `f` and first corners of the samples at fine-grid points `g`
/// of cells `c` in bricks `first`, as [`density8`] reads them: u = clamp(g − cell·r, 0, r),
/// base = min(trunc u, r − 1), f = u − base, and the corner at `base` (its offset in the
/// brick in f32, exact: below (r + 1)³ ≤ 33³).
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
fn split8(density: &TextureCubes, g: [__m256; 3], c: [__m256; 3], first: __m256i) -> ([__m256; 3], __m256i) {
    let r = density.brick as f32;
    let zero = _mm256_setzero_ps();
    let split = |a: usize| {
        let u = _mm256_min_ps(_mm256_max_ps(_mm256_sub_ps(g[a], _mm256_mul_ps(c[a], _mm256_set1_ps(r))), zero), _mm256_set1_ps(r));
        let base = _mm256_min_ps(_mm256_cvtepi32_ps(_mm256_cvttps_epi32(u)), _mm256_set1_ps(r - 1.0));
        (_mm256_sub_ps(u, base), base)
    };
    let (fx, bx) = split(0);
    let (fy, by) = split(1);
    let (fz, bz) = split(2);
    let ef = _mm256_set1_ps(r + 1.0);
    ([fx, fy, fz], _mm256_add_epi32(first, _mm256_cvttps_epi32(_mm256_fmadd_ps(_mm256_fmadd_ps(bz, ef, by), ef, bx))))
}

/// [`density8`]'s row reads for the points `g` of cells `c` in bricks `first` (dead lanes
/// read as brick 0), from the f16 copy `h`.
///
/// # Safety
/// As [`density8`]; `h` is the cubes' f16 copy and their bricks have up to 5³ cells.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
pub(super) unsafe fn fetch8(density: &TextureCubes, h: &[u16], g: [__m256; 3], c: [__m256; 3], first: __m256i) -> Rows8 {
    let (f, idx0) = split8(density, g, c, first);
    // SAFETY: the caller's guarantee.
    unsafe { rows8(h, density.brick as i32 + 1, f, idx0) }
}

/// The row reads of [`density8`] from its corner offsets `idx0`.
///
/// # Safety
/// As [`density8`]'s row reads; `e ≤ 6`.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
unsafe fn rows8(h: &[u16], e: i32, [fx, fy, fz]: [__m256; 3], idx0: __m256i) -> Rows8 {
    // A lane's 4 corners in a z plane, (x, y), (x + 1, y), (x, y + 1) and (x + 1, y + 1),
    // lie in the 8 f16s from (x, y): one 16-byte load per lane and plane, then (in
    // `sum_rows8`) a 4 × 8 transpose into 8 lanes per corner (0.94 of the time per lego
    // frame at 640×480 and 1280×720 on Zen 3, whose gathers are slow, and the same
    // frames; reading the pairs one lane at a time: 0.945–0.955).
    let mut first_of = [0i32; 8];
    unsafe { _mm256_storeu_si256(first_of.as_mut_ptr().cast(), idx0) };
    let eb = 2 * e as i8;
    // Per 128-bit half: the 4 corners' u16s to the low 8 bytes.
    let pick = _mm256_setr_epi8(0, 1, 2, 3, eb, eb + 1, eb + 2, eb + 3, -1, -1, -1, -1, -1, -1, -1, -1, 0, 1, 2, 3, eb, eb + 1, eb + 2, eb + 3, -1, -1, -1, -1, -1, -1, -1, -1);
    let plane = |dz: usize| {
        let plane = (e * e) as usize * dz;
        let row = |l: usize| unsafe { _mm_loadu_si128(h.as_ptr().add(first_of[l] as usize + plane).cast()) };
        let lanes = |l: usize| _mm256_shuffle_epi8(_mm256_inserti128_si256::<1>(_mm256_castsi128_si256(row(l)), row(l + 4)), pick);
        [lanes(0), lanes(1), lanes(2), lanes(3)]
    };
    Rows8 { f: [fx, fy, fz], lanes: [plane(0), plane(1)] }
}

/// The second half of [`density8`]'s row reads: σ from [`Rows8`], in its order.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
pub(super) fn sum_rows8(rows: &Rows8) -> __m256 {
    let [fx, fy, fz] = rows.f;
    let one = _mm256_set1_ps(1.0);
    let (hx, hy, hz) = (_mm256_sub_ps(one, fx), _mm256_sub_ps(one, fy), _mm256_sub_ps(one, fz));
    let mut acc = _mm256_setzero_ps();
    for (dz, l) in rows.lanes.iter().enumerate() {
        let (low, high) = (_mm256_unpacklo_epi16(l[0], l[1]), _mm256_unpacklo_epi16(l[2], l[3]));
        // [a0–3 b0–3 | a4–7 b4–7] → [a0–7 | b0–7]; the same for c and d.
        let (ab, cd) = (_mm256_unpacklo_epi32(low, high), _mm256_unpackhi_epi32(low, high));
        for (dy, pair) in [ab, cd].into_iter().enumerate() {
            let pair = _mm256_permute4x64_epi64::<0b11_01_10_00>(pair);
            let (v0, v1) = (_mm256_cvtph_ps(_mm256_castsi256_si128(pair)), _mm256_cvtph_ps(_mm256_extracti128_si256::<1>(pair)));
            let wyz = |w: __m256| _mm256_mul_ps(_mm256_mul_ps(w, if dy == 1 { fy } else { hy }), if dz == 1 { fz } else { hz });
            acc = _mm256_add_ps(acc, _mm256_mul_ps(wyz(hx), v0));
            acc = _mm256_add_ps(acc, _mm256_mul_ps(wyz(fx), v1));
        }
    }
    acc
}

/// The low and high f16 of each 32-bit lane, as f32.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
fn f16_pairs(bits: std::arch::x86_64::__m256i) -> (std::arch::x86_64::__m256, std::arch::x86_64::__m256) {
    use std::arch::x86_64::*;
    let lo = _mm256_and_si256(bits, _mm256_set1_epi32(0xffff));
    let hi = _mm256_srli_epi32::<16>(bits);
    // 16-bit packing works within 128-bit halves: [lo 0–3, hi 0–3 | lo 4–7, hi 4–7],
    // then reorder the 64-bit quarters to [lo 0–7 | hi 0–7].
    let packed = _mm256_permute4x64_epi64::<0b11_01_10_00>(_mm256_packus_epi32(lo, hi));
    (_mm256_cvtph_ps(_mm256_castsi256_si128(packed)), _mm256_cvtph_ps(_mm256_extracti128_si256::<1>(packed)))
}

/// The first pixels of `rgba`, 8 at a time, from `color` and `alpha` as [`to_unorm8`]
/// makes them (clamped to 0..=1 with NaN → 0, × 255, rounded half away from zero: plus the
/// largest float below ½ and truncated, which rounds every value in 0..=255 the same);
/// returns how many pixels it wrote (a multiple of 8, the rest left to the caller).
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
pub(super) fn pack_rgba(color: &[Vec3], alpha: &[f32], rgba: &mut [u8]) -> usize {
    use std::arch::x86_64::*;
    let (zero, one, scale, below_half) = (_mm256_setzero_ps(), _mm256_set1_ps(1.0), _mm256_set1_ps(255.0), _mm256_set1_ps(0.499_999_97));
    // `max(v, 0)` takes its second operand when `v` is NaN.
    let unorm8 = |v: __m256| _mm256_cvttps_epi32(_mm256_add_ps(_mm256_mul_ps(_mm256_min_ps(_mm256_max_ps(v, zero), one), scale), below_half));
    let channels: &[f32] = bytemuck::cast_slice(color);
    let mut n = 0;
    for ((px, c), a) in rgba.chunks_exact_mut(32).zip(channels.chunks_exact(24)).zip(alpha.chunks_exact(8)) {
        let (mut rgb, mut alpha8) = ([0i32; 24], [0i32; 8]);
        // SAFETY: 8-float loads from `c` (24 floats) and `a` (8), 8-int stores into
        // `rgb` (24) and `alpha8` (8).
        unsafe {
            for k in 0..3 {
                _mm256_storeu_si256(rgb.as_mut_ptr().add(8 * k).cast(), unorm8(_mm256_loadu_ps(c.as_ptr().add(8 * k))));
            }
            _mm256_storeu_si256(alpha8.as_mut_ptr().cast(), unorm8(_mm256_loadu_ps(a.as_ptr())));
        }
        for (p, out) in px.chunks_exact_mut(4).enumerate() {
            out.copy_from_slice(&[rgb[3 * p] as u8, rgb[3 * p + 1] as u8, rgb[3 * p + 2] as u8, alpha8[p] as u8]);
        }
        n += 8;
    }
    n
}

/// [`super::view_inputs`] 8 queries at a time (the spherical harmonics of [`sh4`] by the
/// same operations in the same order: the same bits). Lanes past the tile's end repeat
/// its first query.
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
pub(super) fn view_inputs(tile: &[Query], features: usize, x: &mut TileInput) {
    assert!(features + 17 <= MAX_INPUT);
    let mut d = [[0.0f32; TILE]; 4];
    for (lane, q) in tile.iter().chain(std::iter::repeat(&tile[0])).take(TILE).enumerate() {
        (d[0][lane], d[1][lane], d[2][lane], d[3][lane]) = (q.d.x, q.d.y, q.d.z, q.alpha_c);
    }
    for at in (0..TILE).step_by(8) {
        // SAFETY: 8-lane loads of `d[a][at..at + 8]` and stores into
        // `x[row][at..at + 8]`, `at + 8 ≤ TILE`, `row < features + 17 ≤ MAX_INPUT`.
        unsafe {
            let ld = |a: usize| _mm256_loadu_ps(d[a].as_ptr().add(at));
            let (x_, y, z) = (ld(0), ld(1), ld(2));
            let c = _mm256_set1_ps;
            let mul = |a, b| _mm256_mul_ps(a, b);
            let (xy, yz, xz) = (mul(x_, y), mul(y, z), mul(x_, z));
            let (x2, y2, z2) = (mul(x_, x_), mul(y, y), mul(z, z));
            let one_minus_5z2 = _mm256_sub_ps(c(1.0), mul(c(5.0), z2));
            let rows = [
                c(0.282_094_79),
                mul(c(-0.488_602_51), y),
                mul(c(0.488_602_51), z),
                mul(c(-0.488_602_51), x_),
                mul(c(1.092_548_4), xy),
                mul(c(-1.092_548_4), yz),
                _mm256_sub_ps(mul(c(0.946_174_7), z2), c(0.315_391_57)),
                mul(c(-1.092_548_4), xz),
                _mm256_sub_ps(mul(c(0.546_274_2), x2), mul(c(0.546_274_2), y2)),
                mul(mul(c(0.590_043_6), y), _mm256_add_ps(mul(c(-3.0), x2), y2)),
                mul(mul(c(2.890_611_4), xy), z),
                mul(mul(c(0.457_045_8), y), one_minus_5z2),
                mul(mul(c(0.373_176_33), z), _mm256_sub_ps(mul(c(5.0), z2), c(3.0))),
                mul(mul(c(0.457_045_8), x_), one_minus_5z2),
                mul(mul(c(1.445_305_7), z), _mm256_sub_ps(x2, y2)),
                // −x² + 3y² is 3y² − x² to the bit.
                mul(mul(c(0.590_043_6), x_), _mm256_sub_ps(mul(c(3.0), y2), x2)),
                ld(3),
            ];
            for (k, v) in rows.into_iter().enumerate() {
                _mm256_storeu_ps(x[features + k].as_mut_ptr().add(at), v);
            }
        }
    }
}

/// [`super::composite`]: each query's terms 8 at a time (the same operations in the same
/// order, [`exp_neg8`] for [`exp_neg`]: the same bits), then added to the pixels one query
/// at a time (a pixel may have several queries).
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
pub(super) fn composite(tile: &[Query], o: &[[f32; TILE]; 4], diffuse: &[[f32; TILE]; 4], bg: Vec3, color: &mut [Vec3], alpha: &mut [f32]) {
    let mut beta = [0.0f32; TILE];
    for (b, q) in beta.iter_mut().zip(tile) {
        *b = q.beta;
    }
    let mut add = [[0.0f32; TILE]; 4];
    for at in (0..TILE).step_by(8) {
        // SAFETY: 8-lane loads and stores at `at + 8 ≤ TILE` of `TILE`-lane rows.
        unsafe {
            let ld = |row: &[f32; TILE]| _mm256_loadu_ps(row.as_ptr().add(at));
            let (one, zero) = (_mm256_set1_ps(1.0), _mm256_setzero_ps());
            let sigmoid = |v: __m256| _mm256_div_ps(one, _mm256_add_ps(one, exp_neg8(v)));
            let a = sigmoid(ld(&o[3]));
            let b = ld(&beta);
            let tint = ld(&diffuse[3]);
            for ch in 0..3 {
                let c = _mm256_add_ps(ld(&diffuse[ch]), _mm256_mul_ps(tint, sigmoid(ld(&o[ch]))));
                let c = _mm256_min_ps(_mm256_max_ps(c, zero), one);
                let v = _mm256_add_ps(_mm256_mul_ps(a, c), _mm256_mul_ps(_mm256_sub_ps(one, a), _mm256_set1_ps(bg[ch])));
                _mm256_storeu_ps(add[ch].as_mut_ptr().add(at), _mm256_mul_ps(b, v));
            }
            _mm256_storeu_ps(add[3].as_mut_ptr().add(at), _mm256_mul_ps(b, a));
        }
    }
    for (lane, q) in tile.iter().enumerate() {
        let px = q.pixel as usize;
        color[px] += Vec3::new(add[0][lane], add[1][lane], add[2][lane]);
        alpha[px] += add[3][lane];
    }
}

/// [`exp_neg`] on 8 lanes, the same operations in the same order (bit-identical).
#[inline]
#[target_feature(enable = "avx2,fma,sse4.1,sse4.2,bmi1,bmi2,lzcnt,popcnt,f16c")]
fn exp_neg8(x: std::arch::x86_64::__m256) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    let x = _mm256_sub_ps(_mm256_setzero_ps(), x);
    let underflow = _mm256_cmp_ps::<_CMP_LT_OQ>(x, _mm256_set1_ps(-87.0));
    let nan = _mm256_cmp_ps::<_CMP_UNORD_Q>(x, x);
    let xc = _mm256_min_ps(x, _mm256_set1_ps(88.0));
    let magic = _mm256_set1_ps(12_582_912.0);
    let n = _mm256_sub_ps(_mm256_fmadd_ps(xc, _mm256_set1_ps(std::f32::consts::LOG2_E), magic), magic);
    let r = _mm256_fnmadd_ps(n, _mm256_set1_ps(-2.121_944_4e-4), _mm256_fnmadd_ps(n, _mm256_set1_ps(0.693_359_4), xc));
    let mut p = _mm256_set1_ps(1.987_569_2e-4);
    for c in [1.398_199_9e-3, 8.333_452e-3, 4.166_579_6e-2, 1.666_666_5e-1, 0.5] {
        p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(c));
    }
    let y = _mm256_add_ps(_mm256_fmadd_ps(_mm256_mul_ps(p, r), r, r), _mm256_set1_ps(1.0));
    let scale = _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127))));
    let out = _mm256_mul_ps(y, scale);
    // −0.0 for −0.0 would differ from the scalar path only in sign; σ·δ ≥ 0 here.
    _mm256_blendv_ps(_mm256_andnot_ps(underflow, out), x, nan)
}
