//! The fast CPU renderer: the i-NOLF rule of docs/architecture.md §3 as the reference
//! [`crate::CpuBackend`] computes it (`model.rs`), arranged for the machine:
//!
//! - **Only where cells are live.** A prepass projects every live index cell (a brick with
//!   some non-zero density; blocks of them for fine grids) into the view: pixels outside
//!   every footprint take no sample, and the rest march only the ray interval their
//!   footprints allow ([`Footprints`]).
//! - **Rays in vector lanes** (`avx2::march_wave`, AVX2: 32 rays, four groups of 8 lanes
//!   interleaved stage by stage). Each step
//!   evaluates the next sample of the reference's lattice `t_k = t0 + (k+½)δ` on every lane's
//!   ray (a gather for the cell's brick, the trilinear corners as one 16-byte read per lane
//!   and z plane of the density's f16 values, transposed — AMD's gathers are slow — and a
//!   vector `exp`) and applies the rule to it; a lane in
//!   a dead cell jumps to where its ray leaves the largest dead box of cells that starts at
//!   the cell and reaches out in the ray's direction (up to 8 cells per side, per octant of
//!   directions), a finished lane takes the band's next pixel (in blocks of [`RAY_BLOCK_COLUMNS`] columns). The
//!   rays' dependent reads overlap, and the steps have no branch on the data. Where the CPU
//!   has AVX-512, 64 rays step as four groups of 16 lanes (`avx512`: mask registers
//!   instead of blends; 0.83–0.89 of the time per lego frame, the march alone 0.76–0.82,
//!   with 32 rays; 64 took 0.96–0.98 of that; `NEPHELE_MARCH=avx2` keeps 32 rays in groups
//!   of 8). Without AVX2 (or with `NEPHELE_MARCH=ray`), one ray at a time: its samples
//!   [`BATCH`] at a time, taken front to back by the same rule ([`Scan`]). All three give
//!   the same frames to the bit (tested). σ at each sample is the reference's to the bit; the
//!   only difference is which of two touching cells a sample exactly on their shared face
//!   belongs to (the reference follows its DDA, this the sample's position), measured
//!   against the reference in the tests and in `bench render`.
//! - **The network in tiles.** Each band of rows is marched, its queries gathered, and then
//!   shaded [`TILE`] at a time: inputs written feature-major (hash corners and 8-bit
//!   diffuse corners gathered 8 queries at a time with AVX2, or read lane by lane where the
//!   march is the AVX2 one, on CPUs without AVX-512, whose gathers are slow), the MLP run as
//!   register-blocked matrix products ([`MlpKernel::forward_tile`], AVX-512 or AVX2 + FMA
//!   at run time, skipping hidden units that are zero for the whole tile), the view inputs
//!   and the sigmoids and compositing 8 queries at a time too (0.938–0.945 of the time per
//!   lego frame against one query at a time). Fused
//!   multiply-adds round differently from the reference's separate ones (output differences
//!   ~1e-6), and the sigmoids use the march's `exp` (within 4 ulp of libm's). Where the CPU
//!   has AVX-512 VNNI the hidden layer runs in 8 bits ([`Network::Int8`], 0.94–0.95 of the
//!   time per lego frame; the frame within 2 of 255 of the f32 network's, 65.6 dB), and
//!   with AVX2 and no AVX-512 too, its weights in 7 bits (0.96 of the time per lego
//!   640×480 frame on Zen 3, the network alone 0.86–0.91; within 4 of 255, 98% of the
//!   values equal, 64.9 dB); `NEPHELE_NETWORK=f32` keeps f32.
//! - **The hash laid out by position.** The perfect spatial hash's stored vertices are
//!   rearranged into bricks of the vertex grid ([`PshBricks`]): a query's 8 corners are a
//!   few neighbouring reads instead of 8 hashes to scattered slots, with the same features.

use std::{sync::Arc, time::{Duration, Instant}};

use glam::{UVec3, Vec3};
use rayon::prelude::*;

use crate::{
    asset::Asset,
    camera::RayFrame,
    cubes::TextureCubes,
    mlp::{MAX_INPUT, MlpKernel, TILE, TileInput},
    model::{HitRule, MAX_SEGMENTS, MarchHit, MultiHit, RenderSettings, Segment, Segments, Tracker, clip_ray, closed_slot},
    psh::{self, SpatialHash},
    render::{Backend, CancelFlag, Frame, PreparedAsset, RenderError, RenderOutput, RenderStats, ViewRequest, check_request, to_unorm8},
    sh::sh4,
};

mod cells;
mod detect;
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod avx2;
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod avx512;
#[cfg(test)]
mod tests;

use self::cells::*;
pub use self::detect::{March, Network};

/// Lattice samples evaluated together.
pub const BATCH: usize = 16;
/// Columns of the blocks of a band whose rays the wavefront march takes in turn (the same
/// frames as along whole rows; in-process, frames alternating: 0.97 of the time per lego
/// frame at 640×480 and 352×264 (medians of seven runs), 1.0 at 1280×720, 0.98 on AVX2;
/// blocks of 8 or 16 columns 0.98–1.0, of 64 or 128 no better than 32).
const RAY_BLOCK_COLUMNS: usize = 32;
/// Rows of one work item (8 rather than 4: 0.95 of the time per frame at 352×264, the auto
/// scale's size, 0.98–1.0 at 640×480, the same at 1280×720; then 16 the same as 8, but with
/// the rays taken in blocks of [`RAY_BLOCK_COLUMNS`] columns, 16 rows took 0.98 of the time
/// at 640×480 (median of six in-process runs) and the same at 352×264 and 1280×720).
const BAND_ROWS: u32 = 16;

/// The fast CPU backend (see the module notes); `nephele --backend cpu`.
#[derive(Debug, Default, Clone, Copy)]
pub struct FastCpuBackend;

impl Backend for FastCpuBackend {
    fn name(&self) -> String {
        "cpu".into()
    }
    fn prepare(&self, asset: Arc<Asset>) -> Result<Box<dyn PreparedAsset>, RenderError> {
        self.prepare_with(asset, March::detect(), Network::detect())
    }
}

impl FastCpuBackend {
    /// [`Backend::prepare`] with the given march instead of the widest this CPU has (for
    /// side-by-side measurements, `nephele bench render --marches`); an error if the CPU
    /// lacks what it needs.
    pub fn prepare_with_march(&self, asset: Arc<Asset>, march: March) -> Result<Box<dyn PreparedAsset>, RenderError> {
        self.prepare_with(asset, march, Network::detect())
    }

    /// [`Backend::prepare`] with the given march and network kernel (`nephele bench render
    /// --marches … --networks …`); an error if the CPU lacks what they need.
    pub fn prepare_with(&self, asset: Arc<Asset>, march: March, network: Network) -> Result<Box<dyn PreparedAsset>, RenderError> {
        if !march.available() {
            return Err(RenderError::BadSettings(format!("this CPU cannot run the {} march", march.name())));
        }
        if !network.available() {
            return Err(RenderError::BadSettings(format!("this CPU cannot run the {} network", network.name())));
        }
        let net = match network {
            Network::F32 => asset.mlp.kernel(),
            Network::Int8 => asset.mlp.kernel().with_int8_hidden(),
        };
        let live = LiveCells::new(&asset.density);
        let hash = PshBricks::new(&asset.psh);
        let diffuse = DiffuseBytes::new(&asset.diffuse);
        Ok(Box::new(FastPrepared { asset, net, live, hash, diffuse, march }))
    }
}

struct FastPrepared {
    asset: Arc<Asset>,
    net: MlpKernel,
    live: LiveCells,
    hash: PshBricks,
    diffuse: Option<DiffuseBytes>,
    march: March,
}

/// One network query of a band: where, how it is blended, which pixel it belongs to.
#[derive(Clone, Copy)]
struct Query {
    p_hit: Vec3,
    d: Vec3,
    alpha_c: f32,
    beta: f32,
    pixel: u32,
}

/// Thread time of one band, and its counts.
#[derive(Default, Clone, Copy)]
struct BandStats {
    march_s: f64,
    shade_s: f64,
    /// Of `shade_s`, the network's matrix products ([`MlpKernel::forward_tile`]).
    mlp_s: f64,
    hits: u64,
    samples: u64,
    queries: u64,
}

impl PreparedAsset for FastPrepared {
    fn asset(&self) -> &Arc<Asset> {
        &self.asset
    }

    fn render_cancellable(&self, views: &[ViewRequest], settings: &RenderSettings, cancel: &CancelFlag) -> Result<RenderOutput, RenderError> {
        check_request(views, settings)?;
        let asset = &*self.asset;
        let settings = &settings.for_asset(&asset.march);
        let start = Instant::now();
        let rays: Vec<RayFrame> = views.iter().map(|v| RayFrame::new(&v.view, &v.instance, asset.bounds.center(), asset.bounds.radius())).collect();
        let mut frames: Vec<Frame> = rays
            .iter()
            .map(|f| {
                let (w, h) = (f.intrinsics.width, f.intrinsics.height);
                let n = w as usize * h as usize;
                Frame { width: w, height: h, rgba: vec![0; 4 * n], depth: vec![0.0; n] }
            })
            .collect();
        // Work items: bands of rows of every view.
        let mut bands = Vec::new();
        for (v, frame) in frames.iter_mut().enumerate() {
            let w = frame.width as usize;
            let rows = BAND_ROWS as usize * w;
            for (i, (rgba, depth)) in frame.rgba.chunks_mut(4 * rows).zip(frame.depth.chunks_mut(rows)).enumerate() {
                bands.push((v, i as u32 * BAND_ROWS, rgba, depth));
            }
        }
        let rule = settings.hit_rule(&asset.march.hits);
        let step = asset.march.step * settings.step_scale;
        let footprints: Vec<Option<Footprints>> = rays.par_iter().map(|f| Footprints::new(f, &self.live, &asset.density, step).filter(|_| self.live.footprints)).collect();
        let per_band: Vec<BandStats> = bands
            .into_par_iter()
            .map(|(v, y0, rgba, depth)| {
                if cancel.is_cancelled() {
                    return None;
                }
                let bounds = footprints[v].as_ref().map(|fp| fp.band_bounds(rays[v].intrinsics.width, y0, depth.len()));
                Some(self.band_dispatch(&rays[v], &views[v], settings, &rule, y0, bounds.as_ref(), rgba, depth))
            })
            .collect::<Option<_>>()
            .ok_or(RenderError::Cancelled)?;
        cancel.check()?;
        let total_s = start.elapsed().as_secs_f64();
        let sum = per_band.iter().fold(BandStats::default(), |a, b| BandStats {
            march_s: a.march_s + b.march_s,
            shade_s: a.shade_s + b.shade_s,
            mlp_s: a.mlp_s + b.mlp_s,
            hits: a.hits + b.hits,
            samples: a.samples + b.samples,
            queries: a.queries + b.queries,
        });
        // The stages interleave on every thread: report each stage's share of the wall time.
        let busy = (sum.march_s + sum.shade_s).max(1e-12);
        let stats = RenderStats {
            march_ms: total_s * 1e3 * sum.march_s / busy,
            shade_ms: total_s * 1e3 * sum.shade_s / busy,
            mlp_ms: total_s * 1e3 * sum.mlp_s / busy,
            total_ms: total_s * 1e3,
            rays: frames.iter().map(|f| f.depth.len() as u64).sum(),
            hits: sum.hits,
            samples: sum.samples,
            queries: sum.queries,
        };
        Ok(RenderOutput { frames, stats })
    }
}

impl FastPrepared {
    /// [`Self::band`] compiled for x86-64-v3 (AVX2, FMA, SSE4.1 rounding) where the CPU has
    /// it, else for the baseline.
    #[allow(clippy::too_many_arguments)]
    fn band_dispatch(&self, f: &RayFrame, req: &ViewRequest, settings: &RenderSettings, rule: &HitRule, y0: u32, bounds: Option<&RayBounds>, rgba: &mut [u8], depth: &mut [f32]) -> BandStats {
        #[cfg(target_arch = "x86_64")]
        if crate::mlp::simd::level() != crate::mlp::simd::Level::Portable {
            return avx2::band(self, f, req, settings, rule, y0, bounds, rgba, depth);
        }
        self.band::<false>(f, req, settings, rule, y0, bounds, rgba, depth)
    }

    /// Marches and shades rows `y0..` of one view into `rgba`/`depth` (whole rows); with
    /// `bounds`, each ray only between its pixel's bounds.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn band<const V: bool>(&self, f: &RayFrame, req: &ViewRequest, settings: &RenderSettings, rule: &HitRule, y0: u32, bounds: Option<&RayBounds>, rgba: &mut [u8], depth: &mut [f32]) -> BandStats {
        let asset = &*self.asset;
        let step = asset.march.step * settings.step_scale;
        let alpha_min = settings.alpha_min.unwrap_or(asset.march.alpha_min);
        let bg = req.background;
        let w = f.intrinsics.width;
        let n = depth.len();
        let mut stats = BandStats::default();
        let t = Instant::now();
        let mut queries = Vec::with_capacity(n);
        let mut color = vec![Vec3::ZERO; n];
        let mut alpha = vec![0.0f32; n];
        // A pixel's march result: its depth and queries, or the background.
        let mut take = |i: usize, o: Vec3, d: Vec3, m: MultiHit| {
            stats.samples += m.march.samples as u64;
            if m.march.alpha_c < alpha_min {
                color[i] = bg;
                depth[i] = f32::INFINITY;
                return;
            }
            stats.hits += 1;
            stats.queries += m.count as u64;
            depth[i] = (f.t_shift + m.march.t_hit) * f.scale;
            for q in 0..m.count as usize {
                queries.push(Query { p_hit: o + m.t[q] * d, d, alpha_c: m.march.alpha_c, beta: m.beta[q], pixel: i as u32 });
            }
        };
        let mut marched = false;
        #[cfg(target_arch = "x86_64")]
        if V && self.march != March::Ray {
            #[allow(unsafe_code)]
            // SAFETY: `V` is true only where the CPU has x86-64-v3 (see `sigmas`), and
            // `march` is `Avx512` only where it has AVX-512 F/VL/BW/DQ too
            // (`FastCpuBackend::prepare_with_march` checks `March::available`; the tests
            // check `wide_lanes`).
            unsafe {
                let gap_t = rule.gap_steps * step;
                // The lane's segments are left empty for its next ray.
                let multi = |i, o, d, m, segments: &mut Segments, run| take(i, o, d, segments.finish(run, m, rule));
                match (self.march == March::Avx512, rule.one_hit()) {
                    (true, true) => avx512::march_wave::<false, _>(self, f, settings, step, gap_t, y0, bounds, n, |i, o, d, m, _, _| take(i, o, d, MultiHit::one(m))),
                    (true, false) => avx512::march_wave::<true, _>(self, f, settings, step, gap_t, y0, bounds, n, multi),
                    (false, true) => avx2::march_wave::<false, _>(self, f, settings, step, gap_t, y0, bounds, n, |i, o, d, m, _, _| take(i, o, d, MultiHit::one(m))),
                    (false, false) => avx2::march_wave::<true, _>(self, f, settings, step, gap_t, y0, bounds, n, multi),
                }
            }
            marched = true;
        }
        if !marched {
            for i in 0..n {
                let (t_lo, t_hi) = bounds.map_or((f32::NEG_INFINITY, f32::INFINITY), |b| (b.t_lo[i], b.t_hi[i]));
                // No live cell's footprint covers the pixel: the ray takes no sample (and is not
                // even made).
                let (o, d) = if t_lo > t_hi { (Vec3::ZERO, Vec3::ZERO) } else { f.ray(i as u32 % w, y0 + i as u32 / w) };
                let m = if t_lo > t_hi {
                    MultiHit::default()
                } else if rule.one_hit() {
                    MultiHit::one(self.march::<V, _>(o, d, step, (t_lo, t_hi), settings, &mut ()))
                } else {
                    let mut segments = Segments::new(rule.gap_steps * step);
                    let m = self.march::<V, _>(o, d, step, (t_lo, t_hi), settings, &mut segments);
                    segments.choose(m, rule)
                };
                take(i, o, d, m);
            }
        }
        let t_marched = Instant::now();
        stats.march_s = (t_marched - t).as_secs_f64();
        stats.mlp_s = self.shade::<V>(&queries, bg, &mut color, &mut alpha).as_secs_f64();
        let mut packed = 0;
        #[cfg(target_arch = "x86_64")]
        if V {
            #[allow(unsafe_code)]
            // SAFETY: `V` is true only where the CPU has x86-64-v3 (see `sigmas`).
            unsafe {
                packed = avx2::pack_rgba(&color, &alpha, rgba)
            };
        }
        for (i, px) in rgba.chunks_exact_mut(4).enumerate().skip(packed) {
            let c = color[i];
            px.copy_from_slice(&[to_unorm8(c.x), to_unorm8(c.y), to_unorm8(c.z), to_unorm8(alpha[i])]);
        }
        stats.shade_s = t_marched.elapsed().as_secs_f64();
        stats
    }

    /// Shades `queries` [`TILE`] at a time, adding each one's `β ×` (colour over `bg`, α) to
    /// its pixel (as [`crate::model::shade_multi`] does). `V`: the tile's hash features and
    /// diffuse colours come from the AVX2 kernel where the asset allows ([`avx2::tile_inputs`]).
    /// Returns the time spent in the network's matrix products (timed per tile, which costs
    /// 0.7–1.6% of the shading stage).
    #[inline(always)]
    fn shade<const V: bool>(&self, queries: &[Query], bg: Vec3, color: &mut [Vec3], alpha: &mut [f32]) -> Duration {
        let mut mlp = Duration::ZERO;
        let asset = &*self.asset;
        let features = asset.psh.features as usize;
        let width = self.net.input();
        debug_assert_eq!(width, features + 17);
        let mut x: TileInput = [[0.0; TILE]; MAX_INPUT];
        let mut diffuse = [[0.0f32; TILE]; 4];
        let psh = &asset.psh;
        let vector = V && features.is_multiple_of(8) && self.diffuse.is_some();
        for tile in queries.chunks(TILE) {
            if vector {
                let mut p = [[0.0f32; TILE]; 3];
                // Lanes past the tile's end repeat its first query (their results are unused).
                for (lane, q) in tile.iter().chain(std::iter::repeat(&tile[0])).take(TILE).enumerate() {
                    (p[0][lane], p[1][lane], p[2][lane]) = (q.p_hit.x, q.p_hit.y, q.p_hit.z);
                }
                #[cfg(target_arch = "x86_64")]
                #[allow(unsafe_code)]
                // SAFETY: `V` is true only where the CPU has x86-64-v3 (see `sigmas`).
                // The AVX2 march runs where the CPU has no AVX-512, and such CPUs' gathers
                // are slow (Zen 3: 0.979–0.985 of the time per lego frame at 352×264,
                // 0.986–0.995 at 640×480, 1.0 at 1280×720 with the reads lane by lane).
                unsafe {
                    avx2::tile_inputs(&self.hash, psh, self.diffuse.as_ref().expect("checked above"), &asset.diffuse, &p, &mut x, &mut diffuse, self.march == March::Avx2)
                };
            } else {
                self.tile_inputs_scalar(tile, &mut x, &mut diffuse);
            }
            #[cfg(target_arch = "x86_64")]
            if V {
                #[allow(unsafe_code)]
                // SAFETY: `V` is true only where the CPU has x86-64-v3 (see `sigmas`).
                unsafe {
                    avx2::view_inputs(tile, features, &mut x);
                    let t = Instant::now();
                    let o = self.net.forward_tile(&x);
                    mlp += t.elapsed();
                    avx2::composite(tile, &o, &diffuse, bg, color, alpha);
                }
                continue;
            }
            view_inputs(tile, features, &mut x);
            let t = Instant::now();
            let o = self.net.forward_tile(&x);
            mlp += t.elapsed();
            composite(tile, &o, &diffuse, bg, color, alpha);
        }
        mlp
    }

    /// The hash features (rows `0..features` of `x`) and diffuse colours of a tile's queries,
    /// one query at a time.
    #[inline(always)]
    fn tile_inputs_scalar(&self, tile: &[Query], x: &mut TileInput, diffuse: &mut [[f32; TILE]; 4]) {
        let asset = &*self.asset;
        let psh = &asset.psh;
        let features = psh.features as usize;
        let mut encoded = [0.0f32; MAX_INPUT];
        let mut corners = [Corners { id: [PshBricks::ABSENT; 8], weight: [0.0; 8] }; TILE];
        // Find every query's corner vertices first and prefetch their features, so the
        // tile's cache misses overlap instead of queueing.
        // (A plain loop, not `array::from_fn`: its closure would not be inlined into the
        // x86-64-v3 band.)
        for (lane, q) in tile.iter().enumerate() {
            corners[lane] = self.hash.corners(psh, q.p_hit);
            for &id in &corners[lane].id {
                prefetch(&self.hash.values, id as usize * features);
            }
        }
        for (lane, q) in tile.iter().enumerate() {
            let rgbt = match &self.diffuse {
                Some(bytes) => bytes.sample(&asset.diffuse, q.p_hit),
                None => asset.diffuse.sample::<4>(q.p_hit),
            };
            for (c, v) in diffuse.iter_mut().zip(rgbt) {
                c[lane] = v;
            }
            self.hash.encode(&corners[lane], &mut encoded[..features]);
            for (row, &v) in x.iter_mut().zip(&encoded[..features]) {
                row[lane] = v;
            }
        }
    }

    /// σ and `e^(−σδ)` of lattice samples `k0..k0 + BATCH`, each computed as the reference
    /// does in the brick of the cell the sample lies in (0 outside live cells), and the mask
    /// of lanes with σ ≠ 0. Only the first `n` lanes are needed: the AVX2 kernel skips the
    /// half of the batch past them (left at σ = 0). `V`: with the AVX2 kernel (only
    /// instantiated from the x86-64-v3 band).
    #[inline(always)]
    fn sigmas<const V: bool>(&self, k0: i32, n: usize, o: Vec3, d: Vec3, t0: f32, step: f32) -> ([f32; BATCH], [f32; BATCH], u32) {
        let density = &self.asset.density;
        #[cfg(target_arch = "x86_64")]
        if V {
            #[allow(unsafe_code)]
            // SAFETY: `V` is true only where the CPU has x86-64-v3: in the band compiled for
            // it (`avx2::band_v3`, chosen by `simd::level`) and in a test that checks `level`.
            return unsafe { avx2::sigmas(density, &self.live, k0, n, o, d, t0, step) };
        }
        let mut sigma = [0.0; BATCH];
        let mut e = [1.0; BATCH];
        let (b, r) = (density.grid as f32, density.brick as f32);
        // Live entries hold a brick's first corner; `sample_in_brick` takes its number.
        let corners = density.brick_corners() as u32;
        for l in 0..BATCH {
            let t = t0 + ((k0 + l as i32) as f32 + 0.5) * step;
            let g = density.to_fine(o + t * d);
            let cell = (g / r).as_uvec3().as_vec3().min(Vec3::splat(b - 1.0));
            let first = self.live.index[density.cell_index(cell.as_uvec3())];
            if first >= 0 {
                sigma[l] = density.sample_in_brick::<1>((first as u32 / corners) as usize, cell, g)[0];
                e[l] = exp_neg(sigma[l] * step);
            }
        }
        let nonzero = (0..BATCH).filter(|&l| sigma[l] != 0.0).fold(0, |m, l| m | 1 << l);
        (sigma, e, nonzero)
    }

    /// The reference march ([`crate::model::march_with`]) over the lattice samples inside
    /// `span`, [`BATCH`] at a time (a batch may reach past where the rule stops; the rule
    /// sees the samples one by one, in order).
    #[inline(always)]
    fn march<const V: bool, T: Tracker>(&self, o: Vec3, d: Vec3, step: f32, span: (f32, f32), s: &RenderSettings, tracker: &mut T) -> MarchHit {
        let mut out = MarchHit::default();
        let Some((t0, k_first, k_end)) = lattice(&self.asset.density, o, d, span, step) else { return out };
        let mut scan = Scan { transmittance: 1.0, w_max: 0.0, t_hit: 0.0, samples: 0, done: false };
        let mut k0 = k_first;
        while k0 < k_end && !scan.done {
            let n = ((k_end - k0) as usize).min(BATCH);
            let (_, e, nonzero) = self.sigmas::<V>(k0, n, o, d, t0, step);
            scan.take(k0, n, nonzero, &e, t0, step, s, tracker);
            k0 += n as i32;
        }
        out.t_hit = scan.t_hit;
        out.alpha_c = 1.0 - scan.transmittance;
        out.w_max = scan.w_max;
        out.samples = scan.samples;
        out
    }
}

/// The view inputs of a tile's queries: the spherical harmonics of each one's direction into
/// rows `features..features + 16` of `x`, and its α_c into row `features + 16`.
#[inline(always)]
fn view_inputs(tile: &[Query], features: usize, x: &mut TileInput) {
    for (lane, q) in tile.iter().enumerate() {
        for (row, v) in x[features..].iter_mut().zip(sh4(q.d)) {
            row[lane] = v;
        }
        x[features + 16][lane] = q.alpha_c;
    }
}

/// Adds each query of a tile to its pixel from the network's raw outputs `o` and the diffuse
/// colours (as [`crate::model::shade_multi`]): `β × (α·c + (1 − α)·bg)` to its colour and
/// `β·α` to its alpha, with c = clamp(diffuse + tint·sigmoid(o₀₋₂)) and α = sigmoid(o₃).
#[inline(always)]
fn composite(tile: &[Query], o: &[[f32; TILE]; 4], diffuse: &[[f32; TILE]; 4], bg: Vec3, color: &mut [Vec3], alpha: &mut [f32]) {
    for (lane, q) in tile.iter().enumerate() {
        let [r, g, b, tint] = diffuse.map(|c| c[lane]);
        let c_s = Vec3::new(sigmoid(o[0][lane]), sigmoid(o[1][lane]), sigmoid(o[2][lane]));
        let a = sigmoid(o[3][lane]);
        let c = (Vec3::new(r, g, b) + tint * c_s).clamp(Vec3::ZERO, Vec3::ONE);
        let px = q.pixel as usize;
        color[px] += q.beta * (a * c + (1.0 - a) * bg);
        alpha[px] += q.beta * a;
    }
}

/// The network's output squashing, `1 / (1 + e^(−x))`, with [`exp_neg`] (within 4 ulp of
/// `crate::mlp::sigmoid`'s libm result, tested), as the vector shading computes it.
#[inline(always)]
fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + exp_neg(x))
}

/// `e^(−x)` for the march's `x = σδ`: Cephes' single-precision range reduction and
/// polynomial, inline (the libm call and the register spills around it cost more than the
/// sample itself), in fused multiply-adds (the vector paths' `vfmadd`s, the same bits;
/// 0.98–0.99 of the time per lego frame on Zen 3 against separate products and sums).
/// Within 2 ulp of libm's `expf` over the range the march sees (tested); 0 below e^−87 and
/// NaN for NaN, as `expf`.
#[inline(always)]
pub fn exp_neg(x: f32) -> f32 {
    let x = -x;
    if x < -87.0 {
        return 0.0;
    }
    if x.is_nan() {
        return x;
    }
    let x = x.min(88.0);
    // n = round(x / ln 2) by the 1.5·2²³ trick (no libm `round` on baseline x86-64).
    const MAGIC: f32 = 12_582_912.0;
    let n = x.mul_add(std::f32::consts::LOG2_E, MAGIC) - MAGIC;
    let r = (-n).mul_add(-2.121_944_4e-4, (-n).mul_add(0.693_359_4, x));
    let p: f32 = 1.987_569_2e-4;
    let p = p.mul_add(r, 1.398_199_9e-3);
    let p = p.mul_add(r, 8.333_452e-3);
    let p = p.mul_add(r, 4.166_579_6e-2);
    let p = p.mul_add(r, 1.666_666_5e-1);
    let p = p.mul_add(r, 0.5);
    let y = (p * r).mul_add(r, r) + 1.0;
    y * f32::from_bits(((n as i32 + 127) as u32) << 23)
}
