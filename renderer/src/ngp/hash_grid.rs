//! Multi-resolution hash encoding (Müller et al., "Instant Neural Graphics Primitives",
//! SIGGRAPH 2022, §3). A point in the unit cube is looked up in `L` grids whose resolutions
//! grow geometrically from `base_resolution` to `finest_resolution`; each grid vertex owns
//! [`FEATURES_PER_LEVEL`] trainable f32 features kept in a table of at most `2^log2_table_size`
//! entries. Coarse levels whose `(res+1)³` vertices fit in the table are indexed densely
//! (no collisions); finer levels share the table through the spatial hash
//! `(x·1 ⊕ y·2654435761 ⊕ z·805459861) mod T`. The 8 corners of the cell around the point are
//! blended trilinearly, and the levels' results are concatenated (level-major).
//!
//! Forward only; the backward pass is in the `nephele-train` crate.

use glam::{UVec3, Vec3};
use rand::Rng;

/// Features per vertex and level (`F` in the paper).
pub const FEATURES_PER_LEVEL: usize = 2;
/// The per-axis hash multipliers of instant-ngp (the first is 1 for cache coherence along x).
pub const HASH_PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];
/// Initial parameters are uniform in ±this (as instant-ngp).
pub const INIT_SCALE: f32 = 1e-4;

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct HashGridConfig {
    /// Number of levels `L`.
    pub levels: u32,
    /// `log2` of the largest table size `T` per level.
    pub log2_table_size: u32,
    /// Cells per axis of the coarsest level (`N_min`).
    pub base_resolution: u32,
    /// Cells per axis of the finest level (`N_max`).
    pub finest_resolution: u32,
}

/// One level of the grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Level {
    /// Cells per axis; vertices run `0..=resolution`.
    pub resolution: u32,
    /// Vertices indexed densely (`(res+1)³ ≤ T`), else hashed.
    pub dense: bool,
    /// First entry of this level in the parameter table.
    pub first_entry: usize,
    /// Entries of this level: `(res+1)³` if dense, else `T`.
    pub entries: usize,
}

/// The encoding and its parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct HashGrid {
    pub config: HashGridConfig,
    pub levels: Vec<Level>,
    /// `entries × FEATURES_PER_LEVEL`, all levels back to back, features innermost.
    pub params: Vec<f32>,
}

impl HashGridConfig {
    pub fn validate(&self) -> Result<(), String> {
        let ok = (1..=32).contains(&self.levels)
            && (4..=24).contains(&self.log2_table_size)
            && self.base_resolution >= 1
            && self.finest_resolution >= self.base_resolution
            && self.finest_resolution <= 1 << 20;
        if ok { Ok(()) } else { Err(format!("hash grid config out of range: {self:?}")) }
    }

    /// Resolution, storage and place in the table of every level (no allocation of the
    /// table itself, so checkpoints can check their tensor sizes first).
    pub fn layout(&self) -> Vec<Level> {
        let config = self;
        let table = 1usize << config.log2_table_size;
        let growth = config.growth_factor();
        let mut levels = Vec::with_capacity(config.levels as usize);
        let mut first_entry = 0;
        for l in 0..config.levels {
            let resolution = ((config.base_resolution as f64 * growth.powi(l as i32)) + 1e-9).floor() as u32;
            let resolution = resolution.clamp(config.base_resolution, config.finest_resolution);
            let vertices = (resolution as u64 + 1).pow(3);
            let dense = vertices <= table as u64;
            let entries = if dense { vertices as usize } else { table };
            levels.push(Level { resolution, dense, first_entry, entries });
            first_entry += entries;
        }
        levels
    }

    /// Per-level growth factor `b = exp((ln N_max − ln N_min) / (L − 1))`.
    pub fn growth_factor(&self) -> f64 {
        if self.levels <= 1 {
            return 1.0;
        }
        ((self.finest_resolution as f64 / self.base_resolution as f64).ln() / (self.levels - 1) as f64).exp()
    }
}

impl HashGrid {
    /// A grid with parameters uniform in ±[`INIT_SCALE`].
    pub fn new(config: HashGridConfig, rng: &mut impl Rng) -> Self {
        config.validate().expect("valid hash grid config");
        let levels = config.layout();
        let entries = levels.last().map_or(0, |l| l.first_entry + l.entries);
        let params = (0..entries * FEATURES_PER_LEVEL).map(|_| rng.random_range(-INIT_SCALE..INIT_SCALE)).collect();
        Self { config, levels, params }
    }

    /// Width of the encoding: `L · F`.
    pub fn output_width(&self) -> usize {
        self.levels.len() * FEATURES_PER_LEVEL
    }

    /// Entry of vertex `v` within level `level` (0-based, before adding `first_entry`).
    pub fn vertex_entry(&self, level: &Level, v: UVec3) -> usize {
        if level.dense {
            let side = level.resolution as usize + 1;
            v.x as usize + side * (v.y as usize + side * v.z as usize)
        } else {
            let h = v.x.wrapping_mul(HASH_PRIMES[0]) ^ v.y.wrapping_mul(HASH_PRIMES[1]) ^ v.z.wrapping_mul(HASH_PRIMES[2]);
            h as usize & (level.entries - 1)
        }
    }

    /// Absolute entries and trilinear weights of the 8 corners around `p01` (clamped into
    /// the unit cube) at one level. Corner `c` has offset `(c & 1, c >> 1 & 1, c >> 2 & 1)`.
    #[inline]
    pub fn corners(&self, level: &Level, p01: Vec3) -> ([usize; 8], [f32; 8]) {
        let res = level.resolution as f32;
        let pos = p01.clamp(Vec3::ZERO, Vec3::ONE) * res;
        // pos ≥ 0, so truncation is floor (and avoids a libm call).
        let cell = pos.as_uvec3().min(UVec3::splat(level.resolution - 1));
        let frac = pos - cell.as_vec3();
        let mut entries = [0usize; 8];
        let mut weights = [0f32; 8];
        for c in 0..8u32 {
            let bit = UVec3::new(c & 1, (c >> 1) & 1, (c >> 2) & 1);
            let w = |a: usize| if bit[a] == 1 { frac[a] } else { 1.0 - frac[a] };
            entries[c as usize] = level.first_entry + self.vertex_entry(level, cell + bit);
            weights[c as usize] = w(0) * w(1) * w(2);
        }
        (entries, weights)
    }

    /// Encodes one point of the unit cube into `out` (`L · F` values, level-major).
    pub fn encode(&self, p01: Vec3, out: &mut [f32]) {
        debug_assert_eq!(out.len(), self.output_width());
        for (level, out) in self.levels.iter().zip(out.chunks_exact_mut(FEATURES_PER_LEVEL)) {
            let (entries, weights) = self.corners(level, p01);
            let mut acc = [0f32; FEATURES_PER_LEVEL];
            for (e, w) in entries.iter().zip(weights) {
                let f = &self.params[e * FEATURES_PER_LEVEL..(e + 1) * FEATURES_PER_LEVEL];
                for k in 0..FEATURES_PER_LEVEL {
                    acc[k] += w * f[k];
                }
            }
            out.copy_from_slice(&acc);
        }
    }

    /// Encodes a batch: `out` is `points.len() × L·F`, row-major.
    pub fn encode_batch(&self, points01: &[Vec3], out: &mut [f32]) {
        let width = self.output_width();
        for (p, row) in points01.iter().zip(out.chunks_exact_mut(width)) {
            self.encode(*p, row);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{SeedableRng, rngs::SmallRng};

    fn config() -> HashGridConfig {
        HashGridConfig { levels: 8, log2_table_size: 12, base_resolution: 4, finest_resolution: 128 }
    }

    #[test]
    fn train_hash_grid_levels_grow_and_switch_to_hashing() {
        let grid = HashGrid::new(config(), &mut SmallRng::seed_from_u64(1));
        let res: Vec<u32> = grid.levels.iter().map(|l| l.resolution).collect();
        assert_eq!(res[0], 4);
        assert_eq!(*res.last().unwrap(), 128);
        assert!(res.windows(2).all(|w| w[1] > w[0]), "{res:?}");
        for l in &grid.levels {
            assert_eq!(l.dense, (l.resolution as usize + 1).pow(3) <= 1 << 12, "{l:?}");
        }
        assert!(grid.levels[0].dense && !grid.levels[7].dense);
        let total: usize = grid.levels.iter().map(|l| l.entries).sum();
        assert_eq!(grid.params.len(), total * FEATURES_PER_LEVEL);
    }

    #[test]
    fn train_hash_grid_dense_levels_have_no_collisions_and_hashed_stay_in_range() {
        let grid = HashGrid::new(config(), &mut SmallRng::seed_from_u64(2));
        for level in &grid.levels {
            let side = level.resolution + 1;
            let mut seen = vec![false; level.entries];
            let mut hits = 0usize;
            for z in 0..side {
                for y in 0..side {
                    for x in 0..side {
                        let e = grid.vertex_entry(level, UVec3::new(x, y, z));
                        assert!(e < level.entries, "{level:?}: entry {e}");
                        if level.dense {
                            assert!(!seen[e], "{level:?}: collision at {x},{y},{z}");
                        }
                        hits += !seen[e] as usize;
                        seen[e] = true;
                    }
                }
            }
            if level.dense {
                assert_eq!(hits, level.entries, "dense level not filled");
            } else {
                // The hash spreads vertices over most of the table.
                assert!(hits as f64 > 0.6 * level.entries as f64, "{level:?}: only {hits} entries used");
            }
        }
    }

    #[test]
    fn train_hash_grid_interpolates_corners_and_is_continuous() {
        let mut rng = SmallRng::seed_from_u64(3);
        let mut grid = HashGrid::new(config(), &mut rng);
        grid.params.iter_mut().for_each(|v| *v = rng.random_range(-1.0..1.0));
        let width = grid.output_width();
        // At a vertex of a level, that level's output is the vertex's own features.
        for (l, level) in grid.levels.iter().enumerate() {
            for v in [UVec3::new(0, 0, 0), UVec3::new(1, 2, 3), UVec3::splat(level.resolution)] {
                let p = v.as_vec3() / level.resolution as f32;
                let mut out = vec![0.0; width];
                grid.encode(p, &mut out);
                let e = level.first_entry + grid.vertex_entry(level, v);
                for k in 0..FEATURES_PER_LEVEL {
                    let want = grid.params[e * FEATURES_PER_LEVEL + k];
                    assert!((out[l * FEATURES_PER_LEVEL + k] - want).abs() < 1e-5, "level {l} vertex {v}");
                }
            }
        }
        // Across a cell face of the finest level the encoding does not jump.
        let finest = grid.levels.last().unwrap().resolution as f32;
        for _ in 0..100 {
            let mut p = Vec3::new(rng.random(), rng.random(), rng.random()) * 0.9 + 0.05;
            let axis = rng.random_range(0..3);
            p[axis] = (p[axis] * finest).round() / finest;
            let (mut a, mut b) = (p, p);
            a[axis] -= 1e-5;
            b[axis] += 1e-5;
            let (mut ea, mut eb) = (vec![0.0; width], vec![0.0; width]);
            grid.encode(a, &mut ea);
            grid.encode(b, &mut eb);
            for (x, y) in ea.iter().zip(&eb) {
                assert!((x - y).abs() < 1e-2, "jump across a face at {p}: {x} vs {y}");
            }
        }
    }
}
