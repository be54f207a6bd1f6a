//! What the march reads and skips, prepared once per asset or per view: 8-bit diffuse
//! corners ([`DiffuseBytes`]), the live cells and their dead-box radii ([`LiveCells`]), the
//! per-ray sample scan ([`Scan`]), the hash laid out by position ([`PshBricks`]) and the
//! footprint prepass that bounds each pixel's ray ([`Footprints`]).

use super::*;

/// 8-bit diffuse cubes kept as their bytes (a quarter of the f32 copy's cache footprint);
/// `byte / 255` is exactly the f32 the reference reads.
pub(super) struct DiffuseBytes {
    pub(super) corners: Vec<[u8; 4]>,
}

impl DiffuseBytes {
    pub(super) fn new(c: &TextureCubes) -> Option<Self> {
        let in_range = c.index.iter().all(|&b| b < c.brick_count() as i32) && c.index.len() == (c.grid as usize).pow(3) && c.values.len() < i32::MAX as usize;
        (c.storage == crate::cubes::CubeStorage::Unorm8 && c.channels == 4 && in_range).then(|| Self {
            corners: c.values.chunks_exact(4).map(|v| [0, 1, 2, 3].map(|i| crate::cubes::CubeStorage::unorm8(v[i]))).collect(),
        })
    }

    /// [`TextureCubes::sample`]`::<4>`, reading the bytes (the same f32 values).
    #[inline(always)]
    pub(super) fn sample(&self, c: &TextureCubes, p: Vec3) -> [f32; 4] {
        // One vector division for the 4 channels: the same quotients as 4 scalar ones.
        c.sample_with(p, |at| (glam::UVec4::from_array(self.corners[at].map(u32::from)).as_vec4() / 255.0).to_array())
    }
}

/// Most footprints the prepass projects per view: beyond this, live cells are merged into
/// blocks (on lego, 512³ density has 95k live cells: projecting and binning each cost 13% of
/// a frame, against 4% for the 19k of 256³).
pub(super) const FOOTPRINT_BLOCKS: usize = 32 * 1024;

/// Where a footprint block's edge, seen from the camera at the density's centre, spans fewer
/// pixels than this, the prepass projects the blocks of twice its side. Lego at 352×264 (the
/// auto scale's size of a 640×480 stream; edges of ~6 px): 0.974–0.977 of the frame time;
/// at 640×480 (~10 px) the same time either way.
pub(super) const COARSE_BLOCKS_BELOW_PX: f64 = 8.0;

/// The index grid with only live cells: bricks that have some non-zero density (the others'
/// samples have α = 0 and change nothing). Every entry is negative or the first corner of a
/// brick the density holds.
pub(super) struct LiveCells {
    /// `b³`, x fastest: the brick's first corner (brick × (r + 1)³, so that the march adds
    /// no multiply between reading the entry and reading the corners), or −1 − (the dead
    /// cell's radius per octant of ray directions, 3 bits each: [`dead_radii`]).
    pub(super) index: Vec<i32>,
    pub(super) cells: Vec<UVec3>,
    /// What the footprint prepass projects: the live cells merged into aligned blocks of
    /// `block`³ cells (`block` a power of two, 1 for the cells themselves), as few as keep at
    /// most [`FOOTPRINT_BLOCKS`] of them.
    pub(super) blocks: Vec<UVec3>,
    pub(super) block: u32,
    /// The blocks of twice the side (if `block` < 8), projected instead where a block of
    /// `block`³ cells looks smaller than [`COARSE_BLOCKS_BELOW_PX`].
    pub(super) coarse: Option<Vec<UVec3>>,
    /// Whether the footprint prepass runs (off only in the test that checks it changes no
    /// frame).
    pub(super) footprints: bool,
    /// Whether the march computes cell numbers in f32 (exact while `b³ ≤ 2²⁴`, and shorter
    /// than integer multiplies); larger grids, and a test, take the integer path.
    pub(super) cell_numbers_in_f32: bool,
    /// The density values as the f16 bits they are stored as (`None` if some value is not
    /// an f16, as in cubes built in memory), then 8 zeros: half the bytes, the two corners
    /// of a trilinear sample that differ in x are one 32-bit read, and in bricks of up to
    /// 5³ cells its four corners in a z plane one 16-byte read (the zeros keep the last
    /// brick's reads inside).
    pub(super) values_f16: Option<Vec<u16>>,
}

/// Largest index grid whose cell numbers (below `b³ ≤ 2²⁴`) the march computes in f32.
pub(super) const EXACT_GRID: u32 = 256;

/// Largest dead radius R the wavefront march jumps across: a box of R + 1 index cells per
/// side from the sample's cell towards where its ray heads (R in 3 bits per octant).
pub(super) const MAX_SKIP_RADIUS: u32 = 7;

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
pub(super) fn dead_radii(index: &[i32], g: usize) -> Vec<u32> {
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
    pub(super) fn new(d: &TextureCubes) -> Self {
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
    pub(super) fn with_blocks_at_most(mut self, max: usize) -> Self {
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
    pub(super) fn assert_fits(&self, density: &TextureCubes) {
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
pub(super) struct Scan {
    pub(super) transmittance: f32,
    pub(super) w_max: f32,
    pub(super) t_hit: f32,
    pub(super) samples: u32,
    pub(super) done: bool,
}

impl Scan {
    /// Takes lattice samples `k0..k0 + n` whose `e = e^(−σδ)` are given, visiting only the
    /// lanes set in `nonzero` (σ ≠ 0): a sample with σ = 0 has α = 0 and changes nothing (and
    /// the reference's tracker ignores w = 0). The state lives in locals for the loop.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub(super) fn take<T: Tracker>(&mut self, k0: i32, n: usize, nonzero: u32, e: &[f32; BATCH], t0: f32, step: f32, s: &RenderSettings, tracker: &mut T) {
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
pub(super) fn lattice(density: &TextureCubes, o: Vec3, d: Vec3, span: (f32, f32), step: f32) -> Option<(f32, i32, i32)> {
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
pub(super) struct PshBricks {
    /// Bricks per axis.
    pub(super) grid: usize,
    /// `grid³`, x fastest: the brick's table, or −1 (no stored vertex among its corners).
    pub(super) index: Vec<i32>,
    /// Per brick `(BRICK + 1)³` vertex ids, x fastest.
    pub(super) tables: Vec<u32>,
    /// `(vertices + 1) × features`: the last row is zeros ([`Self::zero_id`]), which the
    /// vector path reads for absent corners.
    pub(super) values: Vec<f32>,
}

impl PshBricks {
    pub(super) const BRICK: u32 = 4;
    pub(super) const EDGE: usize = Self::BRICK as usize + 1;
    pub(super) const ABSENT: u32 = u32::MAX;

    pub(super) fn new(h: &SpatialHash) -> Self {
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
    pub(super) fn zero_id(&self, features: usize) -> usize {
        self.values.len() / features.max(1) - 1
    }

    /// The 8 corners of `p`'s cell (in [`SpatialHash::encode`]'s order and with its
    /// weights): each one's vertex id, or [`Self::ABSENT`].
    #[inline(always)]
    pub(super) fn corners(&self, h: &SpatialHash, p: Vec3) -> Corners {
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
    pub(super) fn encode(&self, c: &Corners, out: &mut [f32]) {
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
pub(super) struct Corners {
    pub(super) id: [u32; 8],
    pub(super) weight: [f32; 8],
}

/// Asks the cache for the line holding `v[at]` (a hint; no effect elsewhere).
#[inline(always)]
pub(super) fn prefetch<T>(v: &[T], at: usize) {
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
pub(super) struct Footprints {
    pub(super) rects: Vec<CellRect>,
    /// Rows per bin and, per bin of rows, the rectangles that touch it.
    pub(super) bin_rows: u32,
    pub(super) bins: Vec<Vec<u32>>,
}

#[derive(Clone, Copy)]
pub(super) struct CellRect {
    pub(super) x0: u32,
    pub(super) x1: u32,
    pub(super) y0: u32,
    pub(super) y1: u32,
    pub(super) t_lo: f32,
    pub(super) t_hi: f32,
}

/// What [`Footprints::new`] needs to project one block: the camera in object space (f64),
/// the block size, and each corner's offset from the block's low corner, with the offsets'
/// components along the camera's axes, so that a block's 8 corners are sums over arrays of 8
/// (which vectorise).
pub(super) struct Projection {
    pub(super) camera: glam::DVec3,
    pub(super) axes: [glam::DVec3; 3],
    pub(super) min: glam::DVec3,
    pub(super) cell_size: glam::DVec3,
    /// Corner offsets per object axis, and along the camera's x, y and z axes.
    pub(super) offset: [[f64; 8]; 3],
    pub(super) along: [[f64; 8]; 3],
    /// Focal lengths and principal point (pixels), and the view's width and height.
    pub(super) focal: [f64; 2],
    pub(super) centre: [f64; 2],
    pub(super) size: [f64; 2],
    pub(super) t_shift: f64,
    pub(super) slack: f64,
}

impl Projection {
    pub(super) fn new(f: &RayFrame, block: u32, density: &TextureCubes, step: f32) -> Self {
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
    pub(super) fn rects(&self, blocks: &[UVec3]) -> Result<Vec<CellRect>, ()> {
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
    pub(super) fn rect(&self, block: &UVec3) -> Result<Option<CellRect>, ()> {
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
pub(super) struct RayBounds {
    pub(super) t_lo: Vec<f32>,
    pub(super) t_hi: Vec<f32>,
}

impl Footprints {
    /// `None` when some live cell reaches behind the camera (then every ray is marched whole).
    pub(super) fn new(f: &RayFrame, live: &LiveCells, density: &TextureCubes, step: f32) -> Option<Self> {
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
    pub(super) fn band_bounds(&self, width: u32, y0: u32, n: usize) -> RayBounds {
        #[cfg(target_arch = "x86_64")]
        if crate::mlp::simd::level() == crate::mlp::simd::Level::Avx512 {
            #[allow(unsafe_code)]
            // SAFETY: the CPU has AVX-512 F and VL, AVX2 and FMA (`Level::Avx512`).
            return unsafe { avx512::band_bounds(self, width, y0, n) };
        }
        self.band_bounds_with(width, y0, n, Self::span_bounds)
    }

    /// Takes one row of rectangle `r` (`lo`, `hi`: its pixels) into the bounds: one pass over
    /// both, as compare-and-select; no NaN handling (none is stored), so it compiles to plain
    /// vector min/max.
    #[inline(always)]
    pub(super) fn span_bounds(lo: &mut [f32], hi: &mut [f32], r: &CellRect) {
        for (lo, hi) in lo.iter_mut().zip(hi) {
            *lo = if r.t_lo < *lo { r.t_lo } else { *lo };
            *hi = if r.t_hi > *hi { r.t_hi } else { *hi };
        }
    }

    /// [`Self::band_bounds`], with `span` taking one row of a rectangle into the bounds.
    #[inline(always)]
    pub(super) fn band_bounds_with(&self, width: u32, y0: u32, n: usize, span: impl Fn(&mut [f32], &mut [f32], &CellRect)) -> RayBounds {
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
