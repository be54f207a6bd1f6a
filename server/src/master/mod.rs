//! The master node (DESIGN §5–6): pairs with clients through signaling, admits and
//! schedules their frames, renders them on its workers, encodes and streams them.
//!
//! - [`core`]: the sans-IO heart — sessions, admission, NEPHELE's scheduler (Algorithm 1),
//!   render tasks, the history table, frame rules; tested on simulated time.
//! - the edge drivers around it: [`driver`] (the event loop and signaling link), [`peer`]
//!   (one WebRTC connection per client), [`encoder`] (RGB → I420 → H.264 per session,
//!   after [`compositor`] has composed a multi-object frame by depth), and the render
//!   workers: [`workers`] (in-process threads, the default) or [`nats_farm`] (worker
//!   processes on other machines, reached through NATS);
//! - [`metrics`]: what `GET /metrics` shows; [`memory`]: freed memory handed back after sessions end.

pub mod compositor;
pub mod core;
pub mod driver;
pub mod encoder;
pub mod memory;
pub mod metrics;
pub mod nats_farm;
pub mod peer;
pub mod workers;

pub use driver::{MasterConfig, run};
