//! The `nephele` command line: one module per group of subcommands, each holding its
//! arguments and its body; `main.rs` only parses and dispatches.

pub mod abuse;
pub mod bench;
pub mod data;
pub mod farm;
pub mod plot;
pub mod quilt;
pub mod render;
pub mod replay;
pub mod serve;
pub mod tradeoff;
pub mod train;
pub mod users;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "nephele", version, about = "Cloud renderer for neural opacity light fields (i-NOLF)")]
pub struct Cli {
    #[command(subcommand)]
    pub command: Option<Command>,
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
    Synth(data::SynthArgs),
    /// Check a dataset folder (NeRF-synthetic or instant-ngp) and print its splits.
    DatasetInfo(data::DatasetInfoArgs),
    /// Train an asset from a posed-image dataset on the CPU: the i-NGP field, then the i-NOLF
    /// stages, checkpointed in the work directory.
    Train(train::TrainOptions),
    /// Render every view of a dataset split with an asset (.nolf) or an i-NGP checkpoint over
    /// white; print per-view and mean PSNR / SSIM, optionally write ground truth | render |
    /// |error|×4 PNGs.
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
        Command::Render(args) => render::render(args),
        Command::Generate(args) => render::generate(args),
        Command::Info(args) => render::info(args),
        Command::Replay(args) => replay::replay(args),
        Command::Traces(args) => replay::traces(args),
        Command::Synth(args) => data::synth(args),
        Command::DatasetInfo(args) => data::dataset_info(args),
        Command::Train(opts) => train::train(&opts).map(|_| ()),
        Command::Eval(args) => data::eval(args),
        Command::Bench { what } => bench::run(what),
    }
}

/// The renderer's speed-for-accuracy knobs, as flags.
#[derive(clap::Args, Debug, Clone)]
pub struct RenderKnobs {
    /// Step-size multiplier (speed/accuracy knob; keep it equal on every worker).
    #[arg(long, default_value_t = 1.0)]
    pub step_scale: f32,
    /// Multi-hit threshold τ: a further query for each part of a ray's weight holding at
    /// least τ of its opacity (1 = one hit per ray); default: the asset's own.
    #[arg(long)]
    pub hit_tau: Option<f32>,
    /// Most network queries per ray (1..=3); default: the asset's own.
    #[arg(long)]
    pub max_hits: Option<u32>,
    /// Stop a ray's march once its transmittance falls below this (its coarse opacity is
    /// then within this of the whole ray's): larger is faster and less exact (`nephele bench
    /// render` prints the PSNR against the default rule); default: the asset's own, the
    /// threshold it was trained with.
    #[arg(long)]
    pub early_stop: Option<f32>,
}

impl RenderKnobs {
    pub fn settings(&self) -> Result<nephele_renderer::RenderSettings> {
        let s = nephele_renderer::RenderSettings { step_scale: self.step_scale, hit_tau: self.hit_tau, max_hits: self.max_hits, early_stop: self.early_stop, ..Default::default() };
        if s.validate().is_err() {
            anyhow::bail!(
                "--step-scale must be in [0.05, 20], --hit-tau in [0, 1], --max-hits in 1..={} and --early-stop in [0, 1) (got {}, {:?}, {:?}, {:?})",
                nephele_renderer::model::MAX_HITS,
                self.step_scale,
                self.hit_tau,
                self.max_hits,
                self.early_stop
            );
        }
        Ok(s)
    }
}
