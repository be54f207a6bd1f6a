//! The `nephele` command: one binary over the workspace's crates, each a room of its own
//! (docs/architecture.md §2):
//!
//! - `nephele-core`: the master's sans-IO core; `nephele-master`: its IO edge;
//! - `nephele-farm`: render tasks, calibration, NATS workers; `nephele-client`: the headless
//!   streaming client; `nephele-bench`: the `nephele bench …` commands;
//! - `nephele-renderer` and (with the `train` feature, on by default) `nephele-train`.
//!
//! This crate holds only [`cli`]: each subcommand's arguments and its body.

pub mod cli;
