//! The march rule an asset is trained with and stores beside its cubes: which parts of a
//! ray's weight get a network query ([`HitRule`], docs/architecture.md §3 "adaptive
//! multi-hit") and where the march stops ([`DEFAULT_EARLY_STOP`] for assets that name none).
//! The asset format ([`crate::asset`]) and the per-ray maths ([`crate::model`]) both build on
//! it, so neither needs the other's internals.

/// The early stop of assets that name none (every asset made before December 2026).
pub const DEFAULT_EARLY_STOP: f32 = 1e-3;

/// Most queries one ray can get (the size of the per-ray hit arrays, CPU and GPU).
pub const MAX_HITS: usize = 3;

/// Which segments of a ray's weight get a network query (the multi-hit notes of [`crate::model`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HitRule {
    /// A segment other than the primary is queried if it holds at least `tau · α_c` of the
    /// weight; 1 = one hit per ray.
    pub tau: f32,
    /// Most queries per ray, 1..=[`MAX_HITS`].
    pub max_hits: u32,
    /// A sample more than this many steps past the current segment's peak starts a new one.
    pub gap_steps: f32,
}

impl Default for HitRule {
    /// One hit per ray (NEPHELE's i-NOLF).
    fn default() -> Self {
        Self { tau: 1.0, max_hits: 1, gap_steps: 3.0 }
    }
}

impl HitRule {
    pub fn one_hit(&self) -> bool {
        self.tau >= 1.0 || self.max_hits <= 1
    }
    pub fn validate(&self) -> Result<(), String> {
        let ok = (0.0..=1.0).contains(&self.tau) && (1..=MAX_HITS as u32).contains(&self.max_hits) && self.gap_steps.is_finite() && (0.5..=64.0).contains(&self.gap_steps);
        if ok { Ok(()) } else { Err(format!("hit rule out of range (τ in [0, 1], max_hits 1..={MAX_HITS}, gap_steps 0.5..=64): {self:?}")) }
    }
}
