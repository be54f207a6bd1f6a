//! What the core reports of itself: every countable thing that happened, as plain values.
//! The core knows no metrics library; the master's edge drains these after each input
//! ([`crate::MasterCore::drain_events`]) and turns them into Prometheus series, and tests and
//! benchmarks may count them directly.

/// One thing that happened inside the core.
#[derive(Debug, Clone, PartialEq)]
pub enum CoreEvent {
    /// A user was admitted, asking for `target_fps` at render scale `scale`.
    UserAdmitted { session: String, target_fps: f64, scale: f32 },
    /// A user's session ended; per-user series of it are to be dropped.
    UserLeft { session: String },
    /// The number of admitted users changed.
    Users { count: usize },
    /// A join was refused; `reason` is the stable code the client sees.
    Refused { reason: &'static str },
    /// The fair scale moved a user's render scale.
    RenderScale { session: String, scale: f32 },
    /// A user fell behind its target time by more than the grace.
    Starved,
    /// The queue and the farm after a scheduling pass: tasks waiting for each farm (heavy,
    /// light), tasks on workers and their primary rays, and the farm's calibrated rays per
    /// second.
    Queue { waiting_heavy: usize, waiting_light: usize, in_flight: usize, rays_in_flight: u64, farm_rays_per_s: f64 },
    /// A render task was formed with this many views for this many users.
    TaskFormed { views: usize, users: usize },
    /// A render task was dropped because every user of it left.
    TaskCancelled,
    /// A render task came back after `render_ms` from `worker`, rendered (`ok`) or not.
    TaskRendered { render_ms: f64, worker: String, ok: bool },
    /// A render worker joined the farm (`workers` are up now).
    WorkerUp { worker: String, workers: usize },
    /// A render worker left or was lost (`workers` are up now).
    WorkerLost { worker: String, workers: usize },
    /// A frame was served from the history table (or a user's own last frame).
    HistoryHit,
    /// A frame failed to render or encode.
    FrameFailed,
    /// A frame was encoded in `encode_ms` (RGB → I420 plus H.264) and sent; the user now
    /// gets `achieved_fps` on average.
    FrameSent { session: String, encode_ms: f64, achieved_fps: f64 },
}
