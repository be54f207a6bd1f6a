//! Sparse texture cubes (NEPHELE §4.1): a coarse `b³` index grid over the object's box; each
//! occupied cell points to a brick of `r³` fine cells whose `(r+1)³` corner samples are stored,
//! so trilinear filtering never reads across bricks. Used for density (1 channel) and for the
//! baked diffuse colour + specular tint (4 channels). Empty cells read as zero.
//!
//! Values are stored as f16, or for values in [0, 1] (diffuse colour and tint) optionally as
//! 8-bit unorm, in assets and in the GPU atlas (both hardware-filterable); here they are kept
//! as the same rounded values in f32 so the CPU reference sees exactly what the GPU sees.

use glam::{UVec3, Vec3};
use serde::{Deserialize, Serialize};

/// Axis-aligned box in object space.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    pub fn cube(half_extent: f32) -> Self {
        Self { min: Vec3::splat(-half_extent), max: Vec3::splat(half_extent) }
    }
    pub fn size(&self) -> Vec3 {
        self.max - self.min
    }
    pub fn center(&self) -> Vec3 {
        0.5 * (self.min + self.max)
    }
    pub fn radius(&self) -> f32 {
        0.5 * self.size().length()
    }
    pub fn is_valid(&self) -> bool {
        self.min.is_finite() && self.max.is_finite() && self.size().min_element() > 0.0 && self.size().max_element() < 1e6
    }
}

/// How corner values are stored (in assets and in the GPU atlas).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CubeStorage {
    /// IEEE half floats: any finite value up to 65504.
    #[default]
    F16,
    /// `round(255 v) / 255` for `v` in [0, 1]: half the bytes, 1/510 worst-case error.
    Unorm8,
}

impl CubeStorage {
    pub fn bytes_per_value(self) -> u64 {
        match self {
            Self::F16 => 2,
            Self::Unorm8 => 1,
        }
    }

    /// `v` as it reads back after storing.
    pub fn round(self, v: f32) -> f32 {
        match self {
            Self::F16 => half::f16::from_f32(v).to_f32(),
            Self::Unorm8 => Self::unorm8(v) as f32 / 255.0,
        }
    }

    /// The stored byte of an [`Self::Unorm8`] value (NaN stores 0).
    pub fn unorm8(v: f32) -> u8 {
        (v.clamp(0.0, 1.0) * 255.0).round() as u8
    }

    pub fn is_f16(&self) -> bool {
        *self == Self::F16
    }
}

/// Sparse bricked grid with `channels` values per corner sample.
#[derive(Debug, Clone, PartialEq)]
pub struct TextureCubes {
    pub bounds: Aabb,
    /// Index grid cells per axis (`b`).
    pub grid: u32,
    /// Fine cells per brick edge (`r`); a brick stores `(r+1)³` corners.
    pub brick: u32,
    pub channels: u32,
    /// `b³` entries, x fastest; brick number or −1 for empty.
    pub index: Vec<i32>,
    /// `n_bricks × (r+1)³ × channels`, corner x fastest, channels innermost; values as
    /// `storage` reads them back.
    pub values: Vec<f32>,
    pub storage: CubeStorage,
}

impl TextureCubes {
    pub fn brick_corners(&self) -> usize {
        let e = self.brick as usize + 1;
        e * e * e
    }
    pub fn brick_count(&self) -> usize {
        self.values.len() / (self.brick_corners() * self.channels as usize).max(1)
    }
    /// Fine grid resolution per axis (`b·r`).
    pub fn fine_res(&self) -> u32 {
        self.grid * self.brick
    }
    /// Fine-grid units per object-space unit along each axis (`b·r / size`).
    pub fn fine_per_unit(&self) -> Vec3 {
        self.fine_res() as f32 / self.bounds.size()
    }
    /// Object-space point → fine-grid coordinates: `(p − min) · (b·r / size)` (a product,
    /// not a quotient, so that the vector kernels take no division per sample).
    pub fn to_fine(&self, p: Vec3) -> Vec3 {
        (p - self.bounds.min) * self.fine_per_unit()
    }
    pub fn cell_index(&self, cell: UVec3) -> usize {
        let b = self.grid as usize;
        cell.x as usize + b * (cell.y as usize + b * cell.z as usize)
    }
    pub fn brick_at(&self, cell: UVec3) -> i32 {
        self.index[self.cell_index(cell)]
    }

    /// Trilinear lookup at an object-space point; zero in empty cells and outside the box
    /// (clamped to the border cell, as the GPU kernel does).
    #[inline(always)]
    pub fn sample<const C: usize>(&self, p: Vec3) -> [f32; C] {
        self.sample_with(p, |at| self.corner(at))
    }

    /// [`Self::sample`] reading corner `at` (a corner number, brick-major) through `read`,
    /// for callers that keep the values in another form (the fast renderer's 8-bit copy).
    #[inline(always)]
    pub fn sample_with<const C: usize>(&self, p: Vec3, read: impl Fn(usize) -> [f32; C]) -> [f32; C] {
        let g = self.to_fine(p);
        // Truncate-then-clamp equals floor-then-clamp for every input (negatives clamp to 0).
        let cell = (g / self.brick as f32).as_ivec3().as_vec3().clamp(Vec3::ZERO, Vec3::splat(self.grid as f32 - 1.0));
        let brick = self.brick_at(cell.as_uvec3());
        if brick < 0 {
            return [0.0; C];
        }
        self.sample_in_brick_with(brick as usize, cell, g, read)
    }

    /// Trilinear lookup of fine-grid point `g` in the brick of index cell `cell` (the march
    /// already knows both); `g` is clamped into the brick.
    #[inline(always)]
    pub fn sample_in_brick<const C: usize>(&self, brick: usize, cell: Vec3, g: Vec3) -> [f32; C] {
        self.sample_in_brick_with(brick, cell, g, |at| self.corner(at))
    }

    /// The `C` values of corner `at`.
    #[inline(always)]
    fn corner<const C: usize>(&self, at: usize) -> [f32; C] {
        debug_assert_eq!(C, self.channels as usize);
        self.values[at * C..(at + 1) * C].try_into().expect("C channels")
    }

    #[inline(always)]
    fn sample_in_brick_with<const C: usize>(&self, brick: usize, cell: Vec3, g: Vec3, read: impl Fn(usize) -> [f32; C]) -> [f32; C] {
        let r = self.brick as f32;
        let u = (g - cell * r).clamp(Vec3::ZERO, Vec3::splat(r));
        // u ≥ 0, so truncation is floor (and stays inline; `floor` is a libm call on
        // baseline x86-64).
        let base = u.as_uvec3().as_vec3().min(Vec3::splat(r - 1.0));
        let f = u - base;
        let base = base.as_uvec3();
        let e = self.brick as usize + 1;
        let brick_start = brick * self.brick_corners();
        let mut out = [0.0; C];
        for corner in 0..8u32 {
            let (dx, dy, dz) = (corner & 1, (corner >> 1) & 1, corner >> 2);
            let w = if dx == 1 { f.x } else { 1.0 - f.x } * if dy == 1 { f.y } else { 1.0 - f.y } * if dz == 1 { f.z } else { 1.0 - f.z };
            let (x, y, z) = ((base.x + dx) as usize, (base.y + dy) as usize, (base.z + dz) as usize);
            let v = read(brick_start + x + e * (y + e * z));
            for (o, v) in out.iter_mut().zip(v) {
                *o += w * v;
            }
        }
        out
    }

    /// Builds cubes by evaluating `value` at the corners of every cell `occupied` accepts.
    /// `value(p, out)` writes `channels` values for object-space point `p`. Values are rounded
    /// to f16 as they would be stored.
    pub fn bake(
        bounds: Aabb,
        grid: u32,
        brick: u32,
        channels: u32,
        occupied: impl Fn(UVec3) -> bool + Sync,
        value: impl Fn(Vec3, &mut [f32]) + Sync,
    ) -> Self {
        use rayon::prelude::*;
        let c = channels as usize;
        Self::bake_batched(bounds, grid, brick, channels, occupied, |points| {
            let mut out = vec![0.0; points.len() * c];
            out.par_chunks_mut(c).zip(points.par_iter()).for_each(|(dst, &p)| value(p, dst));
            out
        })
    }

    /// As [`Self::bake`], with every corner evaluated in one call: `values(points)` returns
    /// `channels` values per point, in order (for batched evaluators such as a network).
    pub fn bake_batched(
        bounds: Aabb,
        grid: u32,
        brick: u32,
        channels: u32,
        occupied: impl Fn(UVec3) -> bool + Sync,
        values: impl FnOnce(&[Vec3]) -> Vec<f32>,
    ) -> Self {
        use rayon::prelude::*;
        let b = grid as usize;
        let cells: Vec<bool> = (0..b * b * b)
            .into_par_iter()
            .map(|i| occupied(UVec3::new((i % b) as u32, ((i / b) % b) as u32, (i / (b * b)) as u32)))
            .collect();
        let mut index = vec![-1i32; b * b * b];
        let mut n = 0;
        for (i, &occ) in cells.iter().enumerate() {
            if occ {
                index[i] = n;
                n += 1;
            }
        }
        let mut cubes = Self { bounds, grid, brick, channels, index, values: Vec::new(), storage: CubeStorage::F16 };
        let points = cubes.corner_points();
        let mut values = values(&points);
        assert_eq!(values.len(), points.len() * channels as usize, "bake_batched: one value per corner and channel");
        values.iter_mut().for_each(|v| *v = half::f16::from_f32(*v).to_f32());
        cubes.values = values;
        cubes
    }

    /// Object-space positions of the corners of every brick, in the order of
    /// [`Self::values`] (brick by brick, corner x fastest).
    pub fn corner_points(&self) -> Vec<Vec3> {
        let b = self.grid as usize;
        let e = self.brick as usize + 1;
        let fine = Vec3::splat(self.fine_res() as f32);
        let mut points = Vec::new();
        let mut cells: Vec<(i32, usize)> = self.index.iter().enumerate().filter(|(_, k)| **k >= 0).map(|(i, &k)| (k, i)).collect();
        cells.sort_unstable();
        for (_, i) in cells {
            let cell = Vec3::new((i % b) as f32, ((i / b) % b) as f32, (i / (b * b)) as f32);
            for z in 0..e {
                for y in 0..e {
                    for x in 0..e {
                        let g = cell * self.brick as f32 + Vec3::new(x as f32, y as f32, z as f32);
                        points.push(self.bounds.min + g / fine * self.bounds.size());
                    }
                }
            }
        }
        points
    }

    /// The same cubes with only the bricks `keep(cell index, brick values)` accepts,
    /// renumbered in index order.
    pub fn retain(&self, keep: impl Fn(usize, &[f32]) -> bool) -> Self {
        let per_brick = self.brick_corners() * self.channels as usize;
        let mut out = Self { index: vec![-1; self.index.len()], values: Vec::new(), ..self.clone() };
        for (i, &brick) in self.index.iter().enumerate() {
            if brick < 0 {
                continue;
            }
            let values = &self.values[brick as usize * per_brick..(brick as usize + 1) * per_brick];
            if keep(i, values) {
                out.index[i] = (out.values.len() / per_brick) as i32;
                out.values.extend_from_slice(values);
            }
        }
        out
    }

    /// The same cubes stored as `storage` (values rounded to what it reads back).
    pub fn stored_as(mut self, storage: CubeStorage) -> Self {
        self.values.iter_mut().for_each(|v| *v = storage.round(*v));
        self.storage = storage;
        self
    }

    /// Whether assets store the index grid as i16 (fewer than 32768 bricks) rather than i32.
    pub fn narrow_index(&self) -> bool {
        self.brick_count() <= i16::MAX as usize
    }

    /// Bytes as stored (index + values).
    pub fn stored_bytes(&self) -> u64 {
        let index = if self.narrow_index() { 2 } else { 4 };
        self.index.len() as u64 * index + self.values.len() as u64 * self.storage.bytes_per_value()
    }
    /// Bytes a dense grid of the same fine resolution and storage would take.
    pub fn dense_bytes(&self) -> u64 {
        (self.fine_res() as u64 + 1).pow(3) * self.channels as u64 * self.storage.bytes_per_value()
    }
}

/// How bricks are packed into a 3D texture atlas: bricks per axis.
pub fn atlas_bricks_per_axis(brick_count: usize, brick_edge_texels: u32, max_dim: u32) -> Option<UVec3> {
    let per_axis_max = (max_dim / brick_edge_texels).max(1);
    let n = brick_count.max(1) as u32;
    let nx = ((n as f64).cbrt().ceil() as u32).clamp(1, per_axis_max);
    let ny = n.div_ceil(nx).min(nx).max(1);
    let nz = n.div_ceil(nx * ny);
    (nz <= per_axis_max).then_some(UVec3::new(nx, ny, nz))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn linear_cubes() -> TextureCubes {
        // A linear field is reproduced exactly by trilinear filtering.
        TextureCubes::bake(Aabb::cube(1.0), 4, 4, 1, |c| c.x != 0, |p, out| out[0] = 2.0 + p.x + 0.5 * p.y - 0.25 * p.z)
    }

    #[test]
    fn trilinear_reproduces_linear_fields_and_empty_cells_read_zero() {
        let cubes = linear_cubes();
        assert_eq!(cubes.brick_count(), 48);
        for p in [Vec3::new(0.3, -0.2, 0.7), Vec3::new(-0.49, 0.99, -0.99), Vec3::new(0.999, 0.0, 0.0)] {
            let want = 2.0 + p.x + 0.5 * p.y - 0.25 * p.z;
            let got = cubes.sample::<1>(p)[0];
            assert!((got - want).abs() < 4e-3, "{p}: {got} vs {want}");
        }
        // Cells with x index 0 (x < -0.5) are empty.
        assert_eq!(cubes.sample::<1>(Vec3::new(-0.8, 0.1, 0.1)), [0.0]);
    }

    #[test]
    fn retaining_bricks_keeps_their_values() {
        let cubes = linear_cubes();
        let wanted = [cubes.cell_index(UVec3::new(1, 2, 3)), cubes.cell_index(UVec3::new(0, 0, 0))];
        let kept = cubes.retain(|i, _| wanted.contains(&i));
        // (0, 0, 0) had no brick.
        assert_eq!(kept.brick_count(), 1);
        // A predicate on the values: bricks whose field exceeds 3 somewhere (x + y/2 − z/4 > 1).
        let high = cubes.retain(|_, v| v.iter().any(|&x| x > 3.0));
        assert!(high.brick_count() > 0 && high.brick_count() < cubes.brick_count());
        assert!(high.values.chunks(high.brick_corners()).all(|b| b.iter().any(|&x| x > 3.0)));
        let p = Vec3::new(-0.3, 0.2, 0.7); // in cell (1, 2, 3)
        assert_eq!(kept.sample::<1>(p), cubes.sample::<1>(p));
        assert_eq!(kept.sample::<1>(Vec3::new(0.6, 0.6, 0.6)), [0.0]);
    }

    #[test]
    fn atlas_layout_fits() {
        for n in [0usize, 1, 2, 7, 8, 9, 1000, 12345] {
            let a = atlas_bricks_per_axis(n, 9, 2048).unwrap();
            assert!((a.x * a.y * a.z) as usize >= n.max(1), "{n}: {a}");
        }
        assert!(atlas_bricks_per_axis(1 << 30, 9, 2048).is_none());
    }
}
