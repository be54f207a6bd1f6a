//! The master node's edge: everything with sockets, threads and clocks around the sans-IO
//! [`MasterCore`]. One tokio task runs the core: it turns signaling messages, peer events,
//! render results and encoded frames into [`Input`]s stamped with `Instant::now()`, and
//! carries out each [`Output`]:
//! - a **signaling link** task keeps one websocket to signaling (registers with the scenes
//!   served, reconnects with back-off; sessions live on across a reconnect, since their media
//!   is peer to peer);
//! - a **peer task** per session owns its WebRTC connection ([`crate::peer`]): answers the
//!   offer, trickles ICE, sends video samples and pose-channel text in order;
//! - **encoder threads**: each session's OpenH264 encoder runs on the blocking pool, one frame
//!   at a time and in order (a frame rendered while the previous one encodes waits its turn);
//! - **render workers** (`nephele_farm::local`, or NATS workers through [`crate::nats_farm`])
//!   render tasks on their own threads.

use std::{
    collections::HashMap,
    sync::Arc,
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail};
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use nephele_signaling::{Health, ToMaster, ToSignal};
use serde_json::Value;
use tokio::sync::{mpsc, oneshot};
use tokio_tungstenite::tungstenite::Message;

use nephele_core::{
    CoreConfig, EncodeJob, EncodeView, Input, JoinRequest, MasterCore, Output,
    events::CoreEvent,
    task::{RenderTask, TaskId, TaskResult, WorkerId},
};
use nephele_farm::{
    catalog::Catalog,
    local::{LocalWorkers, WorkerEvent},
    worker::NatsAuth,
};
use nephele_rtc::{RtcConfig, build_api};
use nephele_wire::{
    FrameTimes,
    depth::{DepthFrame, DepthView},
};

use crate::{
    compositor::{ComposeChoice, Compositor},
    encoder::{EncoderConfig, FrameEncoder, upscale_bilinear},
    metrics::MasterMetrics,
    nats_farm::NatsFarm,
    peer::{MAX_CHANNEL_MESSAGE, MasterPeer, PeerEvent, WebrtcPeer},
};

/// How a master node runs.
#[derive(Debug, Clone)]
pub struct MasterConfig {
    /// Name shown in signaling's /status.
    pub name: String,
    /// Token presented to signaling.
    pub token: Option<String>,
    pub rtc: RtcConfig,
    /// Admission, scheduling and frame rules.
    pub core: CoreConfig,
    /// In-process render workers.
    pub workers: usize,
    /// Where multi-object frames are composed.
    pub compose: ComposeChoice,
    /// Video bits per pixel per frame (quality against bandwidth).
    pub bits_per_pixel: f64,
    /// Render on NATS workers instead of in-process ones.
    pub nats: Option<NatsSettings>,
}

impl MasterConfig {
    /// A master on this machine for benchmarks and tests: loopback ICE only, one in-process
    /// render worker, CPU composition, the default bit rate.
    pub fn loopback(name: &str, core: CoreConfig) -> Self {
        Self {
            name: name.into(),
            token: None,
            rtc: RtcConfig::loopback(),
            core,
            workers: 1,
            compose: ComposeChoice::Cpu,
            bits_per_pixel: crate::encoder::DEFAULT_BITS_PER_PIXEL,
            nats: None,
        }
    }
}

/// Where the NATS farm is and how to log in.
#[derive(Debug, Clone)]
pub struct NatsSettings {
    pub url: String,
    pub auth: NatsAuth,
}

/// The render workers a master sends tasks to.
enum Farm {
    Local(LocalWorkers),
    Nats(NatsFarm),
}

impl Farm {
    fn submit(&self, worker: &WorkerId, task: RenderTask) -> Result<(), (RenderTask, String)> {
        match self {
            Self::Local(w) => w.submit(worker, task),
            Self::Nats(n) => n.submit(worker.clone(), task).map_err(|t| (t, format!("worker {} is gone", worker.0))),
        }
    }

    fn cancel(&self, task: TaskId) {
        match self {
            Self::Local(w) => w.cancel(task),
            Self::Nats(n) => n.cancel(task),
        }
    }
}

/// Everything the driver loop hears.
enum Event {
    Signal(ToMaster),
    /// Signaling refused our credentials: stop.
    Fatal(String),
    Peer(String, PeerEvent),
    Worker(WorkerEvent),
    /// `encoder` is `None` when it could not be made (the session cannot stream).
    Encoded { session: String, frame: u64, encoder: Option<Box<FrameEncoder>>, result: Result<Encoded, String> },
    Sent { session: String, frame: u64, times: FrameTimes },
    SendFailed { session: String, frame: u64, error: String },
}

/// What a session's peer task is asked to do, in order.
enum PeerCommand {
    Offer(String),
    Ice(Value),
    Video { access_unit: Bytes, duration: Duration, frame: u64, times: FrameTimes, depth: Option<Vec<u8>> },
    Text(String),
    Close,
}

/// The driver's side of one session.
struct SessionEdge {
    commands: mpsc::UnboundedSender<PeerCommand>,
    /// Home when no frame of this session is encoding; made on the first frame (on the
    /// blocking pool, not in this loop).
    encoder: Option<FrameEncoder>,
    encoder_config: EncoderConfig,
    encoder_made: bool,
    /// Frames waiting for the encoder, in order.
    waiting: std::collections::VecDeque<EncodeJob>,
    started: Instant,
    last_sent: Option<Instant>,
    fps: u32,
}

/// What clients are told when their master drains.
pub const DRAIN_REASON: &str = "this render server is shutting down; reconnect to continue on another";

/// How a master stops, and what its `/readyz` says.
pub struct Lifecycle {
    /// Resolves when the master is to drain and stop (SIGTERM); by default never.
    pub stop: std::pin::Pin<Box<dyn std::future::Future<Output = ()> + Send>>,
    /// Longest a drain waits for render tasks on workers and for signaling to hear that
    /// the sessions ended.
    pub drain_deadline: Duration,
    /// Readiness: `signaling` (registered) and `workers` (one up); not ready from the
    /// moment the drain starts.
    pub health: Health,
}

impl Default for Lifecycle {
    fn default() -> Self {
        Self {
            stop: Box::pin(std::future::pending()),
            drain_deadline: Duration::from_secs(10),
            health: Health::starting(&[("signaling", "not registered yet"), ("workers", "no render worker up yet")]),
        }
    }
}

/// Connects to `signal_url` (ws://host:port/signal), registers, and serves sessions until
/// signaling refuses our credentials; reconnects with back-off if signaling goes away.
pub async fn run(signal_url: String, cfg: MasterConfig, catalog: Arc<Catalog>, metrics: Arc<MasterMetrics>) -> Result<()> {
    run_with(signal_url, cfg, catalog, metrics, Lifecycle::default()).await
}

/// [`run`] until `life.stop` resolves, then drains: joins are refused, every session ends
/// with [`DRAIN_REASON`] (its client hears it through signaling at once), tasks on workers
/// finish, and it returns `Ok` once nothing is left or at `life.drain_deadline`.
pub async fn run_with(signal_url: String, cfg: MasterConfig, catalog: Arc<Catalog>, metrics: Arc<MasterMetrics>, mut life: Lifecycle) -> Result<()> {
    let api = build_api(&cfg.rtc)?;
    crate::memory::spawn_trimmer();
    let (events_tx, mut events) = mpsc::unbounded_channel::<Event>();
    let (to_signal, outbox) = mpsc::unbounded_channel::<ToSignal>();
    let (flush_tx, flushes) = mpsc::unbounded_channel::<oneshot::Sender<()>>();
    let register = ToSignal::Register { name: cfg.name.clone(), capacity: cfg.core.capacity, scenes: catalog.names(), token: cfg.token.clone() };
    tokio::spawn(signaling_link(signal_url, register, events_tx.clone(), outbox, flushes, life.health.clone()));
    let worker_events = events_tx.clone();
    let report = move |e| {
        let _ = worker_events.send(Event::Worker(e));
    };
    let workers = match &cfg.nats {
        None => Farm::Local(LocalWorkers::spawn(Arc::clone(&catalog), cfg.workers, report).context("starting render workers")?),
        Some(n) => Farm::Nats(NatsFarm::start(&n.url, &n.auth, &cfg.name, report).await.context("joining the NATS render farm")?),
    };

    let compositor = Arc::new(Compositor::new(cfg.compose).context("creating the compositor")?);
    let mut core = MasterCore::new(cfg.core.clone(), catalog.infos(), Instant::now());
    let mut sessions: HashMap<String, SessionEdge> = HashMap::new();
    let mut inputs: Vec<Input> = Vec::new();
    let mut drain_until: Option<tokio::time::Instant> = None;
    loop {
        let wake = loop {
            match core.poll_output() {
                Output::Timeout(t) => {
                    for event in core.drain_events() {
                        metrics.record(&event);
                        if let CoreEvent::WorkerUp { workers, .. } | CoreEvent::WorkerLost { workers, .. } = &event {
                            match workers {
                                0 => life.health.fail("workers", "no render worker up"),
                                _ => life.health.pass("workers"),
                            }
                        }
                    }
                    break t;
                }
                out => execute(out, &mut sessions, &workers, &api, &to_signal, &events_tx, &compositor, cfg.bits_per_pixel, &mut inputs),
            }
        };
        if let Some(input) = inputs.pop() {
            core.handle_input(Instant::now(), input);
            continue;
        }
        if let Some(deadline) = drain_until {
            let now = tokio::time::Instant::now();
            if (core.is_idle() && sessions.is_empty()) || now >= deadline {
                // Signaling hears every `end` queued so far before this master goes.
                let (done, flushed) = oneshot::channel();
                let _ = flush_tx.send(done);
                let flushed = tokio::time::timeout_at(deadline.max(now + Duration::from_secs(1)), flushed).await.is_ok();
                let left = if core.is_idle() { "every task finished" } else { "the drain deadline passed with tasks left" };
                tracing::info!(flushed, "drained: {left}");
                return Ok(());
            }
        }
        let wake = tokio::time::Instant::from_std(wake);
        let wake = drain_until.map_or(wake, |d| wake.min(d));
        tokio::select! {
            () = &mut life.stop, if drain_until.is_none() => {
                life.health.drain();
                core.handle_input(Instant::now(), Input::Drain { reason: DRAIN_REASON.into() });
                drain_until = Some(tokio::time::Instant::now() + life.drain_deadline);
            }
            ev = events.recv() => {
                let Some(ev) = ev else { bail!("the master's event channel closed") };
                let input = match ev {
                    Event::Fatal(why) => bail!("{why}"),
                    other => translate(other, &mut sessions, &events_tx, &to_signal, &compositor),
                };
                if let Some(input) = input {
                    core.handle_input(Instant::now(), input);
                }
            }
            _ = tokio::time::sleep_until(wake) => core.handle_input(Instant::now(), Input::Timeout),
        }
    }
}

/// An event as the core's input (or handled here: encoded frames go on to the peer).
fn translate(
    ev: Event,
    sessions: &mut HashMap<String, SessionEdge>,
    events: &mpsc::UnboundedSender<Event>,
    to_signal: &mpsc::UnboundedSender<ToSignal>,
    compositor: &Arc<Compositor>,
) -> Option<Input> {
    match ev {
        Event::Fatal(_) => None,
        Event::Signal(msg) => match msg {
            ToMaster::Registered { master } => {
                tracing::info!(%master, "registered with signaling");
                Some(Input::SignalingUp)
            }
            ToMaster::Join { session, spec } => Some(Input::Join(JoinRequest { session, spec })),
            ToMaster::Offer { session, sdp } => {
                command(sessions, &session, PeerCommand::Offer(sdp));
                None
            }
            ToMaster::Ice { session, candidate } => {
                command(sessions, &session, PeerCommand::Ice(candidate));
                None
            }
            ToMaster::Leave { session } => Some(Input::Leave { session }),
            ToMaster::Error { code, message } => {
                tracing::warn!(?code, %message, "signaling refused a message");
                None
            }
        },
        Event::Peer(session, ev) => match ev {
            PeerEvent::Connected => {
                // Signaling stops counting it as a pending join of its client's address.
                let _ = to_signal.send(ToSignal::Connected { session: session.clone() });
                Some(Input::PeerConnected { session })
            }
            PeerEvent::ChannelOpen => Some(Input::ChannelOpen { session }),
            PeerEvent::Binary(bytes) => Some(Input::Pose { session, bytes }),
            PeerEvent::Text(text) => {
                let shown: String = text.chars().take(40).collect();
                Some(Input::ChannelMisuse { session, message: format!("pose messages are binary; got text {shown:?}") })
            }
            PeerEvent::Oversized(len) => {
                Some(Input::ChannelMisuse { session, message: format!("message of {len} bytes refused (limit {MAX_CHANNEL_MESSAGE})") })
            }
            PeerEvent::PictureLoss => Some(Input::PictureLoss { session }),
            PeerEvent::Closed(reason) => Some(Input::PeerClosed { session, reason }),
            PeerEvent::LocalIce(_) => None, // sent to signaling by the peer task
        },
        Event::Worker(WorkerEvent::Up { worker, rays_per_s, slots, farm, assets }) => Some(Input::WorkerUp { worker, rays_per_s, slots, farm, assets }),
        Event::Worker(WorkerEvent::Down { worker, tasks_lost }) => Some(Input::WorkerDown { worker, tasks_lost }),
        Event::Worker(WorkerEvent::Done(result)) => Some(Input::RenderDone(result)),
        Event::Encoded { session, frame, encoder, result } => {
            let edge = sessions.get_mut(&session)?;
            let Some(encoder) = encoder else {
                return Some(Input::PeerClosed { session, reason: result.err().unwrap_or_default() });
            };
            edge.encoder = Some(*encoder);
            next_encode(edge, events, compositor);
            match result {
                Ok(Encoded { access_unit, times, depth }) => {
                    let now = Instant::now();
                    let period = Duration::from_secs_f64(1.0 / f64::from(edge.fps.max(1)));
                    let duration = edge.last_sent.map_or(period, |t| now.duration_since(t));
                    edge.last_sent = Some(now);
                    command(sessions, &session, PeerCommand::Video { access_unit, duration, frame, times, depth });
                    None
                }
                Err(error) => Some(Input::FrameFailed { session, frame, error }),
            }
        }
        Event::Sent { session, frame, times } => Some(Input::FrameSent { session, frame, times }),
        Event::SendFailed { session, frame, error } => Some(Input::FrameFailed { session, frame, error }),
    }
}

fn command(sessions: &HashMap<String, SessionEdge>, session: &str, cmd: PeerCommand) {
    match sessions.get(session) {
        Some(edge) => {
            let _ = edge.commands.send(cmd);
        }
        None => tracing::debug!(session, "message for an unknown session"),
    }
}

/// Carries out one output of the core. Inputs it produces (e.g. an encoder that cannot be
/// created) go to `inputs`.
#[allow(clippy::too_many_arguments)]
fn execute(
    out: Output,
    sessions: &mut HashMap<String, SessionEdge>,
    workers: &Farm,
    api: &Arc<nephele_rtc::RtcApi>,
    to_signal: &mpsc::UnboundedSender<ToSignal>,
    events: &mpsc::UnboundedSender<Event>,
    compositor: &Arc<Compositor>,
    bits_per_pixel: f64,
    inputs: &mut Vec<Input>,
) {
    match out {
        Output::Accept(req) => {
            let (tx, rx) = mpsc::unbounded_channel();
            let edge = SessionEdge {
                commands: tx,
                encoder: None,
                encoder_config: EncoderConfig::with_bits_per_pixel(req.spec.width, req.spec.height, req.spec.fps, bits_per_pixel),
                encoder_made: false,
                waiting: Default::default(),
                started: Instant::now(),
                last_sent: None,
                fps: req.spec.fps,
            };
            sessions.insert(req.session.clone(), edge);
            tokio::spawn(peer_task(req.session, Arc::clone(api), rx, events.clone(), to_signal.clone()));
        }
        Output::Reject { session, reason } => {
            let _ = to_signal.send(ToSignal::Reject { session, reason });
        }
        Output::Close { session, reason, tell_signaling } => {
            if let Some(edge) = sessions.remove(&session) {
                let _ = edge.commands.send(PeerCommand::Close);
                crate::memory::session_ended();
            }
            if tell_signaling {
                let _ = to_signal.send(ToSignal::End { session, reason });
            }
        }
        Output::ToViewer { session, msg } => command(sessions, &session, PeerCommand::Text(msg.to_json())),
        Output::Render { worker, task } => {
            if let Err((task, why)) = workers.submit(&worker, task) {
                let result = TaskResult::failed(task.id, why);
                inputs.push(Input::RenderDone(result));
            }
        }
        Output::Cancel { task, .. } => workers.cancel(task),
        Output::Encode(job) => {
            let Some(edge) = sessions.get_mut(&job.session) else { return };
            edge.waiting.push_back(job);
            next_encode(edge, events, compositor);
        }
        Output::Heartbeat { sessions: count, free_rays_per_s, saturated } => {
            let _ = to_signal.send(ToSignal::Heartbeat { sessions: count, free_rays_per_s, saturated });
        }
        Output::Timeout(_) => {}
    }
}

/// Starts the session's next waiting frame if its encoder is home (or not made yet).
fn next_encode(edge: &mut SessionEdge, events: &mpsc::UnboundedSender<Event>, compositor: &Arc<Compositor>) {
    if edge.encoder.is_none() && edge.encoder_made {
        return; // busy with the previous frame
    }
    let Some(job) = edge.waiting.pop_front() else { return };
    let encoder = edge.encoder.take();
    edge.encoder_made = true;
    let (events, started, config, compositor) = (events.clone(), edge.started, edge.encoder_config, Arc::clone(compositor));
    tokio::task::spawn_blocking(move || {
        let (session, frame) = (job.session.clone(), job.frame);
        let made = encoder.map_or_else(|| FrameEncoder::new(config).map_err(|e| format!("cannot create the encoder: {e}")), Ok);
        let (encoder, result) = match made {
            Ok(encoder) => {
                let (encoder, result) = encode(encoder, &job, started, &compositor);
                (Some(Box::new(encoder)), result)
            }
            Err(e) => (None, Err(e)),
        };
        let _ = events.send(Event::Encoded { session, frame, encoder, result });
    });
}

/// One encoded frame, and its depth if the session asked for it.
struct Encoded {
    access_unit: Bytes,
    times: FrameTimes,
    /// The encoded depth message, its RTP ticks still 0: set when the frame is sent.
    depth: Option<Vec<u8>>,
}

/// The depth of each view of the frame (docs/architecture.md §5 "Depth"): the nearest hit of
/// its objects, at the render scale. `None` when a part came without depth (a history hit
/// from a remote worker's task that did not carry it).
fn frame_depth(job: &EncodeJob) -> Option<DepthFrame> {
    let viewports: Vec<nephele_wire::Viewport> = job.views.iter().map(|v| v.viewport).collect();
    let stride = nephele_wire::depth::stride_for(&viewports);
    let views = job
        .views
        .iter()
        .map(|v| {
            let first = v.parts.first()?;
            let layers: Vec<&[f32]> = v.parts.iter().map(|p| &p.depth[..]).collect();
            if layers.iter().any(|l| l.len() != (first.width * first.height) as usize) {
                return None;
            }
            Some(DepthView::build(&v.camera, v.viewport, &layers, first.width, first.height, stride, nephele_wire::depth::DEPTH_LEVELS))
        })
        .collect::<Option<Vec<_>>>()?;
    Some(DepthFrame { frame: job.frame, pose_seq: job.pose_seq, rtp_ticks: 0, views })
}

/// Blocking: compose each view's objects if several, upscale each view to its viewport if
/// needed, tile the views into the frame, convert and encode; build the depth message.
fn encode(mut encoder: FrameEncoder, job: &EncodeJob, session_start: Instant, compositor: &Compositor) -> (FrameEncoder, Result<Encoded, String>) {
    let _span = tracing::trace_span!("frame", session = %job.session, frame = job.frame, pose = job.pose_seq).entered();
    let (w, h) = (job.width, job.height);
    let t_compose = Instant::now();
    let frame = match assemble(job, compositor) {
        Ok(f) => f,
        Err(e) => return (encoder, Err(e)),
    };
    let compose_ms = t_compose.elapsed().as_secs_f64() * 1e3;
    let ready_ms = job.started_at.elapsed().as_secs_f64() * 1e3;
    let rgba: &[u8] = &frame;
    if job.idr {
        encoder.force_idr();
    }
    let t_ms = job.started_at.saturating_duration_since(session_start).as_millis() as u64;
    let result = encoder
        .encode_at(rgba, w, h, u64::from(job.pose_seq), t_ms)
        .map(|f| {
            let t_depth = Instant::now();
            let depth = job.depth.then(|| frame_depth(job)).flatten().map(|d| d.encode());
            let depth_ms = if job.depth { t_depth.elapsed().as_secs_f64() * 1e3 } else { 0.0 };
            let times = FrameTimes { compose_ms, ready_ms, convert_ms: f.convert_ms, encode_ms: f.encode_ms, bytes: f.annex_b.len(), idr: f.is_idr, depth_ms, ..Default::default() };
            Encoded { access_unit: Bytes::from(f.annex_b), times, depth }
        })
        .map_err(|e| format!("encode: {e}"));
    (encoder, result)
}

/// A view's pixels at its viewport size: its objects composed by depth (if several), then
/// upscaled from the render scale.
fn view_pixels<'a>(view: &'a EncodeView, compose_over: Option<glam::Vec3>, compositor: &Compositor) -> Result<std::borrow::Cow<'a, [u8]>, String> {
    use std::borrow::Cow;
    let composed = match compose_over {
        Some(background) if view.parts.len() > 1 => Some(compositor.compose(&view.parts, background).map_err(|e| format!("compose: {e}"))?),
        _ => None,
    };
    let (vw, vh) = (view.viewport.width, view.viewport.height);
    let (pw, ph) = match (&composed, view.parts.first()) {
        (Some(c), _) => (c.width, c.height),
        (None, Some(p)) => (p.width, p.height),
        (None, None) => return Err("a view with no rendered parts (internal error)".into()),
    };
    Ok(match composed {
        Some(c) if (pw, ph) == (vw, vh) => Cow::Owned(c.rgba),
        Some(c) => Cow::Owned(upscale_bilinear(&c.rgba, pw, ph, vw, vh)),
        None if (pw, ph) == (vw, vh) => Cow::Borrowed(&view.parts[0].rgba[..]),
        None => Cow::Owned(upscale_bilinear(&view.parts[0].rgba, pw, ph, vw, vh)),
    })
}

/// The frame's RGBA: one view filling it, or the views tiled at their viewports over black.
fn assemble<'a>(job: &'a EncodeJob, compositor: &Compositor) -> Result<std::borrow::Cow<'a, [u8]>, String> {
    let (w, h) = (job.width, job.height);
    if let [view] = &job.views[..]
        && view.viewport == nephele_wire::Viewport::full(w, h)
    {
        return view_pixels(view, job.compose_over, compositor);
    }
    let mut frame = [0u8, 0, 0, 255].repeat(w as usize * h as usize);
    for view in &job.views {
        let pixels = view_pixels(view, job.compose_over, compositor)?;
        let r = view.viewport;
        if r.x + r.width > w || r.y + r.height > h {
            return Err(format!("view at {},{} {}x{} is outside the {w}x{h} frame (internal error)", r.x, r.y, r.width, r.height));
        }
        let row_bytes = 4 * r.width as usize;
        for (y, src) in pixels.chunks_exact(row_bytes).enumerate() {
            let at = 4 * ((r.y as usize + y) * w as usize + r.x as usize);
            frame[at..at + row_bytes].copy_from_slice(src);
        }
    }
    Ok(std::borrow::Cow::Owned(frame))
}

/// One session's WebRTC connection: answers, trickles ICE, sends what it is told in order,
/// and reports what happens. A panic inside ends this session only.
async fn peer_task(
    session: String,
    api: Arc<nephele_rtc::RtcApi>,
    commands: mpsc::UnboundedReceiver<PeerCommand>,
    events: mpsc::UnboundedSender<Event>,
    to_signal: mpsc::UnboundedSender<ToSignal>,
) {
    let (id, ev) = (session.clone(), events.clone());
    let outcome = tokio::spawn(peer_loop(session, api, commands, events, to_signal)).await;
    if let Err(e) = outcome {
        let _ = ev.send(Event::Peer(id, PeerEvent::Closed(format!("internal error in the session ({e})"))));
    }
}

async fn peer_loop(
    session: String,
    api: Arc<nephele_rtc::RtcApi>,
    mut commands: mpsc::UnboundedReceiver<PeerCommand>,
    events: mpsc::UnboundedSender<Event>,
    to_signal: mpsc::UnboundedSender<ToSignal>,
) {
    let (ev_tx, mut peer_events) = mpsc::channel::<PeerEvent>(256);
    let peer = match WebrtcPeer::new(&api, ev_tx).await {
        Ok(p) => p,
        Err(e) => {
            let _ = events.send(Event::Peer(session, PeerEvent::Closed(format!("cannot create a peer connection: {e:#}"))));
            return;
        }
    };
    // The RTP clock as the track's packetizer advances it: each sample moves it by its
    // duration in whole 90 kHz ticks.
    let mut rtp_ticks = 0u32;
    loop {
        tokio::select! {
            cmd = commands.recv() => match cmd {
                None | Some(PeerCommand::Close) => break,
                Some(PeerCommand::Offer(sdp)) => match peer.answer(&sdp).await {
                    Ok(answer) => { let _ = to_signal.send(ToSignal::Answer { session: session.clone(), sdp: answer }); }
                    Err(e) => { let _ = events.send(Event::Peer(session.clone(), PeerEvent::Closed(format!("bad offer: {e:#}")))); }
                },
                Some(PeerCommand::Ice(candidate)) => if let Err(e) = peer.add_remote_ice(&candidate).await {
                    tracing::debug!(%session, "ignoring a bad ICE candidate: {e:#}");
                },
                Some(PeerCommand::Video { access_unit, duration, frame, mut times, depth }) => {
                    let t = Instant::now();
                    times.rtp_ticks = rtp_ticks;
                    // The depth goes first (it is on the data channel, the picture on RTP): a
                    // client has it by the time the picture decodes.
                    if let Some(mut depth) = depth {
                        nephele_wire::depth::set_rtp_ticks(&mut depth, rtp_ticks);
                        let bytes = Bytes::from(depth);
                        times.depth_bytes = bytes.len();
                        if let Err(e) = peer.send_binary(bytes).await {
                            tracing::debug!(%session, "depth send failed: {e:#}");
                        }
                    }
                    let ev = match peer.send_video(access_unit, duration).await {
                        Ok(()) => {
                            rtp_ticks = rtp_ticks.wrapping_add((duration.as_secs_f64() * f64::from(nephele_rtc::H264_CLOCK_HZ)) as u32);
                            times.send_ms = t.elapsed().as_secs_f64() * 1e3;
                            Event::Sent { session: session.clone(), frame, times }
                        }
                        Err(e) => Event::SendFailed { session: session.clone(), frame, error: format!("{e:#}") },
                    };
                    let _ = events.send(ev);
                }
                Some(PeerCommand::Text(text)) => if let Err(e) = peer.send_text(text).await {
                    tracing::debug!(%session, "pose channel send failed: {e:#}");
                },
            },
            ev = peer_events.recv() => match ev {
                None => break,
                Some(PeerEvent::LocalIce(candidate)) => {
                    let _ = to_signal.send(ToSignal::Ice { session: Some(session.clone()), candidate });
                }
                Some(ev) => { let _ = events.send(Event::Peer(session.clone(), ev)); }
            },
        }
    }
    peer.close().await;
}

/// Keeps one registered websocket to signaling, reconnecting with back-off (0.5 s doubling
/// to 10 s, back to 0.5 s after a successful registration).
async fn signaling_link(
    url: String,
    register: ToSignal,
    events: mpsc::UnboundedSender<Event>,
    mut outbox: mpsc::UnboundedReceiver<ToSignal>,
    mut flushes: mpsc::UnboundedReceiver<oneshot::Sender<()>>,
    health: Health,
) {
    let mut backoff = Duration::from_millis(500);
    loop {
        let outcome = link_once(&url, &register, &events, &mut outbox, &mut flushes, &mut backoff, &health).await;
        health.fail("signaling", "the connection to signaling is lost; reconnecting");
        match outcome {
            Ok(()) => tracing::warn!("signaling closed the connection; reconnecting"),
            Err(LinkError::Refused(why)) => {
                let _ = events.send(Event::Fatal(format!("signaling refused our token: {why}")));
                return;
            }
            Err(LinkError::Other(e)) => tracing::warn!("signaling connection: {e:#}"),
        }
        if events.is_closed() {
            return;
        }
        tokio::time::sleep(backoff).await;
        backoff = (backoff * 2).min(Duration::from_secs(10));
    }
}

enum LinkError {
    Refused(String),
    Other(anyhow::Error),
}

impl<E: Into<anyhow::Error>> From<E> for LinkError {
    fn from(e: E) -> Self {
        Self::Other(e.into())
    }
}

async fn link_once(
    url: &str,
    register: &ToSignal,
    events: &mpsc::UnboundedSender<Event>,
    outbox: &mut mpsc::UnboundedReceiver<ToSignal>,
    flushes: &mut mpsc::UnboundedReceiver<oneshot::Sender<()>>,
    backoff: &mut Duration,
    health: &Health,
) -> Result<(), LinkError> {
    let (ws, _) = tokio_tungstenite::connect_async(url).await.with_context(|| format!("connecting to {url}"))?;
    let (mut ws_tx, mut ws_rx) = ws.split();
    ws_tx.send(Message::text(serde_json::to_string(register)?)).await?;
    loop {
        tokio::select! {
            msg = ws_rx.next() => {
                let text = match msg {
                    None | Some(Ok(Message::Close(_))) => return Ok(()),
                    Some(Err(e)) => return Err(e.into()),
                    Some(Ok(Message::Text(t))) => t,
                    Some(Ok(_)) => continue,
                };
                let msg: ToMaster = match serde_json::from_str(&text) {
                    Ok(m) => m,
                    Err(e) => { tracing::warn!("unreadable message from signaling: {e}"); continue }
                };
                match &msg {
                    ToMaster::Registered { .. } => {
                        *backoff = Duration::from_millis(500);
                        health.pass("signaling");
                    }
                    ToMaster::Error { code: nephele_signaling::ErrorCode::Unauthorized, message } => return Err(LinkError::Refused(message.clone())),
                    _ => {}
                }
                if events.send(Event::Signal(msg)).is_err() {
                    return Ok(());
                }
            }
            out = outbox.recv() => {
                let Some(out) = out else { return Ok(()) };
                ws_tx.send(Message::text(serde_json::to_string(&out)?)).await?;
            }
            // Everything queued before the request goes out, then it is answered.
            Some(done) = flushes.recv() => {
                while let Ok(out) = outbox.try_recv() {
                    ws_tx.send(Message::text(serde_json::to_string(&out)?)).await?;
                }
                ws_tx.flush().await?;
                let _ = done.send(());
            }
        }
    }
}
