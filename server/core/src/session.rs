//! One user's frame rules, sans-IO (no sockets, no clocks, no threads): the master core
//! feeds it pose bytes, PLIs and finished frames with the time they happened, and asks it
//! whether a frame is wanted, what to render next and when to wake up. The render scale of
//! a moving camera is the scheduler's to choose ([`super::scheduler`]). Tested on simulated
//! time.
//!
//! Rules (docs/architecture.md §5):
//! - a pose is validated before it is kept; a refused pose gets a reason and the session
//!   keeps its last good pose;
//! - latest pose wins: the channel is unordered, so a pose older than the newest seen is
//!   dropped, and a pose superseded before its frame slot is never rendered;
//! - at most `fps` frames per second on average, nothing rendered before the first pose;
//!   frames are pipelined: the next frame may render while the previous one encodes, but at
//!   most one renders and at most [`MAX_IN_FLIGHT`] are in flight, and they finish in order. Frame slots lie on a grid one period apart, so a frame that
//!   started late does not delay the next one (a late start can gain back at most half a
//!   period), and a frame may start up to [`EARLY_START`] of a period before its slot, so
//!   that users whose slots fall close together share a render round;
//! - the first frame is an IDR; PLI/FIR ask for another (at most one per 250 ms);
//! - with dynamic resolution, a camera at rest for [`REFINE_AFTER`] gets one full-size
//!   frame (sent as an IDR), then that frame is reused while the camera stays put;
//! - pose latch ([`Session::with_pose_latch`]): when the waiting pose is nearly a pose
//!   period old, the next one is due within a share of a period: the frame would rather
//!   wait for it (until that share past its due time), so that it shows a pose that is fresh
//!   instead of one a period old ([`Session::latched`]; the core waits only when no other
//!   user starts a round that the frame could share). The period is learnt from the poses'
//!   arrivals.

use std::{
    sync::Arc,
    time::{Duration, Instant},
};

use nephele_renderer::Instance;

pub use nephele_wire::FrameTimes;
use nephele_wire::{FrameInfo, FrameLayout, FrameView, PoseRejection, check_pose};

/// With dynamic resolution, a camera still for this long gets one full-size frame.
pub const REFINE_AFTER: Duration = Duration::from_millis(150);

/// Frames of one session between start and sent: one rendering, one encoding.
pub const MAX_IN_FLIGHT: usize = 2;

/// Share of a frame period a frame may start before its slot.
pub const EARLY_START: f64 = 0.1;

/// Shortest gap between two IDRs forced by picture-loss reports.
pub const IDR_MIN_GAP: Duration = Duration::from_millis(250);

/// A validated pose waiting for its frame: one view or several (stereo eyes, quilt tiles),
/// each with its place in the frame.
#[derive(Debug, Clone, PartialEq)]
pub struct PendingPose {
    pub seq: u32,
    pub t_client_ms: f64,
    /// How far ahead the client predicted these cameras, ms.
    pub predicted_ms: f64,
    pub views: Arc<[FrameView]>,
    pub instance: Instance,
    pub received_at: Instant,
}

impl PendingPose {
    fn same_cameras(&self, other: &PendingPose) -> bool {
        self.views == other.views && self.instance == other.instance
    }
}

/// What the core should do now: render (or reuse) and encode this pose.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameJob {
    pub frame: u64,
    pub pose: PendingPose,
    /// Encode as an IDR (first frame, or a picture-loss report).
    pub idr: bool,
    /// Same camera, placement and scale as the previous frame: its pixels can be reused.
    pub same_as_previous: bool,
    /// Render at this fraction of the stream size, then upscale.
    pub render_scale: f32,
    pub started_at: Instant,
}

/// Counters for the session's life, for logs and tests.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SessionCounters {
    pub poses_accepted: u64,
    pub poses_rejected: u64,
    /// Older than a pose already seen (reordered by the unordered channel).
    pub poses_stale: u64,
    /// Accepted but replaced by a newer pose before a frame slot came.
    pub poses_superseded: u64,
    pub frames: u64,
    pub idrs_requested: u64,
}

/// One user's frame rules.
#[derive(Debug)]
pub struct Session {
    size: (u32, u32),
    layout: FrameLayout,
    frame_period: Duration,
    /// Newest validated pose not yet rendered.
    pending: Option<PendingPose>,
    newest_seq: Option<u32>,
    /// The pose of the newest frame started.
    last_started: Option<PendingPose>,
    /// Frames started and not yet sent, oldest first, with whether each is still rendering.
    in_flight: std::collections::VecDeque<(FrameJob, bool)>,
    /// Earliest start of the next frame.
    next_slot: Option<Instant>,
    idr_wanted: bool,
    last_idr_at: Option<Instant>,
    frame_number: u64,
    counters: SessionCounters,
    /// Dynamic resolution: refine a camera at rest to full size.
    refine_at_rest: bool,
    /// Origin of the slot grid (the first frame's start if not given).
    epoch: Option<Instant>,
    last_scale: f32,
    /// When the camera (or anchor) last changed.
    still_since: Option<Instant>,
    /// Share of the pose period a frame may wait for the next pose (0: never waits).
    pose_latch: f64,
    /// The client's pose period (moving average of the accepted poses' spacing), and when
    /// the last one arrived.
    pose_period: Option<Duration>,
    last_pose_at: Option<Instant>,
}

/// Pose spacings outside this range do not teach the session the pose period (a pause, or
/// a burst).
const POSE_PERIOD_RANGE: std::ops::RangeInclusive<Duration> = Duration::from_millis(2)..=Duration::from_millis(250);

impl Session {
    /// A session at a fixed render scale (no refinement at rest).
    pub fn new(width: u32, height: u32, fps: u32) -> Self {
        Self::with_refinement(width, height, fps, false)
    }

    /// `refine_at_rest`: dynamic resolution, where a still camera gets one full-size frame.
    pub fn with_refinement(width: u32, height: u32, fps: u32, refine_at_rest: bool) -> Self {
        Self::with_epoch(width, height, fps, refine_at_rest, None)
    }

    /// Frame slots at `epoch + k / fps` (shared by every session of a master).
    pub fn with_epoch(width: u32, height: u32, fps: u32, refine_at_rest: bool, epoch: Option<Instant>) -> Self {
        let fps = fps.clamp(nephele_limits::MIN_FPS, nephele_limits::MAX_FPS);
        Self {
            size: (width, height),
            layout: FrameLayout::Views { width, height },
            frame_period: Duration::from_secs_f64(1.0 / f64::from(fps)),
            pending: None,
            newest_seq: None,
            last_started: None,
            in_flight: std::collections::VecDeque::new(),
            next_slot: None,
            idr_wanted: true,
            last_idr_at: None,
            frame_number: 0,
            counters: SessionCounters::default(),
            refine_at_rest,
            epoch,
            last_scale: f32::NAN,
            still_since: None,
            pose_latch: 0.0,
            pose_period: None,
            last_pose_at: None,
        }
    }

    /// Lets a frame wait up to `share` of the pose period for a pose that is due (see the
    /// module notes); 0 never waits.
    pub fn with_pose_latch(mut self, share: f64) -> Self {
        self.pose_latch = if share.is_finite() { share.clamp(0.0, 0.5) } else { 0.0 };
        self
    }

    /// The pose period learnt so far.
    pub fn pose_period(&self) -> Option<Duration> {
        self.pose_period
    }

    /// When the frame would wait for the next pose: `[due − share, due + share)` of a
    /// period, `due` a period after the waiting pose arrived.
    fn latch_window(&self) -> Option<(Instant, Instant)> {
        let (period, pose) = (self.pose_period?, self.pending.as_ref()?);
        if self.pose_latch <= 0.0 || self.idr_wanted {
            return None;
        }
        let (due, share) = (pose.received_at + period, period.mul_f64(self.pose_latch));
        Some((due - share, due + share))
    }

    /// A frame would rather wait for the pose that is due: the core starts no round for
    /// this session alone, but takes it along in a round that others start.
    pub fn latched(&self, now: Instant) -> bool {
        self.latch_window().is_some_and(|(from, to)| (from..to).contains(&now))
    }

    /// Lays the frame out as `layout` (a quilt; the default is the views of each pose).
    pub fn with_layout(mut self, layout: FrameLayout) -> Self {
        self.layout = layout;
        self
    }

    pub fn counters(&self) -> SessionCounters {
        self.counters
    }

    pub fn size(&self) -> (u32, u32) {
        self.size
    }

    /// A pose message arrived. `Ok(false)`: well-formed but older than one already seen.
    pub fn on_pose(&mut self, bytes: &[u8], now: Instant) -> Result<bool, PoseRejection> {
        let msg = match check_pose(bytes, &self.layout) {
            Ok(x) => x,
            Err(e) => {
                self.counters.poses_rejected += 1;
                return Err(e);
            }
        };
        // Serial-number order (RFC 1982): sequence numbers wrap after 2³²−1, and a pose is
        // newer when it is less than 2³¹ ahead.
        if self.newest_seq.is_some_and(|newest| (msg.seq.wrapping_sub(newest) as i32) <= 0) {
            self.counters.poses_stale += 1;
            return Ok(false);
        }
        self.newest_seq = Some(msg.seq);
        self.counters.poses_accepted += 1;
        if let Some(spacing) = self.last_pose_at.map(|t| now.saturating_duration_since(t)).filter(|d| POSE_PERIOD_RANGE.contains(d)) {
            self.pose_period = Some(self.pose_period.map_or(spacing, |p| p.mul_f64(0.875) + spacing.mul_f64(0.125)));
        }
        self.last_pose_at = Some(now);
        if self.pending.is_some() {
            self.counters.poses_superseded += 1;
        }
        let pose = PendingPose { seq: msg.seq, t_client_ms: msg.t_client_ms, predicted_ms: msg.predicted_ms, views: msg.views.into(), instance: msg.instance, received_at: now };
        let previous = self.pending.as_ref().or(self.last_started.as_ref());
        if previous.is_none_or(|p| !p.same_cameras(&pose)) {
            self.still_since = Some(now);
        }
        self.pending = Some(pose);
        Ok(true)
    }

    /// The client lost a picture (RTCP PLI or FIR): the next frame is an IDR. Returns
    /// whether the request was taken (repeats within [`IDR_MIN_GAP`] are ignored).
    pub fn on_picture_loss(&mut self, now: Instant) -> bool {
        if self.idr_wanted || self.last_idr_at.is_some_and(|t| now.duration_since(t) < IDR_MIN_GAP) {
            return false;
        }
        self.idr_wanted = true;
        self.counters.idrs_requested += 1;
        // An IDR must go out even if the camera is still: re-send the last pose.
        true
    }

    /// Something is waiting to be rendered: a new pose, or an owed IDR once a pose was seen.
    pub fn wants_frame(&self) -> bool {
        self.pending.is_some() || (self.idr_wanted && self.last_started.is_some())
    }

    /// [`Self::poll_frame`] would start a frame now.
    pub fn ready(&self, now: Instant) -> bool {
        self.can_start() && self.slot_open(now) && self.wants_frame()
    }

    /// No frame rendering, and room in the pipeline.
    fn can_start(&self) -> bool {
        self.in_flight.len() < MAX_IN_FLIGHT && self.in_flight.iter().all(|(_, rendering)| !rendering)
    }

    fn slot_open(&self, now: Instant) -> bool {
        self.next_slot.is_none_or(|t| now + self.frame_period.mul_f64(EARLY_START) >= t)
    }

    /// Frames rendering or encoding, oldest first.
    pub fn in_flight(&self) -> impl Iterator<Item = &FrameJob> {
        self.in_flight.iter().map(|(job, _)| job)
    }

    /// When the camera last moved (a new pose that differs from the one before).
    pub fn moved_at(&self) -> Option<Instant> {
        self.still_since
    }

    /// The frame to start now, if any: a new pose is waiting (or an IDR is owed and a pose
    /// was ever seen), no frame is rendering, the pipeline has room, and the frame slot has
    /// come. A moving camera renders at `moving_scale` (the scheduler's choice).
    pub fn poll_frame(&mut self, now: Instant, moving_scale: f32) -> Option<FrameJob> {
        if !self.can_start() || !self.slot_open(now) {
            return None;
        }
        let pose = match self.pending.take() {
            Some(p) => p,
            None if self.idr_wanted => self.repeat_pose(now)?,
            None => return None,
        };
        self.frame_number += 1;
        let same_pose = self.last_started.as_ref().is_some_and(|p| p.same_cameras(&pose));
        // Moving: the controller's scale. Still: keep the last pixels, or, with dynamic
        // resolution and a camera at rest for REFINE_AFTER, render once at full size.
        let at_rest = self.refine_at_rest && self.still_since.is_some_and(|t| now.duration_since(t) >= REFINE_AFTER);
        let render_scale = match (same_pose, at_rest) {
            (false, _) => moving_scale,
            (true, true) => 1.0,
            (true, false) => self.last_scale,
        };
        let same_as_previous = same_pose && self.last_scale == render_scale;
        // A refinement is sent as an IDR: the whole picture at the quality a still camera
        // affords, instead of P-frames that keep the motion frames' coding artefacts.
        let refine = same_pose && !same_as_previous;
        let idr = self.idr_wanted || refine;
        let job = FrameJob { frame: self.frame_number, pose: pose.clone(), idr, same_as_previous, render_scale, started_at: now };
        if idr {
            self.last_idr_at = Some(now);
        }
        self.idr_wanted = false;
        // The next slot: the first grid point at least half a period away.
        let epoch = *self.epoch.get_or_insert(now);
        let period = self.frame_period.as_secs_f64();
        let earliest = now.saturating_duration_since(epoch).as_secs_f64() + 0.5 * period;
        self.next_slot = Some(epoch + Duration::from_secs_f64((earliest / period).ceil() * period));
        self.last_started = Some(pose);
        self.last_scale = render_scale;
        self.in_flight.push_back((job.clone(), true));
        Some(job)
    }

    /// `frame`'s pixels are ready (rendered, or reused): it moves on to encoding, and the
    /// next frame may start rendering.
    pub fn rendered(&mut self, frame: u64) {
        if let Some((_, rendering)) = self.in_flight.iter_mut().find(|(j, _)| j.frame == frame) {
            *rendering = false;
        }
    }

    /// `frame` was encoded and sent. Returns the frame info for the client.
    pub fn frame_done(&mut self, frame: u64, times: FrameTimes) -> Option<FrameInfo> {
        let i = self.in_flight.iter().position(|(j, _)| j.frame == frame)?;
        let (job, _) = self.in_flight.remove(i)?;
        self.counters.frames += 1;
        Some(FrameInfo {
            frame: job.frame,
            pose_seq: job.pose.seq,
            t_client_ms: job.pose.t_client_ms,
            width: self.size.0,
            height: self.size.1,
            queue_ms: job.started_at.duration_since(job.pose.received_at).as_secs_f64() * 1e3,
            times,
            render_scale: job.render_scale,
            batch_views: 0,
            reused: false,
            views: job.pose.views.len() as u32,
            predicted_ms: job.pose.predicted_ms,
        })
    }

    /// `frame` failed (render or encode error); the next frame must be an IDR.
    pub fn frame_failed(&mut self, frame: u64) {
        if let Some(i) = self.in_flight.iter().position(|(j, _)| j.frame == frame) {
            self.in_flight.remove(i);
            self.idr_wanted = true;
        }
    }

    /// When the core should call [`Self::poll_frame`] again (asked at `now`), if a frame is
    /// waiting for its slot or for the pose latch to close.
    pub fn next_wakeup(&self, now: Instant) -> Option<Instant> {
        if !self.can_start() || !self.wants_frame() {
            return None;
        }
        let slot = self.next_slot.map(|t| t.checked_sub(self.frame_period.mul_f64(EARLY_START)).unwrap_or(t));
        // A frame that could start inside the latch window waits until the window closes
        // (a pose arriving first wakes the core anyway).
        let earliest = slot.map_or(now, |t| t.max(now));
        match self.latch_window() {
            Some((from, to)) if (from..to).contains(&earliest) => Some(to),
            _ => slot,
        }
    }

    fn repeat_pose(&self, now: Instant) -> Option<PendingPose> {
        self.last_started.clone().map(|p| PendingPose { received_at: now, ..p })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nephele_wire::PoseMessage;
    use glam::DVec3;
    use nephele_renderer::{Intrinsics, View};

    const W: u32 = 64;
    const H: u32 = 48;

    fn pose(seq: u32, azimuth_deg: f64) -> Vec<u8> {
        let view = View::orbit(DVec3::ZERO, 4.0, azimuth_deg, 20.0, Intrinsics::from_fov_x(W, H, 0.8));
        PoseMessage {
            seq,
            t_client_ms: f64::from(seq) * 20.0,
            world_from_camera: view.world_from_camera.as_mat4(),
            intrinsics: view.intrinsics,
            world_from_anchor: None,
            predicted: None,
        }
        .encode()
    }

    fn ms(t0: Instant, ms: u64) -> Instant {
        t0 + Duration::from_millis(ms)
    }

    /// Renders and sends the oldest frame in flight.
    fn finish(s: &mut Session, times: FrameTimes) -> Option<FrameInfo> {
        let frame = s.in_flight().next()?.frame;
        s.rendered(frame);
        s.frame_done(frame, times)
    }

    /// Poses every 20 ms, frames rendering for 26: a frame that would start on a pose 17 ms
    /// old waits for the one due (latch 0.25: from 15 to 25 ms after the old pose), and
    /// starts on it when it comes; if it does not come, the frame starts when the window
    /// closes. Pauses (over 250 ms) teach no period; without a latch nothing waits.
    #[test]
    fn a_frame_waits_for_a_pose_that_is_due() {
        let t0 = Instant::now();
        let mut s = Session::new(W, H, 50).with_pose_latch(0.25);
        for k in 0..5u32 {
            s.on_pose(&pose(k + 1, f64::from(k)), ms(t0, 20 * u64::from(k))).unwrap();
        }
        assert_eq!(s.pose_period(), Some(Duration::from_millis(20)));
        // The first frame (an IDR) never waits.
        let first = s.poll_frame(ms(t0, 80), 1.0).unwrap();
        assert!(first.idr && !s.latched(ms(t0, 80)));
        s.on_pose(&pose(6, 5.0), ms(t0, 100)).unwrap();
        finish(&mut s, FrameTimes::default()).unwrap();
        // At 106 the pose of 100 is 6 ms old: no wait.
        assert!(!s.latched(ms(t0, 106)) && s.ready(ms(t0, 106)));
        let job = s.poll_frame(ms(t0, 106), 1.0).unwrap();
        assert_eq!(job.pose.seq, 6);
        s.on_pose(&pose(7, 6.0), ms(t0, 120)).unwrap();
        finish(&mut s, FrameTimes::default()).unwrap();
        // At 137 the pose of 120 is 17 ms old and the next is due at 140: latched until 145.
        assert!(s.ready(ms(t0, 137)) && s.latched(ms(t0, 137)));
        assert_eq!(s.next_wakeup(ms(t0, 137)), Some(ms(t0, 145)));
        s.on_pose(&pose(8, 7.0), ms(t0, 140)).unwrap();
        assert!(!s.latched(ms(t0, 140)));
        let job = s.poll_frame(ms(t0, 140), 1.0).unwrap();
        assert_eq!((job.pose.seq, job.started_at.duration_since(job.pose.received_at)), (8, Duration::ZERO));
        // The pose due at 180 is late: the window closes at 185 and the frame starts then.
        s.on_pose(&pose(9, 8.0), ms(t0, 160)).unwrap();
        finish(&mut s, FrameTimes::default()).unwrap();
        assert!(s.latched(ms(t0, 177)) && s.latched(ms(t0, 184)) && !s.latched(ms(t0, 185)));
        assert_eq!(s.next_wakeup(ms(t0, 184)), Some(ms(t0, 185)));
        assert_eq!(s.poll_frame(ms(t0, 185), 1.0).unwrap().pose.seq, 9);
        // A pause of a second teaches nothing; a jump in spacing moves the average by 1/8.
        let mut t = Session::new(W, H, 50).with_pose_latch(0.25);
        t.on_pose(&pose(1, 0.0), t0).unwrap();
        t.on_pose(&pose(2, 1.0), ms(t0, 1000)).unwrap();
        assert_eq!(t.pose_period(), None);
        t.on_pose(&pose(3, 2.0), ms(t0, 1020)).unwrap();
        t.on_pose(&pose(4, 3.0), ms(t0, 1060)).unwrap();
        assert_eq!(t.pose_period(), Some(Duration::from_micros(22_500)));
        // Without a latch (the default) a frame never waits.
        let mut u = Session::new(W, H, 50);
        for k in 0..3u32 {
            u.on_pose(&pose(k + 1, f64::from(k)), ms(t0, 20 * u64::from(k))).unwrap();
        }
        assert!(!u.latched(ms(t0, 57)));
    }

    #[test]
    fn nothing_before_the_first_pose_then_an_idr() {
        let t0 = Instant::now();
        let mut s = Session::new(W, H, 50);
        assert_eq!(s.poll_frame(t0, 1.0), None);
        assert_eq!(s.next_wakeup(t0), None);
        // A PLI before any pose does not invent a frame.
        assert!(!s.on_picture_loss(t0));
        assert_eq!(s.poll_frame(ms(t0, 5), 1.0), None);
        s.on_pose(&pose(1, 0.0), ms(t0, 10)).unwrap();
        let job = s.poll_frame(ms(t0, 10), 1.0).unwrap();
        assert!(job.idr && job.frame == 1 && job.pose.seq == 1);
        assert!(!job.same_as_previous);
    }

    #[test]
    fn latest_pose_wins_and_frames_are_paced() {
        let t0 = Instant::now();
        let mut s = Session::new(W, H, 25); // 40 ms period
        s.on_pose(&pose(1, 0.0), t0).unwrap();
        let job = s.poll_frame(t0, 1.0).unwrap();
        // While a frame is in flight, new poses queue; only the newest survives.
        s.on_pose(&pose(2, 1.0), ms(t0, 10)).unwrap();
        s.on_pose(&pose(4, 3.0), ms(t0, 20)).unwrap();
        assert_eq!(s.on_pose(&pose(3, 2.0), ms(t0, 21)), Ok(false), "reordered older pose is dropped");
        assert_eq!(s.poll_frame(ms(t0, 25), 1.0), None, "one frame in flight");
        let info = finish(&mut s, FrameTimes { render_ms: 5.0, ..Default::default() }).unwrap();
        assert_eq!((info.frame, info.pose_seq), (1, 1));
        assert_eq!(info.t_client_ms, 20.0);
        // The slot opens 40 ms after the previous start, less the early-start allowance (4 ms).
        assert_eq!(s.next_wakeup(t0), Some(ms(t0, 36)));
        assert_eq!(s.poll_frame(ms(t0, 35), 1.0), None);
        let job2 = s.poll_frame(ms(t0, 40), 1.0).unwrap();
        assert_eq!((job2.frame, job2.pose.seq), (2, 4));
        assert!(!job2.idr);
        assert!((job2.started_at.duration_since(job2.pose.received_at).as_millis()) == 20);
        let c = s.counters();
        assert_eq!((c.poses_accepted, c.poses_stale, c.poses_superseded), (3, 1, 1));
        let _ = job;
    }

    #[test]
    fn frames_are_pipelined_render_next_while_encoding_and_finish_in_order() {
        let t0 = Instant::now();
        let mut s = Session::new(W, H, 100);
        s.on_pose(&pose(1, 0.0), t0).unwrap();
        let one = s.poll_frame(t0, 1.0).unwrap();
        s.on_pose(&pose(2, 1.0), ms(t0, 5)).unwrap();
        assert!(!s.ready(ms(t0, 10)), "frame 1 is still rendering");
        s.rendered(one.frame);
        let two = s.poll_frame(ms(t0, 10), 1.0).expect("frame 2 renders while frame 1 encodes");
        s.rendered(two.frame);
        s.on_pose(&pose(3, 2.0), ms(t0, 15)).unwrap();
        assert!(!s.ready(ms(t0, 20)), "two frames in flight is the most");
        assert_eq!(s.next_wakeup(t0), None);
        assert_eq!(s.frame_done(one.frame, FrameTimes::default()).unwrap().pose_seq, 1);
        assert!(s.ready(ms(t0, 20)));
        assert_eq!(s.frame_done(two.frame, FrameTimes::default()).unwrap().pose_seq, 2);
        assert_eq!(s.frame_done(two.frame, FrameTimes::default()), None, "each frame is done once");
        // A failure of either frame makes the next one an IDR.
        let three = s.poll_frame(ms(t0, 20), 1.0).unwrap();
        s.frame_failed(three.frame);
        s.on_pose(&pose(4, 3.0), ms(t0, 25)).unwrap();
        assert!(s.poll_frame(ms(t0, 30), 1.0).unwrap().idr);
    }

    #[test]
    fn at_most_fps_frames_per_second_under_a_pose_flood() {
        let t0 = Instant::now();
        let mut s = Session::new(W, H, 30);
        let mut frames = 0;
        let mut seq = 0;
        // Poses every 1 ms for 2 s, rendering takes 3 ms.
        for t in 0..2000u64 {
            seq += 1;
            s.on_pose(&pose(seq, t as f64 * 0.1), ms(t0, t)).unwrap();
            if s.poll_frame(ms(t0, t), 1.0).is_some() {
                frames += 1;
            }
            if t % 3 == 2 {
                finish(&mut s, FrameTimes::default());
            }
        }
        assert!((59..=61).contains(&frames), "{frames} frames in 2 s at 30 fps");
    }

    #[test]
    fn sequence_numbers_wrap() {
        let t0 = Instant::now();
        let mut s = Session::new(W, H, 50);
        for seq in [u32::MAX - 1, u32::MAX, 0, 1] {
            assert_eq!(s.on_pose(&pose(seq, 0.0), t0), Ok(true), "seq {seq} follows");
        }
        assert_eq!(s.on_pose(&pose(u32::MAX, 0.0), t0), Ok(false), "a pose from before the wrap is stale");
        assert_eq!(s.on_pose(&pose(1, 0.0), t0), Ok(false));
    }

    #[test]
    fn bad_poses_are_refused_and_the_last_good_pose_is_kept() {
        let t0 = Instant::now();
        let mut s = Session::new(W, H, 50);
        s.on_pose(&pose(1, 0.0), t0).unwrap();
        let mut nan = pose(2, 5.0);
        nan[20..24].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(s.on_pose(&nan, t0).is_err());
        assert!(s.on_pose(&pose(3, 5.0)[..50], t0).is_err());
        assert!(s.on_pose(&[0u8; 4096], t0).is_err());
        let job = s.poll_frame(t0, 1.0).unwrap();
        assert_eq!(job.pose.seq, 1);
        // A refused pose does not advance the sequence: seq 2 may still come, valid.
        finish(&mut s, FrameTimes::default());
        assert_eq!(s.on_pose(&pose(2, 5.0), ms(t0, 30)), Ok(true));
        assert_eq!(s.counters().poses_rejected, 3);
    }

    #[test]
    fn picture_loss_forces_an_idr_even_for_a_still_camera() {
        let t0 = Instant::now();
        let mut s = Session::new(W, H, 50);
        s.on_pose(&pose(1, 0.0), t0).unwrap();
        s.poll_frame(t0, 1.0).unwrap();
        finish(&mut s, FrameTimes::default());
        assert!(!s.on_picture_loss(ms(t0, 100)), "within 250 ms of the first IDR");
        assert!(s.on_picture_loss(ms(t0, 300)));
        assert!(!s.on_picture_loss(ms(t0, 301)), "already owed");
        assert_eq!(s.next_wakeup(t0), Some(ms(t0, 18)), "the 20 ms slot less the early-start allowance");
        let job = s.poll_frame(ms(t0, 300), 1.0).unwrap();
        assert!(job.idr && job.same_as_previous && job.pose.seq == 1);
        finish(&mut s, FrameTimes::default());
        assert_eq!(s.poll_frame(ms(t0, 400), 1.0), None, "no new pose, no IDR owed: nothing to do");
    }

    #[test]
    fn a_still_camera_gets_one_full_size_frame_then_reuses_it() {
        let t0 = Instant::now();
        let mut s = Session::with_refinement(W, H, 50, true);
        let mut seq = 0;
        let mut step = |s: &mut Session, t: u64, az: f64, moving_scale: f32| {
            seq += 1;
            s.on_pose(&pose(seq, az), ms(t0, t)).unwrap();
            let job = s.poll_frame(ms(t0, t), moving_scale).expect("a frame");
            finish(s, FrameTimes::default());
            job
        };
        // Moving: the scheduler's scale.
        let moving = step(&mut s, 0, 0.0, 0.5);
        assert_eq!(moving.render_scale, 0.5);
        let moving = step(&mut s, 20, 1.0, 0.625);
        assert_eq!(moving.render_scale, 0.625);
        // Stopped, but not for long: the last pixels are reused, whatever the scheduler says.
        let held = step(&mut s, 40, 1.0, 0.25);
        assert!(held.same_as_previous && held.render_scale == 0.625);
        // At rest for 150 ms: one full-size render, sent as an IDR, then reuse at full size.
        let refined = step(&mut s, 180, 1.0, 0.25);
        assert!(!refined.same_as_previous && refined.render_scale == 1.0 && refined.idr);
        let reuse = step(&mut s, 200, 1.0, 0.25);
        assert!(reuse.same_as_previous && reuse.render_scale == 1.0);
        // Moving again: back to the scheduler's scale.
        let again = step(&mut s, 220, 2.0, 0.5);
        assert_eq!(again.render_scale, 0.5);
        // A fixed scale never refines.
        let mut f = Session::new(W, H, 50);
        f.on_pose(&pose(1, 0.0), t0).unwrap();
        f.poll_frame(t0, 0.5).unwrap();
        finish(&mut f, FrameTimes::default());
        f.on_pose(&pose(2, 0.0), ms(t0, 500)).unwrap();
        let job = f.poll_frame(ms(t0, 500), 0.5).unwrap();
        assert!(job.same_as_previous && job.render_scale == 0.5);
    }

    #[test]
    fn a_failed_frame_makes_the_next_one_an_idr() {
        let t0 = Instant::now();
        let mut s = Session::new(W, H, 50);
        s.on_pose(&pose(1, 0.0), t0).unwrap();
        s.poll_frame(t0, 1.0).unwrap();
        finish(&mut s, FrameTimes::default());
        s.on_pose(&pose(2, 1.0), ms(t0, 20)).unwrap();
        s.poll_frame(ms(t0, 20), 1.0).unwrap();
        let failing = s.in_flight().next().unwrap().frame;
        s.frame_failed(failing);
        s.on_pose(&pose(3, 2.0), ms(t0, 40)).unwrap();
        assert!(s.poll_frame(ms(t0, 40), 1.0).unwrap().idr);
    }
}
