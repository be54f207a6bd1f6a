//! The master's Prometheus metrics (`GET /metrics`, OpenMetrics text, `prometheus-client`):
//! per-user target and achieved FPS and render scale, starvation events, refusals by reason,
//! the task queue of each farm, batch sizes, render and encode times (seconds), history hits
//! and the farm's measured throughput. The core reports events ([`CoreEvent`]); the driver
//! records them here (plain atomics, no IO) and the HTTP edge encodes the registry on
//! request. A user's series go when the user leaves, a worker's when it is lost.

use prometheus_client::{
    encoding::EncodeLabelSet,
    metrics::{
        counter::Counter,
        family::Family,
        gauge::Gauge,
        histogram::{Histogram, exponential_buckets},
    },
    registry::{Registry, Unit},
};
use std::sync::atomic::AtomicU64;

use nephele_core::events::CoreEvent;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct SessionLabel {
    pub session: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct WorkerLabel {
    pub worker: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ReasonLabel {
    pub reason: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct FarmLabel {
    /// `heavy` or `light`.
    pub farm: &'static str,
}

type GaugeF64 = Gauge<f64, AtomicU64>;

/// Every metric of one master.
pub struct MasterMetrics {
    registry: Registry,
    pub users: Gauge,
    pub target_fps: Family<SessionLabel, GaugeF64>,
    pub achieved_fps: Family<SessionLabel, GaugeF64>,
    pub render_scale: Family<SessionLabel, GaugeF64>,
    pub starvation_events: Counter,
    pub refusals: Family<ReasonLabel, Counter>,
    pub task_queue_depth: Family<FarmLabel, Gauge>,
    pub tasks_in_flight: Gauge,
    pub rays_in_flight: Gauge,
    pub tasks_cancelled: Counter,
    pub batch_views: Histogram,
    pub batch_users: Histogram,
    pub render_seconds: Histogram,
    pub encode_seconds: Histogram,
    pub frames: Counter,
    pub frames_failed: Counter,
    pub history_hits: Counter,
    pub farm_rays_per_s: GaugeF64,
    pub heap_in_use_bytes: Gauge,
    pub workers: Gauge,
    pub workers_lost: Counter,
    pub tasks_rendered: Family<WorkerLabel, Counter>,
}

impl Default for MasterMetrics {
    fn default() -> Self {
        Self::new()
    }
}

impl MasterMetrics {
    /// A master's metrics (`nephele master`).
    pub fn new() -> Self {
        Self::with_registry(nephele_signaling::metrics::registry("master"))
    }

    /// `nephele serve`: the master's metrics and signaling's in one registry.
    pub fn serving(signaling: &nephele_signaling::SignalState) -> Self {
        let mut registry = nephele_signaling::metrics::registry("serve");
        nephele_signaling::metrics::register_signaling(&mut registry, signaling);
        Self::with_registry(registry)
    }

    fn with_registry(mut registry: Registry) -> Self {
        let m = Self {
            users: Gauge::default(),
            target_fps: Family::default(),
            achieved_fps: Family::default(),
            render_scale: Family::default(),
            starvation_events: Counter::default(),
            refusals: Family::default(),
            task_queue_depth: Family::default(),
            tasks_in_flight: Gauge::default(),
            rays_in_flight: Gauge::default(),
            tasks_cancelled: Counter::default(),
            batch_views: Histogram::new(exponential_buckets(1.0, 2.0, 8)),
            batch_users: Histogram::new(exponential_buckets(1.0, 2.0, 8)),
            render_seconds: Histogram::new(exponential_buckets(0.001, 2.0, 14)),
            encode_seconds: Histogram::new(exponential_buckets(0.000_25, 2.0, 12)),
            frames: Counter::default(),
            frames_failed: Counter::default(),
            history_hits: Counter::default(),
            farm_rays_per_s: GaugeF64::default(),
            heap_in_use_bytes: Gauge::default(),
            workers: Gauge::default(),
            workers_lost: Counter::default(),
            tasks_rendered: Family::default(),
            registry: Registry::default(),
        };
        registry.register("users", "Admitted users (sessions)", m.users.clone());
        registry.register("user_target_fps", "Frame rate each user asked for", m.target_fps.clone());
        registry.register("user_achieved_fps", "Frame rate each user gets (moving average)", m.achieved_fps.clone());
        registry.register("user_render_scale", "Render scale of each user's moving camera", m.render_scale.clone());
        registry.register("starvation_events", "Users falling behind their target time by more than the grace", m.starvation_events.clone());
        registry.register("refusals", "Joins refused, by reason", m.refusals.clone());
        registry.register("task_queue_depth", "Render tasks formed and waiting for a worker of each farm", m.task_queue_depth.clone());
        registry.register("tasks_in_flight", "Render tasks on workers", m.tasks_in_flight.clone());
        registry.register("rays_in_flight", "Primary rays of the render tasks on workers", m.rays_in_flight.clone());
        registry.register("tasks_cancelled", "Render tasks dropped because every user of them left", m.tasks_cancelled.clone());
        registry.register("batch_views", "Views per render task", m.batch_views.clone());
        registry.register("batch_users", "Users per render task", m.batch_users.clone());
        registry.register_with_unit("render", "Render time per task, as its worker measured it", Unit::Seconds, m.render_seconds.clone());
        registry.register_with_unit("encode", "RGB to I420 plus H.264 encode time per frame", Unit::Seconds, m.encode_seconds.clone());
        registry.register("frames", "Frames sent", m.frames.clone());
        registry.register("frames_failed", "Frames that failed to render or encode", m.frames_failed.clone());
        registry.register("history_hits", "Frames served from the history table or a user's own last frame", m.history_hits.clone());
        registry.register("farm_rays_per_second", "Measured render throughput of the farm, rays per second", m.farm_rays_per_s.clone());
        registry.register("heap_in_use_bytes", "Bytes the process's allocator has handed out and not had back (live heap), read when scraped", m.heap_in_use_bytes.clone());
        registry.register("workers", "Render workers up", m.workers.clone());
        registry.register("workers_lost", "Render workers that left or were lost", m.workers_lost.clone());
        registry.register("tasks_rendered", "Render tasks rendered, by the worker that rendered them", m.tasks_rendered.clone());
        Self { registry, ..m }
    }

    /// The metrics as OpenMetrics text (what Prometheus scrapes).
    pub fn encode(&self) -> String {
        if let Some(bytes) = crate::memory::heap_in_use() {
            self.heap_in_use_bytes.set(i64::try_from(bytes).unwrap_or(i64::MAX));
        }
        nephele_signaling::metrics::encode_text(&self.registry)
    }

    /// Turns what the core reported into series (the core knows no metrics library).
    pub fn record(&self, event: &CoreEvent) {
        match event {
            CoreEvent::UserAdmitted { session, target_fps, scale } => {
                let l = SessionLabel { session: session.clone() };
                self.target_fps.get_or_create(&l).set(*target_fps);
                self.render_scale.get_or_create(&l).set(f64::from(*scale));
            }
            CoreEvent::UserLeft { session } => self.forget_user(session),
            CoreEvent::Users { count } => {
                self.users.set(i64::try_from(*count).unwrap_or(i64::MAX));
            }
            CoreEvent::Refused { reason } => self.refuse(reason),
            CoreEvent::RenderScale { session, scale } => {
                self.render_scale.get_or_create(&SessionLabel { session: session.clone() }).set(f64::from(*scale));
            }
            CoreEvent::Starved => {
                self.starvation_events.inc();
            }
            CoreEvent::Queue { waiting_heavy, waiting_light, in_flight, rays_in_flight, farm_rays_per_s } => {
                for (farm, waiting) in [("heavy", waiting_heavy), ("light", waiting_light)] {
                    self.task_queue_depth.get_or_create(&FarmLabel { farm }).set(i64::try_from(*waiting).unwrap_or(i64::MAX));
                }
                self.tasks_in_flight.set(i64::try_from(*in_flight).unwrap_or(i64::MAX));
                self.rays_in_flight.set(i64::try_from(*rays_in_flight).unwrap_or(i64::MAX));
                self.farm_rays_per_s.set(*farm_rays_per_s);
            }
            CoreEvent::TaskFormed { views, users } => {
                self.batch_views.observe(*views as f64);
                self.batch_users.observe(*users as f64);
            }
            CoreEvent::TaskCancelled => {
                self.tasks_cancelled.inc();
            }
            CoreEvent::TaskRendered { render_ms, worker, ok } => {
                self.render_seconds.observe(render_ms / 1e3);
                if *ok {
                    self.tasks_rendered.get_or_create(&WorkerLabel { worker: worker.clone() }).inc();
                }
            }
            CoreEvent::WorkerUp { workers, .. } => {
                self.workers.set(i64::try_from(*workers).unwrap_or(i64::MAX));
            }
            CoreEvent::WorkerLost { worker, workers } => {
                self.workers.set(i64::try_from(*workers).unwrap_or(i64::MAX));
                self.workers_lost.inc();
                self.tasks_rendered.remove(&WorkerLabel { worker: worker.clone() });
            }
            CoreEvent::HistoryHit => {
                self.history_hits.inc();
            }
            CoreEvent::FrameFailed => {
                self.frames_failed.inc();
            }
            CoreEvent::FrameSent { session, encode_ms, achieved_fps } => {
                self.frames.inc();
                self.encode_seconds.observe(encode_ms / 1e3);
                self.achieved_fps.get_or_create(&SessionLabel { session: session.clone() }).set(*achieved_fps);
            }
        }
    }

    pub fn refuse(&self, reason: &str) {
        self.refusals.get_or_create(&ReasonLabel { reason: reason.into() }).inc();
    }

    pub fn forget_user(&self, session: &str) {
        let l = SessionLabel { session: session.into() };
        self.target_fps.remove(&l);
        self.achieved_fps.remove(&l);
        self.render_scale.remove(&l);
    }
}
