//! Nephele signaling: pairs browser/replay clients with master (render) nodes and
//! relays WebRTC SDP and ICE between them over one websocket endpoint, `/signal`.
//!
//! - [`protocol`]: the JSON messages (the `nephele-protocol` crate), shared with the master
//!   node, the replay client and the web page.
//! - [`hub`]: the sans-IO state machine that pairs and routes.
//! - [`server`]: the axum edge: websockets, `/status`, the heartbeat tick.
//! - [`health`], [`metrics`]: `/healthz`, `/readyz` and `/metrics` as every role serves them.
//!
//! This crate knows nothing about rendering.

/// The messages, defined once in `nephele-protocol` (shared with masters and clients).
pub use nephele_protocol as protocol;

pub mod health;
pub mod hub;
pub mod metrics;
pub mod net;
pub mod server;

pub use hub::{ConnId, Hub, HubConfig, HubStats, MasterStats, Outgoing, SignalError};
pub use protocol::{ErrorCode, Mode, QuiltSpec, ToClient, ToMaster, ToPeer, ToSignal};
pub use health::Health;
pub use net::{ConnGate, ConnPermit, serve_limited};
pub use server::{SignalState, app, serve};
