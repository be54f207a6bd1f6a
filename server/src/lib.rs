//! Nephele master node: asset loading, render backends, benchmarks, and (as they land)
//! sessions, scheduler, encoder and WebRTC transport. The `nephele` binary is the CLI.

pub mod assets;
pub mod bench;
pub mod encode;
