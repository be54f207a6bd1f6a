//! NEPHELE's multi-user scheduler (Luo et al., arXiv 2303.04086, §6.2, Algorithm 1), as
//! pure functions and small state the core owns.
//!
//! Per user `i`: the target rate `FPS_i` from its `join`; `t_i`, the moving average of its
//! job time (render + encode + send of its frames); the slack `w_i = 1/FPS_i − t_i`; and
//! `target_time_i = T_last_frame_i + w_i`, the latest moment its next job may start and
//! still finish one period after the last frame. A user whose target time has passed while
//! it waits for a frame is *starved*.
//!
//! Each round (whenever a worker can take work): users ready for a frame are sorted —
//! starved first, then fewer tasks already loaded on the farm, then earlier target time —
//! and the farm is filled with them: every starved user (they are late already; holding one
//! back only makes it later, and one batch renders them faster than one task each), then
//! others until the round's ray budget (the farm's measured rays per second times the
//! shortest frame period among them) is spent. Users of one scene share a task; shared tasks go before dedicated ones, heavy
//! before light.
//!
//! Quality before frame rate: with dynamic resolution the scheduler lowers every moving
//! user's render scale by one common factor so that the predicted load fits the measured
//! throughput ([`fair_scale`]), never below the configured minimum, and never so large that
//! one frame alone would exceed the frame budget. Admission refuses a newcomer while anyone
//! is starved beyond [`STARVED_GRACE`] of a period, or when the users already admitted
//! could not all be served at their lowest scale with the newcomer added.

use std::time::{Duration, Instant};

/// How large to render before upscaling to the stream size: the speed/accuracy knob.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RenderScale {
    /// Always this fraction of the stream's width and height (1 = exact).
    Fixed(f32),
    /// Dynamic resolution: the scheduler picks the scale (fairly across users) so that the
    /// farm keeps up and a frame renders in about `budget_ms`; never below `min`.
    Auto { budget_ms: f64, min: f32 },
}

impl RenderScale {
    /// Parses `auto` or a number in 0.05..=1.
    pub fn parse(s: &str, budget_ms: f64) -> Result<Self, String> {
        if s == "auto" {
            if !(1.0..=10_000.0).contains(&budget_ms) {
                return Err(format!("frame budget {budget_ms} ms should be in 1..=10000"));
            }
            return Ok(Self::Auto { budget_ms, min: 0.25 });
        }
        match s.parse::<f32>() {
            Ok(v) if (0.05..=1.0).contains(&v) => Ok(Self::Fixed(v)),
            _ => Err(format!("render scale {s:?} should be auto or a number in 0.05..=1")),
        }
    }

    /// The lowest scale a user may be served at.
    pub fn floor(&self) -> f32 {
        match *self {
            Self::Fixed(s) => s,
            Self::Auto { min, .. } => min,
        }
    }
}

/// A starved user counts against admission once it is this fraction of its period late.
pub const STARVED_GRACE: f64 = 0.5;
/// Share of the measured throughput the fair scale plans to use (the rest absorbs noise).
pub const TARGET_UTILISATION: f64 = 0.85;
/// Scales move in steps of 1/32 of the stream size (so they settle instead of jittering).
pub const SCALE_STEP: f32 = 1.0 / 32.0;
/// Most users in one round (bounds a task's buffers).
pub const MAX_ROUND_USERS: usize = 64;

/// Exponential moving average.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ema {
    value: Option<f64>,
    /// Weight of each new sample.
    alpha: f64,
}

impl Ema {
    pub const fn new(alpha: f64) -> Self {
        Self { value: None, alpha }
    }

    pub fn observe(&mut self, x: f64) {
        if !x.is_finite() {
            return;
        }
        self.value = Some(match self.value {
            None => x,
            Some(v) => v + self.alpha * (x - v),
        });
    }

    pub fn get(&self) -> Option<f64> {
        self.value
    }
}

/// Algorithm 1's per-user clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UserClock {
    pub fps: u32,
    /// `t_i`: moving average of the job time, seconds.
    pub job_time_s: Ema,
    /// `T_last_frame`: when the user's last frame went out (or when it joined).
    pub last_frame_at: Instant,
    /// Moving average of the time between frames, seconds.
    pub interval_s: Ema,
    /// Frames delivered.
    pub frames: u64,
    /// When the user, idle until then, asked for a frame again (a pose after a pause): the
    /// target time counts from here, not from a frame long ago.
    pub waiting_since: Option<Instant>,
}

impl UserClock {
    pub fn new(fps: u32, now: Instant) -> Self {
        Self { fps: fps.max(1), job_time_s: Ema::new(0.2), last_frame_at: now, interval_s: Ema::new(0.1), frames: 0, waiting_since: None }
    }

    pub fn period_s(&self) -> f64 {
        1.0 / f64::from(self.fps)
    }

    /// `w_i = 1/FPS_i − t_i` (negative when a job takes longer than a period).
    pub fn slack_s(&self) -> f64 {
        self.period_s() - self.job_time_s.get().unwrap_or(0.0)
    }

    /// `target_time = T_last_frame + w_i` (from the end of a pause, if later).
    pub fn target_time(&self) -> Instant {
        let since = self.waiting_since.map_or(self.last_frame_at, |w| w.max(self.last_frame_at));
        offset(since, self.slack_s())
    }

    /// How late the user is against its target time (zero if not yet).
    pub fn lateness(&self, now: Instant) -> Duration {
        now.saturating_duration_since(self.target_time())
    }

    /// A frame went out at `now` after a job of `job_s` seconds.
    pub fn frame_sent(&mut self, now: Instant, job_s: f64) {
        if self.frames > 0 {
            self.interval_s.observe(now.saturating_duration_since(self.last_frame_at).as_secs_f64());
        }
        self.job_time_s.observe(job_s);
        self.last_frame_at = now;
        self.frames += 1;
    }

    /// Achieved frames per second (moving average), 0 before two frames.
    pub fn achieved_fps(&self) -> f64 {
        self.interval_s.get().map_or(0.0, |s| if s > 0.0 { 1.0 / s } else { 0.0 })
    }
}

/// `t + seconds`, for negative seconds too.
pub fn offset(t: Instant, seconds: f64) -> Instant {
    let d = Duration::from_secs_f64(seconds.abs().min(1e6));
    if seconds >= 0.0 { t + d } else { t.checked_sub(d).unwrap_or(t) }
}

/// A ready user as the round planner sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    pub session: String,
    pub starved: bool,
    /// Tasks of this user already on the farm.
    pub loaded_tasks: u32,
    pub target_time: Instant,
    /// Rays its next frame will cost.
    pub rays: u64,
    pub fps: u32,
}

/// Algorithm 1's order: starved first, then fewer loaded tasks, then earlier target time
/// (then session id, so the order is total).
pub fn sort_candidates(c: &mut [Candidate]) {
    c.sort_by(|a, b| {
        b.starved
            .cmp(&a.starved)
            .then(a.loaded_tasks.cmp(&b.loaded_tasks))
            .then(a.target_time.cmp(&b.target_time))
            .then(a.session.cmp(&b.session))
    });
}

/// How many of the sorted candidates go into this round: every starved one, then others
/// while the rays fit `rays_per_s ×` the shortest frame period of the candidates; always at
/// least one, at most [`MAX_ROUND_USERS`].
pub fn round_size(sorted: &[Candidate], rays_per_s: f64) -> usize {
    let Some(round_s) = sorted.iter().map(|c| 1.0 / f64::from(c.fps.max(1))).reduce(f64::min) else { return 0 };
    let budget = rays_per_s.max(0.0) * round_s;
    let mut spent = 0.0;
    let mut n = 0;
    for c in sorted.iter().take(MAX_ROUND_USERS) {
        let rays = c.rays as f64;
        if n > 0 && !c.starved && spent + rays > budget {
            break;
        }
        spent += rays;
        n += 1;
    }
    n
}

/// What one admitted user asks of the farm, for the fair scale and admission.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Demand {
    /// Pixels per frame at full size.
    pub pixels: f64,
    pub fps: f64,
    /// Its render scale is fixed at this value (no dynamic resolution).
    pub fixed_scale: Option<f32>,
    /// Moving now (a still camera reuses its last frame and costs nothing).
    pub active: bool,
}

impl Demand {
    /// Rays per second at `scale`.
    pub fn rays_per_s(&self, scale: f32) -> f64 {
        self.pixels * self.fps * f64::from(scale * scale)
    }
}

/// The common scale for moving users with dynamic resolution: the largest `s` (a multiple of
/// [`SCALE_STEP`], within `[min, 1]`) with `Σ fixed + Σ auto·s² ≤ TARGET_UTILISATION × R`.
pub fn fair_scale(demands: &[Demand], rays_per_s: f64, min: f32) -> f32 {
    let budget = TARGET_UTILISATION * rays_per_s.max(0.0);
    let fixed: f64 = demands.iter().filter(|d| d.active).filter_map(|d| d.fixed_scale.map(|s| d.rays_per_s(s))).sum();
    let auto: f64 = demands.iter().filter(|d| d.active && d.fixed_scale.is_none()).map(|d| d.rays_per_s(1.0)).sum();
    if auto <= 0.0 {
        return 1.0;
    }
    let s = ((budget - fixed).max(0.0) / auto).sqrt() as f32;
    quantise(s, min)
}

/// A user's own cap: one frame of `pixels` at the returned scale renders in about
/// `budget_ms` at `rays_per_s`.
pub fn latency_scale(pixels: f64, rays_per_s: f64, budget_ms: f64, min: f32) -> f32 {
    if pixels <= 0.0 {
        return 1.0;
    }
    quantise((budget_ms / 1e3 * rays_per_s.max(0.0) / pixels).sqrt() as f32, min)
}

fn quantise(s: f32, min: f32) -> f32 {
    let s = if s.is_finite() { s } else { 1.0 };
    ((s / SCALE_STEP).floor() * SCALE_STEP).clamp(min, 1.0)
}

/// Whether `newcomer` fits beside `admitted`, all at their lowest scales, within the
/// utilisation target of `rays_per_s`. Returns the rays/s it would need and the free rays/s.
pub fn fits(admitted: &[Demand], newcomer: &Demand, floor: f32, rays_per_s: f64) -> (bool, f64, f64) {
    let floor_of = |d: &Demand| d.fixed_scale.unwrap_or(floor);
    let used: f64 = admitted.iter().map(|d| d.rays_per_s(floor_of(d))).sum();
    let free = TARGET_UTILISATION * rays_per_s.max(0.0) - used;
    let need = newcomer.rays_per_s(floor_of(newcomer));
    (need <= free, need, free)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(t: Instant, ms: u64) -> Instant {
        t + Duration::from_millis(ms)
    }

    #[test]
    fn target_time_is_last_frame_plus_slack() {
        let t0 = Instant::now();
        let mut c = UserClock::new(25, t0);
        assert_eq!(c.target_time(), ms(t0, 40));
        c.frame_sent(ms(t0, 50), 0.010);
        // w = 40 − 10 ms → target 30 ms after the frame.
        assert_eq!(c.target_time(), ms(t0, 80));
        assert_eq!(c.lateness(ms(t0, 79)), Duration::ZERO);
        assert_eq!(c.lateness(ms(t0, 90)), Duration::from_millis(10));
        // A job longer than a period makes the slack negative: the target is before the frame.
        let mut slow = UserClock::new(50, t0);
        slow.frame_sent(ms(t0, 100), 0.060);
        assert_eq!(slow.target_time(), ms(t0, 60));
        c.frame_sent(ms(t0, 90), 0.010);
        assert!((c.achieved_fps() - 25.0).abs() < 1e-9);
        // After a pause, the target counts from when the user asked again.
        c.waiting_since = Some(ms(t0, 5000));
        assert_eq!(c.target_time(), ms(t0, 5030));
    }

    fn cand(session: &str, starved: bool, loaded: u32, target_ms: u64, rays: u64, t0: Instant) -> Candidate {
        Candidate { session: session.into(), starved, loaded_tasks: loaded, target_time: ms(t0, target_ms), rays, fps: 25 }
    }

    #[test]
    fn starved_first_then_loaded_then_target() {
        let t0 = Instant::now();
        let mut c = vec![
            cand("a", false, 0, 10, 1, t0),
            cand("b", true, 1, 50, 1, t0),
            cand("c", false, 0, 5, 1, t0),
            cand("d", false, 1, 0, 1, t0),
            cand("e", true, 0, 60, 1, t0),
        ];
        sort_candidates(&mut c);
        let order: Vec<&str> = c.iter().map(|c| c.session.as_str()).collect();
        assert_eq!(order, ["e", "b", "c", "a", "d"]);
    }

    #[test]
    fn rounds_take_every_starved_user_then_fill_the_budget() {
        let t0 = Instant::now();
        // 1 M rays/s, 25 fps → 40 000 rays per round.
        let c = [cand("a", false, 0, 0, 30_000, t0), cand("b", false, 0, 0, 30_000, t0)];
        assert_eq!(round_size(&c, 1e6), 1);
        let c = [cand("a", false, 0, 0, 20_000, t0), cand("b", false, 0, 0, 20_000, t0), cand("c", false, 0, 0, 1, t0)];
        assert_eq!(round_size(&c, 1e6), 2);
        // Starved users all go, past the budget; then the budget holds again.
        let c = [cand("a", true, 0, 0, 60_000, t0), cand("b", true, 0, 0, 60_000, t0), cand("c", false, 0, 0, 1, t0)];
        assert_eq!(round_size(&c, 1e6), 2);
        let many: Vec<Candidate> = (0..100).map(|i| cand(&format!("u{i}"), true, 0, 0, 200_000, t0)).collect();
        assert_eq!(round_size(&many, 1e6), MAX_ROUND_USERS);
        // One user always goes, however large; nothing measured yet still renders.
        assert_eq!(round_size(&[cand("a", false, 0, 0, 1 << 30, t0)], 1e6), 1);
        assert_eq!(round_size(&[cand("a", false, 0, 0, 5, t0), cand("b", false, 0, 0, 5, t0)], 0.0), 1);
        assert_eq!(round_size(&[], 1e6), 0);
    }

    #[test]
    fn fair_scale_lowers_quality_evenly_before_frame_rate() {
        let d = |pixels: f64, fixed: Option<f32>| Demand { pixels, fps: 25.0, fixed_scale: fixed, active: true };
        // Two 640×480 users at 25 fps want 15.36 M rays/s; 85% of 3.5 M → s² = 0.194, s = 0.44.
        let users = [d(307_200.0, None), d(307_200.0, None)];
        let s = fair_scale(&users, 3.5e6, 0.25);
        assert_eq!(s, 0.4375);
        let load: f64 = users.iter().map(|u| u.rays_per_s(s)).sum();
        assert!(load <= TARGET_UTILISATION * 3.5e6);
        // Plenty of room: full size. No room: the floor. Fixed users take theirs first.
        assert_eq!(fair_scale(&users, 1e9, 0.25), 1.0);
        assert_eq!(fair_scale(&users, 1.0, 0.25), 0.25);
        let mixed = [d(307_200.0, Some(1.0)), d(307_200.0, None)];
        assert_eq!(fair_scale(&mixed, 7.68e6 / TARGET_UTILISATION, 0.25), 0.25);
        // Resting users cost nothing.
        let resting = [Demand { active: false, ..d(307_200.0, None) }, d(307_200.0, None)];
        assert_eq!(fair_scale(&resting, 7.68e6 / TARGET_UTILISATION, 0.25), 1.0);
        assert_eq!(fair_scale(&[], 0.0, 0.25), 1.0);
        assert_eq!(fair_scale(&users, f64::NAN, 0.25), 0.25);
        // Latency cap: 307 200 px at 2 M rays/s within 30 ms → s = 0.44 → 0.4375.
        assert_eq!(latency_scale(307_200.0, 2e6, 30.0, 0.25), 0.4375);
        assert_eq!(latency_scale(100.0, 2e6, 30.0, 0.25), 1.0);
    }

    #[test]
    fn admission_counts_everyone_at_the_floor() {
        let d = |pixels: f64| Demand { pixels, fps: 25.0, fixed_scale: None, active: true };
        // At scale 0.25 a 640×480 user at 25 fps needs 480 000 rays/s.
        let admitted = [d(307_200.0), d(307_200.0)];
        let (ok, need, free) = fits(&admitted, &d(307_200.0), 0.25, 1.2e6);
        assert!(!ok && (need - 480_000.0).abs() < 1e-6 && (free - (1.02e6 - 960_000.0)).abs() < 1e-3, "{need} {free}");
        assert!(fits(&admitted, &d(307_200.0), 0.25, 2e6).0);
        // A fixed-scale user counts at its own scale.
        let fixed = Demand { fixed_scale: Some(1.0), ..d(307_200.0) };
        assert!(!fits(&[], &fixed, 0.25, 7e6).0 && fits(&[], &fixed, 0.25, 1e7).0);
    }
}
