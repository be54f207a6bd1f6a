//! `nephele bench glass`: what the eye sees. A motion trace is replayed through a real
//! in-process server (real WebRTC, H.264, depth on the data channel) over a client socket
//! that adds a round-trip delay; a 60 Hz display clock on the client picks, at every display
//! frame, the newest decoded picture and shows it four ways:
//!
//! | mode | what is sent | what is shown |
//! |---|---|---|
//! | stale | the present pose | the picture as decoded (today's viewer) |
//! | reproject | the present pose | the picture warped by its depth to the display frame's pose |
//! | predict | the pose predicted for when its frame will be shown | the picture as decoded |
//! | both | predicted | warped |
//!
//! Stale and reproject share one stream, predict and both another (a fresh server each). After
//! the streams, every display frame is compared with a direct render at that frame's true
//! pose (the trace sampled at the display tick): PSNR (mean and 5th percentile), the pose age
//! of what is shown (display time minus the time of the camera it shows; a warped picture
//! shows the display pose itself, unless its depth was missing), and bytes per frame of
//! video and depth. The stream may be rendered with a guard band (`--overscan`) that a
//! turn can reveal; the display is the centre. A still camera at 0 ms checks that
//! reprojection loses nothing when nothing moves.

use std::{collections::HashMap, fmt::Write, path::PathBuf, sync::Arc, time::Duration};

use anyhow::{Context, Result, bail};
use glam::{DMat3, DMat4, DQuat};
use nephele_client::{
    ClientOptions, Receive, StreamClient,
    delay::delayed_net,
    glass::{PosePredictor, crop, overscanned, warp},
    replay::Trace,
};
use nephele_core::CoreConfig;
use nephele_farm::{
    assets::{BackendChoice, DEFAULT_ASSET, make_backend, parse_size},
    catalog::Catalog,
};
use nephele_master::{MasterConfig, web};
use nephele_protocol::Mode;
use nephele_renderer::{Instance, Intrinsics, RenderSettings, View, render::psnr_rgb};
use nephele_wire::{PoseMessage, Predicted, ToViewer, VIEWER_BACKGROUND, depth::DepthFrame};
use serde::Serialize;

/// What the eye sees at added round trips, four ways (see the module notes).
#[derive(clap::Args, Debug, Clone)]
pub struct GlassArgs {
    #[arg(long, default_value = DEFAULT_ASSET)]
    asset: String,
    /// Display size (the stream adds the guard band).
    #[arg(long, default_value = "320x240")]
    size: String,
    /// A built-in trace (`head`, `orbit`, `shake`, `zoom`) or a trace file.
    #[arg(long, default_value = "head")]
    trace: String,
    #[arg(long, value_enum, default_value = "auto")]
    backend: BackendChoice,
    /// Stream frame rate asked for.
    #[arg(long, default_value_t = 50)]
    fps: u32,
    /// The display's refresh rate, Hz.
    #[arg(long, default_value_t = 60.0)]
    display_hz: f64,
    /// Round-trip delays added to the path, ms.
    #[arg(long, value_delimiter = ',', default_value = "0,50,100,150")]
    rtts: Vec<u32>,
    /// Guard band rendered around the display on each side, as a fraction of its size.
    #[arg(long, default_value_t = 0.1)]
    overscan: f64,
    /// Display frames before this are not scored (the stream starting), ms.
    #[arg(long, default_value_t = 500.0)]
    warmup_ms: f64,
    /// Also draw the chart (PNG, and SVG beside it).
    #[arg(long)]
    chart: Option<PathBuf>,
    /// Print the report as JSON on stdout (the tables go to stderr).
    #[arg(long)]
    pub json: bool,
}

/// The four ways a display frame can be made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum GlassMode {
    Stale,
    Reproject,
    Predict,
    Both,
}

impl GlassMode {
    pub const ALL: [GlassMode; 4] = [GlassMode::Stale, GlassMode::Reproject, GlassMode::Predict, GlassMode::Both];
    fn name(self) -> &'static str {
        match self {
            Self::Stale => "stale",
            Self::Reproject => "reproject",
            Self::Predict => "predict",
            Self::Both => "both",
        }
    }
    fn predicts(self) -> bool {
        matches!(self, Self::Predict | Self::Both)
    }
    fn warps(self) -> bool {
        matches!(self, Self::Reproject | Self::Both)
    }
}

/// One mode at one round trip.
#[derive(Debug, Clone, Serialize)]
pub struct GlassRow {
    pub rtt_ms: u32,
    pub mode: GlassMode,
    pub psnr_mean_db: f64,
    pub psnr_p5_db: f64,
    /// Display time minus the time of the camera shown, ms.
    pub pose_age_mean_ms: f64,
    pub pose_age_p95_ms: f64,
    /// Angle between the camera shown and the true one, degrees (0 when warped).
    pub rotation_error_mean_deg: f64,
    /// Display frames scored, and of those how many had no picture yet or no depth.
    pub display_frames: usize,
    pub missing_depth: usize,
    pub video_bytes_per_frame: f64,
    pub depth_bytes_per_frame: f64,
    /// The master's mean render time of the frames it rendered (the guard band's cost), ms.
    pub render_ms_mean: f64,
    /// Mean pose→display latency the client learnt (and predicted by in predict modes), ms.
    pub learnt_latency_ms: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct GlassReport {
    pub asset: String,
    pub backend: String,
    pub trace: String,
    pub display: (u32, u32),
    pub stream: (u32, u32),
    pub overscan: f64,
    pub display_hz: f64,
    pub fps: u32,
    pub rows: Vec<GlassRow>,
    /// Mean PSNR per mode and round trip: `psnr_db["both"]["100"]`.
    pub psnr_db: HashMap<String, HashMap<String, f64>>,
    /// A still camera at 0 ms: PSNR shown as decoded and warped.
    pub still_stale_db: f64,
    pub still_reproject_db: f64,
}

/// One display frame as the client saw it.
struct Shown {
    t_ms: f64,
    /// Index into the run's decoded frames.
    frame: usize,
}

/// A decoded frame with what it answers.
struct Decoded {
    pose_seq: u64,
    rgba: Vec<u8>,
}

/// What one stream recorded.
struct Run {
    decoded: Vec<Decoded>,
    shown: Vec<Shown>,
    /// Pose seq → (time sent, ms; camera sent; horizon predicted, ms).
    sent: HashMap<u64, (f64, DMat4, f64)>,
    depth: HashMap<u64, DepthFrame>,
    video_bytes: Vec<usize>,
    depth_bytes: Vec<usize>,
    render_ms: Vec<f64>,
    latency_ms: Vec<f64>,
}

pub fn run(args: GlassArgs) -> Result<()> {
    let (dw, dh) = parse_size(&args.size)?;
    anyhow::ensure!((0.0..=0.5).contains(&args.overscan), "--overscan must be in 0..=0.5");
    anyhow::ensure!(args.display_hz.is_finite() && (10.0..=240.0).contains(&args.display_hz), "--display-hz must be in 10..=240");
    let trace = Trace::from_spec(&args.trace)?;
    let display = trace.intrinsics(dw, dh);
    let stream = overscanned(&display, args.overscan);
    let backend = make_backend(args.backend)?;
    let catalog = Arc::new(Catalog::load(&[format!("bench={}", args.asset)], backend.as_ref(), RenderSettings::default())?);
    let rt = tokio::runtime::Runtime::new()?;
    let period_ms = 1e3 / args.display_hz;
    let ticks = (trace.duration_ms() / period_ms).floor() as usize + 1;
    let first = (args.warmup_ms / period_ms).ceil() as usize;
    anyhow::ensure!(first < ticks, "the trace ({:.0} ms) is shorter than the warm-up", trace.duration_ms());

    // The truth: a direct render at every scored display frame's pose.
    eprintln!("rendering {} display frames of {} directly ...", ticks - first, trace.name);
    let render = |camera: DMat4| -> Result<Vec<u8>> {
        let view = View { world_from_camera: camera, intrinsics: display };
        Ok(catalog.render_scene("bench", view, Instance::default(), VIEWER_BACKGROUND)?.rgba)
    };
    let truth: Vec<Vec<u8>> = (first..ticks).map(|k| render(trace.pose_at(k as f64 * period_ms))).collect::<Result<_>>()?;

    let mut rows = Vec::new();
    for &rtt in &args.rtts {
        for predict in [false, true] {
            eprintln!("streaming {} at {rtt} ms round trip, {} ...", trace.name, if predict { "predicting" } else { "present pose" });
            let run = rt.block_on(stream_run(&catalog, &trace, &args, stream, predict, rtt, period_ms, ticks))?;
            for mode in GlassMode::ALL.into_iter().filter(|m| m.predicts() == predict) {
                rows.push(score(&run, mode, rtt, &trace, &display, stream, &truth, first, period_ms));
            }
        }
    }

    // A still camera: reprojection must lose nothing.
    eprintln!("a still camera at 0 ms ...");
    let still_pose = trace.pose_at(0.0);
    let still = Trace { name: "still".into(), description: "one pose".into(), poses: vec![still_pose.as_mat4().to_cols_array(); 100], ..trace.clone() };
    let (still_ticks, still_first) = (120, 30);
    let run = rt.block_on(stream_run(&catalog, &still, &args, stream, false, 0, period_ms, still_ticks))?;
    let still_truth = vec![render(still_pose)?; still_ticks - still_first];
    let still_scored = |mode: GlassMode| score(&run, mode, 0, &still, &display, stream, &still_truth, still_first, period_ms).psnr_mean_db;
    let (still_stale_db, still_reproject_db) = (still_scored(GlassMode::Stale), still_scored(GlassMode::Reproject));

    let mut psnr_db: HashMap<String, HashMap<String, f64>> = HashMap::new();
    for r in &rows {
        psnr_db.entry(r.mode.name().into()).or_default().insert(r.rtt_ms.to_string(), r.psnr_mean_db);
    }
    let report = GlassReport {
        asset: args.asset.clone(),
        backend: backend.name(),
        trace: trace.name.clone(),
        display: (dw, dh),
        stream: (stream.width, stream.height),
        overscan: args.overscan,
        display_hz: args.display_hz,
        fps: args.fps,
        rows,
        psnr_db,
        still_stale_db,
        still_reproject_db,
    };
    if let Some(path) = &args.chart {
        chart(path, &report)?;
    }
    crate::emit(args.json, &format_tables(&report), &report)
}

/// Streams `trace` once and records what a 60 Hz display would have shown.
#[allow(clippy::too_many_arguments)]
async fn stream_run(catalog: &Arc<Catalog>, trace: &Trace, args: &GlassArgs, stream: Intrinsics, predict: bool, rtt_ms: u32, period_ms: f64, ticks: usize) -> Result<Run> {
    let cfg = MasterConfig::loopback("bench", CoreConfig::default());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let server = web::spawn_local(listener, Arc::clone(catalog), cfg).await?;
    let opts = ClientOptions {
        signal_url: server.signal_url(),
        scene: "bench".into(),
        mode: Mode::Viewer,
        width: stream.width,
        height: stream.height,
        fps: args.fps,
        token: None,
        receive: Receive::Pixels,
        quilt: None,
        depth: true,
    };
    let net = delayed_net(Duration::from_millis(u64::from(rtt_ms))).await?;
    let mut client = StreamClient::connect_with(&opts, &net).await.context("connecting through the delayed socket")?;

    let mut run = Run { decoded: Vec::new(), shown: Vec::new(), sent: HashMap::new(), depth: HashMap::new(), video_bytes: Vec::new(), depth_bytes: Vec::new(), render_ms: Vec::new(), latency_ms: Vec::new() };
    let mut predictor = PosePredictor::new();
    let mut learnt_ms: Option<f64> = None;
    let start = tokio::time::Instant::now();
    let mut pose_tick = tokio::time::interval_at(start, Duration::from_secs_f64(trace.period_ms / 1e3));
    let mut display_tick = tokio::time::interval_at(start, Duration::from_secs_f64(period_ms / 1e3));
    for t in [&mut pose_tick, &mut display_tick] {
        t.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Burst);
    }
    let (mut seq, mut k) = (0u32, 0usize);
    while k < ticks {
        tokio::select! {
            _ = pose_tick.tick(), if (seq as usize) < trace.poses.len() => {
                let t_ms = f64::from(seq) * trace.period_ms;
                let present = trace.pose_at(t_ms);
                predictor.observe(t_ms, present);
                let horizon = if predict { learnt_ms.unwrap_or(0.0) } else { 0.0 };
                let camera = if predict { predictor.predict(horizon).unwrap_or(present) } else { present };
                seq += 1;
                run.sent.insert(u64::from(seq), (t_ms, camera, horizon));
                // A predicted camera goes with the present one (the master checks the two agree).
                let predicted = predict.then(|| Predicted { horizon_ms: horizon, present_world_from_camera: present.as_mat4() });
                let pose = PoseMessage { seq, t_client_ms: t_ms, world_from_camera: camera.as_mat4(), intrinsics: stream, world_from_anchor: None, predicted };
                client.send_pose(&pose).await?;
            }
            _ = display_tick.tick() => {
                let t_ms = k as f64 * period_ms;
                if let Some(last) = run.decoded.last() {
                    run.shown.push(Shown { t_ms, frame: run.decoded.len() - 1 });
                    // Pose → display latency, learnt as a running mean (the horizon).
                    if let Some(&(sent_ms, _, _)) = run.sent.get(&last.pose_seq) {
                        let age = t_ms - sent_ms;
                        run.latency_ms.push(age);
                        learnt_ms = Some(learnt_ms.map_or(age, |l| l + 0.1 * (age - l)));
                    }
                }
                k += 1;
            }
            f = client.frames.recv() => match f {
                Some(f) => if let Some(pose_seq) = f.pose_seq {
                    run.decoded.push(Decoded { pose_seq, rgba: f.rgba });
                },
                None => bail!("the video stream ended"),
            },
            d = client.depth.recv() => match d {
                Some(Ok(d)) => { run.depth.insert(u64::from(d.pose_seq), d); }
                Some(Err(e)) => bail!("a depth message did not parse: {e}"),
                None => bail!("the pose channel closed"),
            },
            m = client.messages.recv() => match m {
                Some(ToViewer::Frame(info)) => {
                    run.video_bytes.push(info.times.bytes);
                    run.depth_bytes.push(info.times.depth_bytes);
                    if !info.reused {
                        run.render_ms.push(info.times.render_ms);
                    }
                }
                Some(ToViewer::Error { code, message }) => bail!("the master refused a pose ({code}): {message}"),
                Some(_) => {}
                None => bail!("the pose channel closed"),
            },
        }
    }
    client.close().await;
    drop(server);
    Ok(run)
}

/// Scores one mode of a run against the direct renders.
#[allow(clippy::too_many_arguments)]
fn score(run: &Run, mode: GlassMode, rtt_ms: u32, trace: &Trace, display: &Intrinsics, stream: Intrinsics, truth: &[Vec<u8>], first: usize, period_ms: f64) -> GlassRow {
    let bg = (VIEWER_BACKGROUND * 255.0).round().as_uvec3();
    let background = [bg.x as u8, bg.y as u8, bg.z as u8];
    let (mut psnr, mut age, mut rot) = (Vec::new(), Vec::new(), Vec::new());
    let mut missing_depth = 0;
    for s in &run.shown {
        let k = (s.t_ms / period_ms).round() as usize;
        let Some(truth) = k.checked_sub(first).and_then(|i| truth.get(i)) else { continue };
        let d = &run.decoded[s.frame];
        let Some(&(sent_ms, camera, horizon)) = run.sent.get(&d.pose_seq) else { continue };
        let true_camera = trace.pose_at(s.t_ms);
        let depth = run.depth.get(&d.pose_seq).and_then(|f| f.views.first());
        let target = View { world_from_camera: true_camera, intrinsics: *display };
        let warped_rgba = if mode.warps() { depth.and_then(|depth| warp(&d.rgba, stream.width, depth, &target, background)) } else { None };
        let warped = warped_rgba.is_some();
        if mode.warps() && !warped {
            missing_depth += 1;
        }
        let shown = warped_rgba.unwrap_or_else(|| crop(&d.rgba, stream.width, stream.height, display.width, display.height));
        psnr.push(psnr_rgb(&shown, truth).min(99.0));
        if warped {
            age.push(0.0);
            rot.push(0.0);
        } else {
            age.push(s.t_ms - (sent_ms + horizon));
            let (a, b) = (DQuat::from_mat3(&DMat3::from_mat4(camera)), DQuat::from_mat3(&DMat3::from_mat4(true_camera)));
            rot.push(a.angle_between(b).to_degrees());
        }
    }
    let mean = |v: &[f64]| if v.is_empty() { f64::NAN } else { v.iter().sum::<f64>() / v.len() as f64 };
    let pct = |v: &[f64], q: f64| {
        let mut v = v.to_vec();
        v.sort_by(f64::total_cmp);
        if v.is_empty() { f64::NAN } else { v[((q * (v.len() - 1) as f64).round() as usize).min(v.len() - 1)] }
    };
    let bytes = |v: &[usize]| mean(&v.iter().map(|&b| b as f64).collect::<Vec<_>>());
    GlassRow {
        rtt_ms,
        mode,
        psnr_mean_db: mean(&psnr),
        psnr_p5_db: pct(&psnr, 0.05),
        pose_age_mean_ms: mean(&age),
        pose_age_p95_ms: pct(&age, 0.95),
        rotation_error_mean_deg: mean(&rot),
        display_frames: psnr.len(),
        missing_depth,
        video_bytes_per_frame: bytes(&run.video_bytes),
        depth_bytes_per_frame: bytes(&run.depth_bytes),
        render_ms_mean: mean(&run.render_ms),
        learnt_latency_ms: mean(&run.latency_ms),
    }
}

pub fn format_tables(r: &GlassReport) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "asset {}, backend {}, trace {}, display {}x{} at {} Hz, stream {}x{} (guard band {} a side) at {} fps\n",
        r.asset, r.backend, r.trace, r.display.0, r.display.1, r.display_hz, r.stream.0, r.stream.1, r.overscan, r.fps
    );
    let _ = writeln!(out, "| RTT ms | mode | PSNR mean dB | PSNR p5 dB | pose age mean / p95 ms | rotation error ° | frames | no depth | video B/frame | depth B/frame | render ms | latency learnt ms |");
    let _ = writeln!(out, "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for row in &r.rows {
        let _ = writeln!(
            out,
            "| {} | {} | {:.2} | {:.2} | {:.1} / {:.1} | {:.2} | {} | {} | {:.0} | {:.0} | {:.1} | {:.1} |",
            row.rtt_ms,
            row.mode.name(),
            row.psnr_mean_db,
            row.psnr_p5_db,
            row.pose_age_mean_ms,
            row.pose_age_p95_ms,
            row.rotation_error_mean_deg,
            row.display_frames,
            row.missing_depth,
            row.video_bytes_per_frame,
            row.depth_bytes_per_frame,
            row.render_ms_mean,
            row.learnt_latency_ms
        );
    }
    let _ = writeln!(out, "\nStill camera, 0 ms: as decoded {:.2} dB, reprojected {:.2} dB", r.still_stale_db, r.still_reproject_db);
    let get = |mode: GlassMode, rtt: u32| r.rows.iter().find(|x| x.mode == mode && x.rtt_ms == rtt).map(|x| x.psnr_mean_db);
    if let (Some(both), Some(stale), Some(stale0)) = (get(GlassMode::Both, 100), get(GlassMode::Stale, 100), get(GlassMode::Stale, 0)) {
        let _ = writeln!(out, "At 100 ms: prediction + reprojection {:+.2} dB over stale, {:+.2} dB against the 0 ms stale stream", both - stale, both - stale0);
    }
    out
}

fn chart(path: &std::path::Path, r: &GlassReport) -> Result<()> {
    use crate::plot::{Labels, Series, line_chart};
    let colours = [[200, 60, 60], [60, 120, 200], [230, 150, 30], [40, 160, 80]];
    let series: Vec<Series> = GlassMode::ALL
        .iter()
        .zip(colours)
        .map(|(&mode, rgb)| Series { name: mode.name().into(), rgb, points: r.rows.iter().filter(|x| x.mode == mode).map(|x| (f64::from(x.rtt_ms), x.psnr_mean_db)).collect() })
        .collect();
    let title = format!("What the eye sees: {} trace, {}x{} at {} Hz", r.trace, r.display.0, r.display.1, r.display_hz);
    line_chart(path, &Labels { title: &title, x: "added round trip, ms", y: "PSNR against the true pose, dB" }, &series, false)
}
