//! `nephele replay` (the headless client against a running server) and `nephele traces`
//! (write the built-in pose traces).

use std::path::PathBuf;

use anyhow::{Result, bail};
use nephele_renderer::{Backend as _, CpuBackend};
use nephele_protocol::Mode;

use nephele_client::{
    Receive,
    ClientOptions,
    replay::{self, BUILTIN_TRACES, Trace},
};
use nephele_farm::assets::{load_asset, parse_size};

#[derive(clap::Args)]
pub struct ReplayArgs {
    /// A trace file (JSON) or a built-in trace: orbit, zoom, shake.
    #[arg(long, default_value = "orbit")]
    trace: String,
    /// Signaling websocket of the server.
    #[arg(long, default_value = "ws://127.0.0.1:8080/signal")]
    signal: String,
    #[arg(long, default_value = "trio")]
    scene: String,
    /// The display mode the client asks for.
    #[arg(long, default_value = "viewer", value_parser = ["viewer", "ar"])]
    mode: String,
    #[arg(long, default_value = "640x480")]
    size: String,
    #[arg(long, default_value_t = 50)]
    fps: u32,
    #[arg(long)]
    token: Option<String>,
    /// The asset the server streams (e.g. builtin:trio), rendered here for PSNR.
    #[arg(long)]
    reference: Option<String>,
    /// Compare every n-th frame with the reference.
    #[arg(long, default_value_t = 10)]
    quality_every: usize,
    #[command(flatten)]
    knobs: nephele_farm::assets::RenderKnobs,
    /// Save the decoded frames as PNG here.
    #[arg(long)]
    save: Option<PathBuf>,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
pub struct TracesArgs {
    #[arg(long, default_value = "examples/traces")]
    out: PathBuf,
}

pub fn parse_mode(s: &str) -> Result<Mode> {
    serde_json::from_value(serde_json::Value::String(s.into())).map_err(|_| anyhow::anyhow!("mode {s:?}: use viewer or ar"))
}

pub fn replay(args: ReplayArgs) -> Result<()> {
    let trace = Trace::from_spec(&args.trace)?;
    let (width, height) = parse_size(&args.size)?;
    let mode = parse_mode(&args.mode)?;
    let settings = args.knobs.settings()?;
    let reference = match &args.reference {
        Some(spec) => Some(CpuBackend.prepare(load_asset(spec)?)?),
        None => {
            eprintln!("note: no --reference asset; PSNR is not measured");
            None
        }
    };
    let opts = replay::ReplayOptions {
        client: ClientOptions { signal_url: args.signal, scene: args.scene, mode, width, height, fps: args.fps, token: args.token, receive: if reference.is_some() || args.save.is_some() { Receive::Pixels } else { Receive::Decode }, quilt: None, depth: false },
        anchor: None,
        quality_every: args.quality_every,
        save_dir: args.save,
        drain: std::time::Duration::from_secs(1), start_at: None, stereo_baseline: None
    };
    let rt = tokio::runtime::Runtime::new()?;
    let reference = reference.as_deref().map(|r| replay::asset_reference(r, settings));
    let report = rt.block_on(replay::replay(&trace, &opts, reference.as_ref().map(|r| r as replay::Reference<'_>)))?;
    if args.json { println!("{}", serde_json::to_string_pretty(&report)?) } else { print!("{report}") }
    if report.frames_decoded == 0 {
        bail!("no frames were decoded");
    }
    Ok(())
}

pub fn traces(args: TracesArgs) -> Result<()> {
    std::fs::create_dir_all(&args.out)?;
    for name in BUILTIN_TRACES {
        let trace = Trace::builtin(name)?;
        let path = args.out.join(format!("{name}.json"));
        std::fs::write(&path, trace.to_json())?;
        println!("wrote {} ({} poses: {})", path.display(), trace.poses.len(), trace.description);
    }
    Ok(())
}
