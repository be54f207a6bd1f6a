//! The master node's IO edge (docs/architecture.md §5–6): pairs with clients through
//! signaling, admits and schedules their frames with the sans-IO core (`nephele-core`), has
//! them rendered by the farm (`nephele-farm`), encodes and streams them.
//!
//! - [`driver`]: the event loop that runs the core and carries out what it says, and the
//!   signaling link;
//! - [`peer`]: one WebRTC connection per client; [`encoder`]: RGB → I420 → H.264 per
//!   session, after [`compositor`] has composed a multi-object frame by depth;
//! - [`nats_farm`]: the client side of the NATS render farm (the in-process workers are
//!   `nephele_farm::local`);
//! - [`metrics`]: what `GET /metrics` shows, recorded from the core's events; [`memory`]:
//!   freed memory handed back after sessions end;
//! - [`web`]: the HTTP side of `nephele serve` (pages, `/signal`, `/status`, `/metrics`).

pub mod compositor;
pub mod driver;
pub mod encoder;
pub mod memory;
pub mod metrics;
pub mod nats_farm;
pub mod peer;
pub mod web;

pub use driver::{DRAIN_REASON, Lifecycle, MasterConfig, run, run_with};
