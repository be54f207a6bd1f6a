//! The master's Prometheus metrics (`GET /metrics`, OpenMetrics text, `prometheus-client`):
//! per-user target and achieved FPS and render scale, starvation events, refusals by reason,
//! the task queue, batch sizes, render and encode times, history hits and the farm's
//! measured throughput. The core reports events ([`CoreEvent`]); the driver records them here
//! (plain atomics, no IO) and the HTTP edge encodes the registry on request.

use prometheus_client::{
    encoding::{EncodeLabelSet, text::encode},
    metrics::{
        counter::Counter,
        family::Family,
        gauge::Gauge,
        histogram::{Histogram, exponential_buckets},
    },
    registry::Registry,
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
    pub task_queue_depth: Gauge,
    pub tasks_in_flight: Gauge,
    pub rays_in_flight: Gauge,
    pub tasks_cancelled: Counter,
    pub batch_views: Histogram,
    pub batch_users: Histogram,
    pub render_ms: Histogram,
    pub encode_ms: Histogram,
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
    pub fn new() -> Self {
        let mut registry = Registry::with_prefix("nephele");
        let m = Self {
            users: Gauge::default(),
            target_fps: Family::default(),
            achieved_fps: Family::default(),
            render_scale: Family::default(),
            starvation_events: Counter::default(),
            refusals: Family::default(),
            task_queue_depth: Gauge::default(),
            tasks_in_flight: Gauge::default(),
            rays_in_flight: Gauge::default(),
            tasks_cancelled: Counter::default(),
            batch_views: Histogram::new(exponential_buckets(1.0, 2.0, 8)),
            batch_users: Histogram::new(exponential_buckets(1.0, 2.0, 8)),
            render_ms: Histogram::new(exponential_buckets(1.0, 2.0, 14)),
            encode_ms: Histogram::new(exponential_buckets(0.25, 2.0, 12)),
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
        registry.register("task_queue_depth", "Render tasks formed and waiting for a worker", m.task_queue_depth.clone());
        registry.register("tasks_in_flight", "Render tasks on workers", m.tasks_in_flight.clone());
        registry.register("rays_in_flight", "Primary rays of the render tasks on workers", m.rays_in_flight.clone());
        registry.register("tasks_cancelled", "Render tasks dropped because every user of them left", m.tasks_cancelled.clone());
        registry.register("batch_views", "Views per render task", m.batch_views.clone());
        registry.register("batch_users", "Users per render task", m.batch_users.clone());
        registry.register("render_ms", "Render time per task, ms", m.render_ms.clone());
        registry.register("encode_ms", "RGB to I420 plus H.264 encode time per frame, ms", m.encode_ms.clone());
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
        let mut out = String::new();
        // Writing into a String cannot fail.
        encode(&mut out, &self.registry).expect("metrics encode into a String");
        out
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
            CoreEvent::Queue { depth, in_flight, rays_in_flight, farm_rays_per_s } => {
                self.task_queue_depth.set(i64::try_from(*depth).unwrap_or(i64::MAX));
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
                self.render_ms.observe(*render_ms);
                if *ok {
                    self.tasks_rendered.get_or_create(&WorkerLabel { worker: worker.clone() }).inc();
                }
            }
            CoreEvent::WorkerUp { workers, .. } => {
                self.workers.set(i64::try_from(*workers).unwrap_or(i64::MAX));
            }
            CoreEvent::WorkerLost { workers, .. } => {
                self.workers.set(i64::try_from(*workers).unwrap_or(i64::MAX));
                self.workers_lost.inc();
            }
            CoreEvent::HistoryHit => {
                self.history_hits.inc();
            }
            CoreEvent::FrameFailed => {
                self.frames_failed.inc();
            }
            CoreEvent::FrameSent { session, encode_ms, achieved_fps } => {
                self.frames.inc();
                self.encode_ms.observe(*encode_ms);
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
