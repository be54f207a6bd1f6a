//! The `nephele bench …` commands: whole-system measurements that print tables (and, with
//! `--json`, the same figures as JSON on stdout with the table on stderr). Each runs in the
//! test suite at a tiny size, so a later change cannot break one unseen.
//!
//! - [`render`]: where a frame's time goes, per backend and size, against the FMA floor;
//! - [`encode`]: RGB→I420 and H.264 encode times, bytes and PSNR;
//! - [`stream`]: per-stage and end-to-end latency through an in-process server;
//! - [`users`]: many users on one server, batching on and off (NEPHELE §6.2);
//! - [`farm`]: the NATS render farm against the in-process worker, and failover;
//! - [`abuse`]: a viewer's frame rate while the server is attacked;
//! - [`glass`]: what the eye sees at added round trips, with and without reprojection and
//!   pose prediction;
//! - `quilt` and `tradeoff` (with the `train` feature: they need an i-NGP teacher): Looking
//!   Glass quilts, and the speed/accuracy trade of NEPHELE's Table 5 and Fig. 14.
//!
//! [`plot`] draws their charts.

pub mod abuse;
pub mod encode;
pub mod farm;
pub mod glass;
pub mod plot;
#[cfg(feature = "train")]
pub mod quilt;
pub mod render;
pub mod stream;
#[cfg(feature = "train")]
pub mod tradeoff;
pub mod users;

use anyhow::Result;
use serde::Serialize;

#[derive(clap::Subcommand)]
pub enum BenchCommand {
    /// The speed/accuracy table (NEPHELE Table 5) and distance sweep (Fig. 14) from a trained
    /// i-NGP checkpoint: trains the i-NOLF variants, scores held-out views, times frames.
    #[cfg(feature = "train")]
    Tradeoff(tradeoff::TradeoffArgs),
    /// RGB→I420 and H.264 encode times on a moving test pattern and on real content (an asset
    /// orbiting, rendered on the CPU before the timing starts).
    Encode(encode::EncodeArgs),
    /// Per-stage and end-to-end streaming latency through an in-process server and the
    /// replay client, per frame size.
    Stream(stream::StreamArgs),
    /// Ray-march / network / total ms, rays/s and hit fraction per backend and size.
    Render(render::RenderArgs),
    /// Many users on one server (NEPHELE §6.2): 1, 2, 4, 8 real replay clients, each
    /// replaying the orbit at its own phase, with batching on and off, per backend; plus
    /// two clients sharing one view (history hits).
    Users(users::UsersArgs),
    /// The render farm on NATS (its own nats-server and worker processes) against the
    /// in-process worker: frame time, the NATS hop, NEPHELE Eq. 9 for a composed scene, and
    /// the failover gap when a worker is killed.
    Farm(farm::FarmArgs),
    /// Looking Glass quilts (NEPHELE §7): a 45-view quilt's frame time for i-NOLF (one task,
    /// and 45 separate renders) and its i-NGP teacher, per backend in one run; and streaming
    /// stereo (both eyes in one task) against mono at the same total pixels.
    #[cfg(feature = "train")]
    Quilt(quilt::QuiltBenchArgs),
    /// A well-behaved viewer against thousands of idle connections, a relay flood, a 4K
    /// join/leave loop and an empty-message loop at once, on a `nephele serve` child: its
    /// frame rate before, during and after, and the server's peak memory.
    Abuse(abuse::AbuseArgs),
    /// What the eye sees: a motion trace through a real server at added round trips
    /// (0–150 ms), a 60 Hz display showing each display frame stale, reprojected by depth,
    /// predicted, or both; PSNR against a direct render at the true pose, pose age, bytes.
    Glass(glass::GlassArgs),
}

/// Runs one `nephele bench` subcommand.
pub fn run(what: BenchCommand) -> Result<()> {
    match what {
        #[cfg(feature = "train")]
        BenchCommand::Tradeoff(args) => tradeoff::run_args(args),
        BenchCommand::Encode(args) => encode::run(args),
        BenchCommand::Stream(args) => stream::run(args),
        BenchCommand::Render(args) => render::run(args),
        BenchCommand::Users(args) => users::run(args),
        BenchCommand::Farm(args) => farm::run(args),
        #[cfg(feature = "train")]
        BenchCommand::Quilt(args) => quilt::run(args),
        BenchCommand::Abuse(args) => abuse::run(args),
        BenchCommand::Glass(args) => glass::run(args),
    }
}

/// Prints a bench's result: its table on stdout; or, with `--json`, the report as JSON on
/// stdout and the table on stderr, so a script reads only JSON and a person still sees the
/// table.
pub fn emit<T: Serialize>(json: bool, table: &str, report: &T) -> Result<()> {
    if json {
        eprint!("{table}");
        println!("{}", serde_json::to_string_pretty(report)?);
    } else {
        print!("{table}");
    }
    Ok(())
}
