//! `nephele`: the command line of the Nephele master node.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use glam::{DMat4, DVec3};
use std::sync::Arc;

use nephele::{
    assets::{BackendChoice, DEFAULT_ASSET, DEFAULT_SCENES, load_asset, make_backend, parse_color, parse_size},
    bench,
    farm::Farm,
    client::ClientOptions,
    master::{self, MasterConfig},
    replay,
    rtc::RtcConfig,
    session::RenderScale,
    web,
};
use nephele_signaling::Mode;
use nephele_renderer::{
    CpuBackend, Backend as _, Intrinsics, RenderSettings, View, ViewRequest,
    procedural::{self, ProceduralConfig, Scene},
};

#[derive(Parser)]
#[command(name = "nephele", version, about = "Cloud renderer for neural opacity light fields (i-NOLF)")]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Render one view of an asset to PNG.
    Render(RenderArgs),
    /// Build a procedural asset and write it as .nolf.
    Generate {
        /// diffuse, shiny, translucent or trio.
        #[arg(long, default_value = "trio")]
        scene: String,
        /// Small grids (test fixtures) instead of full quality.
        #[arg(long)]
        small: bool,
        #[arg(long)]
        out: PathBuf,
    },
    /// Print an asset's metadata and memory by part.
    Info {
        #[arg(default_value = DEFAULT_ASSET)]
        asset: String,
    },
    /// Run the signaling server alone (pairs clients with master nodes, relays SDP/ICE).
    Signal {
        /// Address to listen on; port 0 picks a free port (printed).
        #[arg(long, default_value = "127.0.0.1:8000")]
        listen: String,
        /// Shared token that clients and masters must present.
        #[arg(long)]
        token: Option<String>,
    },
    /// The main job: signaling, a master with its render farm, and the web pages in one
    /// process. Prints the URL to open.
    Serve(ServeArgs),
    /// A master node alone, registering with a signaling server (`nephele signal`).
    Master {
        /// Signaling websocket, e.g. ws://host:8000/signal.
        #[arg(long)]
        signal: String,
        /// Name shown in signaling's /status.
        #[arg(long, default_value = "master")]
        name: String,
        #[command(flatten)]
        farm: FarmArgs,
    },
    /// A headless streaming client: replays a pose trace through a server and reports
    /// latency, fps, bitrate and PSNR against a direct render.
    Replay(ReplayArgs),
    /// Write the built-in pose traces (orbit, zoom, shake) as JSON into a directory.
    Traces {
        #[arg(long, default_value = "examples/traces")]
        out: PathBuf,
    },
    /// Write an analytic (ray-traced) scene as a NeRF-synthetic dataset with exact alpha.
    Synth {
        /// diffuse, glossy, translucent or mixed.
        #[arg(long, default_value = "mixed")]
        scene: String,
        #[arg(long, default_value = "200x200")]
        size: String,
        #[arg(long, default_value_t = 100)]
        train: usize,
        #[arg(long, default_value_t = 20)]
        val: usize,
        #[arg(long, default_value_t = 20)]
        test: usize,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long)]
        out: PathBuf,
    },
    /// Check a dataset folder (NeRF-synthetic or instant-ngp) and print its splits.
    DatasetInfo {
        dataset: PathBuf,
        /// instant-ngp: move every n-th frame to the test split.
        #[arg(long)]
        holdout_every: Option<usize>,
        /// Also decode every image of every split (finds broken files).
        #[arg(long)]
        load: bool,
    },
    /// Train an asset from a posed-image dataset on the CPU: the i-NGP field, then the i-NOLF
    /// stages, checkpointed in the work directory.
    Train(nephele::train_cli::TrainOptions),
    /// Render every view of a dataset split with an asset (.nolf) or an i-NGP checkpoint over
    /// white; print per-view and mean PSNR / SSIM, optionally write ground truth | render |
    /// |error|×4 PNGs.
    Eval {
        checkpoint: PathBuf,
        dataset: PathBuf,
        /// test, val or train.
        #[arg(long, default_value = "test")]
        split: String,
        #[arg(long, default_value_t = 1)]
        downscale: u32,
        /// Views held out of training with `train --holdout-every N` (the test split).
        #[arg(long)]
        holdout_every: Option<usize>,
        /// Directory for the side-by-side PNGs.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Benchmarks that print tables.
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
    },
}

#[derive(clap::Args)]
struct ReplayArgs {
    /// A trace file (JSON) or a built-in trace: orbit, zoom, shake.
    #[arg(long, default_value = "orbit")]
    trace: String,
    /// Signaling websocket of the server.
    #[arg(long, default_value = "ws://127.0.0.1:8080/signal")]
    signal: String,
    #[arg(long, default_value = "trio")]
    scene: String,
    /// viewer or ar.
    #[arg(long, default_value = "viewer")]
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
    /// Step-size multiplier the server uses (for the reference render).
    #[arg(long, default_value_t = 1.0)]
    step_scale: f32,
    /// Save the decoded frames as PNG here.
    #[arg(long)]
    save: Option<PathBuf>,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Subcommand)]
enum BenchCommand {
    /// The speed/accuracy table (NEPHELE Table 5) and distance sweep (Fig. 14) from a trained
    /// i-NGP checkpoint: trains the i-NOLF variants, scores held-out views, times frames.
    Tradeoff {
        dataset: PathBuf,
        /// The teacher: an i-NGP checkpoint (e.g. DIR.train/ngp.ckpt from `nephele train`).
        #[arg(long)]
        teacher: PathBuf,
        #[arg(long, default_value_t = 2)]
        downscale: u32,
        /// Held-out views as in `train --holdout-every` (needed without a test split).
        #[arg(long)]
        holdout_every: Option<usize>,
        /// Appearance steps per student.
        #[arg(long, default_value_t = 2000)]
        nolf_steps: u64,
        /// PSH grid sizes (must include 256).
        #[arg(long, default_value = "128,256,512", value_delimiter = ',')]
        psh: Vec<u32>,
        /// Frame size for the timings.
        #[arg(long, default_value = "800x800")]
        size: String,
        /// Held-out views scored.
        #[arg(long, default_value_t = 10)]
        views: usize,
        /// Camera distances in the sweep.
        #[arg(long, default_value_t = 7)]
        distances: usize,
        /// Where the plot and JSON go.
        #[arg(long, default_value = "tradeoff")]
        out: PathBuf,
        /// Also time i-NGP and the asset on wgpu (one frame each; slow on software Vulkan).
        #[arg(long)]
        gpu: bool,
    },
    /// RGB→I420 and H.264 encode times on a moving test pattern.
    Encode {
        #[arg(long, default_value = "640x480,1280x720")]
        sizes: String,
        #[arg(long, default_value_t = 200)]
        frames: u32,
    },
    /// Per-stage and end-to-end streaming latency through an in-process server and the
    /// replay client, per frame size.
    Stream {
        #[arg(long, default_value = "builtin:trio-small")]
        asset: String,
        #[arg(long, default_value = "640x480,1280x720")]
        sizes: String,
        #[arg(long, default_value = "orbit")]
        trace: String,
        #[arg(long, value_enum, default_value = "auto")]
        backend: BackendChoice,
        #[arg(long, default_value_t = 50)]
        fps: u32,
        /// Render scales to compare (each a fresh server): numbers in 0.05..=1 or auto.
        #[arg(long, value_delimiter = ',', default_value = "1,0.5,auto")]
        render_scales: Vec<String>,
        /// Render-time target of the auto scale, ms.
        #[arg(long, default_value_t = 30.0)]
        frame_budget_ms: f64,
    },
    /// Ray-march / network / total ms, rays/s and hit fraction per backend and size.
    Render {
        #[arg(long, default_value = DEFAULT_ASSET)]
        asset: String,
        /// Comma-separated sizes.
        #[arg(long, default_value = "256x256,800x800,1920x1080")]
        sizes: String,
        /// Backends to compare side by side.
        #[arg(long, value_delimiter = ',', default_value = "gpu,cpu")]
        backends: Vec<BackendChoice>,
        #[arg(long, default_value_t = 3)]
        runs: usize,
        /// Camera distance from the object centre.
        #[arg(long, default_value_t = 4.0)]
        distance: f64,
    },
}

#[derive(clap::Args)]
struct FarmArgs {
    /// Scenes to serve: `name=asset` or an asset (a .nolf path or builtin:<scene>[-small]);
    /// repeat for several. The first is the default.
    #[arg(long = "scene", default_values = DEFAULT_SCENES)]
    scenes: Vec<String>,
    #[arg(long, value_enum, default_value = "auto")]
    backend: BackendChoice,
    /// Step-size multiplier (speed/accuracy knob).
    #[arg(long, default_value_t = 1.0)]
    step_scale: f32,
    /// Sessions this master accepts at once.
    #[arg(long, default_value_t = 4)]
    capacity: u32,
    /// Shared token for signaling (clients must present it too).
    #[arg(long)]
    token: Option<String>,
    /// Offer loopback ICE candidates only (a browser on this machine, tests).
    #[arg(long)]
    loopback_only: bool,
    /// Public IP(s) to advertise in ICE candidates (server behind 1:1 NAT).
    #[arg(long)]
    public_ip: Vec<String>,
    /// Render at this fraction of the stream size and upscale (1 = exact), or `auto`:
    /// dynamic resolution that keeps render time near --frame-budget-ms.
    #[arg(long, default_value = "auto")]
    render_scale: String,
    /// Render-time target of `--render-scale auto`, ms.
    #[arg(long, default_value_t = 30.0)]
    frame_budget_ms: f64,
}

impl FarmArgs {
    fn load(&self) -> Result<(Arc<Farm>, MasterConfig)> {
        let render_scale = RenderScale::parse(&self.render_scale, self.frame_budget_ms).map_err(anyhow::Error::msg)?;
        let backend = make_backend(self.backend)?;
        let settings = RenderSettings { step_scale: self.step_scale, ..Default::default() };
        settings.validate().map_err(anyhow::Error::msg)?;
        eprintln!("preparing {} scene(s) on {} ...", self.scenes.len(), backend.name());
        let farm = Arc::new(Farm::load(&self.scenes, backend.as_ref(), settings)?);
        let cfg = MasterConfig {
            name: "local".into(),
            capacity: self.capacity,
            token: self.token.clone(),
            rtc: RtcConfig { loopback_only: self.loopback_only, public_ips: self.public_ip.clone() },
            render_scale,
        };
        Ok((farm, cfg))
    }
}

#[derive(clap::Args)]
struct ServeArgs {
    /// HTTP address for the pages and signaling; port 0 picks a free port.
    #[arg(long, default_value = "127.0.0.1:8080")]
    listen: String,
    #[command(flatten)]
    farm: FarmArgs,
}

#[derive(clap::Args)]
struct RenderArgs {
    /// A .nolf file or builtin:<diffuse|shiny|translucent|trio>[-small].
    #[arg(default_value = DEFAULT_ASSET)]
    asset: String,
    /// Camera pose: JSON with a row-major 4×4 camera-to-world `transform_matrix` (NeRF style)
    /// and optionally `camera_angle_x`. Overrides the orbit options.
    #[arg(long)]
    pose: Option<PathBuf>,
    /// Orbit azimuth in degrees (about +z).
    #[arg(long, default_value_t = 35.0)]
    azimuth: f64,
    /// Orbit elevation in degrees.
    #[arg(long, default_value_t = 25.0)]
    elevation: f64,
    /// Orbit distance from the object centre, scene units.
    #[arg(long, default_value_t = 4.0)]
    distance: f64,
    /// Horizontal field of view in degrees (NeRF-synthetic uses ~39.6).
    #[arg(long, default_value_t = 39.6)]
    fov: f64,
    #[arg(long, default_value = "800x800")]
    size: String,
    #[arg(long, value_enum, default_value = "auto")]
    backend: BackendChoice,
    /// r,g,b in [0,1] or white/black/green.
    #[arg(long, default_value = "white")]
    background: String,
    #[arg(long, default_value = "out/render.png")]
    out: PathBuf,
    /// Also write depth (grey, near = bright) here.
    #[arg(long)]
    depth: Option<PathBuf>,
    /// Also write alpha here.
    #[arg(long)]
    alpha: Option<PathBuf>,
    /// Step-size multiplier (speed/accuracy knob).
    #[arg(long, default_value_t = 1.0)]
    step_scale: f32,
}

fn main() -> Result<()> {
    tracing_subscriber::fmt().with_env_filter(tracing_subscriber::EnvFilter::from_default_env()).with_writer(std::io::stderr).init();
    match Cli::parse().command {
        None => {
            let Some(Command::Serve(args)) = Cli::parse_from(["nephele", "serve"]).command else { unreachable!() };
            serve(args)
        }
        Some(Command::Serve(args)) => serve(args),
        Some(Command::Master { signal, name, farm }) => {
            let (farm, cfg) = farm.load()?;
            let cfg = MasterConfig { name, ..cfg };
            tokio::runtime::Runtime::new()?.block_on(master::run(signal, cfg, farm))
        }
        Some(Command::Render(args)) => render(args),
        Some(Command::Generate { scene, small, out }) => {
            let scene: Scene = scene.parse().map_err(anyhow::Error::msg)?;
            let cfg = if small { ProceduralConfig::small(scene) } else { ProceduralConfig::default_quality(scene) };
            let asset = procedural::generate(&cfg)?;
            asset.save(&out)?;
            println!("wrote {} ({} bytes)\n{}", out.display(), std::fs::metadata(&out)?.len(), asset.memory());
            Ok(())
        }
        Some(Command::Info { asset }) => {
            let a = load_asset(&asset)?;
            println!("name: {}\nbounds: {:?}\nstep: {}\nprovenance: {}\n\n{}", a.name, a.bounds, a.march.step, a.provenance, a.memory());
            Ok(())
        }
        Some(Command::Signal { listen, token }) => {
            let rt = tokio::runtime::Runtime::new()?;
            rt.block_on(async {
                let listener = tokio::net::TcpListener::bind(&listen).await.with_context(|| format!("binding {listen}"))?;
                let addr = listener.local_addr()?;
                println!("signaling on ws://{addr}/signal (status: http://{addr}/status)");
                let cfg = nephele_signaling::HubConfig { token, ..Default::default() };
                nephele_signaling::serve(listener, cfg).await.context("signaling server failed")
            })
        }
        Some(Command::Replay(args)) => replay(args),
        Some(Command::Synth { scene, size, train, val, test, seed, out }) => {
            use nephele_renderer::synth::{SynthConfig, SynthScene, generate};
            let scene: SynthScene = scene.parse().map_err(|e| anyhow::anyhow!("{e}"))?;
            let (width, height) = parse_size(&size)?;
            let cfg = SynthConfig { scene, width, height, n_train: train, n_val: val, n_test: test, seed };
            let t = std::time::Instant::now();
            generate(&cfg, &out)?;
            println!("wrote {} ({scene}, {width}x{height}, {train}/{val}/{test} views) in {:.1} s", out.display(), t.elapsed().as_secs_f64());
            Ok(())
        }
        Some(Command::DatasetInfo { dataset, holdout_every, load }) => {
            use nephele_renderer::dataset::{Dataset, LoadOptions, inspect};
            let info = inspect(&dataset, holdout_every)?;
            println!("{} ({:?}), aabb_scale {:?}", info.name, info.format, info.aabb_scale);
            for s in &info.splits {
                println!("  {:5} {:4} frames, first image {:?} ({})", s.split.to_string(), s.frames, s.first_image_size, s.transforms_file.display());
                if load {
                    let t = std::time::Instant::now();
                    let d = Dataset::load(&dataset, &LoadOptions { holdout_every, ..LoadOptions::split(s.split) })?;
                    println!("        decoded {} images in {:.2} s", d.images.len(), t.elapsed().as_secs_f64());
                }
            }
            Ok(())
        }
        Some(Command::Train(opts)) => nephele::train_cli::train(&opts).map(|_| ()),
        Some(Command::Eval { checkpoint, dataset, split, downscale, holdout_every, out, json }) => {
            use nephele::train_cli::{EvalOptions, eval};
            let split = split.parse().map_err(anyhow::Error::msg)?;
            eval(&EvalOptions { checkpoint, dataset, split, downscale, holdout_every, out, json }).map(|_| ())
        }
        Some(Command::Traces { out }) => {
            std::fs::create_dir_all(&out)?;
            for name in replay::BUILTIN_TRACES {
                let trace = replay::Trace::builtin(name)?;
                let path = out.join(format!("{name}.json"));
                std::fs::write(&path, trace.to_json())?;
                println!("wrote {} ({} poses: {})", path.display(), trace.poses.len(), trace.description);
            }
            Ok(())
        }
        Some(Command::Bench { what: BenchCommand::Stream { asset, sizes, trace, backend, fps, render_scales, frame_budget_ms } }) => {
            bench_stream(&asset, &sizes, &trace, backend, fps, &render_scales, frame_budget_ms)
        }
        Some(Command::Bench { what: BenchCommand::Tradeoff { dataset, teacher, downscale, holdout_every, nolf_steps, psh, size, views, distances, out, gpu } }) => {
            use nephele::tradeoff::{TradeoffOptions, format_report, run};
            let size = parse_size(&size)?;
            let report = run(&TradeoffOptions { dataset, teacher, downscale, holdout_every, nolf_steps, psh_grids: psh, size, views, distances, out, gpu })?;
            print!("{}", format_report(&report));
            Ok(())
        }
        Some(Command::Bench { what: BenchCommand::Encode { sizes, frames } }) => {
            println!("| size | frames | kbit/s target | RGB→I420 p50 / p99 ms | encode p50 / p99 ms | bytes/frame | IDR bytes |");
            println!("|---|---:|---:|---:|---:|---:|---:|");
            for size in sizes.split(',') {
                let (w, h) = parse_size(size)?;
                let r = nephele::encode::bench_encode(w, h, frames)?;
                println!(
                    "| {w}x{h} | {} | {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.0} | {} |",
                    r.frames, r.bitrate_bps / 1000, r.convert_ms_p50, r.convert_ms_p99, r.encode_ms_p50, r.encode_ms_p99, r.bytes_per_frame, r.idr_bytes
                );
            }
            Ok(())
        }
        Some(Command::Bench { what: BenchCommand::Render { asset, sizes, backends, runs, distance } }) => {
            let a = load_asset(&asset)?;
            let sizes: Vec<(u32, u32)> = sizes.split(',').map(parse_size).collect::<Result<_>>()?;
            let mut rows = Vec::new();
            for b in backends {
                let backend = make_backend(b)?;
                eprintln!("benchmarking {} ...", backend.name());
                rows.extend(bench::bench_render(backend.as_ref(), a.clone(), &sizes, runs, distance)?);
            }
            println!("asset: {asset}\n\n{}\nmemory:\n{}", bench::format_table(&rows), a.memory());
            Ok(())
        }
    }
}

fn serve(args: ServeArgs) -> Result<()> {
    let (farm, cfg) = args.farm.load()?;
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(&args.listen).await.with_context(|| format!("binding {}", args.listen))?;
        let addr = web::spawn_local(listener, Arc::clone(&farm), cfg).await?;
        println!("Nephele is serving {} on {} — open http://{addr}/ (AR: http://{addr}/ar.html)", farm.names().join(", "), farm.backend_name);
        tokio::signal::ctrl_c().await?;
        eprintln!("stopping");
        Ok(())
    })
}

fn load_trace(spec: &str) -> Result<replay::Trace> {
    if replay::BUILTIN_TRACES.contains(&spec) { replay::Trace::builtin(spec) } else { replay::Trace::load(std::path::Path::new(spec)) }
}

fn parse_mode(s: &str) -> Result<Mode> {
    serde_json::from_value(serde_json::Value::String(s.into())).map_err(|_| anyhow::anyhow!("mode {s:?}: use viewer or ar"))
}

fn replay(args: ReplayArgs) -> Result<()> {
    let trace = load_trace(&args.trace)?;
    let (width, height) = parse_size(&args.size)?;
    let mode = parse_mode(&args.mode)?;
    let settings = RenderSettings { step_scale: args.step_scale, ..Default::default() };
    let reference = match &args.reference {
        Some(spec) => Some(CpuBackend.prepare(load_asset(spec)?)?),
        None => {
            eprintln!("note: no --reference asset; PSNR is not measured");
            None
        }
    };
    let opts = replay::ReplayOptions {
        client: ClientOptions { signal_url: args.signal, scene: args.scene, mode, width, height, fps: args.fps, token: args.token, keep_pixels: reference.is_some() || args.save.is_some() },
        anchor: None,
        quality_every: args.quality_every,
        save_dir: args.save,
        drain: std::time::Duration::from_secs(1),
    };
    let rt = tokio::runtime::Runtime::new()?;
    let report = rt.block_on(replay::replay(&trace, &opts, reference.as_deref().map(|r| (r, settings))))?;
    if args.json { println!("{}", serde_json::to_string_pretty(&report)?) } else { print!("{report}") }
    if report.frames_decoded == 0 {
        bail!("no frames were decoded");
    }
    Ok(())
}

fn bench_stream(asset: &str, sizes: &str, trace: &str, backend: BackendChoice, fps: u32, scales: &[String], budget_ms: f64) -> Result<()> {
    let trace = load_trace(trace)?;
    let sizes: Vec<(u32, u32)> = sizes.split(',').map(parse_size).collect::<Result<_>>()?;
    let scales: Vec<(String, RenderScale)> =
        scales.iter().map(|s| RenderScale::parse(s, budget_ms).map(|r| (s.clone(), r)).map_err(anyhow::Error::msg)).collect::<Result<_>>()?;
    let backend = make_backend(backend)?;
    let settings = RenderSettings::default();
    let farm = Arc::new(Farm::load(&[format!("bench={asset}")], backend.as_ref(), settings)?);
    let rt = tokio::runtime::Runtime::new()?;
    let mut reports = Vec::new();
    for (label, scale) in &scales {
        for &(width, height) in &sizes {
            eprintln!("streaming {} at {width}x{height}, render scale {label} ...", trace.name);
            let cfg = MasterConfig {
                name: "bench".into(),
                capacity: 4,
                token: None,
                rtc: RtcConfig { loopback_only: true, public_ips: vec![] },
                render_scale: *scale,
            };
            let farm = Arc::clone(&farm);
            let report = rt.block_on(async {
                let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
                let addr = web::spawn_local(listener, Arc::clone(&farm), cfg).await?;
                let opts = replay::ReplayOptions {
                    client: ClientOptions { signal_url: format!("ws://{addr}/signal"), scene: "bench".into(), mode: Mode::Viewer, width, height, fps, token: None, keep_pixels: true },
                    anchor: None,
                    quality_every: 10,
                    save_dir: None,
                    drain: std::time::Duration::from_secs(2),
                };
                let scene = &farm.scenes["bench"];
                replay::replay(&trace, &opts, Some((scene.prepared.as_ref(), farm.settings))).await
            })?;
            reports.push((label.clone(), report));
        }
    }
    println!("asset {asset}, backend {}, trace {} ({} poses every {} ms), target {fps} fps, auto budget {budget_ms} ms\n", backend.name(), trace.name, trace.poses.len(), trace.period_ms);
    println!("Per stage, p50 / p99 ms (master stages from frame info; end to end on the client clock):\n");
    println!("| size | scale | queue | render | RGB→I420 | encode | RTP send | pose→frame info | pose→decoded |");
    println!("|---|---|---:|---:|---:|---:|---:|---:|---:|");
    let pp = |p: replay::Percentiles| format!("{:.1} / {:.1}", p.p50, p.p99);
    for (label, r) in &reports {
        println!(
            "| {}x{} | {label} | {} | {} | {} | {} | {} | {} | {} |",
            r.width, r.height, pp(r.queue_ms), pp(r.render_ms), pp(r.convert_ms), pp(r.encode_ms), pp(r.send_ms), pp(r.info_latency_ms), pp(r.latency_ms)
        );
    }
    println!("\n| size | scale | frames | fps | kbit/s | IDR | PSNR mean / min dB | bad frames |");
    println!("|---|---|---:|---:|---:|---:|---:|---:|");
    for (label, r) in &reports {
        println!(
            "| {}x{} | {label} | {} | {:.1} | {:.0} | {} | {:.2} / {:.2} | {} |",
            r.width, r.height, r.frames_decoded, r.fps, r.bitrate_kbps, r.idr_frames,
            r.mean_psnr().unwrap_or(f64::NAN), r.min_psnr().unwrap_or(f64::NAN), r.frames_unknown_pose + r.frames_without_pose
        );
    }
    Ok(())
}

#[derive(serde::Deserialize)]
struct PoseFile {
    transform_matrix: [[f64; 4]; 4],
    camera_angle_x: Option<f64>,
}

fn render(args: RenderArgs) -> Result<()> {
    let (w, h) = parse_size(&args.size)?;
    let background = parse_color(&args.background)?;
    let asset = load_asset(&args.asset)?;
    let backend = make_backend(args.backend)?;
    let view = match &args.pose {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading pose {}", path.display()))?;
            let pose: PoseFile = serde_json::from_str(&text).with_context(|| format!("parsing pose {}", path.display()))?;
            let fov = pose.camera_angle_x.unwrap_or(args.fov.to_radians());
            let m = DMat4::from_cols_array_2d(&pose.transform_matrix).transpose();
            View { world_from_camera: m, intrinsics: Intrinsics::from_fov_x(w, h, fov as f32) }
        }
        None => View::orbit(DVec3::ZERO, args.distance, args.azimuth, args.elevation, Intrinsics::from_fov_x(w, h, args.fov.to_radians() as f32)),
    };
    let settings = RenderSettings { step_scale: args.step_scale, ..Default::default() };
    let prepared = backend.prepare(asset)?;
    let out = prepared.render(&[ViewRequest::new(view).with_background(background)], &settings)?;
    let frame = &out.frames[0];
    if let Some(dir) = args.out.parent() {
        std::fs::create_dir_all(dir)?;
    }
    frame.save_png(&args.out)?;
    if let Some(p) = &args.depth {
        frame.save_depth_png(p)?;
    }
    if let Some(p) = &args.alpha {
        frame.save_alpha_png(p)?;
    }
    let s = out.stats;
    if s.hits == 0 {
        eprintln!("note: no ray hit the object; check the camera");
    }
    println!(
        "wrote {} ({w}×{h}, {}) — march {:.1} ms, network {:.1} ms, total {:.1} ms, {:.1}% of rays hit",
        args.out.display(),
        backend.name(),
        s.march_ms,
        s.shade_ms,
        s.total_ms,
        100.0 * s.hits as f64 / s.rays.max(1) as f64
    );
    if !args.out.exists() {
        bail!("output was not written");
    }
    Ok(())
}
