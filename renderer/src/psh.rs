//! Perfect spatial hash (Lefebvre & Hoppe, "Perfect Spatial Hashing", SIGGRAPH 2006) over the
//! occupied vertices of an `N³` grid, used for the specular encoding E_s (NEPHELE §4.2).
//!
//! `h(p) = (h0(p) + Φ[h1(p)]) mod m̄` with `h0(p) = p mod m̄`, `h1(p) = p mod r̄`, all per axis.
//! The offset table Φ is built greedily, largest buckets first; every slot stores its key so
//! a vertex outside the set reads as zero. Construction and loading both verify that every
//! stored key hashes to its own slot (no collisions, every member found).

use glam::{UVec3, Vec3};
use rand::{Rng, SeedableRng, rngs::SmallRng};

use crate::cubes::Aabb;

/// Marks an empty slot.
pub const EMPTY_KEY: u32 = u32::MAX;
/// Largest vertex coordinate a key can hold (10 bits per axis).
pub const MAX_COORD: u32 = 1023;

pub fn pack(p: UVec3) -> u32 {
    p.x | (p.y << 10) | (p.z << 20)
}
pub fn unpack(k: u32) -> UVec3 {
    UVec3::new(k & 1023, (k >> 10) & 1023, (k >> 20) & 1023)
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PshError {
    #[error("vertex {0} is outside the 10-bit key range")]
    OutOfRange(UVec3),
    #[error("duplicate vertex {0}")]
    Duplicate(UVec3),
    #[error("no offset table found after {0} attempts")]
    NoSolution(u32),
    #[error("hash table is inconsistent: {0}")]
    Corrupt(String),
}

/// The perfect hash table with `features` f16-rounded values per entry.
#[derive(Debug, Clone, PartialEq)]
pub struct SpatialHash {
    pub bounds: Aabb,
    /// Grid cells per axis (`N`); vertices are `0..=N`.
    pub grid: u32,
    /// Hash table edge `m̄` (table has `m̄³` slots).
    pub table_edge: u32,
    /// Offset table edge `r̄` (`r̄³` offsets).
    pub offset_edge: u32,
    pub features: u32,
    /// `m̄³` packed keys, [`EMPTY_KEY`] where free.
    pub keys: Vec<u32>,
    /// `r̄³` packed offsets (10 bits per axis, each `< m̄`).
    pub offsets: Vec<u32>,
    /// `m̄³ × features`.
    pub values: Vec<f32>,
}

fn wrap(v: UVec3, m: u32) -> UVec3 {
    UVec3::new(v.x % m, v.y % m, v.z % m)
}
fn linear(v: UVec3, m: u32) -> usize {
    v.x as usize + m as usize * (v.y as usize + m as usize * v.z as usize)
}
fn gcd(a: u32, b: u32) -> u32 {
    if b == 0 { a } else { gcd(b, a % b) }
}

impl SpatialHash {
    /// Slot of `p` under the hash (whether or not `p` is stored there).
    pub fn slot(&self, p: UVec3) -> usize {
        let (m, r) = (self.table_edge, self.offset_edge);
        let phi = unpack(self.offsets[linear(wrap(p, r), r)]);
        linear(wrap(wrap(p, m) + phi, m), m)
    }

    /// The slot holding `p`, or `None` if `p` is not in the set.
    pub fn find(&self, p: UVec3) -> Option<usize> {
        if p.max_element() > MAX_COORD {
            return None;
        }
        let slot = self.slot(p);
        (self.keys[slot] == pack(p)).then_some(slot)
    }

    /// Builds the table for `points` (distinct, each coordinate ≤ [`MAX_COORD`]); `value(p, out)`
    /// fills each entry's features.
    pub fn build(
        bounds: Aabb,
        grid: u32,
        features: u32,
        points: &[UVec3],
        value: impl Fn(UVec3, &mut [f32]),
        seed: u64,
    ) -> Result<Self, PshError> {
        if let Some(p) = points.iter().find(|p| p.max_element() > MAX_COORD) {
            return Err(PshError::OutOfRange(*p));
        }
        let mut packed: Vec<u32> = points.iter().map(|&p| pack(p)).collect();
        packed.sort_unstable();
        if let Some(w) = packed.windows(2).find(|w| w[0] == w[1]) {
            return Err(PshError::Duplicate(unpack(w[0])));
        }
        let n = points.len().max(1);
        let mut table_edge = ((n as f64 * 1.03).cbrt().ceil() as u32).max(1);
        let mut offset_edge = ((n as f64 / 6.0).cbrt().ceil() as u32).max(1);
        let mut rng = SmallRng::seed_from_u64(seed);
        for attempt in 0..24 {
            while gcd(offset_edge, table_edge) != 1 {
                offset_edge += 1;
            }
            if table_edge > MAX_COORD + 1 {
                break;
            }
            if let Some((keys, offsets)) = try_build(points, table_edge, offset_edge, &mut rng) {
                let mut values = vec![0.0; keys.len() * features as usize];
                for (slot, &k) in keys.iter().enumerate() {
                    if k != EMPTY_KEY {
                        let out = &mut values[slot * features as usize..(slot + 1) * features as usize];
                        value(unpack(k), out);
                        for v in out.iter_mut() {
                            *v = half::f16::from_f32(*v).to_f32();
                        }
                    }
                }
                let table = Self { bounds, grid, table_edge, offset_edge, features, keys, offsets, values };
                table.verify()?;
                return Ok(table);
            }
            // Alternate: a larger offset table first, then a roomier hash table.
            if attempt % 2 == 0 {
                offset_edge = (offset_edge as f64 * 1.2).ceil() as u32 + 1;
            } else {
                table_edge += 1;
            }
        }
        Err(PshError::NoSolution(24))
    }

    /// Every stored key hashes to its own slot, lies in the grid and appears once; offsets are
    /// in range; sizes agree. Run at build and at load.
    pub fn verify(&self) -> Result<(), PshError> {
        let (m, r) = (self.table_edge as usize, self.offset_edge as usize);
        let bad = |s: String| Err(PshError::Corrupt(s));
        if self.keys.len() != m * m * m || self.offsets.len() != r * r * r {
            return bad(format!("table sizes {} / {} do not match edges {m} / {r}", self.keys.len(), self.offsets.len()));
        }
        if self.values.len() != self.keys.len() * self.features as usize {
            return bad("feature table size does not match".into());
        }
        if let Some(o) = self.offsets.iter().find(|&&o| unpack(o).max_element() as usize >= m || o >> 30 != 0) {
            return bad(format!("offset {o:#x} out of range"));
        }
        for (slot, &k) in self.keys.iter().enumerate() {
            if k == EMPTY_KEY {
                continue;
            }
            let p = unpack(k);
            if k >> 30 != 0 || p.max_element() > self.grid {
                return bad(format!("key {k:#x} outside the {}-cell grid", self.grid));
            }
            if self.slot(p) != slot {
                return bad(format!("key {p} stored in slot {slot} but hashes to {}", self.slot(p)));
            }
        }
        if let Some(v) = self.values.iter().find(|v| !v.is_finite()) {
            return bad(format!("non-finite feature {v}"));
        }
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.keys.iter().filter(|&&k| k != EMPTY_KEY).count()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// E_s: trilinear blend of the features at the 8 corners of the cell containing `p`
    /// (object space); absent vertices contribute zero.
    pub fn encode(&self, p: Vec3, out: &mut [f32]) {
        out.fill(0.0);
        let nf = self.features as usize;
        for (slot, w) in self.corner_slots(p) {
            for (o, v) in out.iter_mut().zip(&self.values[slot * nf..(slot + 1) * nf]) {
                *o += w * v;
            }
        }
    }

    /// Slots and trilinear weights of the stored corners of the cell containing `p`: the
    /// terms of [`Self::encode`] (and where its gradient goes).
    #[inline]
    pub fn corner_slots(&self, p: Vec3) -> impl Iterator<Item = (usize, f32)> + '_ {
        let n = self.grid as f32;
        let g = (p - self.bounds.min) / self.bounds.size() * n;
        let base = g.floor().clamp(Vec3::ZERO, Vec3::splat(n - 1.0));
        let f = (g - base).clamp(Vec3::ZERO, Vec3::ONE);
        let base = base.as_uvec3();
        (0..8u32).filter_map(move |corner| {
            let d = UVec3::new(corner & 1, (corner >> 1) & 1, corner >> 2);
            let w = if d.x == 1 { f.x } else { 1.0 - f.x } * if d.y == 1 { f.y } else { 1.0 - f.y } * if d.z == 1 { f.z } else { 1.0 - f.z };
            self.find(base + d).map(|slot| (slot, w))
        })
    }

    pub fn stored_bytes(&self) -> u64 {
        (self.keys.len() * 4 + self.offsets.len() * 4 + self.values.len() * 2) as u64
    }
    /// Bytes a dense f16 feature grid of the same resolution would take.
    pub fn dense_bytes(&self) -> u64 {
        (self.grid as u64 + 1).pow(3) * self.features as u64 * 2
    }
}

/// One greedy pass over distinct points; `None` if some bucket found no offset.
fn try_build(points: &[UVec3], m: u32, r: u32, rng: &mut SmallRng) -> Option<(Vec<u32>, Vec<u32>)> {
    let r3 = (r as usize).pow(3);
    let mut buckets: Vec<Vec<UVec3>> = vec![Vec::new(); r3];
    for &p in points {
        buckets[linear(wrap(p, r), r)].push(p);
    }
    let mut order: Vec<usize> = (0..r3).filter(|&b| !buckets[b].is_empty()).collect();
    order.sort_by_key(|&b| std::cmp::Reverse(buckets[b].len()));
    let m3 = (m as usize).pow(3);
    let mut keys = vec![EMPTY_KEY; m3];
    let mut offsets = vec![0u32; r3];
    let mut slots = Vec::new();
    for b in order {
        let bucket = &buckets[b];
        let fits = |phi: UVec3, keys: &[u32], slots: &mut Vec<usize>| {
            slots.clear();
            for &p in bucket {
                let s = linear(wrap(wrap(p, m) + phi, m), m);
                if keys[s] != EMPTY_KEY || slots.contains(&s) {
                    return false;
                }
                slots.push(s);
            }
            true
        };
        let mut found = None;
        for _ in 0..64 {
            let phi = UVec3::new(rng.random_range(0..m), rng.random_range(0..m), rng.random_range(0..m));
            if fits(phi, &keys, &mut slots) {
                found = Some(phi);
                break;
            }
        }
        if found.is_none() {
            // Exhaustive: every free slot for the bucket's first point fixes one offset.
            let h0 = wrap(bucket[0], m);
            let start = rng.random_range(0..m3);
            for i in 0..m3 {
                let s = (start + i) % m3;
                if keys[s] != EMPTY_KEY {
                    continue;
                }
                let sv = UVec3::new((s % m as usize) as u32, ((s / m as usize) % m as usize) as u32, (s / (m as usize * m as usize)) as u32);
                let phi = wrap(sv + UVec3::splat(m) - h0, m);
                if fits(phi, &keys, &mut slots) {
                    found = Some(phi);
                    break;
                }
            }
        }
        let phi = found?;
        for (&p, &s) in bucket.iter().zip(&slots) {
            keys[s] = pack(p);
        }
        offsets[b] = pack(phi);
    }
    Some((keys, offsets))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    fn random_set(rng: &mut SmallRng, grid: u32, fill: f64) -> Vec<UVec3> {
        let mut set = HashSet::new();
        let target = ((grid + 1).pow(3) as f64 * fill) as usize;
        while set.len() < target.max(1) {
            set.insert(UVec3::new(rng.random_range(0..=grid), rng.random_range(0..=grid), rng.random_range(0..=grid)));
        }
        set.into_iter().collect()
    }

    #[test]
    fn random_sparse_sets_hash_perfectly() {
        let mut rng = SmallRng::seed_from_u64(7);
        for (case, (grid, fill)) in [(8, 0.3), (16, 0.05), (32, 0.02), (64, 0.004), (40, 0.5), (1, 1.0), (128, 0.0005)].into_iter().enumerate() {
            let points = random_set(&mut rng, grid, fill);
            let table = SpatialHash::build(Aabb::cube(1.0), grid, 2, &points, |p, out| {
                out[0] = p.x as f32;
                out[1] = 1.0;
            }, case as u64)
            .unwrap();
            assert_eq!(table.len(), points.len());
            table.verify().unwrap();
            let members: HashSet<UVec3> = points.iter().copied().collect();
            for p in &points {
                let slot = table.find(*p).expect("member not found");
                assert_eq!(table.values[slot * 2], half::f16::from_f32(p.x as f32).to_f32());
            }
            for _ in 0..2000 {
                let q = UVec3::new(rng.random_range(0..=grid), rng.random_range(0..=grid), rng.random_range(0..=grid));
                assert_eq!(table.find(q).is_some(), members.contains(&q), "{q}");
            }
            // Compactness: the table is barely larger than the set.
            assert!(table.keys.len() as f64 <= points.len() as f64 * 2.0 + 64.0, "{} slots for {}", table.keys.len(), points.len());
        }
    }

    #[test]
    fn duplicates_and_out_of_range_are_errors() {
        let p = UVec3::new(1, 2, 3);
        let err = SpatialHash::build(Aabb::cube(1.0), 8, 1, &[p, UVec3::ONE, p], |_, _| {}, 1).unwrap_err();
        assert_eq!(err, PshError::Duplicate(p));
        let far = UVec3::new(2000, 0, 0);
        assert_eq!(SpatialHash::build(Aabb::cube(1.0), 8, 1, &[far], |_, _| {}, 1).unwrap_err(), PshError::OutOfRange(far));
    }

    #[test]
    fn tampering_is_detected() {
        let mut rng = SmallRng::seed_from_u64(3);
        let points = random_set(&mut rng, 16, 0.1);
        let table = SpatialHash::build(Aabb::cube(1.0), 16, 1, &points, |_, o| o[0] = 1.0, 3).unwrap();
        let mut t = table.clone();
        let i = t.offsets.iter().position(|&o| o != 0).unwrap();
        t.offsets[i] ^= 1;
        assert!(t.verify().is_err());
        let mut t = table.clone();
        let s = t.keys.iter().position(|&k| k != EMPTY_KEY).unwrap();
        let e = t.keys.iter().position(|&k| k == EMPTY_KEY).unwrap();
        t.keys.swap(s, e);
        assert!(t.verify().is_err());
    }

    #[test]
    fn encoding_blends_corners_and_absent_vertices_are_zero() {
        let points = [UVec3::new(0, 0, 0), UVec3::new(1, 0, 0)];
        let table = SpatialHash::build(Aabb { min: Vec3::ZERO, max: Vec3::splat(2.0) }, 2, 1, &points, |_, o| o[0] = 1.0, 9).unwrap();
        let mut out = [0.0];
        table.encode(Vec3::new(0.5, 0.0, 0.0), &mut out);
        assert!((out[0] - 1.0).abs() < 1e-6);
        table.encode(Vec3::new(0.5, 0.5, 0.0), &mut out);
        assert!((out[0] - 0.5).abs() < 1e-6);
        table.encode(Vec3::new(1.5, 1.5, 1.5), &mut out);
        assert_eq!(out[0], 0.0);
    }
}
