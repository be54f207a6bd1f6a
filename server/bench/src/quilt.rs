//! `nephele bench quilt`: NEPHELE §7's multi-view claim measured here. A Looking Glass quilt
//! (default 5×9 = 45 views) of one asset, per backend, in one run: i-NOLF with all views in
//! one render task (one parallel pass / one dispatch), i-NOLF as 45 separate renders, and
//! the i-NGP teacher on the same backend (every ray of every view in one call). Then
//! streaming: a mono viewer against a stereo headset session of the same total pixels
//! (both eyes in one task, side by side), pose→decoded latency on a real WebRTC client.

use std::{fmt::Write as _, path::PathBuf, sync::Arc, time::Instant};

use anyhow::{Context, Result};
use glam::{DVec3, Vec3};
use nephele_renderer::{
    Backend, Intrinsics, RenderSettings, View, ViewRequest,
    gpu::{GpuBackend, ngp::GpuNgp},
    views::{QuiltLayout, focal_distance},
};
use nephele_signaling::Mode;
use nephele_train::Trainer;
use serde::Serialize;

use nephele_client::{
    Receive,
    ClientOptions,
    replay::{self, Percentiles, ReplayOptions, Trace},
};
use nephele_core::{CoreConfig, scheduler::RenderScale};
use nephele_farm::{
    assets::{BackendChoice, DEFAULT_ASSET, load_asset, make_backend, parse_size},
    catalog::Catalog,
};
use nephele_master::MasterConfig;

#[derive(clap::Args)]
pub struct QuiltBenchArgs {
    /// The i-NOLF asset.
    #[arg(long, default_value = DEFAULT_ASSET)]
    asset: String,
    /// Its i-NGP teacher (`DIR.train/ngp.ckpt` from `nephele train`), for the i-NGP rows.
    #[arg(long)]
    teacher: PathBuf,
    /// Quilt layout, COLSxROWS.
    #[arg(long, default_value = "5x9")]
    quilt: String,
    /// View cone, degrees.
    #[arg(long, default_value_t = 40.0)]
    cone: f32,
    /// One view's size (the streamed default: 5×9 tiles of 120×160 = 600×1440).
    #[arg(long, default_value = "120x160")]
    tile: String,
    #[arg(long, value_delimiter = ',', default_value = "cpu,gpu")]
    backends: Vec<BackendChoice>,
    /// Timed runs of each i-NOLF variant (median); i-NGP runs once.
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// Camera distance from the object centre (the focal plane goes through the centre).
    #[arg(long, default_value_t = 4.0)]
    distance: f64,
    /// Mono frame size of the stereo comparison (stereo: two eyes of half the width).
    #[arg(long, default_value = "640x320")]
    stereo_size: String,
    /// Poses replayed per streaming run (20 ms apart).
    #[arg(long, default_value_t = 200)]
    stereo_poses: usize,
    /// Skip the streaming comparison.
    #[arg(long)]
    no_stream: bool,
    #[arg(long)]
    json: bool,
}

/// One backend's quilt frame.
#[derive(Debug, Clone, Serialize)]
pub struct QuiltRow {
    pub backend: String,
    /// i-NOLF, all views in one task, ms per quilt (median).
    pub nolf_batched_ms: f64,
    /// i-NOLF, one render call per view, ms per quilt (median).
    pub nolf_separate_ms: f64,
    /// i-NGP teacher, every ray of the quilt in one call, ms per quilt.
    pub ngp_ms: f64,
    pub nolf_fps: f64,
    pub ngp_fps: f64,
    /// i-NGP ms / i-NOLF batched ms.
    pub speedup_vs_ngp: f64,
    /// Separate ms / batched ms.
    pub speedup_batched: f64,
}

/// Mono against stereo streaming at the same total pixels.
#[derive(Debug, Clone, Serialize)]
pub struct StereoRow {
    pub width: u32,
    pub height: u32,
    pub mono_latency_ms: Percentiles,
    pub stereo_latency_ms: Percentiles,
    pub mono_fps: f64,
    pub stereo_fps: f64,
    pub mono_render_ms: Percentiles,
    pub stereo_render_ms: Percentiles,
    /// Stereo p50 pose→decoded / mono p50.
    pub latency_ratio: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct QuiltReport {
    pub asset: String,
    pub quilt: String,
    pub views: u32,
    pub tile_width: u32,
    pub tile_height: u32,
    pub rows: Vec<QuiltRow>,
    /// The smallest i-NGP / i-NOLF ratio over the backends.
    pub speedup_vs_ngp: f64,
    /// Batched against separate renders on wgpu (where each dispatch has a fixed cost), or
    /// on the first backend when wgpu was not measured.
    pub speedup_batched: f64,
    pub stereo: Option<StereoRow>,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn timed<T>(f: impl FnOnce() -> Result<T>) -> Result<(T, f64)> {
    let t = Instant::now();
    let out = f()?;
    Ok((out, t.elapsed().as_secs_f64() * 1e3))
}

/// World-space rays of every view, in order.
fn quilt_rays(views: &[View]) -> Vec<(Vec3, Vec3)> {
    views
        .iter()
        .flat_map(|v| {
            let k = v.intrinsics;
            (0..k.height).flat_map(move |y| (0..k.width).map(move |x| (x, y))).map(move |(x, y)| {
                let (o, d) = v.ray_in_world(f64::from(x) + 0.5, f64::from(y) + 0.5);
                (o.as_vec3(), d.as_vec3())
            })
        })
        .collect()
}

pub fn run(args: QuiltBenchArgs) -> Result<()> {
    let layout = QuiltLayout::parse(&args.quilt, args.cone).map_err(anyhow::Error::msg)?;
    let (tw, th) = parse_size(&args.tile)?;
    let asset = load_asset(&args.asset)?;
    let centre = View::orbit(DVec3::ZERO, args.distance, 35.0, 25.0, Intrinsics::from_fov_x(tw, th, 39.6f32.to_radians()));
    let views = layout.cameras(&centre, focal_distance(&centre, DVec3::ZERO, 1e-3));
    let requests: Vec<ViewRequest> = views.iter().map(|v| ViewRequest::new(*v).with_background(Vec3::ONE)).collect();
    let rays = quilt_rays(&views);
    let settings = RenderSettings::default();
    eprintln!("loading the teacher {} ...", args.teacher.display());
    let (teacher, _) = Trainer::load_checkpoint(&args.teacher, None).with_context(|| format!("loading {}", args.teacher.display()))?;
    let mut rows = Vec::new();
    for choice in &args.backends {
        let backend: Box<dyn Backend> = make_backend(*choice)?;
        let name = backend.name().to_string();
        eprintln!("{name}: {} views of {tw}x{th} ...", views.len());
        let prepared = backend.prepare(Arc::clone(&asset))?;
        prepared.render(&requests, &settings)?; // warm-up (kernels, caches)
        let mut batched = Vec::new();
        let mut separate = Vec::new();
        for _ in 0..args.runs.max(1) {
            batched.push(timed(|| Ok(prepared.render(&requests, &settings)?))?.1);
            separate.push(timed(|| requests.iter().try_for_each(|r| prepared.render(std::slice::from_ref(r), &settings).map(|_| ())).map_err(anyhow::Error::from))?.1);
        }
        eprintln!("{name}: i-NGP on {} rays ...", rays.len());
        let ngp_ms = match choice {
            BackendChoice::Gpu => {
                let gpu = GpuBackend::new()?;
                let ngp = GpuNgp::new(gpu.ctx.clone(), &teacher)?;
                ngp.render(&rays[..64.min(rays.len())], Vec3::ONE)?; // compiles the kernel
                timed(|| Ok(ngp.render(&rays, Vec3::ONE)?))?.1
            }
            _ => timed(|| Ok(teacher.render(&rays, Vec3::ONE)))?.1,
        };
        let (b, s) = (median(batched), median(separate));
        rows.push(QuiltRow {
            backend: name,
            nolf_batched_ms: b,
            nolf_separate_ms: s,
            ngp_ms,
            nolf_fps: 1e3 / b,
            ngp_fps: 1e3 / ngp_ms,
            speedup_vs_ngp: ngp_ms / b,
            speedup_batched: s / b,
        });
    }
    let stereo = if args.no_stream { None } else { Some(stream_stereo(&args)?) };
    let speedup_vs_ngp = rows.iter().map(|r| r.speedup_vs_ngp).fold(f64::INFINITY, f64::min);
    let speedup_batched = rows.iter().find(|r| r.backend.contains("wgpu")).or(rows.first()).map_or(f64::NAN, |r| r.speedup_batched);
    let report = QuiltReport { asset: args.asset.clone(), quilt: args.quilt.clone(), views: layout.views(), tile_width: tw, tile_height: th, rows, speedup_vs_ngp, speedup_batched, stereo };
    crate::emit(args.json, &format_report(&report), &report)?;
    Ok(())
}

/// The same orbit streamed by a mono viewer and by a stereo headset session of the same
/// total pixels, one after the other on one in-process server (CPU renderer, scale 1).
fn stream_stereo(args: &QuiltBenchArgs) -> Result<StereoRow> {
    let (width, height) = parse_size(&args.stereo_size)?;
    let catalog = Arc::new(Catalog::load(&[format!("bench={}", args.asset)], make_backend(BackendChoice::Cpu)?.as_ref(), RenderSettings::default())?);
    let mut trace = Trace::builtin("orbit").map_err(anyhow::Error::msg)?;
    trace.poses.truncate(args.stereo_poses);
    let rt = tokio::runtime::Runtime::new()?;
    let run = |mode: Mode, baseline: Option<f32>| -> Result<replay::ReplayReport> {
        let cfg = MasterConfig::loopback("bench", CoreConfig { render_scale: RenderScale::Fixed(1.0), ..Default::default() });
        let catalog = Arc::clone(&catalog);
        let trace = &trace;
        rt.block_on(async move {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
            let server = nephele_master::web::spawn_local(listener, catalog, cfg).await?;
            let opts = ReplayOptions {
                client: ClientOptions { signal_url: server.signal_url(), scene: "bench".into(), mode, width, height, fps: 25, token: None, receive: Receive::Decode, quilt: None, depth: false },
                anchor: None,
                quality_every: 0,
                save_dir: None,
                drain: std::time::Duration::from_secs(2),
                start_at: None,
                stereo_baseline: baseline,
            };
            replay::replay(trace, &opts, None).await
        })
    };
    eprintln!("streaming mono {width}x{height} ...");
    let mono = run(Mode::Viewer, None)?;
    eprintln!("streaming stereo 2 x {}x{height} ...", width / 2);
    let stereo = run(Mode::Vr, Some(0.1))?;
    anyhow::ensure!(stereo.errors.is_empty() && mono.errors.is_empty(), "errors while streaming: {:?} {:?}", mono.errors, stereo.errors);
    Ok(StereoRow {
        width,
        height,
        latency_ratio: stereo.latency_ms.p50 / mono.latency_ms.p50,
        mono_latency_ms: mono.latency_ms,
        stereo_latency_ms: stereo.latency_ms,
        mono_fps: mono.fps,
        stereo_fps: stereo.fps,
        mono_render_ms: mono.render_ms,
        stereo_render_ms: stereo.render_ms,
    })
}

pub fn format_report(r: &QuiltReport) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "asset {}, quilt {} ({} views of {}x{}), one run\n", r.asset, r.quilt, r.views, r.tile_width, r.tile_height);
    let _ = writeln!(out, "| backend | i-NOLF one task ms | i-NOLF {} separate ms | i-NGP ms | i-NOLF fps | i-NGP fps | vs i-NGP | one task vs separate |", r.views);
    let _ = writeln!(out, "|---|---:|---:|---:|---:|---:|---:|---:|");
    for row in &r.rows {
        let _ = writeln!(
            out,
            "| {} | {:.1} | {:.1} | {:.1} | {:.2} | {:.3} | {:.1}× | {:.2}× |",
            row.backend, row.nolf_batched_ms, row.nolf_separate_ms, row.ngp_ms, row.nolf_fps, row.ngp_fps, row.speedup_vs_ngp, row.speedup_batched
        );
    }
    if let Some(s) = &r.stereo {
        let _ = writeln!(out, "\nStreaming the orbit at {}x{} total pixels (CPU renderer, render scale 1, 25 fps):\n", s.width, s.height);
        let _ = writeln!(out, "| session | pose→decoded p50 / p99 ms | render p50 ms | fps |");
        let _ = writeln!(out, "|---|---:|---:|---:|");
        let _ = writeln!(out, "| mono {}x{} | {:.1} / {:.1} | {:.1} | {:.1} |", s.width, s.height, s.mono_latency_ms.p50, s.mono_latency_ms.p99, s.mono_render_ms.p50, s.mono_fps);
        let _ = writeln!(
            out,
            "| stereo 2 × {}x{} | {:.1} / {:.1} | {:.1} | {:.1} |",
            s.width / 2,
            s.height,
            s.stereo_latency_ms.p50,
            s.stereo_latency_ms.p99,
            s.stereo_render_ms.p50,
            s.stereo_fps
        );
        let _ = writeln!(out, "\nstereo / mono p50 latency: {:.2}×", s.latency_ratio);
    }
    out
}
