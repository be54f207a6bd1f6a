//! The fast CPU renderer: the i-NOLF rule of docs/architecture.md §3 as the reference
//! [`crate::CpuBackend`] computes it (`model.rs`), arranged for the machine:
//!
//! - **Only where cells are live.** A prepass projects every live index cell (a brick with
//!   some non-zero density; blocks of them for fine grids) into the view: pixels outside
//!   every footprint take no sample, and the rest march only the ray interval their
//!   footprints allow ([`Footprints`]).
//! - **Rays in vector lanes** (`v3::march_wave`, AVX2: 32 rays, four groups of 8 lanes
//!   interleaved stage by stage). Each step
//!   evaluates the next sample of the reference's lattice `t_k = t0 + (k+½)δ` on every lane's
//!   ray (a gather for the cell's brick, the trilinear corners as one 16-byte read per lane
//!   and z plane of the density's f16 values, transposed — AMD's gathers are slow — and a
//!   vector `exp`) and applies the rule to it; a lane in
//!   a dead cell jumps to where its ray leaves the largest dead box of cells that starts at
//!   the cell and reaches out in the ray's direction (up to 8 cells per side, per octant of
//!   directions), a finished lane takes the band's next pixel (in blocks of [`RAY_BLOCK_COLUMNS`] columns). The
//!   rays' dependent reads overlap, and the steps have no branch on the data. Where the CPU
//!   has AVX-512, 64 rays step as four groups of 16 lanes (`v4`: mask registers
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

/// How a band's rays are marched (all give the same frames to the bit; tested).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum March {
    /// One ray at a time along its lattice ([`FastPrepared::march`]): CPUs without AVX2.
    Ray,
    /// 32 rays at a time, one per lane, in four groups of 8 AVX2 lanes ([`v3::march_wave`]).
    Avx2,
    /// 64 rays at a time, in four groups of 16 AVX-512 lanes ([`v4::march_wave`]).
    Avx512,
}

impl std::str::FromStr for March {
    type Err = String;
    /// By [`March::name`].
    fn from_str(s: &str) -> Result<Self, String> {
        [Self::Avx512, Self::Avx2, Self::Ray].into_iter().find(|m| m.name() == s).ok_or_else(|| "the marches are avx512, avx2 and ray".to_string())
    }
}

/// Whether the CPU has what [`v4`] is compiled for.
fn wide_lanes() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        has!("avx512f") && has!("avx512vl") && has!("avx512bw") && has!("avx512dq") && has!("avx2") && has!("fma") && has!("f16c") && has!("bmi2") && has!("lzcnt")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

impl March {
    /// The widest march this CPU has; `NEPHELE_MARCH=ray|avx2` caps it (for side-by-side
    /// measurements), as does `NEPHELE_SIMD`.
    pub fn detect() -> Self {
        let cap = std::env::var("NEPHELE_MARCH").unwrap_or_default();
        match () {
            _ if cap == "ray" || !Self::Avx2.available() => Self::Ray,
            _ if cap != "avx2" && Self::Avx512.available() => Self::Avx512,
            _ => Self::Avx2,
        }
    }

    /// Whether this CPU runs it (within the cap of `NEPHELE_SIMD`).
    pub fn available(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            use crate::mlp::simd::{Level, level};
            match self {
                Self::Ray => true,
                Self::Avx2 => level() != Level::Portable,
                Self::Avx512 => level() == Level::Avx512 && wide_lanes(),
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self == Self::Ray
        }
    }

    /// Its short name, as `NEPHELE_MARCH` and `bench render --marches` spell it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Ray => "ray",
            Self::Avx2 => "avx2",
            Self::Avx512 => "avx512",
        }
    }

    /// What it does, in words.
    pub fn describe(self) -> &'static str {
        match self {
            Self::Ray => "one ray at a time",
            Self::Avx2 => "32 rays, four groups of 8 AVX2 lanes",
            Self::Avx512 => "64 rays, four groups of 16 AVX-512 lanes",
        }
    }
}

/// The arithmetic of the specular network's tiles ([`MlpKernel::forward_tile`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Network {
    /// f32 throughout: the reference's sums up to fused rounding (~1e-6).
    F32,
    /// The hidden layer in 8 bits ([`MlpKernel::with_int8_hidden`]): CPUs with AVX-512 VNNI
    /// (on lego, 0.94–0.95 of the f32 kernel's time per 640×480 frame, the frame within 2 of
    /// 255 of its, 65.6 dB), or with AVX2 and no AVX-512 (weights in 7 bits; on Zen 3, 0.96
    /// of the time, within 4 of 255, 64.9 dB).
    Int8,
}

impl std::str::FromStr for Network {
    type Err = String;
    /// By [`Network::name`].
    fn from_str(s: &str) -> Result<Self, String> {
        [Self::F32, Self::Int8].into_iter().find(|m| m.name() == s).ok_or_else(|| "the networks are f32 and int8".to_string())
    }
}

impl Network {
    /// Int8 where the CPU has it, unless `NEPHELE_NETWORK=f32` (or `NEPHELE_SIMD`) says f32.
    pub fn detect() -> Self {
        if std::env::var("NEPHELE_NETWORK").is_ok_and(|v| v == "f32") || !Self::Int8.available() { Self::F32 } else { Self::Int8 }
    }

    /// Whether this CPU runs it (within the cap of `NEPHELE_SIMD`).
    pub fn available(self) -> bool {
        match self {
            Self::F32 => true,
            #[cfg(target_arch = "x86_64")]
            Self::Int8 => crate::mlp::simd::vnni() || crate::mlp::simd::level() == crate::mlp::simd::Level::Avx2,
            #[cfg(not(target_arch = "x86_64"))]
            Self::Int8 => false,
        }
    }

    /// Its short name, as `NEPHELE_NETWORK` and `bench render --networks` spell it.
    pub fn name(self) -> &'static str {
        match self {
            Self::F32 => "f32",
            Self::Int8 => "int8",
        }
    }

    /// What it does, in words.
    pub fn describe(self) -> &'static str {
        match self {
            Self::F32 => "f32 matrix products",
            Self::Int8 if crate::mlp::simd_vnni() => "hidden layer in 8 bits (AVX-512 VNNI)",
            Self::Int8 => "hidden layer in 8 bits (AVX2; weights in 7 bits)",
        }
    }
}

/// 8-bit diffuse cubes kept as their bytes (a quarter of the f32 copy's cache footprint);
/// `byte / 255` is exactly the f32 the reference reads.
struct DiffuseBytes {
    corners: Vec<[u8; 4]>,
}

impl DiffuseBytes {
    fn new(c: &TextureCubes) -> Option<Self> {
        let in_range = c.index.iter().all(|&b| b < c.brick_count() as i32) && c.index.len() == (c.grid as usize).pow(3) && c.values.len() < i32::MAX as usize;
        (c.storage == crate::cubes::CubeStorage::Unorm8 && c.channels == 4 && in_range).then(|| Self {
            corners: c.values.chunks_exact(4).map(|v| [0, 1, 2, 3].map(|i| crate::cubes::CubeStorage::unorm8(v[i]))).collect(),
        })
    }

    /// [`TextureCubes::sample`]`::<4>`, reading the bytes (the same f32 values).
    #[inline(always)]
    fn sample(&self, c: &TextureCubes, p: Vec3) -> [f32; 4] {
        // One vector division for the 4 channels: the same quotients as 4 scalar ones.
        c.sample_with(p, |at| (glam::UVec4::from_array(self.corners[at].map(u32::from)).as_vec4() / 255.0).to_array())
    }
}

/// Most footprints the prepass projects per view: beyond this, live cells are merged into
/// blocks (on lego, 512³ density has 95k live cells: projecting and binning each cost 13% of
/// a frame, against 4% for the 19k of 256³).
const FOOTPRINT_BLOCKS: usize = 32 * 1024;

/// Where a footprint block's edge, seen from the camera at the density's centre, spans fewer
/// pixels than this, the prepass projects the blocks of twice its side. Lego at 352×264 (the
/// auto scale's size of a 640×480 stream; edges of ~6 px): 0.974–0.977 of the frame time;
/// at 640×480 (~10 px) the same time either way.
const COARSE_BLOCKS_BELOW_PX: f64 = 8.0;

/// The index grid with only live cells: bricks that have some non-zero density (the others'
/// samples have α = 0 and change nothing). Every entry is negative or the first corner of a
/// brick the density holds.
struct LiveCells {
    /// `b³`, x fastest: the brick's first corner (brick × (r + 1)³, so that the march adds
    /// no multiply between reading the entry and reading the corners), or −1 − (the dead
    /// cell's radius per octant of ray directions, 3 bits each: [`dead_radii`]).
    index: Vec<i32>,
    cells: Vec<UVec3>,
    /// What the footprint prepass projects: the live cells merged into aligned blocks of
    /// `block`³ cells (`block` a power of two, 1 for the cells themselves), as few as keep at
    /// most [`FOOTPRINT_BLOCKS`] of them.
    blocks: Vec<UVec3>,
    block: u32,
    /// The blocks of twice the side (if `block` < 8), projected instead where a block of
    /// `block`³ cells looks smaller than [`COARSE_BLOCKS_BELOW_PX`].
    coarse: Option<Vec<UVec3>>,
    /// Whether the footprint prepass runs (off only in the test that checks it changes no
    /// frame).
    footprints: bool,
    /// Whether the march computes cell numbers in f32 (exact while `b³ ≤ 2²⁴`, and shorter
    /// than integer multiplies); larger grids, and a test, take the integer path.
    cell_numbers_in_f32: bool,
    /// The density values as the f16 bits they are stored as (`None` if some value is not
    /// an f16, as in cubes built in memory), then 8 zeros: half the bytes, the two corners
    /// of a trilinear sample that differ in x are one 32-bit read, and in bricks of up to
    /// 5³ cells its four corners in a z plane one 16-byte read (the zeros keep the last
    /// brick's reads inside).
    values_f16: Option<Vec<u16>>,
}

/// Largest index grid whose cell numbers (below `b³ ≤ 2²⁴`) the march computes in f32.
const EXACT_GRID: u32 = 256;

/// Largest dead radius R the wavefront march jumps across: a box of R + 1 index cells per
/// side from the sample's cell towards where its ray heads (R in 3 bits per octant).
const MAX_SKIP_RADIUS: u32 = 7;

/// For each cell of a `g`³ grid (x fastest) whose `index` entries are negative where dead,
/// and each octant `oct` of ray directions (bit a set where the ray rises along axis a): the
/// largest R ≤ [`MAX_SKIP_RADIUS`] such that the box of cells `c + s∘[0, R]³` is all dead,
/// s = ±1 per axis by the octant; packed 3 bits per octant (`R << 3·oct`). A ray in a dead
/// cell stays in that box until it leaves it by one of its far faces, which are as far as
/// the dead space allows in the ray's own direction (a cube centred on the cell is cut short
/// by live cells behind the ray, too; the octant boxes took 0.914–0.930 of the time per
/// lego frame of centred cubes of radius ≤ 4).
///
/// Computed on bit rows along x: the live cells are dilated one cell at a time towards
/// −s (a cell is "near" after k rounds if its box of radius k holds a live cell), and each
/// cell's count of rounds it stayed outside is kept in three bit planes.
fn dead_radii(index: &[i32], g: usize) -> Vec<u32> {
    let words = g.div_ceil(64);
    let rows = g * g;
    let mut live = vec![0u64; rows * words];
    for (i, _) in index.iter().enumerate().filter(|(_, e)| **e >= 0) {
        let (x, row) = (i % g, i / g);
        live[row * words + x / 64] |= 1 << (x % 64);
    }
    // The valid bits of each row's last word.
    let last_mask = if g.is_multiple_of(64) { u64::MAX } else { (1u64 << (g % 64)) - 1 };
    let mut packed = vec![0u32; g * g * g];
    for oct in 0..8u32 {
        let mut near = live.clone();
        let mut planes = [vec![0u64; rows * words], vec![0u64; rows * words], vec![0u64; rows * words]];
        for _ in 1..=MAX_SKIP_RADIUS {
            // Along x, within each row: bit x takes bit x + 1 (rising) or x − 1.
            for row in near.chunks_exact_mut(words) {
                if oct & 1 != 0 {
                    for w in 0..words {
                        let above = row.get(w + 1).map_or(0, |&n| n << 63);
                        row[w] |= (row[w] >> 1) | above;
                    }
                } else {
                    for w in (0..words).rev() {
                        let below = if w > 0 { row[w - 1] >> 63 } else { 0 };
                        row[w] |= (row[w] << 1) | below;
                    }
                    row[words - 1] &= last_mask;
                }
            }
            // Along y and z: whole rows OR their neighbour row (in an order that reads it
            // before it changes).
            for (axis, stride) in [(1, words), (2, g * words)] {
                let rising = oct >> axis & 1 != 0;
                let coord = |row: usize| if axis == 1 { row % g } else { row / g };
                for i in 0..rows {
                    let row = if rising { i } else { rows - 1 - i };
                    let has_next = if rising { coord(row) + 1 < g } else { coord(row) > 0 };
                    if has_next {
                        let at = row * words;
                        let from = if rising { at + stride } else { at - stride };
                        for w in 0..words {
                            near[at + w] |= near[from + w];
                        }
                    }
                }
            }
            // Cells still outside the dilated set have R ≥ this round: count them.
            for (i, &n) in near.iter().enumerate() {
                let mut carry = !n & if i % words == words - 1 { last_mask } else { u64::MAX };
                for plane in &mut planes {
                    let next = plane[i] & carry;
                    plane[i] ^= carry;
                    carry = next;
                }
            }
        }
        for (row, cells) in packed.chunks_exact_mut(g).enumerate() {
            for (w, cells) in cells.chunks_mut(64).enumerate() {
                let [p0, p1, p2] = [0, 1, 2].map(|b| planes[b][row * words + w]);
                for (bit, p) in cells.iter_mut().enumerate() {
                    let r = (p0 >> bit & 1) | (p1 >> bit & 1) << 1 | (p2 >> bit & 1) << 2;
                    *p |= (r as u32) << (3 * oct);
                }
            }
        }
    }
    packed
}

impl LiveCells {
    fn new(d: &TextureCubes) -> Self {
        let per_brick = (d.brick_corners() * d.channels as usize).max(1);
        let nonzero: Vec<bool> = d.values.chunks_exact(per_brick).map(|v| v.iter().any(|&s| s != 0.0)).collect();
        let mut index = d.index.clone();
        let mut cells = Vec::new();
        for (i, brick) in index.iter_mut().enumerate() {
            if *brick >= 0 && nonzero.get(*brick as usize) == Some(&true) {
                let g = d.grid as usize;
                cells.push(UVec3::new((i % g) as u32, ((i / g) % g) as u32, (i / (g * g)) as u32));
            } else {
                *brick = -1;
            }
        }
        // Dead cells say how far from them is dead, per octant of ray directions
        // ([`dead_radii`]); the wavefront march jumps to where its ray leaves that box.
        let g = d.grid as usize;
        let radii = dead_radii(&index, g);
        for (entry, radii) in index.iter_mut().zip(radii) {
            if *entry < 0 {
                *entry = -1 - radii as i32;
            }
        }
        // Live entries: the brick's first corner.
        let corners = d.brick_corners() as i32;
        for entry in index.iter_mut().filter(|e| **e >= 0) {
            *entry = entry.saturating_mul(corners);
        }
        let values_f16 = (d.channels == 1)
            .then(|| d.values.iter().map(|&v| half::f16::from_f32(v)).collect::<Vec<_>>())
            .filter(|h| h.iter().zip(&d.values).all(|(h, v)| h.to_f32().to_bits() == v.to_bits()))
            .map(|h| h.into_iter().map(half::f16::to_bits).chain([0; 8]).collect());
        let cell_numbers_in_f32 = d.grid <= EXACT_GRID;
        Self { index, blocks: cells.clone(), block: 1, coarse: None, footprints: true, cell_numbers_in_f32, cells, values_f16 }.with_blocks_at_most(FOOTPRINT_BLOCKS)
    }

    /// Merges the live cells into blocks for the footprints, doubling the block's side (up to
    /// 8 cells) until at most `max` blocks remain.
    fn with_blocks_at_most(mut self, max: usize) -> Self {
        let merged = |block: u32| {
            let mut blocks: Vec<UVec3> = self.cells.iter().map(|&c| c / block).collect();
            blocks.sort_unstable_by_key(|c| (c.z, c.y, c.x));
            blocks.dedup();
            blocks
        };
        while self.blocks.len() > max && self.block < 8 {
            self.block *= 2;
            self.blocks = merged(self.block);
        }
        self.coarse = (self.block < 8).then(|| merged(2 * self.block));
        self
    }

    /// What the AVX2 kernels' gathers rely on: one density channel, a live entry per index
    /// cell, whole bricks, 32-bit offsets, and the f16 copy (if any) the size of the values.
    /// (Every entry of `index` is negative or the first corner of a brick below
    /// `brick_count`, by construction.)
    fn assert_fits(&self, density: &TextureCubes) {
        assert!(
            density.channels == 1
                && self.index.len() == (density.grid as usize).pow(3)
                && density.values.len() == density.brick_count() * density.brick_corners()
                && density.values.len() < i32::MAX as usize
                && self.values_f16.as_ref().is_none_or(|h| h.len() == density.values.len() + 8)
        );
    }
}

/// The front-to-back rule of docs/architecture.md §3 over samples in order: transmittance, the heaviest
/// sample, and whether a stopping rule has fired.
struct Scan {
    transmittance: f32,
    w_max: f32,
    t_hit: f32,
    samples: u32,
    done: bool,
}

impl Scan {
    /// Takes lattice samples `k0..k0 + n` whose `e = e^(−σδ)` are given, visiting only the
    /// lanes set in `nonzero` (σ ≠ 0): a sample with σ = 0 has α = 0 and changes nothing (and
    /// the reference's tracker ignores w = 0). The state lives in locals for the loop.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn take<T: Tracker>(&mut self, k0: i32, n: usize, nonzero: u32, e: &[f32; BATCH], t0: f32, step: f32, s: &RenderSettings, tracker: &mut T) {
        let (mut transmittance, mut w_max, mut t_hit, mut samples) = (self.transmittance, self.w_max, self.t_hit, self.samples);
        let mut lanes = nonzero & (u32::MAX >> (32 - n as u32));
        while lanes != 0 {
            let l = lanes.trailing_zeros() as usize;
            lanes &= lanes - 1;
            samples += 1;
            let t = t0 + ((k0 + l as i32) as f32 + 0.5) * step;
            let alpha = 1.0 - e[l];
            let w = transmittance * alpha;
            let new_max = w > w_max;
            if new_max {
                (w_max, t_hit) = (w, t);
            }
            tracker.sample(t, w, new_max);
            transmittance *= 1.0 - alpha;
            if transmittance < s.stop_ratio * w_max || transmittance < s.stop_below() {
                self.done = true;
                break;
            }
        }
        (self.transmittance, self.w_max, self.t_hit, self.samples) = (transmittance, w_max, t_hit, samples);
    }
}

/// A ray's lattice samples inside `span` (a ray-parameter interval): the box entry `t0` (the
/// lattice's origin) and the samples `k_first..k_end` with `t_k` in
/// [max(t0, span.0), min(t1, span.1)), counted as the reference counts a cell's; `None`
/// without any.
fn lattice(density: &TextureCubes, o: Vec3, d: Vec3, span: (f32, f32), step: f32) -> Option<(f32, i32, i32)> {
    let (t0, t1) = clip_ray(&density.bounds, o, d)?;
    let (t_begin, t_end) = (t0.max(span.0), t1.min(span.1));
    let k_first = ((t_begin - t0) / step - 0.5).ceil().max(0.0) as i32;
    let k_end = ((t_end - t0) / step - 0.5).ceil() as i32;
    (t_begin < t_end && k_first < k_end).then_some((t0, k_first, k_end))
}

/// The perfect spatial hash's stored vertices rearranged for lookups by position: the
/// vertex grid cut into bricks of [`PshBricks::BRICK`]³ cells, each brick a table of its
/// `(BRICK + 1)³` corner vertices' ids (or [`PshBricks::ABSENT`]), and the vertices' features
/// in brick order, so that a query's 8 corners are a few neighbouring reads instead of 8
/// hashes (offset table, key check, scattered slots). A vertex has an id exactly when the
/// hash stores it, so features come out as [`SpatialHash::encode`]'s.
struct PshBricks {
    /// Bricks per axis.
    grid: usize,
    /// `grid³`, x fastest: the brick's table, or −1 (no stored vertex among its corners).
    index: Vec<i32>,
    /// Per brick `(BRICK + 1)³` vertex ids, x fastest.
    tables: Vec<u32>,
    /// `(vertices + 1) × features`: the last row is zeros ([`Self::zero_id`]), which the
    /// vector path reads for absent corners.
    values: Vec<f32>,
}

impl PshBricks {
    const BRICK: u32 = 4;
    const EDGE: usize = Self::BRICK as usize + 1;
    const ABSENT: u32 = u32::MAX;

    fn new(h: &SpatialHash) -> Self {
        let b = Self::BRICK;
        let grid = h.grid.div_ceil(b) as usize;
        let nf = h.features as usize;
        // Stored vertices in brick order (the brick of the cell they are the low corner of).
        let mut stored: Vec<(UVec3, usize)> = h.keys.iter().enumerate().filter(|(_, k)| **k != psh::EMPTY_KEY).map(|(slot, &k)| (psh::unpack(k), slot)).collect();
        let order = |q: UVec3| {
            let (c, l) = (q.min(UVec3::splat(h.grid.max(1) - 1)) / b, q % b);
            (c.z, c.y, c.x, l.z, l.y, l.x)
        };
        stored.sort_unstable_by_key(|(q, _)| order(*q));
        let mut index = vec![-1i32; grid.pow(3)];
        let mut tables = Vec::new();
        let mut values = Vec::with_capacity(stored.len() * nf);
        // Every brick whose corners include a vertex: along each axis the brick it lies in
        // and, on a brick face, the one below.
        let along = |a: u32| [Some(a / b), (a.is_multiple_of(b) && a > 0).then(|| a / b - 1)].map(|c| c.filter(|&c| (c as usize) < grid));
        for (id, (q, slot)) in stored.iter().enumerate() {
            values.extend_from_slice(&h.values[slot * nf..(slot + 1) * nf]);
            for z in along(q.z).into_iter().flatten() {
                for y in along(q.y).into_iter().flatten() {
                    for x in along(q.x).into_iter().flatten() {
                        let at = x as usize + grid * (y as usize + grid * z as usize);
                        if index[at] < 0 {
                            index[at] = (tables.len() / Self::EDGE.pow(3)) as i32;
                            tables.resize(tables.len() + Self::EDGE.pow(3), Self::ABSENT);
                        }
                        let l = *q - UVec3::new(x, y, z) * b;
                        tables[index[at] as usize * Self::EDGE.pow(3) + l.x as usize + Self::EDGE * (l.y as usize + Self::EDGE * l.z as usize)] = id as u32;
                    }
                }
            }
        }
        values.resize(values.len() + nf, 0.0);
        Self { grid, index, tables, values }
    }

    /// The id of the all-zero feature row.
    fn zero_id(&self, features: usize) -> usize {
        self.values.len() / features.max(1) - 1
    }

    /// The 8 corners of `p`'s cell (in [`SpatialHash::encode`]'s order and with its
    /// weights): each one's vertex id, or [`Self::ABSENT`].
    #[inline(always)]
    fn corners(&self, h: &SpatialHash, p: Vec3) -> Corners {
        let n = h.grid as f32;
        let g = (p - h.bounds.min) / h.bounds.size() * n;
        let base = g.floor().clamp(Vec3::ZERO, Vec3::splat(n - 1.0));
        let f = (g - base).clamp(Vec3::ZERO, Vec3::ONE);
        let base = base.as_uvec3();
        let mut out = Corners { id: [Self::ABSENT; 8], weight: [0.0; 8] };
        for corner in 0..8u32 {
            let d = UVec3::new(corner & 1, (corner >> 1) & 1, corner >> 2);
            out.weight[corner as usize] = if d.x == 1 { f.x } else { 1.0 - f.x } * if d.y == 1 { f.y } else { 1.0 - f.y } * if d.z == 1 { f.z } else { 1.0 - f.z };
        }
        let (c, l) = (base / Self::BRICK, base % Self::BRICK);
        let brick = self.index[c.x as usize + self.grid * (c.y as usize + self.grid * c.z as usize)];
        if brick >= 0 {
            let table = &self.tables[brick as usize * Self::EDGE.pow(3)..][..Self::EDGE.pow(3)];
            for corner in 0..8usize {
                let q = l + UVec3::new(corner as u32 & 1, (corner as u32 >> 1) & 1, corner as u32 >> 2);
                out.id[corner] = table[q.x as usize + Self::EDGE * (q.y as usize + Self::EDGE * q.z as usize)];
            }
        }
        out
    }

    /// [`SpatialHash::encode`] from [`Self::corners`]: the same terms in the same order.
    #[inline(always)]
    fn encode(&self, c: &Corners, out: &mut [f32]) {
        out.fill(0.0);
        let nf = out.len();
        for i in 0..8 {
            if c.id[i] != Self::ABSENT {
                let at = c.id[i] as usize * nf;
                for (o, v) in out.iter_mut().zip(&self.values[at..at + nf]) {
                    *o += c.weight[i] * v;
                }
            }
        }
    }
}

/// A query point's 8 hash corners (see [`PshBricks::corners`]).
#[derive(Clone, Copy)]
struct Corners {
    id: [u32; 8],
    weight: [f32; 8],
}

/// Asks the cache for the line holding `v[at]` (a hint; no effect elsewhere).
#[inline(always)]
fn prefetch<T>(v: &[T], at: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(x) = v.get(at) {
        #[allow(unsafe_code)]
        // SAFETY: a prefetch never faults and reads nothing into the program.
        unsafe {
            std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>((x as *const T).cast())
        };
    }
}

/// Screen-space footprints of a view's live cells (or of blocks of them,
/// [`LiveCells::blocks`]): the pixel rectangle each cell's projection can touch (one pixel
/// of slack) and the ray-parameter interval it can occupy (distance from the camera to the
/// cell, nearest and farthest, minus the ray origin's shift, with two steps of slack). A ray outside every footprint takes no sample in the reference
/// march either; inside, no live cell lies outside the union of its footprints' intervals.
struct Footprints {
    rects: Vec<CellRect>,
    /// Rows per bin and, per bin of rows, the rectangles that touch it.
    bin_rows: u32,
    bins: Vec<Vec<u32>>,
}

#[derive(Clone, Copy)]
struct CellRect {
    x0: u32,
    x1: u32,
    y0: u32,
    y1: u32,
    t_lo: f32,
    t_hi: f32,
}

/// What [`Footprints::new`] needs to project one block: the camera in object space (f64),
/// the block size, and each corner's offset from the block's low corner, with the offsets'
/// components along the camera's axes, so that a block's 8 corners are sums over arrays of 8
/// (which vectorise).
struct Projection {
    camera: glam::DVec3,
    axes: [glam::DVec3; 3],
    min: glam::DVec3,
    cell_size: glam::DVec3,
    /// Corner offsets per object axis, and along the camera's x, y and z axes.
    offset: [[f64; 8]; 3],
    along: [[f64; 8]; 3],
    /// Focal lengths and principal point (pixels), and the view's width and height.
    focal: [f64; 2],
    centre: [f64; 2],
    size: [f64; 2],
    t_shift: f64,
    slack: f64,
}

impl Projection {
    fn new(f: &RayFrame, block: u32, density: &TextureCubes, step: f32) -> Self {
        use glam::DVec3;
        let k = &f.intrinsics;
        let axes = f.object_from_camera.map(|c| c.as_dvec3());
        let t_shift = f.t_shift as f64;
        let cell_size = (density.bounds.size() / density.grid as f32).as_dvec3() * block as f64;
        let corner: [DVec3; 8] = std::array::from_fn(|c| DVec3::new((c & 1) as f64, (c >> 1 & 1) as f64, (c >> 2) as f64) * cell_size);
        Self {
            camera: f.origin_near_in_object.as_dvec3() + t_shift * axes[2],
            axes,
            min: density.bounds.min.as_dvec3(),
            cell_size,
            offset: [0, 1, 2].map(|a| corner.map(|o| o[a])),
            along: axes.map(|axis| corner.map(|o| o.dot(axis))),
            focal: [k.fx as f64, k.fy as f64],
            centre: [k.cx as f64, k.cy as f64],
            size: [k.width as f64, k.height as f64],
            t_shift,
            slack: 2.0 * step as f64 + 1e-5 * (1.0 + t_shift),
        }
    }

    /// The rectangles of `blocks` that some pixel's ray meets; `Err` when one reaches behind
    /// the camera. Compiled for AVX-512 too, where its corner loops run 8 wide.
    fn rects(&self, blocks: &[UVec3]) -> Result<Vec<CellRect>, ()> {
        #[cfg(target_arch = "x86_64")]
        if crate::mlp::simd::level() == crate::mlp::simd::Level::Avx512 {
            #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx2,fma")]
            fn wide(p: &Projection, blocks: &[UVec3]) -> Result<Vec<CellRect>, ()> {
                blocks.iter().filter_map(|b| p.rect(b).transpose()).collect()
            }
            #[allow(unsafe_code)]
            // SAFETY: the CPU has AVX-512 F/VL/DQ, AVX2 and FMA (`Level::Avx512`); the body
            // is safe code.
            return unsafe { wide(self, blocks) };
        }
        blocks.iter().filter_map(|b| self.rect(b).transpose()).collect()
    }

    /// One block's rectangle: the pixels whose centres fall inside the hull of its corners'
    /// projections (pixel i's ray goes through i here), with a margin of 1/16 pixel, far
    /// above the rounding of the rays and their samples (~1e-4 pixel); `None` if no pixel's;
    /// `Err` when it reaches behind the camera.
    #[inline(always)]
    fn rect(&self, block: &UVec3) -> Result<Option<CellRect>, ()> {
        const MARGIN: f64 = 1.0 / 16.0;
        let lo = self.min + block.as_dvec3() * self.cell_size;
        let base = lo - self.camera;
        let [bx, by, bz] = self.axes.map(|a| base.dot(a));
        let (mut xs, mut ys, mut behind, mut far2) = ([0.0f64; 8], [0.0f64; 8], false, 0.0f64);
        for c in 0..8 {
            let v = [base.x + self.offset[0][c], base.y + self.offset[1][c], base.z + self.offset[2][c]];
            let len2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
            far2 = far2.max(len2);
            let z = -(bz + self.along[2][c]);
            behind |= z <= 1e-9 * (1.0 + len2.sqrt());
            let inv_z = 1.0 / z;
            xs[c] = self.centre[0] + self.focal[0] * (bx + self.along[0][c]) * inv_z - 0.5;
            ys[c] = self.centre[1] - self.focal[1] * (by + self.along[1][c]) * inv_z - 0.5;
        }
        if behind {
            return Err(());
        }
        let (x_min, x_max) = xs.iter().fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
        let (y_min, y_max) = ys.iter().fold((f64::MAX, f64::MIN), |(a, b), &y| (a.min(y), b.max(y)));
        let (x0, x1) = ((x_min - MARGIN).ceil().max(0.0), (x_max + MARGIN).floor().min(self.size[0] - 1.0));
        let (y0, y1) = ((y_min - MARGIN).ceil().max(0.0), (y_max + MARGIN).floor().min(self.size[1] - 1.0));
        if x0 > x1 || y0 > y1 {
            return Ok(None);
        }
        // Nearest and farthest distance from the camera to the block.
        let near = (self.camera.clamp(lo, lo + self.cell_size) - self.camera).length();
        let (t_lo, t_hi) = (near - self.t_shift - self.slack, far2.sqrt() - self.t_shift + self.slack);
        Ok(Some(CellRect { x0: x0 as u32, x1: x1 as u32, y0: y0 as u32, y1: y1 as u32, t_lo: t_lo as f32, t_hi: t_hi as f32 }))
    }
}

/// Per pixel of a band, where along its ray live cells can be (`t_lo > t_hi`: nowhere).
struct RayBounds {
    t_lo: Vec<f32>,
    t_hi: Vec<f32>,
}

impl Footprints {
    /// `None` when some live cell reaches behind the camera (then every ray is marched whole).
    fn new(f: &RayFrame, live: &LiveCells, density: &TextureCubes, step: f32) -> Option<Self> {
        // Blocks that look small in this view bound the rays hardly better than blocks of
        // twice their side, which cost an eighth of the projecting.
        let projection = Projection::new(f, live.block, density, step);
        let edge_px = f.intrinsics.fx as f64 * projection.cell_size.x / (projection.camera - density.bounds.center().as_dvec3()).length().max(1e-9);
        let (blocks, projection) = match &live.coarse {
            Some(coarse) if edge_px < COARSE_BLOCKS_BELOW_PX => (coarse, Projection::new(f, 2 * live.block, density, step)),
            _ => (&live.blocks, projection),
        };
        // In parallel: a frame has one view, and this runs before its bands.
        let chunks: Vec<Vec<CellRect>> = blocks.par_chunks(1024).map(|chunk| projection.rects(chunk)).collect::<Result<_, ()>>().ok()?;
        let rects: Vec<CellRect> = chunks.concat();
        let bin_rows = 16;
        let mut bins = vec![Vec::new(); (f.intrinsics.height as usize).div_ceil(bin_rows as usize)];
        for (i, r) in rects.iter().enumerate() {
            for bin in &mut bins[(r.y0 / bin_rows) as usize..=(r.y1 / bin_rows) as usize] {
                bin.push(i as u32);
            }
        }
        Some(Self { rects, bin_rows, bins })
    }

    /// Bounds for the `n` pixels of rows `y0..` of a `width`-wide view. On a CPU with
    /// AVX-512 a rectangle's row (a few pixels) is one masked min and max per 16 pixels.
    fn band_bounds(&self, width: u32, y0: u32, n: usize) -> RayBounds {
        #[cfg(target_arch = "x86_64")]
        if crate::mlp::simd::level() == crate::mlp::simd::Level::Avx512 {
            #[allow(unsafe_code)]
            // SAFETY: the CPU has AVX-512 F and VL, AVX2 and FMA (`Level::Avx512`).
            return unsafe { v4::band_bounds(self, width, y0, n) };
        }
        self.band_bounds_with(width, y0, n, Self::span_bounds)
    }

    /// Takes one row of rectangle `r` (`lo`, `hi`: its pixels) into the bounds: one pass over
    /// both, as compare-and-select; no NaN handling (none is stored), so it compiles to plain
    /// vector min/max.
    #[inline(always)]
    fn span_bounds(lo: &mut [f32], hi: &mut [f32], r: &CellRect) {
        for (lo, hi) in lo.iter_mut().zip(hi) {
            *lo = if r.t_lo < *lo { r.t_lo } else { *lo };
            *hi = if r.t_hi > *hi { r.t_hi } else { *hi };
        }
    }

    /// [`Self::band_bounds`], with `span` taking one row of a rectangle into the bounds.
    #[inline(always)]
    fn band_bounds_with(&self, width: u32, y0: u32, n: usize, span: impl Fn(&mut [f32], &mut [f32], &CellRect)) -> RayBounds {
        let mut b = RayBounds { t_lo: vec![f32::INFINITY; n], t_hi: vec![f32::NEG_INFINITY; n] };
        let y_end = y0 + (n as u32).div_ceil(width);
        for y_bin in (y0 / self.bin_rows)..=((y_end - 1) / self.bin_rows) {
            if y_bin as usize >= self.bins.len() {
                continue;
            }
            let bin_y0 = y_bin * self.bin_rows;
            for &i in &self.bins[y_bin as usize] {
                let r = &self.rects[i as usize];
                // Each rectangle once per band: in the first bin of the band it touches (its
                // first row in the band lies in this bin; compared, not divided).
                let first_row = r.y0.max(y0);
                if first_row < bin_y0 || first_row >= bin_y0 + self.bin_rows {
                    continue;
                }
                for y in r.y0.max(y0)..=r.y1.min(y_end - 1) {
                    let at = ((y - y0) * width + r.x0) as usize..=((y - y0) * width + r.x1) as usize;
                    span(&mut b.t_lo[at.clone()], &mut b.t_hi[at], r);
                }
            }
        }
        b
    }
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
            return v3::band(self, f, req, settings, rule, y0, bounds, rgba, depth);
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
                    (true, true) => v4::march_wave::<false, _>(self, f, settings, step, gap_t, y0, bounds, n, |i, o, d, m, _, _| take(i, o, d, MultiHit::one(m))),
                    (true, false) => v4::march_wave::<true, _>(self, f, settings, step, gap_t, y0, bounds, n, multi),
                    (false, true) => v3::march_wave::<false, _>(self, f, settings, step, gap_t, y0, bounds, n, |i, o, d, m, _, _| take(i, o, d, MultiHit::one(m))),
                    (false, false) => v3::march_wave::<true, _>(self, f, settings, step, gap_t, y0, bounds, n, multi),
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
                packed = v3::pack_rgba(&color, &alpha, rgba)
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
    /// diffuse colours come from the AVX2 kernel where the asset allows ([`v3::tile_inputs`]).
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
                    v3::tile_inputs(&self.hash, psh, self.diffuse.as_ref().expect("checked above"), &asset.diffuse, &p, &mut x, &mut diffuse, self.march == March::Avx2)
                };
            } else {
                self.tile_inputs_scalar(tile, &mut x, &mut diffuse);
            }
            #[cfg(target_arch = "x86_64")]
            if V {
                #[allow(unsafe_code)]
                // SAFETY: `V` is true only where the CPU has x86-64-v3 (see `sigmas`).
                unsafe {
                    v3::view_inputs(tile, features, &mut x);
                    let t = Instant::now();
                    let o = self.net.forward_tile(&x);
                    mlp += t.elapsed();
                    v3::composite(tile, &o, &diffuse, bg, color, alpha);
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
            // it (`v3::band_v3`, chosen by `simd::level`) and in a test that checks `level`.
            return unsafe { v3::sigmas(density, &self.live, k0, n, o, d, t0, step) };
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

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod v3 {
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
        /// [`closed_slot`]); `v4::close16` does the same on 16 lanes.
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
    /// ([`super::v4::steps`]), else four groups of 8 in AVX2 registers (the first
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
                    finished |= unsafe { super::v4::steps::<MULTI>(density, cells, &rule, &mut wave, &mut runs, &mut segments, finished, step) };
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

}

/// The wavefront march's steps in AVX-512 registers: the same lanes, state and rule as
/// [`v3`], taken as four groups of 16 lanes with mask registers in place of blends (half
/// the instructions per lane of the groups of 8), and the density's f16 pairs split
/// by a 32→16-bit narrowing. The same operations in the same order on every lane, so the
/// same frames to the bit (tested against the AVX2 and per-ray marches).
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod v4 {
    use super::v3::{Closed, LANES, Rule, Runs, Wave};
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

    /// [`v3::march_wave`] with its steps in AVX-512 registers ([`steps`]).
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
        unsafe { v3::march_wave_in::<MULTI, true, F>(p, f, s, step, gap_t, y0, bounds, n, finish) }
    }

    /// One step of every lane, four groups of 16 stage by stage (every group's cell gathers,
    /// then every group's corner gathers and exps, then the rules); lanes set in `finished`
    /// are frozen. Returns the lanes that stopped or have no sample left.
    ///
    /// # Safety
    /// As [`v3::march_wave`]'s step: `cells` fits `density` (asserted by the caller), whose
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

    /// [`v3`]'s `Located` for 16 lanes.
    struct Located {
        k: __m512i,
        t0: __m512,
        t: __m512,
        g: [__m512; 3],
        c: [__m512; 3],
        brick: __m512i,
    }

    /// The next samples of lanes `at..at + 16` (as `v3::locate8`).
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
            // As `v3::cells8`.
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
    /// and which lanes read a live brick (as `v3::sigma8`).
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

    /// σ at fine-grid points `g` of cells `c` from their bricks: `v3::density8` on 16 lanes
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

    /// The rule on lanes `at..at + 16` (as `v3::rule8`, with masks for blends). Returns the
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
                // `Segments::sample` on each lane with w > 0 (not NaN), as `v3::rule8`.
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
            // The dead box's radius for the ray's octant (as `v3::rule8`).
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

    /// [`exp_neg`] on 16 lanes, the same operations in the same order as `v3::exp_neg8`.
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

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    fn ulps(a: f32, b: f32) -> u32 {
        (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs() as u32
    }

    #[test]
    fn exp_neg_is_within_two_ulp_of_libm() {
        let mut worst = 0;
        for i in 0..200_000 {
            let x = 87.0 * i as f32 / 200_000.0;
            let (a, b) = (exp_neg(x), (-x).exp());
            worst = worst.max(ulps(a, b));
        }
        assert!(worst <= 2, "worst {worst} ulp");
        // Negative arguments too, for the shading's sigmoid: 1 / (1 + e^(−x)) within 4 ulp of
        // libm's (2 from the exp, and the rounding of the sum and quotient).
        let mut worst = 0;
        for i in 0..200_000 {
            let x = -87.0 * i as f32 / 200_000.0;
            worst = worst.max(ulps(exp_neg(x), (-x).exp()));
        }
        assert!(worst <= 2, "worst {worst} ulp for x < 0");
        let worst = (-4000..=4000).map(|i| i as f32 / 100.0).map(|x| ulps(sigmoid(x), crate::mlp::sigmoid(x))).max().unwrap();
        assert!(worst <= 4, "sigmoid: worst {worst} ulp");
        assert_eq!(exp_neg(0.0), 1.0);
        assert_eq!(exp_neg(1e30), 0.0);
        assert_eq!(exp_neg(f32::INFINITY), 0.0);
        assert!(exp_neg(f32::NAN).is_nan());
    }

    #[test]
    fn vector_and_scalar_paths_are_bit_identical() {
        if crate::mlp::simd::level() == crate::mlp::simd::Level::Portable {
            eprintln!("no AVX2 on this CPU: only the portable path exists");
            return;
        }
        let stored = crate::procedural::generate(&crate::procedural::ProceduralConfig::small(crate::procedural::Scene::Trio)).unwrap();
        // As stored (f16: the paired reads) and with densities no f16 holds, as cubes built
        // in memory may have (the f32 reads).
        let mut in_memory = stored.clone();
        in_memory.density.values.iter_mut().for_each(|v| *v *= 1.0 + 1e-5);
        for (asset, f16) in [(stored, true), (in_memory, false)] {
            let asset = Arc::new(asset);
            let prepared = FastPrepared { net: asset.mlp.kernel(), live: LiveCells::new(&asset.density), hash: PshBricks::new(&asset.psh), diffuse: None, asset: asset.clone(), march: March::Avx2 };
            // Both kernels' paths are exercised.
            assert_eq!(prepared.live.values_f16.is_some(), f16);
            same_sigmas(&prepared);
        }
    }

    #[test]
    fn psh_bricks_encode_as_the_hash_does() {
        let asset = crate::procedural::generate(&crate::procedural::ProceduralConfig::small(crate::procedural::Scene::Trio)).unwrap();
        let h = &asset.psh;
        let bricks = PshBricks::new(h);
        let nf = h.features as usize;
        let mut rng = SmallRng::seed_from_u64(5);
        let (mut a, mut b) = (vec![0.0; nf], vec![0.0; nf]);
        let mut nonzero = 0;
        for i in 0..20_000 {
            // Anywhere in (and a little outside) the box, and on vertex planes.
            let mut p = h.bounds.min + (h.bounds.size() * 1.1) * Vec3::new(rng.random(), rng.random(), rng.random()) - 0.05 * h.bounds.size();
            if i % 4 == 0 {
                let cell = h.bounds.size() / h.grid as f32;
                p.x = h.bounds.min.x + cell.x * rng.random_range(0..=h.grid) as f32;
            }
            h.encode(p, &mut a);
            bricks.encode(&bricks.corners(h, p), &mut b);
            assert_eq!(a, b, "at {p}");
            nonzero += usize::from(a.iter().any(|v| *v != 0.0));
        }
        assert!(nonzero > 1000, "{nonzero} points with features");
    }

    #[test]
    fn vector_tile_inputs_match_the_scalar_path() {
        if crate::mlp::simd::level() == crate::mlp::simd::Level::Portable {
            eprintln!("no AVX2 on this CPU: only the portable path exists");
            return;
        }
        // The shipped lego asset: 8 PSH features and 8-bit diffuse cubes, as the vector path needs.
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/assets/lego.nolf");
        let asset = Arc::new(Asset::load(&path).unwrap());
        let prepared = FastPrepared {
            net: asset.mlp.kernel(),
            live: LiveCells::new(&asset.density),
            hash: PshBricks::new(&asset.psh),
            diffuse: DiffuseBytes::new(&asset.diffuse),
            asset: asset.clone(),
            march: March::Avx2,
        };
        assert!(prepared.diffuse.is_some() && asset.psh.features.is_multiple_of(8));
        let nf = asset.psh.features as usize;
        let cell = asset.density.bounds.size() / asset.density.grid as f32;
        let mut rng = SmallRng::seed_from_u64(9);
        let (mut with_features, mut with_diffuse) = (0, 0);
        for round in 0..400 {
            // Points in live density cells (where hits are), a few anywhere in or near the box.
            let tile: Vec<Query> = (0..TILE)
                .map(|lane| {
                    let p_hit = if (round + lane) % 8 == 0 {
                        asset.density.bounds.min + asset.density.bounds.size() * (Vec3::new(rng.random(), rng.random(), rng.random()) * 1.2 - 0.1)
                    } else {
                        let c = prepared.live.cells[rng.random_range(0..prepared.live.cells.len())];
                        asset.density.bounds.min + (c.as_vec3() + Vec3::new(rng.random(), rng.random(), rng.random())) * cell
                    };
                    Query { p_hit, d: Vec3::Z, alpha_c: 1.0, beta: 1.0, pixel: 0 }
                })
                .collect();
            let mut p = [[0.0f32; TILE]; 3];
            for (lane, q) in tile.iter().enumerate() {
                (p[0][lane], p[1][lane], p[2][lane]) = (q.p_hit.x, q.p_hit.y, q.p_hit.z);
            }
            let (mut xs, mut ds) = ([[0.0; TILE]; MAX_INPUT], [[0.0; TILE]; 4]);
            let (mut xv, mut dv) = ([[0.0; TILE]; MAX_INPUT], [[0.0; TILE]; 4]);
            prepared.tile_inputs_scalar(&tile, &mut xs, &mut ds);
            // Gathered, and read lane by lane: the same values.
            let (mut xl, mut dl) = ([[0.0; TILE]; MAX_INPUT], [[0.0; TILE]; 4]);
            // SAFETY: the CPU has x86-64-v3 (checked above).
            #[allow(unsafe_code)]
            unsafe {
                v3::tile_inputs(&prepared.hash, &asset.psh, prepared.diffuse.as_ref().unwrap(), &asset.diffuse, &p, &mut xv, &mut dv, false);
                v3::tile_inputs(&prepared.hash, &asset.psh, prepared.diffuse.as_ref().unwrap(), &asset.diffuse, &p, &mut xl, &mut dl, true);
            };
            assert!(xv.iter().flatten().zip(xl.iter().flatten()).chain(dv.iter().flatten().zip(dl.iter().flatten())).all(|(a, b)| a.to_bits() == b.to_bits()), "round {round}");
            for lane in 0..TILE {
                let at = tile[lane].p_hit;
                for f in 0..nf {
                    assert_eq!(xs[f][lane].to_bits(), xv[f][lane].to_bits(), "feature {f} at {at}");
                }
                for c in 0..4 {
                    assert!((ds[c][lane] - dv[c][lane]).abs() <= 1e-6, "diffuse {c} at {at}: {} vs {}", ds[c][lane], dv[c][lane]);
                }
                with_features += usize::from((0..nf).any(|f| xs[f][lane] != 0.0));
                with_diffuse += usize::from((0..4).any(|c| ds[c][lane] != 0.0));
            }
        }
        assert!(with_features > 3000 && with_diffuse > 3000, "{with_features} points with features, {with_diffuse} with diffuse colour");
    }

    #[test]
    fn wavefront_and_per_ray_marches_render_the_same_frames() {
        if crate::mlp::simd::level() == crate::mlp::simd::Level::Portable {
            eprintln!("no AVX2 on this CPU: only the per-ray march exists");
            return;
        }
        if !wide_lanes() {
            eprintln!("no AVX-512 on this CPU: the AVX-512 march is not compared");
        }
        use crate::{Intrinsics, View, ViewRequest};
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/assets/lego.nolf");
        let lego = Asset::load(&path).unwrap();
        let procedural = |scene| crate::procedural::generate(&crate::procedural::ProceduralConfig::small(scene)).unwrap();
        let (trio, translucent) = (procedural(crate::procedural::Scene::Trio), procedural(crate::procedural::Scene::Translucent));
        let orbit = |w, h, azimuth, elevation, distance| ViewRequest::new(View::orbit(glam::DVec3::ZERO, distance, azimuth, elevation, Intrinsics::from_fov_x(w, h, 0.69)));
        // Outside the box, grazing, and inside it (whole rays, no footprints).
        let inside = ViewRequest::new(View::look_at(glam::DVec3::new(-0.2, 0.0, 0.3), glam::DVec3::new(0.65, 0.35, 0.0), glam::DVec3::Z, Intrinsics::from_fov_x(48, 40, 1.2)));
        let views = [orbit(160, 120, 35.0, 25.0, 4.0), orbit(97, 61, 200.0, -10.0, 3.0), orbit(64, 64, 90.0, 0.0, 6.0), inside];
        for asset in [lego, trio, translucent] {
            let asset = Arc::new(asset);
            let prepare = |march| FastPrepared {
                net: asset.mlp.kernel(),
                live: LiveCells::new(&asset.density),
                hash: PshBricks::new(&asset.psh),
                diffuse: DiffuseBytes::new(&asset.diffuse),
                asset: asset.clone(),
                march,
            };
            let (wave, ray) = (prepare(March::Avx2), prepare(March::Ray));
            // The AVX-512 march where the CPU has it.
            let wide = wide_lanes().then(|| prepare(March::Avx512));
            // Footprints of merged blocks bound the rays more loosely, and without footprints
            // every ray is marched whole: the extra samples lie in dead cells and change
            // nothing. (These small views take the coarser blocks, `COARSE_BLOCKS_BELOW_PX`,
            // where there are any; `merged` keeps its own.)
            let merged = FastPrepared { live: LiveCells { coarse: None, ..LiveCells::new(&asset.density).with_blocks_at_most(asset.density.brick_count() / 20) }, ..prepare(March::Avx2) };
            assert!(merged.live.block >= 2, "{} blocks of {}", merged.live.blocks.len(), merged.live.block);
            let whole = FastPrepared { live: LiveCells { footprints: false, ..LiveCells::new(&asset.density) }, ..prepare(March::Avx2) };
            // Cell numbers by integer multiplies (the path of grids above 256³), both marches.
            let integer = |march| FastPrepared { live: LiveCells { cell_numbers_in_f32: false, ..LiveCells::new(&asset.density) }, ..prepare(march) };
            let integer = [Some(integer(March::Avx2)), wide_lanes().then(|| integer(March::Avx512))];
            for settings in [
                RenderSettings { hit_tau: Some(1.0), ..Default::default() },
                RenderSettings::default(),
                RenderSettings { hit_tau: Some(0.02), max_hits: Some(3), ..Default::default() },
                RenderSettings { hit_tau: Some(1.0), step_scale: 0.5, stop_ratio: 0.5, ..Default::default() },
            ] {
                let a = wave.render(&views, &settings).unwrap();
                let b = ray.render(&views, &settings).unwrap();
                let c = merged.render(&views, &settings).unwrap();
                assert_eq!((a.stats.hits, a.stats.queries), (c.stats.hits, c.stats.queries), "{settings:?}: merged footprints");
                let e = whole.render(&views, &settings).unwrap();
                assert_eq!((a.stats.hits, a.stats.samples, a.stats.queries), (e.stats.hits, e.stats.samples, e.stats.queries), "{settings:?}: no footprints");
                let d = wide.as_ref().map(|w| w.render(&views, &settings).unwrap());
                if let Some(d) = &d {
                    assert_eq!((a.stats.hits, a.stats.samples, a.stats.queries), (d.stats.hits, d.stats.samples, d.stats.queries), "{settings:?}: AVX-512 march");
                }
                let integer: Vec<_> = integer.iter().flatten().map(|p| p.render(&views, &settings).unwrap()).collect();
                for i in &integer {
                    assert_eq!((a.stats.hits, a.stats.samples, a.stats.queries), (i.stats.hits, i.stats.samples, i.stats.queries), "{settings:?}: integer cell numbers");
                }
                let integer_frames = integer.iter().flat_map(|i| a.frames.iter().zip(&i.frames));
                let wide_frames = d.iter().flat_map(|d| a.frames.iter().zip(&d.frames)).chain(integer_frames);
                for (fa, fb) in a.frames.iter().zip(&b.frames).chain(a.frames.iter().zip(&c.frames)).chain(a.frames.iter().zip(&e.frames)).chain(wide_frames) {
                    assert!(fa.rgba == fb.rgba, "{settings:?}: the colours differ");
                    assert!(fa.depth.iter().zip(&fb.depth).all(|(x, y)| x.to_bits() == y.to_bits()), "{settings:?}: the depths differ");
                }
                assert_eq!((a.stats.hits, a.stats.samples, a.stats.queries), (b.stats.hits, b.stats.samples, b.stats.queries), "{settings:?}");
                assert!(a.stats.hits > 1000, "{settings:?}: the views should hit ({} hits)", a.stats.hits);
            }
        }
    }

    #[test]
    #[allow(unsafe_code)]
    fn vector_shading_matches_the_scalar_path() {
        if crate::mlp::simd::level() == crate::mlp::simd::Level::Portable {
            eprintln!("no AVX2 on this CPU: only the portable path exists");
            return;
        }
        let mut rng = SmallRng::seed_from_u64(11);
        let features = 8;
        for round in 0..300 {
            // Full and partial tiles; several queries per pixel; outputs from saturated to 0.
            let n = if round % 3 == 0 { 1 + round % TILE } else { TILE };
            let tile: Vec<Query> = (0..n)
                .map(|_| {
                    let d = Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)).normalize_or(Vec3::X);
                    Query { p_hit: Vec3::ZERO, d, alpha_c: rng.random(), beta: rng.random(), pixel: rng.random_range(0..6) }
                })
                .collect();
            let scale = [0.1f32, 3.0, 40.0, 120.0][round % 4];
            let o: [[f32; TILE]; 4] = std::array::from_fn(|_| std::array::from_fn(|_| rng.random_range(-scale..scale)));
            let diffuse: [[f32; TILE]; 4] = std::array::from_fn(|_| std::array::from_fn(|_| rng.random_range(-0.2..1.2)));
            let bg = Vec3::new(rng.random(), rng.random(), 1.0);
            let (mut xs, mut xv) = ([[0.0f32; TILE]; MAX_INPUT], [[0.0f32; TILE]; MAX_INPUT]);
            view_inputs(&tile, features, &mut xs);
            // SAFETY: the CPU has x86-64-v3 (the level above).
            unsafe { v3::view_inputs(&tile, features, &mut xv) };
            for (row, (a, b)) in xs.iter().zip(&xv).enumerate() {
                assert_eq!(a[..n].iter().map(|v| v.to_bits()).collect::<Vec<_>>(), b[..n].iter().map(|v| v.to_bits()).collect::<Vec<_>>(), "round {round}: input row {row}");
            }
            let (mut cs, mut cv) = (vec![Vec3::splat(0.25); 6], vec![Vec3::splat(0.25); 6]);
            let (mut als, mut alv) = (vec![0.5f32; 6], vec![0.5f32; 6]);
            composite(&tile, &o, &diffuse, bg, &mut cs, &mut als);
            // SAFETY: as above.
            unsafe { v3::composite(&tile, &o, &diffuse, bg, &mut cv, &mut alv) };
            let bits = |c: &[Vec3], a: &[f32]| c.iter().flat_map(|v| v.to_array()).chain(a.iter().copied()).map(f32::to_bits).collect::<Vec<_>>();
            assert_eq!(bits(&cs, &als), bits(&cv, &alv), "round {round}: composited pixels");
        }
    }

    /// The vector RGBA pack gives `to_unorm8`'s bytes: NaN, ±0, ±∞, out of range, and
    /// values whose × 255 lies within a few ulps of every k + ½ (the rounding's ties), and it
    /// leaves a band's last pixels (not a multiple of 8) to the caller.
    #[test]
    #[cfg(target_arch = "x86_64")]
    fn vector_rgba_pack_matches_to_unorm8() {
        if crate::mlp::simd::level() == crate::mlp::simd::Level::Portable {
            eprintln!("no AVX2 on this CPU: the vector pack does not run");
            return;
        }
        let mut values = vec![f32::NAN, 0.0, -0.0, f32::INFINITY, f32::NEG_INFINITY, -1.0, 2.0, 1.0, 0.5, 1e-30];
        for k in 0..256 {
            let tie = (k as f32 + 0.5) / 255.0;
            let mut v = tie;
            for _ in 0..3 {
                v = f32::from_bits(v.to_bits() - 1);
            }
            for _ in 0..7 {
                values.push(v);
                v = f32::from_bits(v.to_bits() + 1);
            }
        }
        let mut rng = SmallRng::seed_from_u64(8);
        values.extend((0..1000).map(|_| rng.random_range(-0.1..1.1f32)));
        let n = values.len() / 4;
        let color: Vec<Vec3> = (0..n).map(|i| Vec3::new(values[4 * i], values[4 * i + 1], values[4 * i + 2])).collect();
        let alpha: Vec<f32> = (0..n).map(|i| values[4 * i + 3]).collect();
        let mut rgba = vec![0u8; 4 * n];
        #[allow(unsafe_code)]
        // SAFETY: the CPU has x86-64-v3 (checked above).
        let packed = unsafe { v3::pack_rgba(&color, &alpha, &mut rgba) };
        assert_eq!(packed, n / 8 * 8);
        assert!(n % 8 != 0, "the test leaves a tail");
        for i in 0..packed {
            let want = [to_unorm8(color[i].x), to_unorm8(color[i].y), to_unorm8(color[i].z), to_unorm8(alpha[i])];
            assert_eq!(rgba[4 * i..4 * i + 4], want, "pixel {i}: {:?} {}", color[i], alpha[i]);
        }
        assert!(rgba[4 * packed..].iter().all(|&b| b == 0), "the tail is the caller's");
    }

    /// The AVX-512 band bounds (masked min/max per row of a rectangle) equal the scalar
    /// ones to the bit: rows of 1 to 40 pixels (under, at and past 16 lanes), rectangles
    /// cut by the band's rows and the view's edge, and ties of +0 and −0.
    #[test]
    fn masked_band_bounds_match_the_scalar_ones() {
        if crate::mlp::simd::level() != crate::mlp::simd::Level::Avx512 {
            eprintln!("no AVX-512 on this CPU: the masked band bounds do not run");
        }
        #[cfg(target_arch = "x86_64")]
        if crate::mlp::simd::level() == crate::mlp::simd::Level::Avx512 {
            let (width, height) = (100u32, 37u32);
            let mut rng = SmallRng::seed_from_u64(14);
            let t = |rng: &mut SmallRng| if rng.random_bool(0.5) { [0.0, -0.0, 1.5, -2.25][rng.random_range(0..4)] } else { rng.random_range(-3.0..3.0f32) };
            let rects: Vec<CellRect> = (0..400)
                .map(|_| {
                    let (x0, y0) = (rng.random_range(0..width), rng.random_range(0..height));
                    let (x1, y1) = ((x0 + rng.random_range(0..40)).min(width - 1), (y0 + rng.random_range(0..9)).min(height - 1));
                    let (a, b) = (t(&mut rng), t(&mut rng));
                    CellRect { x0, x1, y0, y1, t_lo: a.min(b), t_hi: a.max(b) }
                })
                .collect();
            let bin_rows = 16;
            let mut bins = vec![Vec::new(); height.div_ceil(bin_rows) as usize];
            for (i, r) in rects.iter().enumerate() {
                for bin in &mut bins[(r.y0 / bin_rows) as usize..=(r.y1 / bin_rows) as usize] {
                    bin.push(i as u32);
                }
            }
            let fp = Footprints { rects, bin_rows, bins };
            for y0 in (0..height).step_by(BAND_ROWS as usize) {
                let n = (BAND_ROWS.min(height - y0) * width) as usize;
                let scalar = fp.band_bounds_with(width, y0, n, Footprints::span_bounds);
                #[allow(unsafe_code)]
                // SAFETY: the CPU has AVX-512 (checked above).
                let masked = unsafe { v4::band_bounds(&fp, width, y0, n) };
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&masked.t_lo), bits(&scalar.t_lo), "t_lo, band at row {y0}");
                assert_eq!(bits(&masked.t_hi), bits(&scalar.t_hi), "t_hi, band at row {y0}");
                assert!(scalar.t_lo.iter().any(|t| t.is_finite()), "the band at row {y0} has bounds");
            }
        }
    }

    #[test]
    fn dead_boxes_hold_no_live_cell() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/assets/lego.nolf");
        let density = Asset::load(&path).unwrap().density;
        let live = LiveCells::new(&density);
        let g = density.grid as usize;
        let mut per_radius = [0usize; MAX_SKIP_RADIUS as usize + 1];
        // The box of cells c + s∘[0, r]³ (cut at the grid's faces) for octant `oct` has no
        // live cell.
        let dead_box = |c: [usize; 3], oct: usize, r: usize| {
            let span = |a: usize| if oct >> a & 1 == 1 { c[a]..=(c[a] + r).min(g - 1) } else { c[a].saturating_sub(r)..=c[a] };
            span(2).all(|z| span(1).all(|y| span(0).all(|x| live.index[x + g * (y + g * z)] < 0)))
        };
        // Every 7th cell (of 128³), every octant: its radius is right, and the largest that is.
        for i in (0..g.pow(3)).step_by(7) {
            let entry = live.index[i];
            if entry >= 0 {
                continue;
            }
            let c = [i % g, (i / g) % g, i / (g * g)];
            for oct in 0..8 {
                let radius = ((-1 - entry) >> (3 * oct) & 7) as usize;
                per_radius[radius] += 1;
                assert!(dead_box(c, oct, radius), "cell {c:?}, octant {oct}: its box of radius {radius} holds a live cell");
                assert!(radius == MAX_SKIP_RADIUS as usize || !dead_box(c, oct, radius + 1), "cell {c:?}, octant {oct}: radius {radius} is not the largest");
            }
        }
        assert!(per_radius.iter().all(|&n| n > 0), "every radius should occur in lego: {per_radius:?}");
    }

    fn same_sigmas(prepared: &FastPrepared) {
        let asset = &prepared.asset;
        let mut rng = SmallRng::seed_from_u64(3);
        let step = asset.march.step;
        let mut live_lanes = 0;
        for _ in 0..2000 {
            let o = Vec3::new(rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0));
            let d = (-o + Vec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5))).normalize();
            let Some((t0, t1)) = clip_ray(&asset.density.bounds, o, d) else { continue };
            let k0 = rng.random_range(0..((t1 - t0) / step).max(1.0) as i32);
            let (s, e, m) = prepared.sigmas::<false>(k0, BATCH, o, d, t0, step);
            let (sv, ev, mv) = prepared.sigmas::<true>(k0, BATCH, o, d, t0, step);
            assert_eq!(s.map(f32::to_bits), sv.map(f32::to_bits));
            assert_eq!(e.map(f32::to_bits), ev.map(f32::to_bits));
            assert_eq!(m, mv);
            live_lanes += s.iter().filter(|v| **v != 0.0).count();
        }
        assert!(live_lanes > 1000, "the rays should cross the objects ({live_lanes} live samples)");
    }

    /// The closed segments kept in vectors file runs as the per-ray tracker does: the scalar
    /// [`v3::Closed::push`] and, on AVX-512, `v4::close16` on 16 lanes at once, with weights
    /// that tie (the first of equals gives way) and primaries that come and go.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn closed_segments_in_vectors_match_the_tracker() {
        use v3::{Closed, LANES, Runs};
        let wide = crate::mlp::simd::level() == crate::mlp::simd::Level::Avx512;
        if !wide {
            eprintln!("no AVX-512 on this CPU: the 16-lane filing does not run");
        }
        let rule = HitRule { tau: 0.1, max_hits: 3, gap_steps: 3.0 };
        let mut rng = SmallRng::seed_from_u64(9);
        let mut trackers: Vec<Segments> = (0..LANES).map(|_| Segments::new(0.3)).collect();
        let (mut scalar, mut vector) = (Closed::default(), Closed::default());
        let mut runs = Runs::default();
        let (mut filed, mut finished) = (0, 0);
        for round in 0..4000 {
            let at = 16 * (round % (LANES / 16));
            let closing = rng.random::<u16>() & rng.random::<u16>();
            for lane in at..at + 16 {
                let weight = [0.05, 0.1, 0.2, 0.4][rng.random_range(0..4)];
                let t = rng.random_range(0.0..4.0f32);
                (runs.weight[lane], runs.peak_w[lane], runs.peak_t[lane], runs.first_t[lane], runs.last_t[lane]) = (weight, weight / 2.0, t, t - 0.1, t + 0.1);
                runs.primary[lane] = if rng.random_bool(0.3) { -1 } else { 0 };
            }
            for bit in 0..16 {
                let lane = at + bit;
                if closing >> bit & 1 != 0 {
                    trackers[lane].close_run(runs.segment(lane), runs.primary[lane] != 0);
                    scalar.push(lane, runs.segment(lane), runs.primary[lane] != 0);
                    filed += 1;
                }
            }
            if wide {
                #[allow(unsafe_code)]
                // SAFETY: the CPU has AVX-512 (checked above); lanes `at..at + 16` of `LANES`.
                unsafe { v4::close16(&mut runs, &mut vector, at, closing) };
                for bit in 0..16 {
                    assert!(closing >> bit & 1 == 0 || runs.primary[at + bit] == 0, "a filed run's primary flag is cleared");
                }
            }
            // Now and then a lane's ray ends: all three give the same queries.
            let lane = rng.random_range(0..LANES);
            if rng.random_bool(0.2) {
                let m = MarchHit { t_hit: 1.0, alpha_c: rng.random_range(0.2..1.0), w_max: 0.4, samples: 9 };
                let want = trackers[lane].finish(None, m, &rule);
                let mut got = Segments::new(0.3);
                scalar.take(lane, &mut got);
                assert_eq!(got.finish(None, m, &rule), want, "scalar, round {round}, lane {lane}");
                if wide {
                    let mut got = Segments::new(0.3);
                    vector.take(lane, &mut got);
                    assert_eq!(got.finish(None, m, &rule), want, "16 lanes, round {round}, lane {lane}");
                }
                finished += 1;
            }
        }
        assert!(filed > 10_000 && finished > 500, "{filed} runs filed, {finished} rays finished");
    }
}
