//! `nephele bench users`: many users on one server (NEPHELE §6.2). For each backend, mode
//! (`batched`: users of a scene share one render task per round; `per_user`: every user
//! frame is its own task) and user count, a fresh in-process server and that many real
//! replay clients (WebRTC; the first `--decoders` decode with OpenH264, the others
//! reassemble access units and read their pose SEI, so that the load generator does not take
//! the server's cores), each replaying the orbit from its own phase so that no two ask for
//! the same view. Reports per-user achieved FPS, pose→decoded latency,
//! render ms per user-frame, user-frames rendered per second and how many users are held at
//! their FPS; then one run where two clients share a view, to show history hits.
//!
//! The server runs with admission `open` (the point is the farm's throughput under
//! overload, which admission by load would otherwise prevent) and, by default, the render
//! scale users get from `nephele serve` (`auto`: lowered fairly under load, down to 0.25);
//! `--render-scale 1` renders every frame at full size instead.

use std::{collections::BTreeMap, sync::Arc, time::Duration};

use anyhow::{Context, Result, bail};
use nephele_renderer::RenderSettings;
use nephele_protocol::Mode;
use serde::Serialize;

use nephele_client::{
    Receive,
    ClientOptions,
    replay::{ReplayOptions, ReplayReport, Trace, replay},
};
use nephele_core::{Admission, CoreConfig, scheduler::RenderScale};
use nephele_farm::{
    assets::{BackendChoice, DEFAULT_ASSET, make_backend, parse_size},
    catalog::Catalog,
};
use nephele_master::{MasterConfig, web};

/// A user counts as held when it gets at least this share of its target FPS.
pub const HELD_SHARE: f64 = 0.96;

#[derive(clap::Args, Debug, Clone)]
pub struct UsersArgs {
    #[arg(long, default_value = DEFAULT_ASSET)]
    asset: String,
    #[arg(long, default_value = "320x240")]
    size: String,
    /// Target FPS of every client.
    #[arg(long, default_value_t = 25)]
    fps: u32,
    #[arg(long, value_delimiter = ',', default_value = "1,2,4,8")]
    users: Vec<usize>,
    #[arg(long, value_delimiter = ',', default_value = "cpu,gpu")]
    backends: Vec<BackendChoice>,
    /// Times each client replays the orbit (5 s each).
    #[arg(long, default_value_t = 2)]
    loops: usize,
    /// Poses each client sends (20 ms apart); default: the orbit × `--loops`.
    #[arg(long)]
    poses: Option<usize>,
    /// `auto` (dynamic resolution, as served by default) or a fixed scale in 0.05..=1.
    #[arg(long, default_value = "auto")]
    render_scale: String,
    /// Render-time target of `--render-scale auto`, ms.
    #[arg(long, default_value_t = 30.0)]
    frame_budget_ms: f64,
    /// Clients that decode H.264 (the first N of each run); the others reassemble every
    /// access unit and read its pose SEI without decoding, so that the bench's own clients
    /// leave this machine's cores to the server they measure.
    #[arg(long, default_value_t = 1)]
    decoders: usize,
    /// Skip the shared-view run.
    #[arg(long)]
    no_shared: bool,
    /// Skip the overload run (admission by load, twice the users the first backend held).
    #[arg(long)]
    no_overload: bool,
    /// Print the report as JSON on stdout (the table goes to stderr).
    #[arg(long)]
    json: bool,
}

/// One (backend, mode, user count) run.
#[derive(Debug, Clone, Serialize)]
pub struct UsersRun {
    pub backend: String,
    pub mode: String,
    pub users: usize,
    pub users_held: usize,
    pub user_frames_per_s: f64,
    /// Rendered megapixels per second over all users: each user's frames/s × its frame's
    /// pixels × its mean render scale² (a farm that holds every user's frame rate shows
    /// what it can do more of in the resolution it keeps).
    pub user_megapixels_per_s: f64,
    pub fps_min: f64,
    pub fps_mean: f64,
    pub latency_p50_ms: f64,
    pub latency_p99_ms: f64,
    pub render_ms_per_user_frame: f64,
    pub mean_batch_views: f64,
    pub mean_render_scale: f64,
    /// Longest gap between two decoded frames of any user, ms.
    pub max_frame_gap_ms: f64,
    pub reused_frames: usize,
    /// Frames answering a pose the client never sent (must be 0).
    pub frames_wrong_pose: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct ModeSummary {
    /// At the largest user count.
    pub users: usize,
    pub users_held: usize,
    pub user_frames_per_s: f64,
    pub user_megapixels_per_s: f64,
    pub runs: Vec<UsersRun>,
}

#[derive(Debug, Clone, Serialize)]
pub struct BackendReport {
    pub batched: ModeSummary,
    pub per_user: ModeSummary,
    /// batched ÷ per_user user-frames per second at the largest user count.
    pub speedup: f64,
    /// batched ÷ per_user rendered megapixels per second there (with `--render-scale auto`
    /// both may hold every frame rate; batching then shows in the resolution kept).
    pub pixel_speedup: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct UsersReport {
    pub asset: String,
    pub width: u32,
    pub height: u32,
    pub fps: u32,
    pub render_scale: String,
    /// Clients per run that decode (the rest count access units).
    pub decoders: usize,
    pub backends: BTreeMap<String, BackendReport>,
    /// Two clients replaying the same orbit from the same phase (batched, first backend).
    pub shared_view: Option<UsersRun>,
    /// Admission by load under twice the users the first backend held (batched).
    pub overload: Option<OverloadRun>,
}

/// Clients join one per second, twice as many as the farm kept at 90% of their FPS with
/// batching; admission by load decides.
#[derive(Debug, Clone, Serialize)]
pub struct OverloadRun {
    pub backend: String,
    pub offered: usize,
    pub admitted: usize,
    /// Why each refused client was refused, as it was told.
    pub refusals: Vec<String>,
    /// The admitted users, measured as in the other runs.
    pub admitted_run: Option<UsersRun>,
    /// Admitted users' lowest FPS as a share of the target.
    pub min_fps_share: f64,
    /// Longest gap between two frames of an admitted user, in target periods.
    pub max_gap_periods: f64,
}

pub fn run(args: UsersArgs) -> Result<()> {
    let (width, height) = parse_size(&args.size)?;
    let mut trace = Trace::from_spec("orbit")?;
    let one_turn = trace.poses.clone();
    for _ in 1..args.loops.max(1) {
        trace.poses.extend_from_slice(&one_turn);
    }
    if let Some(n) = args.poses {
        anyhow::ensure!(n > 0, "--poses must be at least 1");
        trace.poses.truncate(n);
    }
    let scale = RenderScale::parse(&args.render_scale, args.frame_budget_ms).map_err(anyhow::Error::msg)?;
    let rt = tokio::runtime::Runtime::new()?;
    let mut backends = BTreeMap::new();
    let mut shared_view = None;
    let mut overload = None;
    for &choice in &args.backends {
        let backend = make_backend(choice)?;
        let name = format!("{choice:?}").to_lowercase();
        eprintln!("preparing {} on {} ...", args.asset, backend.name());
        let catalog = Arc::new(Catalog::load(&[format!("bench={}", args.asset)], backend.as_ref(), RenderSettings::default())?);
        let mut modes = Vec::new();
        for batching in [true, false] {
            let mode = if batching { "batched" } else { "per_user" };
            let mut runs = Vec::new();
            for &n in &args.users {
                eprintln!("{name} {mode}: {n} users at {width}x{height}, {} fps ...", args.fps);
                let phases: Vec<usize> = (0..n).map(|k| k * one_turn.len() / n.max(1)).collect();
                let reports = rt.block_on(session_run(&catalog, batching, scale, &trace, &phases, (width, height), args.fps, args.decoders, false))?;
                runs.push(summarise(&name, mode, args.fps, &reports));
            }
            let last = runs.last().context("no user counts given")?.clone();
            modes.push(ModeSummary { users: last.users, users_held: last.users_held, user_frames_per_s: last.user_frames_per_s, user_megapixels_per_s: last.user_megapixels_per_s, runs });
        }
        if !args.no_shared && shared_view.is_none() {
            eprintln!("{name} batched: 2 users sharing one view ...");
            let reports = rt.block_on(session_run(&catalog, true, scale, &trace, &[0, 0], (width, height), args.fps, args.decoders, true))?;
            shared_view = Some(summarise(&name, "shared_view", args.fps, &reports));
        }
        if !args.no_overload && overload.is_none() {
            // Twice the users batching kept at 90% of their FPS (the aim's measure).
            let held = modes[0].runs.iter().filter(|r| r.fps_min >= 0.9 * f64::from(args.fps)).map(|r| r.users).max().unwrap_or(1);
            let offered = 2 * held.max(1);
            eprintln!("{name} batched, admission by load: {offered} users join one per second ...");
            let (reports, refusals) = rt.block_on(overload_run(&catalog, scale, &trace, offered, (width, height), args.fps, args.decoders))?;
            let admitted_run = (!reports.is_empty()).then(|| summarise(&name, "admitted", args.fps, &reports));
            let min_fps_share = reports.iter().map(|r| r.fps / f64::from(args.fps)).fold(f64::INFINITY, f64::min);
            let max_gap_periods = reports.iter().map(|r| r.frame_gap_ms.max * f64::from(args.fps) / 1e3).fold(0.0, f64::max);
            overload = Some(OverloadRun { backend: name.clone(), offered, admitted: reports.len(), refusals, admitted_run, min_fps_share, max_gap_periods });
        }
        let per_user = modes.pop().expect("two modes");
        let batched = modes.pop().expect("two modes");
        let speedup = batched.user_frames_per_s / per_user.user_frames_per_s.max(1e-9);
        let pixel_speedup = batched.user_megapixels_per_s / per_user.user_megapixels_per_s.max(1e-9);
        backends.insert(name, BackendReport { batched, per_user, speedup, pixel_speedup });
    }
    let report = UsersReport { asset: args.asset.clone(), width, height, fps: args.fps, render_scale: args.render_scale.clone(), decoders: args.decoders, backends, shared_view, overload };
    crate::emit(args.json, &format_report(&report), &report)?;
    let wrong: usize = report.backends.values().flat_map(|b| b.batched.runs.iter().chain(&b.per_user.runs)).map(|r| r.frames_wrong_pose).sum();
    if wrong > 0 {
        bail!("{wrong} frames answered poses their client never sent");
    }
    Ok(())
}

/// Signaling for `users` benchmark clients, all from this machine's one address: the
/// per-address limits raised to fit them — a burst of `2·users` new sessions, `users`
/// sessions joined but not yet connected, and `2·users` open connections (the defaults suit
/// strangers on the internet, not one machine playing many users).
pub fn hub_for(users: usize) -> nephele_signaling::HubConfig {
    let mut hub = nephele_signaling::HubConfig::default();
    let users_u32 = u32::try_from(users).unwrap_or(u32::MAX);
    let l = &mut hub.limits;
    l.join_burst_per_address = l.join_burst_per_address.max(users_u32.saturating_mul(2));
    l.max_pending_joins_per_address = l.max_pending_joins_per_address.max(users);
    l.max_connections_per_address = l.max_connections_per_address.max(users.saturating_mul(2));
    hub
}

/// One server, `phases.len()` clients replaying `trace` from those pose offsets, at once;
/// `lockstep`: every client sends its first pose at the same moment; the first `decoders`
/// clients decode.
#[allow(clippy::too_many_arguments)]
async fn session_run(
    catalog: &Arc<Catalog>,
    batching: bool,
    scale: RenderScale,
    trace: &Trace,
    phases: &[usize],
    (width, height): (u32, u32),
    fps: u32,
    decoders: usize,
    lockstep: bool,
) -> Result<Vec<ReplayReport>> {
    let start_at = lockstep.then(|| std::time::Instant::now() + Duration::from_secs(4));
    let cfg = MasterConfig::loopback("bench", CoreConfig { capacity: phases.len().max(1) as u32, render_scale: scale, batching, admission: Admission::Open, ..Default::default() });
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let server = web::spawn_local_with(listener, Arc::clone(catalog), cfg, hub_for(phases.len())).await?;
    let mut tasks = Vec::new();
    for (k, &phase) in phases.iter().enumerate() {
        let mut t = trace.clone();
        let len = t.poses.len().max(1);
        t.poses.rotate_left(phase % len);
        let opts = ReplayOptions {
            client: ClientOptions { signal_url: server.signal_url(), scene: "bench".into(), mode: Mode::Viewer, width, height, fps, token: None, receive: receive_of(k, decoders), quilt: None, depth: false },
            anchor: None,
            quality_every: 0,
            save_dir: None,
            drain: Duration::from_secs(1),
            start_at, stereo_baseline: None,
        };
        tasks.push(tokio::spawn(async move { replay(&t, &opts, None).await }));
    }
    let mut reports = Vec::new();
    for t in tasks {
        reports.push(t.await.context("a replay client panicked")??);
    }
    Ok(reports)
}

/// `offered` clients join one per second on a server with admission by load; returns the
/// admitted clients' reports and the refused ones' errors.
#[allow(clippy::too_many_arguments)]
async fn overload_run(
    catalog: &Arc<Catalog>,
    scale: RenderScale,
    trace: &Trace,
    offered: usize,
    (width, height): (u32, u32),
    fps: u32,
    decoders: usize,
) -> Result<(Vec<ReplayReport>, Vec<String>)> {
    let cfg = MasterConfig::loopback("bench", CoreConfig { capacity: offered as u32, render_scale: scale, batching: true, admission: Admission::Load, ..Default::default() });
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let server = web::spawn_local_with(listener, Arc::clone(catalog), cfg, hub_for(offered)).await?;
    let mut tasks = Vec::new();
    for k in 0..offered {
        let mut t = trace.clone();
        let len = t.poses.len().max(1);
        t.poses.rotate_left(k * len / offered.max(1));
        // Everyone replays until the last one has had a full trace.
        let extra = t.poses[..len.min(50 * (offered - k))].to_vec();
        t.poses.extend(extra);
        let opts = ReplayOptions {
            client: ClientOptions { signal_url: server.signal_url(), scene: "bench".into(), mode: Mode::Viewer, width, height, fps, token: None, receive: receive_of(k, decoders), quilt: None, depth: false },
            anchor: None,
            quality_every: 0,
            save_dir: None,
            drain: Duration::from_secs(1), start_at: None, stereo_baseline: None
        };
        tasks.push(tokio::spawn(async move { replay(&t, &opts, None).await }));
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
    let (mut admitted, mut refused) = (Vec::new(), Vec::new());
    for t in tasks {
        match t.await.context("a replay client panicked")? {
            Ok(r) => admitted.push(r),
            Err(e) => refused.push(format!("{e:#}")),
        }
    }
    Ok((admitted, refused))
}

/// Client `k` decodes when it is one of the first `decoders`.
fn receive_of(k: usize, decoders: usize) -> Receive {
    if k < decoders { Receive::Decode } else { Receive::AccessUnits }
}

fn summarise(backend: &str, mode: &str, fps: u32, reports: &[ReplayReport]) -> UsersRun {
    let n = reports.len().max(1) as f64;
    let fps_each: Vec<f64> = reports.iter().map(|r| r.fps).collect();
    let frames: usize = reports.iter().map(|r| r.frames_decoded - r.reused_frames.min(r.frames_decoded)).sum();
    let per_frame: f64 = reports.iter().map(|r| r.render_ms_per_view * (r.frames_decoded - r.reused_frames.min(r.frames_decoded)) as f64).sum();
    UsersRun {
        backend: backend.into(),
        mode: mode.into(),
        users: reports.len(),
        users_held: fps_each.iter().filter(|f| **f >= HELD_SHARE * f64::from(fps)).count(),
        user_frames_per_s: fps_each.iter().sum(),
        user_megapixels_per_s: reports.iter().map(|r| r.fps * f64::from(r.width) * f64::from(r.height) * r.mean_render_scale.powi(2) / 1e6).sum(),
        fps_min: fps_each.iter().copied().fold(f64::INFINITY, f64::min),
        fps_mean: fps_each.iter().sum::<f64>() / n,
        latency_p50_ms: reports.iter().map(|r| r.latency_ms.p50).sum::<f64>() / n,
        latency_p99_ms: reports.iter().map(|r| r.latency_ms.p99).fold(0.0, f64::max),
        render_ms_per_user_frame: if frames > 0 { per_frame / frames as f64 } else { 0.0 },
        mean_batch_views: reports.iter().map(|r| r.mean_batch_views).sum::<f64>() / n,
        mean_render_scale: reports.iter().map(|r| r.mean_render_scale).sum::<f64>() / n,
        max_frame_gap_ms: reports.iter().map(|r| r.frame_gap_ms.max).fold(0.0, f64::max),
        reused_frames: reports.iter().map(|r| r.reused_frames).sum(),
        frames_wrong_pose: reports.iter().map(|r| r.frames_unknown_pose + r.frames_without_pose).sum(),
    }
}

pub fn format_report(r: &UsersReport) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "asset {}, {}x{}, target {} fps, render scale {}, admission open; held = at least {:.0}% of the target FPS; {} client(s) per run decode, the rest count access units\n",
        r.asset,
        r.width,
        r.height,
        r.fps,
        r.render_scale,
        100.0 * HELD_SHARE,
        r.decoders
    );
    let _ = writeln!(out, "| backend | mode | users | held | user-frames/s | rendered Mpx/s | fps min / mean | p50 / p99 ms | render ms per user-frame | views per task | render scale | max gap ms |");
    let _ = writeln!(out, "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let row = |out: &mut String, u: &UsersRun| {
        let _ = writeln!(
            out,
            "| {} | {} | {} | {} | {:.1} | {:.2} | {:.1} / {:.1} | {:.0} / {:.0} | {:.1} | {:.2} | {:.2} | {:.0} |",
            u.backend, u.mode, u.users, u.users_held, u.user_frames_per_s, u.user_megapixels_per_s, u.fps_min, u.fps_mean, u.latency_p50_ms, u.latency_p99_ms, u.render_ms_per_user_frame, u.mean_batch_views, u.mean_render_scale, u.max_frame_gap_ms
        );
    };
    for b in r.backends.values() {
        for u in b.batched.runs.iter().chain(&b.per_user.runs) {
            row(&mut out, u);
        }
    }
    let _ = writeln!(out);
    for (name, b) in &r.backends {
        let _ = writeln!(
            out,
            "{name}: batching raises user-frames/s {:.2}x at {} users ({:.1} vs {:.1}) and rendered pixels/s {:.2}x ({:.2} vs {:.2} Mpx/s)",
            b.speedup, b.batched.users, b.batched.user_frames_per_s, b.per_user.user_frames_per_s, b.pixel_speedup, b.batched.user_megapixels_per_s, b.per_user.user_megapixels_per_s
        );
    }
    if let Some(o) = &r.overload {
        let _ = writeln!(
            out,
            "\noverload ({} batched, admission by load): {} users offered one per second, {} admitted, {} refused; admitted users kept {:.0}% of the target FPS at worst, longest gap {:.1} periods",
            o.backend,
            o.offered,
            o.admitted,
            o.refusals.len(),
            100.0 * o.min_fps_share,
            o.max_gap_periods
        );
        if let Some(a) = &o.admitted_run {
            row(&mut out, a);
        }
        let mut reasons: Vec<&String> = o.refusals.iter().collect();
        reasons.dedup();
        for reason in reasons {
            let _ = writeln!(out, "  refused: {reason}");
        }
    }
    if let Some(s) = &r.shared_view {
        let _ = writeln!(
            out,
            "\nshared view ({} batched, 2 users sending the same poses at the same times): {} of their frames were rendered once for both (history table or a shared view of a task)",
            s.backend, s.reused_frames
        );
        row(&mut out, s);
    }
    out
}
