//! Occupancy grid for empty-space skipping (instant-ngp, Müller et al. 2022,
//! appendix E.2): `res³` cells over the scene box, each holding a running density estimate
//! and one occupancy bit. Every update decays all estimates by a factor (0.95), evaluates σ
//! at one random point in each chosen cell, keeps the maximum of the decayed and the new
//! value, and marks a cell occupied when its estimate exceeds
//! `min(mean estimate, min_optical_thickness / step)` — i.e. when a step through it would
//! be at least that opaque. The grid starts fully occupied, and a cell never evaluated stays
//! occupied. The trainer runs the updates; training and rendering take samples only in
//! occupied cells.

use glam::{UVec3, Vec3};
use rand::Rng;

use crate::cubes::Aabb;

#[derive(Debug, Clone, PartialEq)]
pub struct OccupancyGrid {
    pub bounds: Aabb,
    /// Cells per axis.
    pub resolution: u32,
    /// Running density estimate per cell (x fastest), 1/(scene unit); NaN = never evaluated.
    density: Vec<f32>,
    /// One bit per cell.
    bits: Vec<u64>,
}

impl OccupancyGrid {
    /// A fully occupied grid.
    pub fn new(bounds: Aabb, resolution: u32) -> Self {
        assert!(bounds.is_valid() && (1..=1024).contains(&resolution), "bad occupancy grid {bounds:?} {resolution}");
        let cells = (resolution as usize).pow(3);
        Self { bounds, resolution, density: vec![f32::NAN; cells], bits: vec![u64::MAX; cells.div_ceil(64)] }
    }

    /// Restores a grid from [`Self::densities`] and [`Self::bits`] (checkpoints); `None` if
    /// their lengths do not fit `resolution`.
    pub fn from_state(bounds: Aabb, resolution: u32, density: Vec<f32>, bits: Vec<u64>) -> Option<Self> {
        let cells = (resolution as usize).pow(3);
        let ok = bounds.is_valid() && (1..=1024).contains(&resolution) && density.len() == cells && bits.len() == cells.div_ceil(64);
        ok.then_some(Self { bounds, resolution, density, bits })
    }

    /// Running density estimate per cell (x fastest); NaN = never evaluated.
    pub fn densities(&self) -> &[f32] {
        &self.density
    }

    /// Occupancy bits, 64 cells per word, cell `c` at bit `c % 64` of word `c / 64`.
    pub fn bits(&self) -> &[u64] {
        &self.bits
    }

    pub fn cell_count(&self) -> usize {
        self.density.len()
    }

    /// Cell holding a scene point (points outside the box are clamped to the border cells).
    #[inline]
    pub fn cell_of(&self, p_in_world: Vec3) -> usize {
        let res = self.resolution as f32;
        let g = ((p_in_world - self.bounds.min) / self.bounds.size() * res).clamp(Vec3::ZERO, Vec3::splat(res - 1.0));
        let c = g.as_uvec3();
        let r = self.resolution as usize;
        c.x as usize + r * (c.y as usize + r * c.z as usize)
    }

    #[inline]
    pub fn is_cell_occupied(&self, cell: usize) -> bool {
        self.bits[cell / 64] >> (cell % 64) & 1 == 1
    }

    #[inline]
    pub fn is_occupied(&self, p_in_world: Vec3) -> bool {
        self.is_cell_occupied(self.cell_of(p_in_world))
    }

    pub fn occupied_fraction(&self) -> f64 {
        let occupied: u64 = (0..self.cell_count()).filter(|&c| self.is_cell_occupied(c)).count() as u64;
        occupied as f64 / self.cell_count() as f64
    }

    /// Integer coordinates of a cell.
    pub fn cell_coords(&self, cell: usize) -> UVec3 {
        let r = self.resolution as usize;
        UVec3::new((cell % r) as u32, (cell / r % r) as u32, (cell / (r * r)) as u32)
    }

    /// A uniformly random point inside `cell`, world space.
    pub fn random_point_in(&self, cell: usize, rng: &mut impl Rng) -> Vec3 {
        let jitter = Vec3::new(rng.random(), rng.random(), rng.random());
        self.bounds.min + (self.cell_coords(cell).as_vec3() + jitter) / self.resolution as f32 * self.bounds.size()
    }

    /// One update: decay every estimate, merge the new samples (`densities[k]` measured in
    /// `cells[k]`), and re-threshold at `min(mean, threshold)`.
    pub fn update(&mut self, cells: &[usize], densities: &[f32], decay: f32, threshold: f32) {
        assert_eq!(cells.len(), densities.len());
        for d in &mut self.density {
            *d *= decay;
        }
        for (&c, &sigma) in cells.iter().zip(densities) {
            let old = self.density[c];
            self.density[c] = if old.is_nan() { sigma } else { old.max(sigma) };
        }
        let (sum, count) = self.density.iter().filter(|d| !d.is_nan()).fold((0.0f64, 0usize), |(s, n), &d| (s + d as f64, n + 1));
        let mean = if count > 0 { (sum / count as f64) as f32 } else { 0.0 };
        let cut = mean.min(threshold);
        for (word, chunk) in self.bits.iter_mut().zip(self.density.chunks(64)) {
            *word = chunk.iter().enumerate().fold(0u64, |w, (i, &d)| w | (((d.is_nan() || d > cut) as u64) << i));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn train_occupancy_thresholds_decays_and_keeps_unseen_cells() {
        let mut grid = OccupancyGrid::new(Aabb::cube(1.0), 4);
        assert_eq!(grid.occupied_fraction(), 1.0);
        assert_eq!(grid.cell_of(Vec3::splat(-1.0)), 0);
        assert_eq!(grid.cell_of(Vec3::splat(1.0)), 63);
        assert_eq!(grid.cell_of(Vec3::new(-0.9, -0.9, 0.6)), 48);
        assert_eq!(grid.cell_coords(48), UVec3::new(0, 0, 3));
        // Cell 5 dense, cells 0..4 empty; the rest never evaluated stays occupied.
        let cells: Vec<usize> = (0..6).collect();
        grid.update(&cells, &[0.0, 0.0, 0.0, 0.0, 0.0, 50.0], 0.95, 2.0);
        assert!(!grid.is_cell_occupied(0) && !grid.is_cell_occupied(4));
        assert!(grid.is_cell_occupied(5) && grid.is_cell_occupied(6) && grid.is_cell_occupied(63));
        // Without new samples the dense cell decays below the threshold after ln(25)/ln(1/0.95)
        // ≈ 63 updates, while the re-sampled upper half keeps the mean above the threshold.
        let upper: Vec<usize> = (32..64).collect();
        let mut updates = 0;
        while grid.is_cell_occupied(5) {
            grid.update(&upper, &[50.0; 32], 0.95, 2.0);
            updates += 1;
            assert!(updates < 100);
        }
        assert!((60..=64).contains(&updates), "{updates}");
        let p = grid.random_point_in(48, &mut rand::rngs::SmallRng::seed_from_u64(1));
        assert_eq!(grid.cell_of(p), 48);
    }

    use rand::SeedableRng;
}
