//! Nephele master node: asset loading, render backends, benchmarks, and (as they land)
//! sessions, scheduler, encoder and WebRTC transport. The `nephele` binary is the CLI.

pub mod assets;
pub mod bench;
pub mod client;
pub mod encode;
pub mod farm;
pub mod master;
pub mod plot;
pub mod replay;
pub mod rtc;
pub mod session;
pub mod tradeoff;
pub mod train_cli;
pub mod web;
pub mod wire;
