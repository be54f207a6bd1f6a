//! The i-NOLF per-ray maths of docs/architecture.md §3, written once in plain Rust. The CPU reference
//! renders with it directly; the WGSL kernels (`shaders/*.wgsl`) transcribe the same steps
//! and are tested against it.
//!
//! 1. clip the object-space ray to the box → `[t0, t1]`;
//! 2. DDA over the density index grid (Amanatides & Woo), fixed samples `t_k = t0 + (k+½)δ`
//!    only in occupied cells, each read from the brick of the cell the DDA is in; `α_k = 1 − exp(−σ_k δ)`, `w_k = T_k α_k`; the hit is the sample
//!    of largest weight, `α_c = 1 − T`; stop once `T < early_stop` (`α_c` then within
//!    `early_stop` of `1 − T_end`) or, if enabled, `T < stop_ratio·w_max` (the hit stays exact:
//!    no later weight can exceed `T`; `α_c` may fall short);
//! 3. at the hit: diffuse cubes → `c_d`, tint; PSH → E_s; SH4(dir) → E_v; MLP → `c_s`, α;
//!    `c = clamp(c_d + t·c_s, 0, 1)`, pixel `= α c + (1 − α) bg`.
//!
//! **Adaptive multi-hit** (docs/architecture.md §3, beyond the paper; [`HitRule`]): the same march also
//! splits the weights into segments ([`Segments`]): a sample more than `gap_steps` steps
//! past the current segment's peak starts a new segment. The segment holding the
//! max-weight sample is the primary hit (at that sample, exactly the one-hit rule); every
//! other segment holding at least `τ·α_c` of the weight, heaviest first, gets a query at
//! its own peak, up to `max_hits` in all. Each query is shaded as in 3 (same `α_c` input),
//! and the pixel and α are the queries' results blended by segment weight (normalised over
//! the queried segments). τ = 1 or `max_hits` = 1 is the one-hit renderer, and runs
//! [`march`] without segment tracking.

use glam::{IVec3, Vec3};

pub use crate::rule::{DEFAULT_EARLY_STOP, HitRule, MAX_HITS};
use crate::{asset::{Asset, MarchMeta}, cubes::Aabb, cubes::TextureCubes, mlp::sigmoid, sh::sh4};

/// Stand-in for infinity that survives GPU fast-math (WGSL does not promise IEEE infinities).
pub const BIG: f32 = 1e30;
/// Direction components smaller than this count as zero.
pub const TINY_DIR: f32 = 1e-12;

/// Runtime knobs users trade speed against accuracy with.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RenderSettings {
    /// Multiplies the asset's step δ.
    pub step_scale: f32,
    /// Also stop marching when `T < stop_ratio · w_max`: any value ≤ 1 keeps the hit point
    /// exact (no later weight can exceed `T`) but leaves `α_c` short by up to `T`; 0 disables it.
    pub stop_ratio: f32,
    /// Stop marching when `T < early_stop` (bounds the error of `α_c`); `None` uses the
    /// asset's own threshold, the one it was trained with ([`MarchMeta::early_stop`]).
    #[serde(default)]
    pub early_stop: Option<f32>,
    /// Miss threshold on `α_c`; `None` uses the asset's.
    pub alpha_min: Option<f32>,
    /// Multi-hit threshold τ and most queries per ray; `None` uses the asset's.
    #[serde(default)]
    pub hit_tau: Option<f32>,
    #[serde(default)]
    pub max_hits: Option<u32>,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self { step_scale: 1.0, stop_ratio: 0.0, early_stop: None, alpha_min: None, hit_tau: None, max_hits: None }
    }
}

impl RenderSettings {
    pub fn validate(&self) -> Result<(), String> {
        let ok = self.step_scale.is_finite()
            && (0.05..=20.0).contains(&self.step_scale)
            && (0.0..=1.0).contains(&self.stop_ratio)
            && self.early_stop.is_none_or(|e| (0.0..1.0).contains(&e))
            && self.alpha_min.is_none_or(|a| (0.0..1.0).contains(&a))
            && self.hit_tau.is_none_or(|t| (0.0..=1.0).contains(&t))
            && self.max_hits.is_none_or(|m| (1..=MAX_HITS as u32).contains(&m));
        if ok { Ok(()) } else { Err(format!("render settings out of range: {self:?}")) }
    }

    /// These settings with the asset's own early stop where they name none: what every
    /// backend marches with.
    pub fn for_asset(&self, march: &MarchMeta) -> Self {
        Self { early_stop: Some(self.early_stop.unwrap_or(march.early_stop)), ..*self }
    }

    /// The march's stop threshold on transmittance (settings not yet made
    /// [`for_asset`](Self::for_asset): [`DEFAULT_EARLY_STOP`]).
    #[inline(always)]
    pub fn stop_below(&self) -> f32 {
        self.early_stop.unwrap_or(DEFAULT_EARLY_STOP)
    }

    /// The asset's hit rule with this render's overrides.
    pub fn hit_rule(&self, asset: &HitRule) -> HitRule {
        HitRule { tau: self.hit_tau.unwrap_or(asset.tau), max_hits: self.max_hits.unwrap_or(asset.max_hits), ..*asset }
    }
}

/// Segments remembered while marching; the queried ones are chosen from them at the end.
pub const MAX_SEGMENTS: usize = 4;

/// Ray/box intersection `[t_near, t_far]`, or `None`. Zero direction components are handled
/// without infinities or NaN.
pub fn clip_ray(bounds: &Aabb, o: Vec3, d: Vec3) -> Option<(f32, f32)> {
    let (mut t_near, mut t_far) = (-BIG, BIG);
    for a in 0..3 {
        if d[a].abs() < TINY_DIR {
            if o[a] < bounds.min[a] || o[a] > bounds.max[a] {
                return None;
            }
        } else {
            let ta = (bounds.min[a] - o[a]) / d[a];
            let tb = (bounds.max[a] - o[a]) / d[a];
            t_near = t_near.max(ta.min(tb));
            t_far = t_far.min(ta.max(tb));
        }
    }
    let t0 = t_near.max(0.0);
    (t_far > t0).then_some((t0, t_far))
}

/// Result of marching one ray through the density cubes.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct MarchHit {
    /// Object-space ray parameter of the max-weight sample.
    pub t_hit: f32,
    /// Coarse opacity `1 − T` where marching stopped.
    pub alpha_c: f32,
    pub w_max: f32,
    /// Density samples taken (for the benchmark).
    pub samples: u32,
}

/// Marches the density cubes along `o + t·d` with step `step`.
pub fn march(density: &TextureCubes, o: Vec3, d: Vec3, step: f32, s: &RenderSettings) -> MarchHit {
    march_with(density, o, d, step, s, &mut ())
}

/// [`march`], and the ray's queries under `rule` ([`MultiHit`]); with a one-hit rule,
/// exactly [`march`] with its hit as the only query.
pub fn march_multi(density: &TextureCubes, o: Vec3, d: Vec3, step: f32, s: &RenderSettings, rule: &HitRule) -> MultiHit {
    if rule.one_hit() {
        return MultiHit::one(march(density, o, d, step, s));
    }
    let mut segments = Segments::new(rule.gap_steps * step);
    let m = march_with(density, o, d, step, s, &mut segments);
    segments.choose(m, rule)
}

/// What the march tells a hit tracker about each sample.
pub trait Tracker {
    /// Sample at `t` of weight `w`; `new_max`: it is the heaviest so far.
    fn sample(&mut self, t: f32, w: f32, new_max: bool);
}

/// The one-hit march tracks nothing beyond its own maximum.
impl Tracker for () {
    #[inline(always)]
    fn sample(&mut self, _t: f32, _w: f32, _new_max: bool) {}
}

/// A run of samples: its summed weight, its heaviest sample, and where it starts and ends.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Segment {
    pub weight: f32,
    pub peak_w: f32,
    pub peak_t: f32,
    pub first_t: f32,
    pub last_t: f32,
}

/// Where a closing segment of weight `weight` goes among `n` closed ones (`weight_of(i)`;
/// `primary`: the one holding the ray's heaviest sample, already cleared if the closing one
/// takes that role): slot `n` while there is room, else the lightest that is not the primary
/// (the first of equals) if it is lighter or the closing one `is_primary`; `None`: dropped.
/// [`Segments`] and the fast renderer's vectors of closed segments both file by it.
pub fn closed_slot(n: usize, primary: Option<usize>, is_primary: bool, weight: f32, weight_of: impl Fn(usize) -> f32) -> Option<usize> {
    if n < MAX_SEGMENTS {
        return Some(n);
    }
    let lightest = (0..MAX_SEGMENTS).filter(|&i| Some(i) != primary).min_by(|&a, &b| weight_of(a).total_cmp(&weight_of(b))).expect("at most one primary");
    (is_primary || weight_of(lightest) < weight).then_some(lightest)
}

/// The segment tracker of the multi-hit rule: at most [`MAX_SEGMENTS`] closed segments (when
/// full, the lightest one that is not the primary gives way), the open one, and which one
/// holds the max-weight sample.
#[derive(Debug, Clone)]
pub struct Segments {
    gap_t: f32,
    closed: [Segment; MAX_SEGMENTS],
    n_closed: usize,
    open: Option<Segment>,
    open_is_primary: bool,
    primary: Option<usize>,
}

impl Segments {
    /// `gap_t`: the gap in ray-parameter units (`gap_steps · δ`).
    pub fn new(gap_t: f32) -> Self {
        Self { gap_t, closed: [Segment::default(); MAX_SEGMENTS], n_closed: 0, open: None, open_is_primary: false, primary: None }
    }

    /// Makes the first `n` of `closed` (`primary`: the one holding the heaviest sample) the
    /// closed segments, with no open run: for callers that keep the closed
    /// segments themselves (the fast renderer, in vectors) and then [`Self::finish`] the ray.
    pub fn set_closed(&mut self, closed: &[Segment; MAX_SEGMENTS], n: usize, primary: Option<usize>) {
        assert!(n <= MAX_SEGMENTS && primary.is_none_or(|p| p < n), "{n} closed segments, primary {primary:?}");
        // The whole array (a fixed-size copy, no call to `memcpy`); slots from `n` on are unused.
        self.closed = *closed;
        (self.n_closed, self.primary, self.open, self.open_is_primary) = (n, primary, None, false);
    }

    fn close(&mut self) {
        let Some(seg) = self.open.take() else { return };
        let is_primary = std::mem::take(&mut self.open_is_primary);
        self.push_closed(seg, is_primary);
    }

    /// Adds a closed segment: a free slot, or (full) the lightest closed one that is not the
    /// primary gives way, if it is lighter (or `seg` is the primary).
    fn push_closed(&mut self, seg: Segment, is_primary: bool) {
        let slot = closed_slot(self.n_closed, self.primary, is_primary, seg.weight, |i| self.closed[i].weight);
        if let Some(i) = slot {
            self.n_closed = self.n_closed.max(i + 1);
            self.closed[i] = seg;
            if is_primary {
                self.primary = Some(i);
            }
        }
    }

    /// Closes `run` as [`Tracker::sample`] would have closed it, had it been the open run
    /// (`is_primary`: it holds the ray's heaviest sample so far), for callers that track the
    /// open run themselves (the fast renderer, 8 rays at a time): at a sample past the gap,
    /// and at the ray's end (where [`Self::select`] would close it).
    pub fn close_run(&mut self, run: Segment, is_primary: bool) {
        if is_primary {
            self.primary = None;
        }
        (self.open, self.open_is_primary) = (None, false);
        self.push_closed(run, is_primary);
    }

    /// The segments queried under `rule` for a ray of coarse opacity `alpha_c`, primary
    /// first, and how many there are (0 without any weight).
    pub fn select(&mut self, alpha_c: f32, rule: &HitRule) -> ([Segment; MAX_HITS], usize) {
        self.close();
        let Some(p) = self.primary else { return ([Segment::default(); MAX_HITS], 0) };
        let mut chosen = [self.closed[p]; MAX_HITS];
        let mut n = 1;
        // The heaviest segment not taken yet, again and again (the first of equals), as
        // `march.wgsl` does: no allocation per ray.
        let mut taken = [false; MAX_SEGMENTS];
        taken[p] = true;
        while n < (rule.max_hits as usize).min(MAX_HITS) {
            let best = (0..self.n_closed).filter(|&i| !taken[i]).fold(None, |best: Option<usize>, i| match best {
                Some(b) if self.closed[b].weight >= self.closed[i].weight => Some(b),
                _ => Some(i),
            });
            let Some(best) = best.filter(|&b| self.closed[b].weight >= rule.tau * alpha_c) else { break };
            taken[best] = true;
            chosen[n] = self.closed[best];
            n += 1;
        }
        (chosen, n)
    }

    /// [`Self::choose`] for a caller that tracks the open run itself ([`Self::close_run`]):
    /// `run` is the ray's last run if it is still open (and whether it holds the heaviest
    /// sample), and `self` is left empty for the next ray. Two cases skip the bookkeeping
    /// with what `choose` gives them: a ray whose only run is that one gets its peak as the
    /// only query, β = 1 (most rays that hit: 2% of a lego frame on the fast CPU renderer),
    /// and a ray without any run gets none (rays that met no density: 3%). The others are
    /// chosen in place, not moved out (2%).
    pub fn finish(&mut self, run: Option<(Segment, bool)>, m: MarchHit, rule: &HitRule) -> MultiHit {
        if self.n_closed == 0 && self.open.is_none() {
            match run {
                Some((only, true)) => {
                    let mut out = MultiHit { march: m, count: 1, ..Default::default() };
                    (out.t[0], out.beta[0]) = (only.peak_t, 1.0);
                    return out;
                }
                None => return MultiHit { march: m, ..Default::default() },
                Some((_, false)) => {}
            }
        }
        if let Some((run, is_primary)) = run {
            self.close_run(run, is_primary);
        }
        let out = self.choose_mut(m, rule);
        (self.n_closed, self.open, self.open_is_primary, self.primary) = (0, None, false, None);
        out
    }

    /// The queries under `rule`, from the march's result `m`.
    pub fn choose(mut self, m: MarchHit, rule: &HitRule) -> MultiHit {
        self.choose_mut(m, rule)
    }

    /// [`Self::choose`] on `self` in place (its open run is closed; the caller clears it).
    fn choose_mut(&mut self, m: MarchHit, rule: &HitRule) -> MultiHit {
        let mut out = MultiHit { march: m, ..Default::default() };
        let (chosen, n) = self.select(m.alpha_c, rule);
        let total: f32 = chosen[..n].iter().map(|s| s.weight).sum();
        for (i, seg) in chosen[..n].iter().enumerate() {
            out.t[i] = seg.peak_t;
            out.beta[i] = if total > 0.0 { seg.weight / total } else { 1.0 / n as f32 };
        }
        out.count = n as u32;
        out
    }
}

impl Tracker for Segments {
    #[inline]
    fn sample(&mut self, t: f32, w: f32, new_max: bool) {
        if w.is_nan() || w <= 0.0 {
            return;
        }
        if self.open.is_some_and(|o| t - o.peak_t > self.gap_t) {
            self.close();
        }
        let open = self.open.get_or_insert(Segment { peak_t: t, first_t: t, ..Segment::default() });
        open.weight += w;
        open.last_t = t;
        if w > open.peak_w {
            (open.peak_w, open.peak_t) = (w, t);
        }
        if new_max {
            self.open_is_primary = true;
            self.primary = None;
        }
    }
}

/// A ray's queries: `count` hits at `t[i]` blended by `beta[i]` (summing to 1), the first
/// being the max-weight sample, with the march's result.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct MultiHit {
    pub march: MarchHit,
    pub t: [f32; MAX_HITS],
    pub beta: [f32; MAX_HITS],
    pub count: u32,
}

impl MultiHit {
    /// The one-hit rule: the max-weight sample as the only query (none without weight).
    pub fn one(m: MarchHit) -> Self {
        let mut out = Self { march: m, count: u32::from(m.w_max > 0.0), ..Default::default() };
        (out.t[0], out.beta[0]) = (m.t_hit, 1.0);
        out
    }
}

/// [`march`] reporting every sample to `tracker`.
pub fn march_with<T: Tracker>(density: &TextureCubes, o: Vec3, d: Vec3, step: f32, s: &RenderSettings, tracker: &mut T) -> MarchHit {
    let mut out = MarchHit::default();
    let Some((t0, t1)) = clip_ray(&density.bounds, o, d) else { return out };
    let b = density.grid as i32;
    let cell_size = density.bounds.size() / b as f32;
    let p0 = o + t0 * d;
    let g = (p0 - density.bounds.min) / cell_size;
    let mut cell = g.floor().as_ivec3().clamp(IVec3::ZERO, IVec3::splat(b - 1));
    let mut dir_step = IVec3::ZERO;
    let mut t_max = Vec3::splat(BIG);
    let mut t_delta = Vec3::splat(BIG);
    for a in 0..3 {
        if d[a].abs() >= TINY_DIR {
            dir_step[a] = if d[a] > 0.0 { 1 } else { -1 };
            let boundary = density.bounds.min[a] + (cell[a] + (d[a] > 0.0) as i32) as f32 * cell_size[a];
            t_max[a] = t0 + (boundary - p0[a]) / d[a];
            t_delta[a] = cell_size[a] / d[a].abs();
        }
    }
    let (mut transmittance, mut w_max, mut t_hit) = (1.0f32, 0.0f32, 0.0f32);
    let mut t_enter = t0;
    let mut k_next = 0i32;
    let mut samples = 0u32;
    'cells: for _ in 0..3 * b + 3 {
        if t_enter >= t1 {
            break;
        }
        let t_exit = t_max.min_element().min(t1);
        let brick = density.brick_at(cell.as_uvec3());
        if brick >= 0 {
            // Samples in this cell read its brick (the DDA's cell, not a re-derived one).
            let cell_f = cell.as_vec3();
            let k_a = k_next.max(((t_enter - t0) / step - 0.5).ceil() as i32);
            let k_b = ((t_exit - t0) / step - 0.5).ceil() as i32;
            for k in k_a..k_b {
                let t = t0 + (k as f32 + 0.5) * step;
                let sigma = density.sample_in_brick::<1>(brick as usize, cell_f, density.to_fine(o + t * d))[0];
                let alpha = 1.0 - (-sigma * step).exp();
                let w = transmittance * alpha;
                let new_max = w > w_max;
                if new_max {
                    w_max = w;
                    t_hit = t;
                }
                tracker.sample(t, w, new_max);
                transmittance *= 1.0 - alpha;
                samples += 1;
                if transmittance < s.stop_ratio * w_max || transmittance < s.stop_below() {
                    break 'cells;
                }
            }
            k_next = k_next.max(k_b);
        }
        let axis = if t_max.x <= t_max.y && t_max.x <= t_max.z { 0 } else if t_max.y <= t_max.z { 1 } else { 2 };
        cell[axis] += dir_step[axis];
        if cell[axis] < 0 || cell[axis] >= b {
            break;
        }
        t_enter = t_exit;
        t_max[axis] += t_delta[axis];
    }
    out.t_hit = t_hit;
    out.alpha_c = 1.0 - transmittance;
    out.w_max = w_max;
    out.samples = samples;
    out
}

/// Shades a hit: returns `(rgb over bg, α)`.
pub fn shade(asset: &Asset, net: &crate::mlp::MlpKernel, p_hit: Vec3, d: Vec3, alpha_c: f32, bg: Vec3) -> (Vec3, f32) {
    let [r, g, b, tint] = asset.diffuse.sample::<4>(p_hit);
    let features = asset.psh.features as usize;
    let mut x = [0.0f32; crate::mlp::MAX_INPUT];
    asset.psh.encode(p_hit, &mut x[..features]);
    x[features..features + 16].copy_from_slice(&sh4(d));
    x[features + 16] = alpha_c;
    let o = net.forward(&x[..features + 17]);
    let c_s = Vec3::new(sigmoid(o[0]), sigmoid(o[1]), sigmoid(o[2]));
    let alpha = sigmoid(o[3]);
    let c = (Vec3::new(r, g, b) + tint * c_s).clamp(Vec3::ZERO, Vec3::ONE);
    (alpha * c + (1.0 - alpha) * bg, alpha)
}

/// Shades a ray's queries (`o + t[i]·d`) and blends them by segment weight: returns
/// `(rgb over bg, α)`.
pub fn shade_multi(asset: &Asset, net: &crate::mlp::MlpKernel, hits: &MultiHit, o: Vec3, d: Vec3, bg: Vec3) -> (Vec3, f32) {
    let (mut rgb, mut alpha) = (Vec3::ZERO, 0.0);
    for i in 0..hits.count as usize {
        let (c, a) = shade(asset, net, o + hits.t[i] * d, d, hits.march.alpha_c, bg);
        rgb += hits.beta[i] * c;
        alpha += hits.beta[i] * a;
    }
    (rgb, alpha)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finishing_with_an_open_run_is_choosing_after_closing_it() {
        let rule = HitRule { tau: 0.1, max_hits: 3, gap_steps: 3.0 };
        let m = MarchHit { t_hit: 1.5, alpha_c: 0.9, w_max: 0.6, samples: 9 };
        let seg = |t: f32, w: f32| Segment { weight: w, peak_w: w / 2.0, peak_t: t, first_t: t - 0.1, last_t: t + 0.1 };
        // (closed before, the open run and whether it is the primary)
        type Case = (Vec<(Segment, bool)>, Option<(Segment, bool)>);
        let cases: [Case; 5] = [
            (vec![], Some((seg(1.5, 0.7), true))),
            (vec![(seg(1.0, 0.2), false)], Some((seg(1.5, 0.7), true))),
            (vec![(seg(1.5, 0.7), true)], Some((seg(2.5, 0.2), false))),
            (vec![(seg(1.5, 0.7), true), (seg(2.5, 0.1), false)], None),
            (vec![], None),
        ];
        for (closed, run) in cases {
            let mut tracked = Segments::new(0.3);
            for &(s, p) in &closed {
                tracked.close_run(s, p);
            }
            let mut reference = tracked.clone();
            if let Some((s, p)) = run {
                reference.close_run(s, p);
            }
            let want = reference.choose(m, &rule);
            let got = tracked.finish(run, m, &rule);
            assert_eq!((got.count, got.t, got.beta.map(f32::to_bits)), (want.count, want.t, want.beta.map(f32::to_bits)), "{closed:?} {run:?}");
            assert_eq!(tracked.n_closed, 0, "left empty for the next ray");
            assert!(tracked.primary.is_none() && tracked.open.is_none());
        }
    }

    #[test]
    fn clipping_handles_axis_parallel_and_inside_rays() {
        let b = Aabb::cube(1.0);
        assert_eq!(clip_ray(&b, Vec3::new(0.0, 0.0, 5.0), Vec3::new(0.0, 0.0, -1.0)), Some((4.0, 6.0)));
        // Inside the box: starts at 0.
        assert_eq!(clip_ray(&b, Vec3::ZERO, Vec3::X), Some((0.0, 1.0)));
        // Parallel to a face, outside it: miss; on the face plane: hit.
        assert_eq!(clip_ray(&b, Vec3::new(0.0, 2.0, 5.0), Vec3::new(0.0, 0.0, -1.0)), None);
        assert!(clip_ray(&b, Vec3::new(0.0, 1.0, 5.0), Vec3::new(0.0, 0.0, -1.0)).is_some());
        // Pointing away.
        assert_eq!(clip_ray(&b, Vec3::new(0.0, 0.0, 5.0), Vec3::Z), None);
        // Grazing an edge exactly gives an empty or tiny interval, never NaN.
        if let Some((t0, t1)) = clip_ray(&b, Vec3::new(1.0, 1.0, 5.0), Vec3::new(0.0, 0.0, -1.0)) {
            assert!(t0.is_finite() && t1.is_finite());
        }
    }

    /// Feeds `(t, w)` samples to a [`Segments`] tracker as the march would, and chooses.
    fn segments_of(samples: &[(f32, f32)], rule: &HitRule) -> MultiHit {
        let mut seg = Segments::new(rule.gap_steps);
        let (mut w_max, mut t_hit, mut total) = (0.0f32, 0.0, 0.0);
        for &(t, w) in samples {
            let new_max = w > w_max;
            if new_max {
                (w_max, t_hit) = (w, t);
            }
            total += w;
            seg.sample(t, w, new_max);
        }
        seg.choose(MarchHit { t_hit, alpha_c: total, w_max, samples: samples.len() as u32 }, rule)
    }

    fn rule(tau: f32, max_hits: u32) -> HitRule {
        HitRule { tau, max_hits, gap_steps: 3.0 }
    }

    #[test]
    fn segments_split_at_gaps_and_the_primary_is_the_heaviest_sample() {
        // Two surfaces 10 steps apart (t in steps): a thin heavy one, then a thick light one
        // whose summed weight is larger.
        let samples = [(0.0, 0.5), (1.0, 0.1), (10.0, 0.05), (11.0, 0.2), (12.0, 0.15), (13.0, 0.1)];
        let m = segments_of(&samples, &rule(0.1, 3));
        assert_eq!(m.count, 2);
        assert_eq!(m.t[0], 0.0, "the primary query is at the max-weight sample");
        assert_eq!(m.t[1], 11.0, "the second at its segment's peak");
        assert!((m.beta[0] - 0.6 / 1.1).abs() < 1e-6 && (m.beta[1] - 0.5 / 1.1).abs() < 1e-6, "{m:?}");
        // τ above the second segment's share (0.5 / 1.1): one query; τ = 1 likewise.
        assert_eq!(segments_of(&samples, &rule(0.5, 3)).count, 1);
        assert_eq!(segments_of(&samples, &rule(1.0, 3)).count, 1);
        // Within the gap, one segment: a thick shell is one hit until it runs past the gap.
        let shell = [(0.0, 0.3), (1.0, 0.2), (2.0, 0.15), (3.0, 0.1), (4.0, 0.08), (5.0, 0.06)];
        let m = segments_of(&shell, &rule(0.1, 3));
        assert_eq!((m.count, m.t[0], m.t[1]), (2, 0.0, 4.0), "the tail past 3 steps is its own segment: {m:?}");
    }

    #[test]
    fn segments_stay_bounded_and_keep_the_primary() {
        // 40 separate specks, the heaviest in the middle, then heavier ones later: the tracker
        // holds at most MAX_SEGMENTS, keeps the primary, and queries the heaviest others.
        let mut samples: Vec<(f32, f32)> = (0..40).map(|k| (10.0 * k as f32, 0.01 + 0.001 * k as f32)).collect();
        samples[20].1 = 0.5;
        let m = segments_of(&samples, &rule(0.0, 3));
        assert_eq!(m.count, 3);
        assert_eq!(m.t[0], 200.0);
        assert_eq!((m.t[1], m.t[2]), (390.0, 380.0), "{m:?}");
        assert!((m.beta.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        assert!(m.beta.iter().all(|b| b.is_finite() && *b >= 0.0));
        // No weight at all: no query; zero, negative and NaN weights are ignored.
        assert_eq!(segments_of(&[], &rule(0.0, 3)).count, 0);
        assert_eq!(segments_of(&[(0.0, 0.0), (1.0, f32::NAN), (2.0, -1.0)], &rule(0.0, 3)).count, 0);
        // One sample: one query of weight 1.
        let m = segments_of(&[(5.0, 1e-30)], &rule(0.0, 3));
        assert_eq!((m.count, m.t[0], m.beta[0]), (1, 5.0, 1.0));
    }

    #[test]
    fn hit_rules_are_checked() {
        assert!(HitRule::default().validate().is_ok() && HitRule::default().one_hit());
        for bad in [rule(-0.1, 2), rule(1.5, 2), rule(f32::NAN, 2), rule(0.1, 0), rule(0.1, MAX_HITS as u32 + 1), HitRule { gap_steps: f32::INFINITY, ..rule(0.1, 2) }] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
        let s = RenderSettings { hit_tau: Some(2.0), ..Default::default() };
        assert!(s.validate().is_err());
    }
}
