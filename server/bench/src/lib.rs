//! `nephele bench …`: `render` (per backend and size, where a frame's time goes — ray march
//! vs network — rays/s and the fraction of rays that hit; plus the asset's memory table),
//! `encode`, `stream` (latency per stage through an in-process server), `tradeoff`
//! (NEPHELE Table 5 / Fig. 14, in `tradeoff`, with the `train` feature), `users` (many users
//! on one server, in [`users`]), `farm`, `quilt` and `abuse`.

use std::{fmt::Write, sync::Arc};
#[cfg(feature = "train")]
use std::path::PathBuf;

use anyhow::Result;
use glam::DVec3;
use nephele_renderer::{Backend, Intrinsics, PreparedAsset, RenderSettings, View, ViewRequest};
use nephele_protocol::Mode;

use nephele_client::{
    ClientOptions,
    replay::{self, Trace},
};
use nephele_core::{CoreConfig, scheduler::RenderScale};
use nephele_farm::{
    assets::{BackendChoice, DEFAULT_ASSET, RenderKnobs, load_asset, make_backend, parse_size},
    catalog::Catalog,
};
use nephele_master::{MasterConfig, encoder::DEFAULT_BITS_PER_PIXEL, web};

pub mod abuse;
pub mod farm;
pub mod plot;
#[cfg(feature = "train")]
pub mod quilt;
#[cfg(feature = "train")]
pub mod tradeoff;
pub mod users;

#[derive(clap::Subcommand)]
pub enum BenchCommand {
    /// The speed/accuracy table (NEPHELE Table 5) and distance sweep (Fig. 14) from a trained
    /// i-NGP checkpoint: trains the i-NOLF variants, scores held-out views, times frames.
    #[cfg(feature = "train")]
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
        /// Multi-hit thresholds τ of the rows of `nephele train`'s settings (1 = one hit).
        #[arg(long, default_value = "1,0.2,0.1,0.05", value_delimiter = ',')]
        taus: Vec<f32>,
        /// Most network queries per ray in those rows.
        #[arg(long, default_value_t = 3)]
        max_hits: u32,
    },
    /// RGB→I420 and H.264 encode times on a moving test pattern and on real content (an asset
    /// orbiting, rendered on the CPU before the timing starts).
    Encode {
        #[arg(long, default_value = "640x480,1280x720")]
        sizes: String,
        #[arg(long, default_value_t = 200)]
        frames: u32,
        /// The real content; `none` for the pattern only.
        #[arg(long, default_value = DEFAULT_ASSET)]
        asset: String,
        /// Bits per pixel per frame to compare (the server's `--bits-per-pixel`): encode time
        /// and quality against bandwidth.
        #[arg(long, value_delimiter = ',', default_values_t = [DEFAULT_BITS_PER_PIXEL])]
        bits_per_pixel: Vec<f64>,
        /// OpenH264 threads to compare, 1..=4 (default: one more than the cores, at most 4).
        #[arg(long, value_delimiter = ',')]
        threads: Vec<u16>,
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
        /// Share of the pose period a frame may wait for a pose that is due (`serve
        /// --pose-latch`; 0: never).
        #[arg(long, default_value_t = nephele_core::POSE_LATCH, value_parser = nephele_core::parse_pose_latch)]
        pose_latch: f64,
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
        /// Also render this many views (around the orbit) in one call and one at a time, and
        /// print ms per view of each: what batching a render task saves.
        #[arg(long, default_value_t = 0)]
        batch: usize,
        /// The `cpu` backend with each of these ray marches, frames alternating (all give the
        /// same frames; the PSNR column shows it): avx512, avx2, ray. Default: the widest
        /// this CPU has.
        #[arg(long, value_delimiter = ',')]
        marches: Vec<nephele_renderer::fast::March>,
        /// The `cpu` backend with each of these network kernels, frames alternating (with
        /// --marches: every pair): f32, int8 (the hidden layer in 8 bits: AVX-512 VNNI, or
        /// AVX2 without AVX-512; the PSNR column gives its cost). Default: int8 where the CPU
        /// has it.
        #[arg(long, value_delimiter = ',')]
        networks: Vec<nephele_renderer::fast::Network>,
        #[command(flatten)]
        knobs: RenderKnobs,
    },
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
}

/// Runs one `nephele bench` subcommand.
pub fn run(what: BenchCommand) -> Result<()> {
    match what {
        BenchCommand::Stream { asset, sizes, trace, backend, fps, render_scales, frame_budget_ms, pose_latch } => {
            stream(&asset, &sizes, &trace, backend, fps, &render_scales, frame_budget_ms, pose_latch)
        }
        #[cfg(feature = "train")]
        BenchCommand::Tradeoff { dataset, teacher, downscale, holdout_every, nolf_steps, psh, size, views, distances, out, gpu, taus, max_hits } => {
            use tradeoff::{TradeoffOptions, format_report, run};
            let size = parse_size(&size)?;
            let report = run(&TradeoffOptions { dataset, teacher, downscale, holdout_every, nolf_steps, psh_grids: psh, size, views, distances, out, gpu, taus, max_hits })?;
            print!("{}", format_report(&report));
            Ok(())
        }
        BenchCommand::Encode { sizes, frames, asset, bits_per_pixel, threads } => {
            use nephele_master::encoder::{check_bits_per_pixel, check_encoder_threads, default_encoder_threads};
            for &bpp in &bits_per_pixel {
                check_bits_per_pixel(bpp).map_err(anyhow::Error::msg)?;
            }
            let threads = if threads.is_empty() { vec![default_encoder_threads()] } else { threads };
            for &t in &threads {
                check_encoder_threads(t).map_err(|e| anyhow::anyhow!("--threads: {e}"))?;
            }
            let prepared = if asset == "none" { None } else { Some(nephele_renderer::FastCpuBackend.prepare(load_asset(&asset)?)?) };
            println!("| content | size | frames | bits/pixel | threads | kbit/s target | RGB→I420 p50 / p99 ms | encode p50 / p99 ms | bytes/frame | IDR bytes | PSNR dB |");
            println!("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
            for size in sizes.split(',') {
                let (w, h) = parse_size(size)?;
                let mut contents = vec![("test pattern".to_string(), nephele_master::encoder::pattern_frames(w, h, frames))];
                if let Some(p) = &prepared {
                    eprintln!("rendering {frames} frames of {asset} at {w}x{h} ...");
                    // An orbit at 40°/s seen at 50 fps, as a user turning the object.
                    let rendered = (0..frames.max(1))
                        .map(|i| {
                            let view = View::orbit(DVec3::ZERO, 4.0, 35.0 + 0.8 * i as f64, 25.0, Intrinsics::from_fov_x(w, h, 0.69));
                            p.render(&[ViewRequest::new(view)], &RenderSettings::default()).map(|o| o.frames.into_iter().next().expect("one view").rgba)
                        })
                        .collect::<Result<Vec<_>, _>>()?;
                    contents.push((asset.clone(), rendered));
                }
                for (name, content) in contents {
                    for &bpp in &bits_per_pixel {
                        for &t in &threads {
                            let r = nephele_master::encoder::bench_encode(w, h, &content, bpp, t)?;
                            println!(
                                "| {name} | {w}x{h} | {} | {bpp} | {t} | {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.0} | {} | {:.2} |",
                                r.frames, r.bitrate_bps / 1000, r.convert_ms_p50, r.convert_ms_p99, r.encode_ms_p50, r.encode_ms_p99, r.bytes_per_frame, r.idr_bytes, r.psnr_db
                            );
                        }
                    }
                }
            }
            Ok(())
        }
        BenchCommand::Render { asset, sizes, backends, runs, distance, batch, marches, networks, knobs } => {
            // With knobs set, the default rule is timed beside them (frames alternating), and
            // their frame's PSNR against its frame is printed.
            let settings = knobs.settings()?;
            let rules = if settings == RenderSettings::default() { vec![settings] } else { vec![RenderSettings::default(), settings] };
            let a = load_asset(&asset)?;
            let sizes: Vec<(u32, u32)> = sizes.split(',').map(parse_size).collect::<Result<_>>()?;
            let mut rows = Vec::new();
            let mut batches = Vec::new();
            if !(marches.is_empty() && networks.is_empty()) && !backends.contains(&BackendChoice::Cpu) {
                anyhow::bail!("--marches and --networks compare the `cpu` backend's variants: add cpu to --backends");
            }
            for b in backends {
                let backend = make_backend(b)?;
                eprintln!("benchmarking {} ...", backend.name());
                let variants = if b == BackendChoice::Cpu && !(marches.is_empty() && networks.is_empty()) {
                    use nephele_renderer::fast::{March, Network};
                    let fast = nephele_renderer::FastCpuBackend;
                    let ms = if marches.is_empty() { vec![March::detect()] } else { marches.clone() };
                    let ns = if networks.is_empty() { vec![Network::detect()] } else { networks.clone() };
                    let pairs: Vec<(March, Network)> = ms.iter().flat_map(|&m| ns.iter().map(move |&n| (m, n))).collect();
                    pairs.iter().map(|&(m, n)| Ok((format!("cpu, {} march, {} network", m.name(), n.name()), fast.prepare_with(a.clone(), m, n)?))).collect::<Result<Vec<_>>>()?
                } else {
                    vec![(backend.name(), backend.prepare(a.clone())?)]
                };
                rows.extend(bench_render(&variants, &sizes, runs, distance, &rules)?);
                if batch > 1 {
                    batches.extend(bench_batch(backend.as_ref(), a.clone(), &sizes, runs, distance, batch, &settings)?);
                }
            }
            let peak = nephele_renderer::mlp::peak_fma_gflops();
            // The march the plain `cpu` rows used.
            let march = if rows.iter().any(|r| r.backend == "cpu") {
                format!("\nfast CPU march: {}; network: {}", nephele_renderer::fast::March::detect().describe(), nephele_renderer::fast::Network::detect().describe())
            } else {
                String::new()
            };
            match peak {
                Some((p, threads, level)) => println!("asset: {asset}{march}\npeak FMA rate measured now: {p:.0} GFLOP/s on {threads} threads ({level})\n\n{}", format_table_with_peak(&rows, Some(p))),
                None => println!("asset: {asset}\n\n{}", format_table(&rows)),
            }
            if !batches.is_empty() {
                println!("\n{batch} views around the orbit, median of {runs} runs:\n");
                println!("| backend | size | one call ms per view | one view per call ms per view | batching speed-up |");
                println!("|---|---|---:|---:|---:|");
                for BatchRow { backend, size: (w, h), together_ms, alone_ms } in &batches {
                    println!("| {backend} | {w}×{h} | {together_ms:.1} | {alone_ms:.1} | {:.2}x |", alone_ms / together_ms);
                }
            }
            println!("\nmemory:\n{}", a.memory());
            Ok(())
        }
        BenchCommand::Users(args) => users::run(args),
        BenchCommand::Farm(args) => farm::run(args),
        #[cfg(feature = "train")]
        BenchCommand::Quilt(args) => quilt::run(args),
        BenchCommand::Abuse(args) => abuse::run(args),
    }
}

#[allow(clippy::too_many_arguments)]
fn stream(asset: &str, sizes: &str, trace: &str, backend: BackendChoice, fps: u32, scales: &[String], budget_ms: f64, pose_latch: f64) -> Result<()> {
    let trace = Trace::from_spec(trace)?;
    let sizes: Vec<(u32, u32)> = sizes.split(',').map(parse_size).collect::<Result<_>>()?;
    let scales: Vec<(String, RenderScale)> =
        scales.iter().map(|s| RenderScale::parse(s, budget_ms).map(|r| (s.clone(), r)).map_err(anyhow::Error::msg)).collect::<Result<_>>()?;
    let backend = make_backend(backend)?;
    let settings = RenderSettings::default();
    let catalog = Arc::new(Catalog::load(&[format!("bench={asset}")], backend.as_ref(), settings)?);
    let rt = tokio::runtime::Runtime::new()?;
    let mut reports = Vec::new();
    for (label, scale) in &scales {
        for &(width, height) in &sizes {
            eprintln!("streaming {} at {width}x{height}, render scale {label} ...", trace.name);
            let cfg = MasterConfig::loopback("bench", CoreConfig { render_scale: *scale, pose_latch, ..Default::default() });
            let catalog = Arc::clone(&catalog);
            let report = rt.block_on(async {
                let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
                let server = web::spawn_local(listener, Arc::clone(&catalog), cfg).await?;
                let opts = replay::ReplayOptions {
                    client: ClientOptions { signal_url: server.signal_url(), scene: "bench".into(), mode: Mode::Viewer, width, height, fps, token: None, keep_pixels: true, quilt: None },
                    anchor: None,
                    quality_every: 10,
                    save_dir: None,
                    drain: std::time::Duration::from_secs(2), start_at: None, stereo_baseline: None
                };
                let reference = |view, instance, background| catalog.render_scene("bench", view, instance, background);
                replay::replay(&trace, &opts, Some(&reference)).await
            })?;
            reports.push((label.clone(), report));
        }
    }
    println!("asset {asset}, backend {}, trace {} ({} poses every {} ms), target {fps} fps, auto budget {budget_ms} ms, pose latch {pose_latch}\n", backend.name(), trace.name, trace.poses.len(), trace.period_ms);
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


pub struct RenderBenchRow {
    pub backend: String,
    /// The render knobs, in words ([`describe_rule`]).
    pub rule: String,
    pub width: u32,
    pub height: u32,
    pub march_ms: f64,
    pub shade_ms: f64,
    /// Of `shade_ms`, the matrix products (0 where the backend does not time them).
    pub mlp_ms: f64,
    pub total_ms: f64,
    pub rays_per_s: f64,
    pub hit_fraction: f64,
    /// Network queries of the frame and multiply-adds per query.
    pub queries: u64,
    pub macs_per_query: u64,
    /// Density samples per ray (CPU backends; 0 where not counted).
    pub samples_per_ray: f64,
    /// PSNR of the frame against the same view under the default rule, when the knobs differ.
    pub psnr_vs_first: Option<f64>,
}

/// Median of `runs` renders of an orbit view at each size (after one warm-up), for each
/// prepared variant (named, e.g. a backend or one of its marches) under each of `rules`, their
/// frames alternating so that every variant and rule sees the same machine. Rows after the
/// first carry their PSNR against its frame (the trade of a speed-for-accuracy knob).
pub fn bench_render(variants: &[(String, Box<dyn PreparedAsset>)], sizes: &[(u32, u32)], runs: usize, distance: f64, rules: &[RenderSettings]) -> Result<Vec<RenderBenchRow>> {
    let combos: Vec<(&String, &dyn PreparedAsset, &RenderSettings)> = variants.iter().flat_map(|(name, p)| rules.iter().map(move |r| (name, p.as_ref(), r))).collect();
    let mut rows = Vec::new();
    for &(w, h) in sizes {
        let view = View::orbit(DVec3::ZERO, distance, 35.0, 25.0, Intrinsics::from_fov_x(w, h, 0.69));
        let req = [ViewRequest::new(view)];
        let frames: Vec<Vec<u8>> = combos.iter().map(|(_, p, s)| Ok(p.render(&req, s)?.frames.remove(0).rgba)).collect::<Result<_>>()?;
        let mut samples = vec![Vec::new(); combos.len()];
        for _ in 0..runs.max(1) {
            for ((_, prepared, rule), out) in combos.iter().zip(&mut samples) {
                out.push(prepared.render(&req, rule)?.stats);
            }
        }
        for (i, ((name, prepared, rule), mut samples)) in combos.iter().zip(samples).enumerate() {
            samples.sort_by(|a, b| a.total_ms.total_cmp(&b.total_ms));
            let s = samples[samples.len() / 2];
            rows.push(RenderBenchRow {
                backend: name.to_string(),
                rule: describe_rule(rule),
                width: w,
                height: h,
                march_ms: s.march_ms,
                shade_ms: s.shade_ms,
                mlp_ms: s.mlp_ms,
                total_ms: s.total_ms,
                rays_per_s: s.rays as f64 / (s.total_ms / 1e3),
                hit_fraction: s.hits as f64 / s.rays.max(1) as f64,
                queries: s.queries,
                macs_per_query: prepared.asset().mlp.macs(),
                samples_per_ray: s.samples as f64 / s.rays.max(1) as f64,
                psnr_vs_first: (i > 0).then(|| nephele_renderer::render::psnr_rgb(&frames[i], &frames[0])),
            });
        }
    }
    Ok(rows)
}

/// The knobs of `s` that differ from the default rule, in words ("default" for none).
fn describe_rule(s: &RenderSettings) -> String {
    let d = RenderSettings::default();
    let mut parts = Vec::new();
    if s.step_scale != d.step_scale {
        parts.push(format!("step ×{}", s.step_scale));
    }
    if let Some(t) = s.hit_tau {
        parts.push(format!("τ = {t}"));
    }
    if let Some(m) = s.max_hits {
        parts.push(format!("≤ {m} hits"));
    }
    if let Some(e) = s.early_stop {
        parts.push(format!("early stop {e}"));
    }
    if parts.is_empty() { "default".into() } else { parts.join(", ") }
}

/// One row of `bench render --batch`: ms per view in one call and one view per call.
pub struct BatchRow {
    pub backend: String,
    pub size: (u32, u32),
    pub together_ms: f64,
    pub alone_ms: f64,
}

/// ms per view rendering `n` orbit views in one call, and one per call (medians of `runs`).
pub fn bench_batch(
    backend: &dyn Backend,
    asset: std::sync::Arc<nephele_renderer::Asset>,
    sizes: &[(u32, u32)],
    runs: usize,
    distance: f64,
    n: usize,
    settings: &RenderSettings,
) -> Result<Vec<BatchRow>> {
    let prepared = backend.prepare(asset)?;
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let mut out = Vec::new();
    for &(w, h) in sizes {
        let views: Vec<ViewRequest> = (0..n)
            .map(|i| ViewRequest::new(View::orbit(DVec3::ZERO, distance, 35.0 + 360.0 * i as f64 / n as f64, 25.0, Intrinsics::from_fov_x(w, h, 0.69))))
            .collect();
        prepared.render(&views, settings)?;
        let (mut together, mut alone) = (Vec::new(), Vec::new());
        for _ in 0..runs.max(1) {
            let t = std::time::Instant::now();
            prepared.render(&views, settings)?;
            together.push(t.elapsed().as_secs_f64() * 1e3 / n as f64);
            let t = std::time::Instant::now();
            for v in &views {
                prepared.render(std::slice::from_ref(v), settings)?;
            }
            alone.push(t.elapsed().as_secs_f64() * 1e3 / n as f64);
        }
        out.push(BatchRow { backend: backend.name(), size: (w, h), together_ms: median(together), alone_ms: median(alone) });
    }
    Ok(out)
}

pub fn format_table(rows: &[RenderBenchRow]) -> String {
    format_table_with_peak(rows, None)
}

/// The render table; with the machine's peak FMA rate (GFLOP/s, all threads) also the
/// network's rate over its stage, the FMA floor of the frame (its network FLOPs at peak), how
/// far the frame is above that floor, and the matrix products' own time and rate (their
/// inputs' gathers, view encoding and compositing are the rest of the network stage).
pub fn format_table_with_peak(rows: &[RenderBenchRow], peak_gflops: Option<f64>) -> String {
    let mut out = String::new();
    // The rule and PSNR columns only when some row has knobs set.
    let rules = rows.iter().any(|r| r.rule != "default");
    // The PSNR column also when several marches (or backends' variants) are compared.
    let psnr = rules || rows.iter().any(|r| r.psnr_vs_first.is_some());
    let _ = write!(out, "| backend |{} size | ray-march ms | network ms | total ms | Mrays/s | hit fraction | samples/ray | queries/hit |", if rules { " rule |" } else { "" });
    let _ = write!(out, "{}", if peak_gflops.is_some() { " network GFLOP/s | % of peak | FMA floor ms | total / floor | MLP ms | MLP % of peak |" } else { "" });
    let _ = writeln!(out, "{}", if rules { " PSNR vs default rule dB |" } else if psnr { " PSNR vs first variant dB |" } else { "" });
    let _ = writeln!(out, "|---|{}---|---:|---:|---:|---:|---:|---:|---:|{}{}", if rules { "---|" } else { "" }, if peak_gflops.is_some() { "---:|---:|---:|---:|---:|---:|" } else { "" }, if psnr { "---:|" } else { "" });
    for r in rows {
        let hits = (r.hit_fraction * (r.width as f64 * r.height as f64)).max(1.0);
        // Backends that count no samples or queries (the GPU's) get dashes, not zeros.
        let counted = r.samples_per_ray > 0.0 || r.queries > 0;
        let _ = write!(
            out,
            "| {} |{} {}×{} | {:.1} | {:.1} | {:.1} | {:.2} | {:.3} | {} | {} |",
            r.backend,
            if rules { format!(" {} |", r.rule) } else { String::new() },
            r.width,
            r.height,
            r.march_ms,
            r.shade_ms,
            r.total_ms,
            r.rays_per_s / 1e6,
            r.hit_fraction,
            if counted { format!("{:.1}", r.samples_per_ray) } else { "–".into() },
            if counted { format!("{:.2}", r.queries as f64 / hits) } else { "–".into() }
        );
        if let Some(peak) = peak_gflops {
            let gflop = 2.0 * (r.queries * r.macs_per_query) as f64 / 1e9;
            if gflop > 0.0 {
                let rate = gflop / (r.shade_ms / 1e3).max(1e-9);
                let floor_ms = gflop / peak * 1e3;
                let _ = write!(out, " {rate:.1} | {:.1}% | {floor_ms:.2} | {:.1}× |", 100.0 * rate / peak, r.total_ms / floor_ms);
                if r.mlp_ms > 0.0 {
                    let _ = write!(out, " {:.1} | {:.1}% |", r.mlp_ms, 100.0 * floor_ms / r.mlp_ms);
                } else {
                    let _ = write!(out, " – | – |");
                }
            } else {
                let _ = write!(out, " – | – | – | – | – | – |");
            }
        }
        if psnr {
            let _ = write!(out, " {} |", r.psnr_vs_first.map_or("–".into(), |p| if p.is_infinite() { "∞ (same frame)".into() } else { format!("{p:.1}") }));
        }
        let _ = writeln!(out);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(backend: &str, queries: u64, samples_per_ray: f64) -> RenderBenchRow {
        RenderBenchRow {
            backend: backend.into(),
            rule: "default".into(),
            width: 64,
            height: 48,
            march_ms: 2.0,
            shade_ms: 1.0,
            mlp_ms: 0.6,
            total_ms: 3.0,
            rays_per_s: 1e6,
            hit_fraction: 0.5,
            queries,
            macs_per_query: 6000,
            samples_per_ray,
            psnr_vs_first: None,
        }
    }

    #[test]
    fn uncounted_columns_are_dashes_not_zeros() {
        let untimed = RenderBenchRow { mlp_ms: 0.0, ..row("cpu-ref", 2000, 4.0) };
        let table = format_table_with_peak(&[row("cpu", 2000, 4.0), row("wgpu", 0, 0.0), untimed], Some(100.0));
        let line = |backend: &str| table.lines().find(|l| l.starts_with(&format!("| {backend} |"))).unwrap();
        // 2000 queries × 6000 MACs × 2 = 0.024 GFLOP: 0.24 ms at 100 GFLOP/s, 3 ms is 12.5×,
        // and products timed at 0.6 ms run at 40% of the peak.
        assert!(line("cpu").ends_with("| 4.0 | 1.30 | 24.0 | 24.0% | 0.24 | 12.5× | 0.6 | 40.0% |"), "{}", line("cpu"));
        assert!(line("wgpu").ends_with("| – | – | – | – | – | – |"), "{}", line("wgpu"));
        assert!(line("cpu-ref").ends_with("| 12.5× | – | – |"), "{}", line("cpu-ref"));
    }
}
