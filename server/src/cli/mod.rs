//! The `nephele` command line: one module per group of subcommands, each holding its
//! arguments and its body; `main.rs` only parses and dispatches.

#[cfg(feature = "train")]
pub mod data;
pub mod lifecycle;
pub mod render;
pub mod replay;
pub mod serve;
#[cfg(feature = "train")]
pub mod train;

use nephele_bench as bench;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "nephele", version, about = "Cloud renderer for neural opacity light fields (i-NOLF)")]
pub struct Cli {
    /// How log lines are written to stderr: `text` for people, `json` (one object per line)
    /// for log shippers.
    #[arg(long, global = true, value_enum, default_value = "text", env = "NEPHELE_LOG_FORMAT")]
    pub log_format: LogFormat,
    #[command(subcommand)]
    pub command: Option<Command>,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum LogFormat {
    Text,
    Json,
}

#[derive(Subcommand)]
pub enum Command {
    /// The main job: signaling, a master with its render workers, and the web pages in one
    /// process. Prints the URL to open. (What `nephele` with no subcommand runs.)
    Serve(serve::ServeArgs),
    /// A master node alone, registering with a signaling server (`nephele signal`).
    Master(serve::MasterArgs),
    /// Run the signaling server alone (pairs clients with master nodes, relays SDP/ICE).
    Signal(serve::SignalArgs),
    /// A render worker of the NATS farm: renders tasks for masters started with --nats.
    Worker(serve::WorkerArgs),
    /// Ask a role's health endpoint (exit 0 when it answers 2xx): a container HEALTHCHECK
    /// without curl in the image.
    Health(lifecycle::HealthArgs),
    /// Render one view of an asset to PNG.
    Render(render::RenderArgs),
    /// Build a procedural asset and write it as .nolf.
    Generate(render::GenerateArgs),
    /// Print an asset's metadata and memory by part.
    Info(render::InfoArgs),
    /// A headless streaming client: replays a pose trace through a server and reports
    /// latency, fps, bitrate and PSNR against a direct render.
    Replay(replay::ReplayArgs),
    /// Write the built-in pose traces (orbit, zoom, shake) as JSON into a directory.
    Traces(replay::TracesArgs),
    /// Write an analytic (ray-traced) scene as a NeRF-synthetic dataset with exact alpha.
    #[cfg(feature = "train")]
    Synth(data::SynthArgs),
    /// Check a dataset folder (NeRF-synthetic or instant-ngp) and print its splits.
    #[cfg(feature = "train")]
    DatasetInfo(data::DatasetInfoArgs),
    /// Train an asset from a posed-image dataset on the CPU: the i-NGP field, then the i-NOLF
    /// stages, checkpointed in the work directory.
    #[cfg(feature = "train")]
    Train(train::TrainOptions),
    /// Render every view of a dataset split with an asset (.nolf) or an i-NGP checkpoint over
    /// white; print per-view and mean PSNR / SSIM, optionally write ground truth | render |
    /// |error|×4 PNGs.
    #[cfg(feature = "train")]
    Eval(data::EvalArgs),
    /// Benchmarks that print tables.
    Bench {
        #[command(subcommand)]
        what: bench::BenchCommand,
    },
}

/// Runs the parsed command line.
pub fn run(cli: Cli) -> Result<()> {
    match cli.command.unwrap_or_else(|| Command::Serve(serve::ServeArgs::default_args())) {
        Command::Serve(args) => serve::serve(args),
        Command::Master(args) => serve::master(args),
        Command::Signal(args) => serve::signal(args),
        Command::Worker(args) => serve::worker(args),
        Command::Health(args) => lifecycle::health(&args),
        Command::Render(args) => render::render(args),
        Command::Generate(args) => render::generate(args),
        Command::Info(args) => render::info(args),
        Command::Replay(args) => replay::replay(args),
        Command::Traces(args) => replay::traces(args),
        #[cfg(feature = "train")]
        Command::Synth(args) => data::synth(args),
        #[cfg(feature = "train")]
        Command::DatasetInfo(args) => data::dataset_info(args),
        #[cfg(feature = "train")]
        Command::Train(opts) => train::train(&opts).map(|_| ()),
        #[cfg(feature = "train")]
        Command::Eval(args) => data::eval(args),
        Command::Bench { what } => bench::run(what),
    }
}
