//! The render farm (docs/architecture.md §6): what turns a render task into frames, shared by
//! the master's in-process workers and `nephele worker` on other machines.
//!
//! - [`assets`]: where assets and backends come from (a `.nolf` path, the embedded lego,
//!   procedural scenes) and the renderer's speed-for-accuracy knobs as flags;
//! - [`catalog`]: the scenes a process serves, each asset prepared once on its backend;
//! - [`local`]: running a task on a backend, calibration, and the in-process worker pool;
//! - [`protocol`]: how masters and workers talk over NATS, written once for both;
//! - [`worker`]: the `nephele worker` process loop.
//!
//! The farm knows the core's task types and nothing of the master's edge (peers, encoder,
//! metrics): the master depends on this crate, never the other way round.

pub mod assets;
pub mod catalog;
pub mod local;
pub mod protocol;
pub mod worker;
