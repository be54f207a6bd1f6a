//! `nephele bench stream`: per-stage and end-to-end streaming latency through an in-process
//! server and the replay client, per frame size and render scale (each a fresh server):
//! queue, render, RGB→I420, encode and RTP send from the master's frame info; pose → frame
//! info and pose → decoded frame on the client's clock; fps, bit rate and PSNR against a
//! direct render of each answered pose.

use std::{fmt::Write, sync::Arc};

use anyhow::Result;
use nephele_client::{
    Receive,
    ClientOptions,
    replay::{self, Percentiles, Trace},
};
use nephele_core::{CoreConfig, scheduler::RenderScale};
use nephele_farm::{
    assets::{BackendChoice, DEFAULT_ASSET, make_backend, parse_size},
    catalog::Catalog,
};
use nephele_master::{MasterConfig, web};
use nephele_protocol::Mode;
use nephele_renderer::RenderSettings;
use serde::Serialize;

/// Per-stage and end-to-end streaming latency through an in-process server.
#[derive(clap::Args, Debug, Clone)]
pub struct StreamArgs {
    #[arg(long, default_value = DEFAULT_ASSET)]
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
    /// Poses per run (20 ms apart); default: the whole trace.
    #[arg(long)]
    poses: Option<usize>,
    /// Print the report as JSON on stdout (the tables go to stderr).
    #[arg(long)]
    pub json: bool,
}

/// One size at one render scale.
#[derive(Debug, Clone, Serialize)]
pub struct StreamRow {
    pub width: u32,
    pub height: u32,
    pub scale: String,
    pub queue_ms: Percentiles,
    pub render_ms: Percentiles,
    pub convert_ms: Percentiles,
    pub encode_ms: Percentiles,
    pub send_ms: Percentiles,
    pub pose_to_info_ms: Percentiles,
    pub pose_to_decoded_ms: Percentiles,
    pub frames: usize,
    pub fps: f64,
    pub kbps: f64,
    pub idr_frames: usize,
    /// PSNR of the decoded frames against direct renders of their poses, dB (none when no
    /// frame was compared).
    pub psnr_mean_db: Option<f64>,
    pub psnr_min_db: Option<f64>,
    /// Frames that answer no pose this client sent, or carry none (must be 0).
    pub bad_frames: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct StreamReport {
    pub asset: String,
    pub backend: String,
    pub trace: String,
    pub poses: usize,
    pub pose_period_ms: f64,
    pub fps: u32,
    pub frame_budget_ms: f64,
    pub pose_latch: f64,
    pub rows: Vec<StreamRow>,
}

pub fn run(args: StreamArgs) -> Result<()> {
    let StreamArgs { asset, sizes, trace, backend, fps, render_scales, frame_budget_ms, pose_latch, poses, json } = args;
    let mut trace = Trace::from_spec(&trace)?;
    if let Some(n) = poses {
        anyhow::ensure!(n > 0, "--poses must be at least 1");
        trace.poses.truncate(n);
    }
    let sizes: Vec<(u32, u32)> = sizes.split(',').map(parse_size).collect::<Result<_>>()?;
    let scales: Vec<(String, RenderScale)> = render_scales
        .iter()
        .map(|s| RenderScale::parse(s, frame_budget_ms).map(|r| (s.clone(), r)).map_err(anyhow::Error::msg))
        .collect::<Result<_>>()?;
    let backend = make_backend(backend)?;
    let catalog = Arc::new(Catalog::load(&[format!("bench={asset}")], backend.as_ref(), RenderSettings::default())?);
    let rt = tokio::runtime::Runtime::new()?;
    let mut rows = Vec::new();
    for (label, scale) in &scales {
        for &(width, height) in &sizes {
            eprintln!("streaming {} at {width}x{height}, render scale {label} ...", trace.name);
            let cfg = MasterConfig::loopback("bench", CoreConfig { render_scale: *scale, pose_latch, ..Default::default() });
            let catalog = Arc::clone(&catalog);
            let r = rt.block_on(async {
                let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
                let server = web::spawn_local(listener, Arc::clone(&catalog), cfg).await?;
                let opts = replay::ReplayOptions {
                    client: ClientOptions { signal_url: server.signal_url(), scene: "bench".into(), mode: Mode::Viewer, width, height, fps, token: None, receive: Receive::Pixels, quilt: None, depth: false },
                    anchor: None,
                    quality_every: 10,
                    save_dir: None,
                    drain: std::time::Duration::from_secs(2),
                    start_at: None,
                    stereo_baseline: None,
                };
                let reference = |view, instance, background| catalog.render_scene("bench", view, instance, background);
                replay::replay(&trace, &opts, Some(&reference)).await
            })?;
            rows.push(StreamRow {
                width: r.width,
                height: r.height,
                scale: label.clone(),
                queue_ms: r.queue_ms,
                render_ms: r.render_ms,
                convert_ms: r.convert_ms,
                encode_ms: r.encode_ms,
                send_ms: r.send_ms,
                pose_to_info_ms: r.info_latency_ms,
                pose_to_decoded_ms: r.latency_ms,
                frames: r.frames_decoded,
                fps: r.fps,
                kbps: r.bitrate_kbps,
                idr_frames: r.idr_frames,
                psnr_mean_db: r.mean_psnr(),
                psnr_min_db: r.min_psnr(),
                bad_frames: r.frames_unknown_pose + r.frames_without_pose,
            });
        }
    }
    let report = StreamReport {
        asset,
        backend: backend.name(),
        trace: trace.name.clone(),
        poses: trace.poses.len(),
        pose_period_ms: trace.period_ms,
        fps,
        frame_budget_ms,
        pose_latch,
        rows,
    };
    crate::emit(json, &format_tables(&report), &report)
}

pub fn format_tables(r: &StreamReport) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "asset {}, backend {}, trace {} ({} poses every {} ms), target {} fps, auto budget {} ms, pose latch {}\n",
        r.asset, r.backend, r.trace, r.poses, r.pose_period_ms, r.fps, r.frame_budget_ms, r.pose_latch
    );
    let _ = writeln!(out, "Per stage, p50 / p99 ms (master stages from frame info; end to end on the client clock):\n");
    let _ = writeln!(out, "| size | scale | queue | render | RGB→I420 | encode | RTP send | pose→frame info | pose→decoded |");
    let _ = writeln!(out, "|---|---|---:|---:|---:|---:|---:|---:|---:|");
    let pp = |p: &Percentiles| format!("{:.1} / {:.1}", p.p50, p.p99);
    for row in &r.rows {
        let _ = writeln!(
            out,
            "| {}x{} | {} | {} | {} | {} | {} | {} | {} | {} |",
            row.width,
            row.height,
            row.scale,
            pp(&row.queue_ms),
            pp(&row.render_ms),
            pp(&row.convert_ms),
            pp(&row.encode_ms),
            pp(&row.send_ms),
            pp(&row.pose_to_info_ms),
            pp(&row.pose_to_decoded_ms)
        );
    }
    let _ = writeln!(out, "\n| size | scale | frames | fps | kbit/s | IDR | PSNR mean / min dB | bad frames |");
    let _ = writeln!(out, "|---|---|---:|---:|---:|---:|---:|---:|");
    for row in &r.rows {
        let _ = writeln!(
            out,
            "| {}x{} | {} | {} | {:.1} | {:.0} | {} | {:.2} / {:.2} | {} |",
            row.width,
            row.height,
            row.scale,
            row.frames,
            row.fps,
            row.kbps,
            row.idr_frames,
            row.psnr_mean_db.unwrap_or(f64::NAN),
            row.psnr_min_db.unwrap_or(f64::NAN),
            row.bad_frames
        );
    }
    out
}
