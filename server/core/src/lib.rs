//! The master node's sans-IO core, in the style of str0m: every event goes in through
//! [`MasterCore::handle_input`] with the time it happened, every action comes out of
//! [`MasterCore::poll_output`]; no sockets, threads, clocks or GPUs inside, so tests drive it
//! on simulated time. The edge (`nephele-master`'s driver) owns the WebRTC peers, the signaling
//! socket, the encoder threads and the render workers, and only carries out what the core
//! says.
//!
//! The core owns:
//! - **admission** of joins (limits, scenes, modes, session count, and NEPHELE's load rule:
//!   no newcomer while a user starves, none that the measured farm could not serve at the
//!   lowest render scale — [`scheduler`]);
//! - **sessions**: each user's frame rules ([`session`]: validated poses, latest wins,
//!   pacing at its FPS, IDR on connect/PLI/failure, refinement at rest), its connect
//!   deadline and its Algorithm-1 clock;
//! - **scheduling**: rounds of render tasks ([`task`]) — users of one scene batched into
//!   one task per round, identical requests served once from the [`history`] table, tasks
//!   classified heavy or light by a coarse proxy ([`estimate`]) and handed to workers with a
//!   free slot; render scales lowered fairly before any frame rate falls;
//! - **frame completion**: rendered views become encode jobs, sent frames become frame info
//!   for the client, and the measurements feed the scheduler;
//! - **events** ([`events`]): what happened, as plain values the edge turns into metrics.

pub mod estimate;
pub mod events;
pub mod history;
pub mod scheduler;
pub mod session;
pub mod task;

use std::{
    collections::{BTreeMap, HashMap, VecDeque},
    sync::Arc,
    time::{Duration, Instant},
};

use glam::Vec3;
use nephele_renderer::{Frame, Instance};
use nephele_protocol::{JoinSpec, Mode};

use self::{
    estimate::{Proxy, classify, estimate},
    history::{History, RequestKey},
    scheduler::{Candidate, Demand, Ema, RenderScale, STARVED_GRACE, UserClock, fair_scale, fits, latency_scale, round_size, sort_candidates},
    events::CoreEvent,
    session::{FrameJob, Session},
    task::{CANCELLED, RenderTask, TaskClass, TaskId, TaskResult, TaskView, ViewTag, WorkerId},
};
use nephele_wire::{FrameLayout, FrameTimes, QuiltInfo, ToViewer, Viewport, background_of};

/// A peer must connect within this time of its join.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(30);
/// Heartbeats to signaling carry the session count and free capacity this often.
pub const HEARTBEAT_EVERY: Duration = Duration::from_millis(nephele_limits::MASTER_HEARTBEAT_EVERY_MS);
/// A camera that moved within this time counts as moving for the fair scale.
pub const ACTIVE_WINDOW: Duration = Duration::from_secs(1);
/// How often an unanswered `session` message is sent again (it travels on the unreliable
/// pose channel; the client's first pose answers it).
pub const HELLO_REPEAT: Duration = Duration::from_millis(250);

/// What the core knows of a scene (not its pixels: those live with the workers): one
/// object, or several placed in one world and composed by depth.
#[derive(Debug, Clone)]
pub struct SceneInfo {
    pub name: String,
    /// Centre and radius of the bounding sphere of every object, scene units.
    pub center: Vec3,
    pub radius: f32,
    /// Behind everything in viewer mode.
    pub background: Vec3,
    pub objects: Vec<ObjectInfo>,
}

/// One object of a scene: an asset (by name) and where it stands.
#[derive(Debug, Clone)]
pub struct ObjectInfo {
    pub asset: String,
    pub instance: Instance,
    pub proxy: Proxy,
}

impl SceneInfo {
    /// A scene of one asset at the origin, over white.
    pub fn single(name: &str, asset: &str, proxy: Proxy, center: Vec3, radius: f32) -> Self {
        let objects = vec![ObjectInfo { asset: asset.into(), instance: Instance::default(), proxy }];
        Self { name: name.into(), center, radius, background: Vec3::ONE, objects }
    }

    /// Several objects need composing; one renders straight over the background.
    pub fn composed(&self) -> bool {
        self.objects.len() > 1
    }
}

/// Whether joins are checked against the measured load.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Admission {
    /// Refuse newcomers while a user starves or when the farm could not serve them (NEPHELE).
    Load,
    /// Admit up to the session capacity whatever the load (benchmarks of overload).
    Open,
}

#[derive(Debug, Clone)]
pub struct CoreConfig {
    /// Most sessions at once.
    pub capacity: u32,
    pub render_scale: RenderScale,
    /// Users of one scene share a task per round (off: one task per user frame).
    pub batching: bool,
    pub admission: Admission,
    pub connect_timeout: Duration,
    pub heartbeat_every: Duration,
    /// Share of the pose period a frame may wait for a pose that is due
    /// ([`Session::with_pose_latch`]; 0: never).
    pub pose_latch: f64,
}

/// Default of [`CoreConfig::pose_latch`]. With frames longer than the pose period, a latch
/// of L waits L²·period/2 per frame on average and leaves the started pose (0.5 − L)·period
/// old at the median. Measured (`bench stream`, README), 0.4 lets a CPU render be ~1.5 ms
/// longer than 0.25 did and still hold both 30 fps and a 40 ms median latency; 0.5 gains
/// less, as its waits cost frame rate.
pub const POSE_LATCH: f64 = 0.4;

/// Parses `--pose-latch`: a share of the pose period in 0..=0.5.
pub fn parse_pose_latch(s: &str) -> Result<f64, String> {
    let share: f64 = s.trim().parse().map_err(|_| format!("{s:?} is not a number"))?;
    if (0.0..=0.5).contains(&share) { Ok(share) } else { Err(format!("{share} is outside 0..=0.5 (a share of the pose period; 0 never waits)")) }
}

impl Default for CoreConfig {
    fn default() -> Self {
        Self {
            capacity: 4,
            render_scale: RenderScale::Auto { budget_ms: 30.0, min: 0.25 },
            batching: true,
            admission: Admission::Load,
            connect_timeout: CONNECT_TIMEOUT,
            heartbeat_every: HEARTBEAT_EVERY,
            pose_latch: POSE_LATCH,
        }
    }
}

/// A client signaling paired with this master.
#[derive(Debug, Clone, PartialEq)]
pub struct JoinRequest {
    pub session: String,
    /// What the client asked for, as signaling checked it (mode `quilt` with its layout).
    pub spec: JoinSpec,
}

/// Everything that can happen to a master.
#[derive(Debug, Clone)]
pub enum Input {
    Join(JoinRequest),
    /// The client left through signaling.
    Leave { session: String },
    PeerConnected { session: String },
    ChannelOpen { session: String },
    Pose { session: String, bytes: bytes::Bytes },
    /// A pose-channel message that is not a pose (text, oversized); `message` says why.
    ChannelMisuse { session: String, message: String },
    PictureLoss { session: String },
    /// The peer connection failed or closed.
    PeerClosed { session: String, reason: String },
    RenderDone(TaskResult),
    /// The frame's access unit went out on RTP.
    FrameSent { session: String, frame: u64, times: FrameTimes },
    FrameFailed { session: String, frame: u64, error: String },
    /// A render worker can take tasks (`rays_per_s` from its calibration render).
    /// A render worker can take tasks. `rays_per_s` from its calibration render; `farm`:
    /// the class of tasks it is for (`None`: any); `assets`: what it can render (`None`:
    /// every asset).
    WorkerUp { worker: WorkerId, rays_per_s: f64, slots: u32, farm: Option<TaskClass>, assets: Option<Vec<String>> },
    /// A worker is gone. `tasks_lost`: its tasks will never answer (fail them now); else the
    /// edge re-issues them elsewhere and their results still come.
    WorkerDown { worker: WorkerId, tasks_lost: bool },
    /// Signaling (re)accepted our registration: send a heartbeat at once.
    SignalingUp,
    /// The master is stopping: end every session with `reason` (told through signaling),
    /// refuse joins with it from now on, and say saturated so signaling sends joins
    /// elsewhere. Tasks already on workers finish; see [`MasterCore::is_idle`].
    Drain { reason: String },
    /// Nothing happened; time passed.
    Timeout,
}

/// One view of a frame to encode: its rendered objects and where it goes.
#[derive(Debug, Clone)]
pub struct EncodeView {
    pub viewport: Viewport,
    /// The camera the view was rendered with, at the viewport's size.
    pub camera: nephele_renderer::View,
    /// At the render scale, one per scene object; the edge composes them by depth over
    /// the job's `compose_over` when there are several, then upscales to the viewport.
    pub parts: Vec<Arc<Frame>>,
}

/// Encode this rendered (or reused) frame for a session: one view filling it, or several
/// (stereo eyes, quilt tiles) tiled into it.
#[derive(Debug, Clone)]
pub struct EncodeJob {
    pub session: String,
    pub frame: u64,
    pub pose_seq: u32,
    pub idr: bool,
    pub views: Vec<EncodeView>,
    pub compose_over: Option<Vec3>,
    /// Send the frame's depth ([`nephele_wire::depth`]) after it.
    pub depth: bool,
    pub width: u32,
    pub height: u32,
    /// When the frame started, for the encoder's timestamps.
    pub started_at: Instant,
}

/// Everything the master can be asked to do.
#[derive(Debug, Clone)]
pub enum Output {
    /// Set up a peer connection and an encoder for this session.
    Accept(JoinRequest),
    /// Tell signaling the join is refused (the client sees `reason`).
    Reject { session: String, reason: String },
    /// Tear the session down; `tell_signaling`: send `end` with the reason (not needed when
    /// the client left through signaling).
    Close { session: String, reason: String, tell_signaling: bool },
    ToViewer { session: String, msg: ToViewer },
    Render { worker: WorkerId, task: RenderTask },
    /// Every user of this task is gone: drop it if not started.
    Cancel { worker: WorkerId, task: TaskId },
    Encode(EncodeJob),
    Heartbeat { sessions: u32, free_rays_per_s: f64, saturated: bool },
    /// Nothing to do before this time (or before the next input).
    Timeout(Instant),
}

#[derive(Debug)]
struct FrameInFlight {
    job: FrameJob,
    /// One per view and scene object (`view · objects + object`), filled as renders (or
    /// reuses) come in.
    parts: Vec<Option<Arc<Frame>>>,
    /// Longest render task of its parts, ms.
    render_ms: f64,
    /// All its parts' render tasks, ms.
    render_total_ms: f64,
    /// Longest network hop of its parts, ms, and bytes over the network.
    transfer_ms: f64,
    transfer_bytes: u64,
    batch_views: u32,
    /// No part was rendered for it.
    reused: bool,
}

impl FrameInFlight {
    fn complete(&self) -> bool {
        self.parts.iter().all(Option::is_some)
    }
}

#[derive(Debug)]
struct User {
    req: JoinRequest,
    background: Vec3,
    session: Session,
    clock: UserClock,
    joined_at: Instant,
    connected: bool,
    /// Tasks of this user on workers or queued.
    loaded_tasks: u32,
    /// Render scale of a moving camera (the scheduler's choice).
    scale: f32,
    /// The user's own last render of each view and scene object, for a still camera.
    last_parts: Vec<Option<(RequestKey, Arc<Frame>)>>,
    /// Frames started and not yet sent (at most two: one rendering, one encoding).
    frames: VecDeque<FrameInFlight>,
    /// Currently counted as starved (for the starvation-event metric).
    starved: bool,
    /// When the `session` message goes out again: the pose channel is unreliable (a lost
    /// message is never resent), so it repeats every [`HELLO_REPEAT`] until the client's
    /// first pose shows it arrived. `None`: not sent yet, or answered.
    hello_again: Option<Instant>,
}

impl User {

    fn pixels(&self) -> f64 {
        f64::from(self.req.spec.width) * f64::from(self.req.spec.height)
    }
}

#[derive(Debug)]
struct Worker {
    rays_per_s: Ema,
    slots: u32,
    in_flight: u32,
    farm: Option<TaskClass>,
    assets: Option<std::collections::BTreeSet<String>>,
}

#[derive(Debug)]
struct TaskInFlight {
    worker: WorkerId,
    /// Per view: its history key and who asked.
    views: Vec<(RequestKey, Vec<ViewTag>)>,
    /// Primary rays of each view.
    view_rays: Vec<u64>,
    rays: u64,
}

/// The master's state machine. See the module docs.
pub struct MasterCore {
    cfg: CoreConfig,
    scenes: BTreeMap<String, Arc<SceneInfo>>,
    users: BTreeMap<String, User>,
    workers: BTreeMap<WorkerId, Worker>,
    /// Formed tasks waiting for a worker slot, with their history keys.
    queue: VecDeque<(RenderTask, Vec<RequestKey>)>,
    in_flight: HashMap<TaskId, TaskInFlight>,
    history: History,
    outputs: VecDeque<Output>,
    next_task: u64,
    next_heartbeat: Option<Instant>,
    /// What the last heartbeat said about saturation.
    saturated_said: bool,
    /// Origin of every session's frame-slot grid.
    epoch: Instant,
    /// Users were told the farm is gone (and will hear when it is back).
    farm_was_lost: bool,
    now: Instant,
    /// What happened since the edge last drained them.
    events: Vec<CoreEvent>,
    /// Set by [`Input::Drain`]: why this master takes no more sessions.
    draining: Option<String>,
}

impl MasterCore {
    pub fn new(cfg: CoreConfig, scenes: Vec<SceneInfo>, now: Instant) -> Self {
        Self {
            cfg,
            scenes: scenes.into_iter().map(|s| (s.name.clone(), Arc::new(s))).collect(),
            users: BTreeMap::new(),
            workers: BTreeMap::new(),
            queue: VecDeque::new(),
            in_flight: HashMap::new(),
            history: History::default(),
            outputs: VecDeque::new(),
            next_task: 1,
            next_heartbeat: None,
            saturated_said: false,
            epoch: now,
            farm_was_lost: false,
            now,
            events: Vec::new(),
            draining: None,
        }
    }

    /// No session left and no render task on a worker: a draining master may exit.
    pub fn is_idle(&self) -> bool {
        self.users.is_empty() && self.in_flight.is_empty()
    }

    pub fn config(&self) -> &CoreConfig {
        &self.cfg
    }

    /// Scene names, sorted.
    pub fn scene_names(&self) -> Vec<String> {
        self.scenes.keys().cloned().collect()
    }

    pub fn user_count(&self) -> usize {
        self.users.len()
    }

    /// The farm's measured throughput: the sum of the workers' rays per second.
    pub fn farm_rays_per_s(&self) -> f64 {
        self.workers.values().filter_map(|w| w.rays_per_s.get()).sum()
    }

    /// Frames served from the history table or a user's own last frame.
    pub fn history_hits(&self) -> u64 {
        self.history.hits
    }

    /// Achieved FPS and render scale of a user (tests, benchmarks).
    pub fn user_stats(&self, session: &str) -> Option<(f64, f32)> {
        self.users.get(session).map(|u| (u.clock.achieved_fps(), u.scale))
    }

    /// Feeds one event that happened at `now`.
    pub fn handle_input(&mut self, now: Instant, input: Input) {
        self.now = self.now.max(now);
        let now = self.now;
        match input {
            // Mode `quilt` without a layout gets the default one, as signaling gives it.
            Input::Join(req) => self.join(JoinRequest { spec: req.spec.with_defaults(), ..req }, now),
            Input::Leave { session } => self.drop_user(&session, "the client left", false),
            Input::PeerConnected { session } => {
                if let Some(u) = self.users.get_mut(&session) {
                    u.connected = true;
                    // Anything sent before the track was bound is lost: start with an IDR.
                    u.session.on_picture_loss(now);
                }
            }
            Input::ChannelOpen { session } => self.hello(&session, now),
            Input::Pose { session, bytes } => self.pose(&session, &bytes, now),
            Input::ChannelMisuse { session, message } => {
                if self.users.contains_key(&session) {
                    self.tell(&session, ToViewer::Error { code: "bad_pose".into(), message });
                }
            }
            Input::PictureLoss { session } => {
                if let Some(u) = self.users.get_mut(&session) {
                    u.session.on_picture_loss(now);
                }
            }
            Input::PeerClosed { session, reason } => self.drop_user(&session, &reason, true),
            Input::RenderDone(result) => self.render_done(result, now),
            Input::FrameSent { session, frame, times } => self.frame_sent(&session, frame, times, now),
            Input::FrameFailed { session, frame, error } => {
                if let Some(u) = self.users.get_mut(&session)
                    && let Some(i) = u.frames.iter().position(|f| f.job.frame == frame)
                {
                    u.frames.remove(i);
                    u.session.frame_failed(frame);
                    self.events.push(CoreEvent::FrameFailed);
                    self.tell(&session, ToViewer::Error { code: "frame_failed".into(), message: error });
                }
            }
            Input::WorkerUp { worker, rays_per_s, slots, farm, assets } => {
                let was_empty = self.workers.is_empty();
                let mut ema = Ema::new(0.2);
                ema.observe(rays_per_s);
                let assets = assets.map(|a| a.into_iter().collect());
                if !self.workers.contains_key(&worker) {
                    self.events.push(CoreEvent::WorkerUp { worker: worker.0.clone(), workers: self.workers.len() + 1 });
                }
                let w = self.workers.entry(worker).or_insert(Worker { rays_per_s: ema, slots: slots.max(1), in_flight: 0, farm, assets: None });
                w.slots = slots.max(1);
                w.farm = farm;
                w.assets = assets;
                if w.rays_per_s.get().is_none() {
                    w.rays_per_s = ema;
                }
                // Signaling should hear the new capacity now.
                self.next_heartbeat = Some(now);
                if was_empty && self.farm_was_lost {
                    self.farm_was_lost = false;
                    self.notify_all("farm_back", "the render farm is back; frames resume");
                }
            }
            Input::WorkerDown { worker, tasks_lost } => self.worker_down(&worker, tasks_lost),
            Input::SignalingUp => self.next_heartbeat = Some(now),
            Input::Drain { reason } => {
                tracing::info!(sessions = self.users.len(), %reason, "draining");
                let sessions: Vec<String> = self.users.keys().cloned().collect();
                for session in sessions {
                    self.drop_user(&session, &reason, true);
                }
                self.draining = Some(reason);
                self.next_heartbeat = Some(now);
            }
            Input::Timeout => {}
        }
        self.tick(now);
    }

    /// The next thing to do; [`Output::Timeout`] when there is nothing until then.
    pub fn poll_output(&mut self) -> Output {
        if let Some(out) = self.outputs.pop_front() {
            return out;
        }
        Output::Timeout(self.next_wakeup())
    }

    /// What happened since the last call ([`CoreEvent`]), oldest first: the edge turns these
    /// into metrics.
    pub fn drain_events(&mut self) -> std::vec::Drain<'_, CoreEvent> {
        self.events.drain(..)
    }

    /// The next time something is due without any input: a heartbeat, a connect deadline,
    /// or a frame slot opening while a worker is free (a user ready now but waiting for a
    /// worker needs no timer: the worker's result wakes the core).
    fn next_wakeup(&self) -> Instant {
        let mut t = self.now + Duration::from_secs(1);
        if let Some(h) = self.next_heartbeat {
            t = t.min(h);
        }
        let worker_free = self.free_worker().is_some() && self.queue.is_empty();
        for u in self.users.values() {
            if let Some(hello) = u.hello_again {
                t = t.min(hello);
            }
            if !u.connected {
                t = t.min(u.joined_at + self.cfg.connect_timeout);
            } else if worker_free
                && let Some(w) = u.session.next_wakeup(self.now).filter(|w| *w > self.now)
            {
                t = t.min(w);
            }
        }
        t.max(self.now)
    }

    fn tell(&mut self, session: &str, msg: ToViewer) {
        self.outputs.push_back(Output::ToViewer { session: session.into(), msg });
    }

    // ---- admission ----

    fn join(&mut self, req: JoinRequest, now: Instant) {
        match self.admit(&req, now) {
            Err((reason_code, reason)) => {
                tracing::info!(session = %req.session, reason_code, %reason, "join refused");
                self.events.push(CoreEvent::Refused { reason: reason_code });
                self.outputs.push_back(Output::Reject { session: req.session, reason });
            }
            Ok(()) => {
                let refine = matches!(self.cfg.render_scale, RenderScale::Auto { .. });
                let scale = match self.cfg.render_scale {
                    RenderScale::Fixed(s) => s,
                    RenderScale::Auto { min, .. } => self.initial_scale(&req, min),
                };
                let user = User {
                    background: match req.spec.mode {
                        Mode::Ar => background_of(Mode::Ar),
                        _ => self.scenes.get(&req.spec.scene).map_or(background_of(req.spec.mode), |s| s.background),
                    },
                    session: Session::with_epoch(req.spec.width, req.spec.height, req.spec.fps, refine, Some(self.epoch)).with_layout(self.layout(&req)).with_pose_latch(self.cfg.pose_latch),
                    clock: UserClock::new(req.spec.fps, now),
                    joined_at: now,
                    connected: false,
                    loaded_tasks: 0,
                    scale,
                    last_parts: Vec::new(),
                    frames: VecDeque::new(),
                    starved: false,
                    hello_again: None,
                    req: req.clone(),
                };
                self.events.push(CoreEvent::UserAdmitted { session: req.session.clone(), target_fps: f64::from(req.spec.fps), scale });
                tracing::info!(session = %req.session, scene = %req.spec.scene, mode = ?req.spec.mode, width = req.spec.width, height = req.spec.height, fps = req.spec.fps, "session admitted");
                self.users.insert(req.session.clone(), user);
                self.events.push(CoreEvent::Users { count: self.users.len() });
                self.outputs.push_back(Output::Accept(req));
            }
        }
    }

    /// How a session's frame is made of views: a quilt's are the master's to derive (focal
    /// plane through the scene's centre), the others come with each pose.
    fn layout(&self, req: &JoinRequest) -> FrameLayout {
        let (width, height) = (req.spec.width, req.spec.height);
        match (req.spec.quilt, self.scenes.get(&req.spec.scene)) {
            (Some(q), Some(scene)) => FrameLayout::Quilt {
                width,
                height,
                layout: nephele_renderer::views::QuiltLayout { cols: q.cols, rows: q.rows, cone_rad: f64::from(q.cone_deg).to_radians() },
                focal_target: scene.center.as_dvec3(),
                min_focal: 0.1 * f64::from(scene.radius),
            },
            _ => FrameLayout::Views { width, height },
        }
    }

    /// `Err((metric reason, words for the user))`.
    fn admit(&self, req: &JoinRequest, now: Instant) -> Result<(), (&'static str, String)> {
        if let Some(reason) = &self.draining {
            return Err(("draining", reason.clone()));
        }
        if self.users.contains_key(&req.session) {
            return Err(("duplicate", format!("session {} is already here", req.session)));
        }
        // The same rules and words as signaling's (a master may sit behind another one).
        req.spec.check().map_err(|e| ("limits", e.to_string()))?;
        if !self.scenes.contains_key(&req.spec.scene) {
            return Err(("scene", format!("unknown scene {:?}; this master has: {}", req.spec.scene, self.scene_names().join(", "))));
        }
        if self.users.len() as u32 >= self.cfg.capacity {
            return Err(("capacity", format!("this master serves at most {} sessions at once and all are taken", self.cfg.capacity)));
        }
        if self.cfg.admission == Admission::Open {
            return Ok(());
        }
        let starving: Vec<&User> = self.users.values().filter(|u| self.is_starving(u, now)).collect();
        if let Some(worst) = starving.iter().min_by(|a, b| a.clock.achieved_fps().total_cmp(&b.clock.achieved_fps())) {
            return Err((
                "saturated",
                format!(
                    "the render farm is saturated: {} of {} users are behind their frame rates (one gets {:.1} of its {} fps); try again shortly",
                    starving.len(),
                    self.users.len(),
                    worst.clock.achieved_fps(),
                    worst.req.spec.fps
                ),
            ));
        }
        let rays = self.farm_rays_per_s();
        // A lone user is always served as well as the farm can: refusing it helps nobody.
        if rays > 0.0 && !self.users.is_empty() {
            let floor = self.cfg.render_scale.floor();
            let admitted: Vec<Demand> = self.users.values().map(|u| self.demand(u, now, true)).collect();
            let newcomer = Demand { pixels: f64::from(req.spec.width) * f64::from(req.spec.height), fps: f64::from(req.spec.fps), fixed_scale: self.fixed_scale(), active: true };
            let (ok, need, free) = fits(&admitted, &newcomer, floor, rays);
            if !ok {
                return Err((
                    "full",
                    format!(
                        "the render farm is full: this stream needs {:.2} M rays/s at its lowest render scale ({floor}) and {:.2} M rays/s are free; try a smaller size or frame rate",
                        need / 1e6,
                        free.max(0.0) / 1e6
                    ),
                ));
            }
        }
        Ok(())
    }

    fn fixed_scale(&self) -> Option<f32> {
        match self.cfg.render_scale {
            RenderScale::Fixed(s) => Some(s),
            RenderScale::Auto { .. } => None,
        }
    }

    /// What `u` asks of the farm; `admission`: count every user as moving.
    fn demand(&self, u: &User, now: Instant, admission: bool) -> Demand {
        let active = admission || u.session.moved_at().is_some_and(|t| now.saturating_duration_since(t) <= ACTIVE_WINDOW);
        Demand { pixels: u.pixels(), fps: f64::from(u.req.spec.fps), fixed_scale: self.fixed_scale(), active }
    }

    /// Starved beyond the grace: waiting for a frame, and late against its target time by
    /// more than [`STARVED_GRACE`] of a period.
    fn is_starving(&self, u: &User, now: Instant) -> bool {
        u.session.wants_frame() && u.clock.lateness(now).as_secs_f64() > STARVED_GRACE * u.clock.period_s()
    }

    /// A newcomer starts no larger than the scale everyone else has now (so its first frames
    /// do not slow their rounds), and within the frame budget.
    fn initial_scale(&self, req: &JoinRequest, min: f32) -> f32 {
        let rays = self.farm_rays_per_s();
        let others = self.users.values().map(|u| u.scale).fold(0.5f32.max(min), f32::min);
        match self.cfg.render_scale {
            RenderScale::Auto { budget_ms, .. } if rays > 0.0 => latency_scale(f64::from(req.spec.width) * f64::from(req.spec.height), rays, budget_ms, min).min(others),
            _ => others,
        }
    }

    // ---- sessions ----

    fn hello(&mut self, session: &str, now: Instant) {
        let Some(u) = self.users.get_mut(session) else { return };
        u.hello_again = Some(now + HELLO_REPEAT);
        let u = &self.users[session];
        let Some(scene) = self.scenes.get(&u.req.spec.scene) else { return };
        let msg = ToViewer::Session {
            scene: scene.name.clone(),
            mode: u.req.spec.mode,
            center: scene.center.to_array(),
            radius: scene.radius,
            up: [0.0, 0.0, 1.0],
            width: u.req.spec.width,
            height: u.req.spec.height,
            fps: u.req.spec.fps,
            quilt: u.req.spec.quilt.map(|q| QuiltInfo { cols: q.cols, rows: q.rows, cone_deg: q.cone_deg, tile_width: u.req.spec.width / q.cols, tile_height: u.req.spec.height / q.rows }),
        };
        self.tell(session, msg);
    }

    fn pose(&mut self, session: &str, bytes: &[u8], now: Instant) {
        let Some(u) = self.users.get_mut(session) else { return };
        // A pose: the client has its `session` message.
        u.hello_again = None;
        let was_waiting = u.session.wants_frame() || !u.frames.is_empty();
        match u.session.on_pose(bytes, now) {
            Ok(true) if !was_waiting => u.clock.waiting_since = Some(now),
            Ok(_) => {}
            Err(e) => self.tell(session, ToViewer::Error { code: "bad_pose".into(), message: e.to_string() }),
        }
    }

    fn drop_user(&mut self, session: &str, reason: &str, tell_signaling: bool) {
        let Some(u) = self.users.remove(session) else { return };
        tracing::info!(session, reason, frames = u.clock.frames, "session ended");
        self.events.push(CoreEvent::UserLeft { session: session.into() });
        self.events.push(CoreEvent::Users { count: self.users.len() });
        // Queued views of this user go; tasks left with nobody are dropped.
        for (task, keys) in &mut self.queue {
            let mut keep = Vec::new();
            for (view, key) in task.views.drain(..).zip(keys.drain(..)) {
                let mut view = view;
                view.tags.retain(|t| t.session != session);
                if !view.tags.is_empty() {
                    keep.push((view, key));
                }
            }
            (task.views, *keys) = keep.into_iter().unzip();
        }
        self.queue.retain(|(t, _)| !t.views.is_empty());
        // Running tasks stop at the worker's next safe point when at least half of their rays
        // were for users who are gone (the work saved is at least the work redone): the
        // other users' frames of such a task are dropped quietly and made from their next
        // pose.
        let orphans: Vec<(TaskId, WorkerId)> = self
            .in_flight
            .iter()
            .filter(|(_, t)| {
                let abandoned: u64 = t
                    .views
                    .iter()
                    .zip(&t.view_rays)
                    .filter(|((_, tags), _)| tags.iter().all(|tag| tag.session == session || !self.users.contains_key(&tag.session)))
                    .map(|(_, rays)| rays)
                    .sum();
                2 * abandoned >= t.rays.max(1)
            })
            .map(|(id, t)| (*id, t.worker.clone()))
            .collect();
        for (task, worker) in orphans {
            self.events.push(CoreEvent::TaskCancelled);
            self.outputs.push_back(Output::Cancel { worker, task });
        }
        self.outputs.push_back(Output::Close { session: session.into(), reason: reason.into(), tell_signaling });
    }

    // ---- scheduling ----

    fn tick(&mut self, now: Instant) {
        // Connect deadlines.
        let late: Vec<String> =
            self.users.values().filter(|u| !u.connected && now >= u.joined_at + self.cfg.connect_timeout).map(|u| u.req.session.clone()).collect();
        for s in late {
            let secs = self.cfg.connect_timeout.as_secs();
            self.drop_user(&s, &format!("the peer did not connect within {secs} s"), true);
        }
        // `session` messages not yet answered by a pose go out again.
        let unanswered: Vec<String> = self.users.values().filter(|u| u.hello_again.is_some_and(|t| now >= t)).map(|u| u.req.session.clone()).collect();
        for s in unanswered {
            self.hello(&s, now);
        }
        self.update_scales(now);
        self.count_starvation(now);
        self.schedule(now);
        // With admission open the master takes joins whatever the load, so it never asks
        // signaling to send them elsewhere.
        let saturated = self.draining.is_some() || (self.cfg.admission == Admission::Load && self.users.values().any(|u| self.is_starving(u, now)));
        // Signaling hears at once when the farm saturates or recovers.
        if saturated != self.saturated_said {
            self.next_heartbeat = Some(now);
        }
        if self.next_heartbeat.is_none_or(|t| now >= t) {
            let free = self.free_rays_per_s(now);
            self.saturated_said = saturated;
            self.outputs.push_back(Output::Heartbeat { sessions: self.users.len() as u32, free_rays_per_s: free, saturated });
            self.next_heartbeat = Some(now + self.cfg.heartbeat_every);
        }
        let rays_in_flight = self.in_flight.values().map(|t| t.rays).sum();
        let waiting_heavy = self.queue.iter().filter(|(t, _)| t.class == TaskClass::Heavy).count();
        let waiting_light = self.queue.len() - waiting_heavy;
        self.events.push(CoreEvent::Queue { waiting_heavy, waiting_light, in_flight: self.in_flight.len(), rays_in_flight, farm_rays_per_s: self.farm_rays_per_s() });
    }

    /// Rays per second left after every admitted user at its lowest scale.
    fn free_rays_per_s(&self, now: Instant) -> f64 {
        let floor = self.cfg.render_scale.floor();
        let used: f64 = self.users.values().map(|u| self.demand(u, now, true)).map(|d| d.rays_per_s(d.fixed_scale.unwrap_or(floor))).sum();
        (scheduler::TARGET_UTILISATION * self.farm_rays_per_s() - used).max(0.0)
    }

    fn count_starvation(&mut self, now: Instant) {
        let starving: Vec<(String, bool)> = self.users.values().map(|u| (u.req.session.clone(), self.is_starving(u, now))).collect();
        for (s, starving) in starving {
            let u = self.users.get_mut(&s).expect("listed");
            if starving && !u.starved {
                self.events.push(CoreEvent::Starved);
            }
            u.starved = starving;
        }
    }

    /// Dynamic resolution: one common scale for moving users (quality before FPS), capped
    /// per user by the frame budget. Lowered at once, raised by at most one step per second
    /// of calm, so that it settles.
    fn update_scales(&mut self, now: Instant) {
        let RenderScale::Auto { budget_ms, min } = self.cfg.render_scale else { return };
        let rays = self.farm_rays_per_s();
        if rays <= 0.0 {
            return;
        }
        let demands: Vec<Demand> = self.users.values().map(|u| self.demand(u, now, false)).collect();
        let common = fair_scale(&demands, rays, min);
        for u in self.users.values_mut() {
            let target = common.min(latency_scale(u.pixels(), rays, budget_ms, min));
            if target < u.scale || target >= u.scale + 2.0 * scheduler::SCALE_STEP {
                u.scale = if target < u.scale { target } else { (u.scale + scheduler::SCALE_STEP).min(target) };
                self.events.push(CoreEvent::RenderScale { session: u.req.session.clone(), scale: u.scale });
            }
        }
    }

    fn free_worker(&self) -> Option<WorkerId> {
        self.workers.iter().filter(|(_, w)| w.in_flight < w.slots).min_by_key(|(_, w)| w.in_flight).map(|(id, _)| id.clone())
    }

    /// The worker for `task`: a free one that has its asset, from the task's farm (heavy
    /// tasks to the heavy farm, light to the light) whenever that farm has the asset at all
    /// (a busy farm is waited for), else from any farm; least loaded first.
    fn worker_for(&self, task: &RenderTask) -> Option<WorkerId> {
        let has = |w: &Worker| w.assets.as_ref().is_none_or(|a| a.contains(&task.asset));
        let own_farm = |w: &Worker| w.farm.is_none_or(|f| f == task.class);
        let farm_has_it = self.workers.values().any(|w| has(w) && own_farm(w));
        self.workers
            .iter()
            .filter(|(_, w)| w.in_flight < w.slots && has(w) && (!farm_has_it || own_farm(w)))
            .min_by_key(|(_, w)| w.in_flight)
            .map(|(id, _)| id.clone())
    }

    /// No worker at all has `asset`.
    fn nobody_has(&self, asset: &str) -> bool {
        !self.workers.values().any(|w| w.assets.as_ref().is_none_or(|a| a.contains(asset)))
    }

    fn schedule(&mut self, now: Instant) {
        loop {
            if self.queue.is_empty() && (self.free_worker().is_none() || !self.plan_round(now)) {
                break;
            }
            // Tasks no worker could ever take fail now, in words.
            while let Some(i) = self.queue.iter().position(|(t, _)| !self.workers.is_empty() && self.nobody_has(&t.asset)) {
                let (task, keys) = self.queue.remove(i).expect("found");
                let message = format!("no render worker has asset {:?}", task.asset);
                self.fail_queued(task, keys, &message, now);
            }
            let Some(i) = self.queue.iter().position(|(t, _)| self.worker_for(t).is_some()) else { break };
            let (task, keys) = self.queue.remove(i).expect("found");
            let worker = self.worker_for(&task).expect("checked");
            self.dispatch(worker, task, keys);
        }
    }

    /// A queued task that will not render: its users' frames fail.
    fn fail_queued(&mut self, task: RenderTask, keys: Vec<RequestKey>, message: &str, now: Instant) {
        let id = task.id;
        let views = keys.into_iter().zip(task.views.iter().map(|v| v.tags.clone())).collect();
        self.in_flight.insert(id, TaskInFlight { worker: WorkerId(String::new()), views, view_rays: view_rays(&task), rays: task.rays });
        self.render_done(TaskResult::failed(id, message), now);
    }

    /// A notice to every user (the farm went away or came back).
    fn notify_all(&mut self, code: &str, message: &str) {
        let sessions: Vec<String> = self.users.keys().cloned().collect();
        for s in sessions {
            self.tell(&s, ToViewer::Notice { code: code.into(), message: message.into() });
        }
    }

    fn dispatch(&mut self, worker: WorkerId, task: RenderTask, keys: Vec<RequestKey>) {
        let w = self.workers.get_mut(&worker).expect("a free worker");
        w.in_flight += 1;
        self.events.push(CoreEvent::TaskFormed { views: task.views.len(), users: task.users() });
        let views = keys.into_iter().zip(task.views.iter().map(|v| v.tags.clone())).collect();
        self.in_flight.insert(task.id, TaskInFlight { worker: worker.clone(), views, view_rays: view_rays(&task), rays: task.rays });
        tracing::trace!(task = %task.id, views = task.views.len(), class = ?task.class, "dispatch");
        self.outputs.push_back(Output::Render { worker, task });
    }

    /// Forms one round (Algorithm 1) into the queue. Returns whether anything was started.
    fn plan_round(&mut self, now: Instant) -> bool {
        let rays_per_s = self.farm_rays_per_s();
        let mut candidates: Vec<Candidate> = self
            .users
            .values()
            .filter(|u| u.connected && u.session.ready(now))
            .map(|u| {
                let scale = u.scale;
                Candidate {
                    session: u.req.session.clone(),
                    starved: now > u.clock.target_time(),
                    loaded_tasks: u.loaded_tasks,
                    target_time: u.clock.target_time(),
                    rays: (u.pixels() * f64::from(scale * scale)).ceil() as u64,
                    fps: u.req.spec.fps,
                }
            })
            .collect();
        // A round of users who would all rather wait for their next pose waits (the pose
        // latch); one who would not starts it, and the others come along.
        if candidates.iter().all(|c| self.users[&c.session].session.latched(now)) {
            return false;
        }
        sort_candidates(&mut candidates);
        let n = round_size(&candidates, rays_per_s);
        // Views to render, grouped into tasks by asset (batching) or by user and object.
        let mut groups: BTreeMap<String, Vec<(TaskView, RequestKey)>> = BTreeMap::new();
        for c in &candidates[..n] {
            let u = self.users.get_mut(&c.session).expect("a candidate");
            let Some(scene) = self.scenes.get(&u.req.spec.scene).cloned() else { continue };
            let Some(job) = u.session.poll_frame(now, u.scale) else { continue };
            u.clock.waiting_since = None;
            // Several objects render over black (premultiplied) and are composed later.
            let render_background = if scene.composed() { Vec3::ZERO } else { u.background };
            let n_objects = scene.objects.len();
            let n_parts = job.pose.views.len() * n_objects;
            if u.last_parts.len() != n_parts {
                u.last_parts = vec![None; n_parts];
            }
            let mut fl = FrameInFlight {
                job: job.clone(),
                parts: vec![None; n_parts],
                render_ms: 0.0,
                render_total_ms: 0.0,
                transfer_ms: 0.0,
                transfer_bytes: 0,
                batch_views: 0,
                reused: true,
            };
            for (v, frame_view) in job.pose.views.iter().enumerate() {
                let mut view = frame_view.view;
                if job.render_scale < 1.0 {
                    view.intrinsics = view.intrinsics.scaled(job.render_scale);
                }
                for (o, object) in scene.objects.iter().enumerate() {
                    let part = v * n_objects + o;
                    let instance = job.pose.instance.then_inside(&object.instance);
                    let key = RequestKey {
                        asset: object.asset.clone(),
                        intrinsics: view.intrinsics,
                        background: render_background,
                        instance,
                        world_from_camera: view.world_from_camera,
                    };
                    let own = u.last_parts.get(part).and_then(Option::as_ref).filter(|(k, _)| job.same_as_previous && k.matches(&key)).map(|(_, f)| Arc::clone(f));
                    if let Some(pixels) = own.or_else(|| self.history.lookup(&key)) {
                        self.events.push(CoreEvent::HistoryHit);
                        fl.parts[part] = Some(pixels);
                        continue;
                    }
                    let tag = ViewTag { session: c.session.clone(), frame: job.frame, part: part as u32 };
                    // An identical view already on a worker or in the queue: ride along.
                    let riding = self.in_flight.values_mut().flat_map(|t| t.views.iter_mut()).find(|(k, _)| k.matches(&key)).map(|(_, tags)| tags).or_else(|| {
                        self.queue.iter_mut().flat_map(|(t, keys)| t.views.iter_mut().zip(keys.iter())).find(|(_, k)| k.matches(&key)).map(|(v, _)| &mut v.tags)
                    });
                    if let Some(tags) = riding {
                        tags.push(tag);
                        u.loaded_tasks += 1;
                        self.events.push(CoreEvent::HistoryHit);
                        self.history.hits += 1;
                        continue;
                    }
                    // All views of one user's frame (both eyes, every quilt tile) share a task.
                    let group = if self.cfg.batching { object.asset.clone() } else { format!("{}/{o}", c.session) };
                    let views = groups.entry(group).or_default();
                    // Identical requests in one round are rendered once.
                    match views.iter_mut().find(|(_, k)| k.matches(&key)) {
                        Some((v, _)) => {
                            v.tags.push(tag);
                            self.events.push(CoreEvent::HistoryHit);
                            self.history.hits += 1;
                        }
                        None => {
                            fl.reused = false;
                            let task_view = TaskView { view, instance, background: render_background, render_scale: job.render_scale, tags: vec![tag] };
                            views.push((task_view, key));
                        }
                    }
                }
            }
            let frame = job.frame;
            u.frames.push_back(fl);
            self.finish_if_complete(&c.session, frame);
        }
        let mut tasks: Vec<(RenderTask, Vec<RequestKey>)> = groups.into_values().map(|views| self.make_task(views)).collect();
        // Shared tasks first, then heavy before light.
        tasks.sort_by_key(|(t, _)| (std::cmp::Reverse(t.users().min(2)), t.class));
        for (task, keys) in tasks {
            for tag in task.views.iter().flat_map(|v| &v.tags) {
                if let Some(u) = self.users.get_mut(&tag.session) {
                    u.loaded_tasks += 1;
                }
            }
            self.queue.push_back((task, keys));
        }
        true
    }

    fn make_task(&mut self, views: Vec<(TaskView, RequestKey)>) -> (RenderTask, Vec<RequestKey>) {
        let asset = views[0].1.asset.clone();
        let proxy = self.scenes.values().flat_map(|s| &s.objects).find(|o| o.asset == asset).map(|o| o.proxy.clone());
        let (mut est_pixels, mut min_depth, mut rays, mut radius) = (0u64, f64::INFINITY, 0u64, 0.0f64);
        for (v, _) in &views {
            if let Some(proxy) = &proxy {
                let e = estimate(proxy, &v.view, &v.instance);
                est_pixels += e.n_pixel;
                min_depth = min_depth.min(e.avg_depth);
                radius = radius.max(f64::from(proxy.bound_radius) * v.instance.scale);
            }
            rays += v.view.intrinsics.pixel_count();
        }
        let class = classify(est_pixels, min_depth, radius);
        let id = TaskId(self.next_task);
        self.next_task += 1;
        let (views, keys): (Vec<TaskView>, Vec<RequestKey>) = views.into_iter().unzip();
        // Views over black are objects of composed scenes (see plan_round); a session that
        // asked for depth gets it with every frame.
        let wants_depth = |v: &TaskView| v.tags.iter().any(|t| self.users.get(&t.session).is_some_and(|u| u.req.spec.depth));
        let needs_depth = views.iter().any(|v| v.background == Vec3::ZERO || wants_depth(v));
        (RenderTask { id, asset, views, class, rays, est_pixels, needs_depth }, keys)
    }

    /// Once every part of a user's frame is there: encode it.
    fn finish_if_complete(&mut self, session: &str, frame: u64) {
        let Some(u) = self.users.get_mut(session) else { return };
        let Some(fl) = u.frames.iter().find(|f| f.job.frame == frame) else { return };
        if !fl.complete() {
            return;
        }
        let scene_objects = (fl.parts.len() / fl.job.pose.views.len().max(1)).max(1);
        let composed = scene_objects > 1;
        let job = &fl.job;
        let views = job
            .pose
            .views
            .iter()
            .zip(fl.parts.chunks(scene_objects))
            .map(|(fv, parts)| EncodeView { viewport: fv.viewport, camera: fv.view, parts: parts.iter().flatten().cloned().collect() })
            .collect();
        let (pose_seq, idr, started_at) = (job.pose.seq, job.idr, job.started_at);
        u.session.rendered(frame);
        self.outputs.push_back(Output::Encode(EncodeJob {
            session: session.into(),
            frame,
            pose_seq,
            idr,
            views,
            compose_over: composed.then_some(u.background),
            depth: u.req.spec.depth,
            width: u.req.spec.width,
            height: u.req.spec.height,
            started_at,
        }));
    }

    // ---- results ----

    fn render_done(&mut self, result: TaskResult, now: Instant) {
        let Some(task) = self.in_flight.remove(&result.id) else {
            tracing::debug!(task = %result.id, "result for a task that is not in flight (stale or re-issued); ignored");
            return;
        };
        if let Some(w) = self.workers.get_mut(&task.worker) {
            w.in_flight = w.in_flight.saturating_sub(1);
            if result.frames.is_ok() && result.render_ms > 0.0 {
                w.rays_per_s.observe(task.rays as f64 / (result.render_ms / 1e3));
            }
        }
        let worker = result.rendered_by.clone().unwrap_or_else(|| task.worker.0.clone());
        self.events.push(CoreEvent::TaskRendered { render_ms: result.render_ms, worker, ok: result.frames.is_ok() });
        let n_views = task.views.len();
        let frames = match result.frames {
            Ok(f) if f.len() == n_views => Ok(f),
            Ok(f) => Err(format!("the worker answered {} views for a task of {n_views}", f.len())),
            Err(e) => Err(e),
        };
        for (i, (key, tags)) in task.views.into_iter().enumerate() {
            let frame = frames.as_ref().ok().map(|f| Arc::clone(&f[i]));
            if let Some(f) = &frame {
                self.history.insert(key.clone(), Arc::clone(f));
            }
            for tag in tags {
                let Some(u) = self.users.get_mut(&tag.session) else { continue };
                u.loaded_tasks = u.loaded_tasks.saturating_sub(1);
                let Some(at) = u.frames.iter().position(|f| f.job.frame == tag.frame) else { continue };
                match &frame {
                    Some(pixels) => {
                        let fl = &mut u.frames[at];
                        fl.render_ms = fl.render_ms.max(result.render_ms);
                        fl.render_total_ms += result.render_ms;
                        fl.transfer_ms = fl.transfer_ms.max(result.transfer_ms);
                        fl.transfer_bytes += result.bytes / n_views.max(1) as u64;
                        fl.batch_views = fl.batch_views.max(n_views as u32);
                        if let Some(slot) = fl.parts.get_mut(tag.part as usize) {
                            *slot = Some(Arc::clone(pixels));
                        }
                        if let Some(last) = u.last_parts.get_mut(tag.part as usize) {
                            *last = Some((key.clone(), Arc::clone(pixels)));
                        }
                        self.finish_if_complete(&tag.session, tag.frame);
                    }
                    None if frames.as_ref().is_err_and(|e| e == CANCELLED) => {
                        u.frames.remove(at);
                        u.session.frame_failed(tag.frame);
                    }
                    None => {
                        u.frames.remove(at);
                        u.session.frame_failed(tag.frame);
                        self.events.push(CoreEvent::FrameFailed);
                        let message = frames.as_ref().err().cloned().unwrap_or_default();
                        tracing::warn!(session = %tag.session, frame = tag.frame, %message, "render failed");
                        let msg = ToViewer::Error { code: "frame_failed".into(), message: format!("render: {message}") };
                        self.outputs.push_back(Output::ToViewer { session: tag.session.clone(), msg });
                    }
                }
            }
        }
        let _ = now;
    }

    fn frame_sent(&mut self, session: &str, frame: u64, mut times: FrameTimes, now: Instant) {
        let Some(u) = self.users.get_mut(session) else { return };
        let Some(i) = u.frames.iter().position(|f| f.job.frame == frame) else { return };
        let fl = u.frames.remove(i).expect("found");
        times.render_ms = fl.render_ms;
        times.render_total_ms = fl.render_total_ms;
        times.transfer_ms = fl.transfer_ms;
        times.transfer_bytes = fl.transfer_bytes;
        let job_s = now.saturating_duration_since(fl.job.started_at).as_secs_f64();
        u.clock.frame_sent(now, job_s);
        self.events.push(CoreEvent::FrameSent { session: u.req.session.clone(), encode_ms: times.convert_ms + times.encode_ms, achieved_fps: u.clock.achieved_fps() });
        if let Some(mut info) = u.session.frame_done(frame, times) {
            info.batch_views = fl.batch_views;
            info.reused = fl.reused;
            self.tell(session, ToViewer::Frame(info));
        }
    }

    fn worker_down(&mut self, worker: &WorkerId, tasks_lost: bool) {
        if self.workers.remove(worker).is_none() {
            return;
        }
        self.events.push(CoreEvent::WorkerLost { worker: worker.0.clone(), workers: self.workers.len() });
        if tasks_lost {
            let lost: Vec<TaskId> = self.in_flight.iter().filter(|(_, t)| &t.worker == worker).map(|(id, _)| *id).collect();
            for id in lost {
                self.render_done(TaskResult::failed(id, format!("worker {} went away", worker.0)), self.now);
            }
        }
        if self.workers.is_empty() && !self.users.is_empty() {
            self.farm_was_lost = true;
            self.notify_all("farm_unavailable", "the render farm is unreachable (no render worker is up); frames resume when it returns");
        }
        self.next_heartbeat = Some(self.now);
    }
}

#[cfg(test)]
mod tests;

fn view_rays(task: &RenderTask) -> Vec<u64> {
    task.views.iter().map(|v| v.view.intrinsics.pixel_count()).collect()
}
