//! `nephele bench farm`: the render farm on NATS against the in-process worker, on this
//! machine (the worker processes share its cores, so the point is the cost of the hop, not
//! a speed-up). It starts its own `nats-server` (with a token) on a free loopback port and
//! `nephele worker` processes, then, one fresh master each:
//! - one object (lego) with the in-process worker, 1 and 2 NATS workers: frame time,
//!   throughput, and the NATS hop (serialise + transfer) per frame and per MB;
//! - a composed scene (duo: two objects) in process and on 2 NATS workers: NEPHELE's Eq. 9,
//!   `T_frame = max T_i + Σ D_i / BW + C`, term by term as measured, against the measured
//!   frame time, and the composed frame's cost against the sum of its objects' renders;
//! - failover: a worker killed (SIGKILL) mid-stream, several times; the gap in decoded
//!   frames around each kill.

use std::{
    process::{Child, Command, Stdio},
    sync::Arc,
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail};
use nephele_renderer::{FastCpuBackend, RenderSettings};
use nephele_protocol::Mode;
use serde::Serialize;

use nephele_client::{
    Receive,
    ClientOptions,
    replay::{ReplayOptions, ReplayReport, Trace, replay},
};
use nephele_core::{Admission, CoreConfig, scheduler::RenderScale};
use nephele_farm::{assets::parse_size, catalog::Catalog, worker::NatsAuth};
use nephele_master::{MasterConfig, compositor::ComposeChoice, driver::NatsSettings, encoder::DEFAULT_BITS_PER_PIXEL, web};
use nephele_rtc::RtcConfig;

#[derive(clap::Args, Debug, Clone)]
pub struct FarmArgs {
    /// The one-object scene.
    #[arg(long, default_value = "builtin:lego")]
    asset: String,
    /// The composed scene.
    #[arg(long, default_value = "builtin:duo")]
    scene: String,
    #[arg(long, default_value = "640x480")]
    size: String,
    /// Poses per run (20 ms apart).
    #[arg(long, default_value_t = 250)]
    poses: usize,
    /// Worker kills in the failover run.
    #[arg(long, default_value_t = 3)]
    kills: usize,
    /// Print the report as JSON on stdout (the table goes to stderr).
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct FarmRun {
    pub scene: String,
    pub farm: String,
    pub frames: usize,
    pub fps: f64,
    pub latency_p50_ms: f64,
    pub latency_p99_ms: f64,
    /// Frame start → pixels ready (rendered, gathered, composed), p50.
    pub frame_ms: f64,
    /// Eq. 9 terms, p50: the longest object render, all object renders summed, the NATS
    /// hop (serialise + transfer, both ways), composition.
    pub render_max_ms: f64,
    pub render_sum_ms: f64,
    pub hop_ms: f64,
    pub compose_ms: f64,
    pub result_mb_per_frame: f64,
    /// The hop per MB of results.
    pub hop_ms_per_mb: f64,
    /// The hop as a share of the frame time.
    pub hop_share: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct FarmReport {
    pub width: u32,
    pub height: u32,
    pub runs: Vec<FarmRun>,
    /// Per kill: from the kill to the first frame decoded after it, ms.
    pub failover_gaps_ms: Vec<f64>,
    /// The longest of them.
    pub failover_gap_ms: f64,
    /// Per kill: the longest time between two decoded frames around it (includes the
    /// ordinary frame interval), ms.
    pub frame_gaps_ms: Vec<f64>,
    /// Sessions that ended during the failover run (must be 0).
    pub sessions_lost: usize,
}

/// A child process killed when dropped.
struct Proc(Child);

impl Drop for Proc {
    fn drop(&mut self) {
        self.0.kill().ok();
        self.0.wait().ok();
    }
}

struct Nats {
    _proc: Proc,
    url: String,
    token: String,
}

impl Nats {
    fn settings(&self) -> NatsSettings {
        NatsSettings { url: self.url.clone(), auth: NatsAuth { token: Some(self.token.clone()), ..Default::default() } }
    }
}

fn start_nats() -> Result<Nats> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
    let token = format!("bench{}", std::process::id());
    let child = Command::new("nats-server")
        .args(["-a", "127.0.0.1", "-p", &port.to_string(), "--auth", &token])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .context("starting nats-server (install the `nats-server` package)")?;
    for _ in 0..200 {
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
            return Ok(Nats { _proc: Proc(child), url: format!("nats://127.0.0.1:{port}"), token });
        }
        std::thread::sleep(Duration::from_millis(25));
    }
    bail!("nats-server did not listen within 5 s")
}

/// Starts `nephele worker` (this binary) and waits for it to serve.
fn spawn_worker(nats: &Nats, id: &str, scenes: &[String]) -> Result<Proc> {
    use std::io::{BufRead, BufReader};
    let mut cmd = Command::new(std::env::current_exe()?);
    cmd.args(["worker", "--nats", &nats.url, "--farm", "light", "--id", id, "--backend", "cpu"]).env("NEPHELE_NATS_TOKEN", &nats.token);
    for s in scenes {
        cmd.args(["--scene", s]);
    }
    let mut child = cmd.stdout(Stdio::piped()).stderr(Stdio::null()).spawn()?;
    let mut out = BufReader::new(child.stdout.take().expect("piped"));
    let mut line = String::new();
    out.read_line(&mut line)?;
    if !line.contains(" serves ") {
        bail!("worker {id} did not start: {line:?}");
    }
    std::thread::spawn(move || std::io::copy(&mut out, &mut std::io::sink()));
    Ok(Proc(child))
}

async fn stream(scenes: &[String], scene: &str, nats: Option<NatsSettings>, trace: &Trace, size: (u32, u32)) -> Result<ReplayReport> {
    let catalog = Arc::new(Catalog::load(scenes, &FastCpuBackend, RenderSettings::default())?);
    let cfg = MasterConfig {
        name: "bench".into(),
        token: None,
        rtc: RtcConfig::loopback(),
        core: CoreConfig { capacity: 4, render_scale: RenderScale::Fixed(1.0), admission: Admission::Open, ..Default::default() },
        workers: 1,
        compose: ComposeChoice::Cpu,
        bits_per_pixel: DEFAULT_BITS_PER_PIXEL,
        nats: nats.clone(),
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let server = web::spawn_local(listener, catalog, cfg).await?;
    // A NATS master finds its workers through discovery: give it a moment.
    if nats.is_some() {
        tokio::time::sleep(Duration::from_millis(1500)).await;
    }
    let opts = ReplayOptions {
        client: ClientOptions { signal_url: server.signal_url(), scene: scene.into(), mode: Mode::Viewer, width: size.0, height: size.1, fps: 25, token: None, receive: Receive::Decode, quilt: None, depth: false },
        anchor: None,
        quality_every: 0,
        save_dir: None,
        drain: Duration::from_secs(2),
        start_at: None, stereo_baseline: None,
    };
    replay(trace, &opts, None).await
}

fn summarise(scene: &str, farm: &str, r: &ReplayReport) -> FarmRun {
    let mb = r.transfer_bytes_mean / 1e6;
    let frame_ms = r.ready_ms.p50;
    FarmRun {
        scene: scene.into(),
        farm: farm.into(),
        frames: r.frames_decoded,
        fps: r.fps,
        latency_p50_ms: r.latency_ms.p50,
        latency_p99_ms: r.latency_ms.p99,
        frame_ms,
        render_max_ms: r.render_ms.p50,
        render_sum_ms: r.render_total_ms.p50,
        hop_ms: r.transfer_ms.p50,
        compose_ms: r.compose_ms.p50,
        result_mb_per_frame: mb,
        hop_ms_per_mb: if mb > 0.0 { r.transfer_ms.p50 / mb } else { 0.0 },
        hop_share: if frame_ms > 0.0 { r.transfer_ms.p50 / frame_ms } else { 0.0 },
    }
}

pub fn run(args: FarmArgs) -> Result<()> {
    let size = parse_size(&args.size)?;
    let mut trace = Trace::from_spec("orbit")?;
    trace.poses = trace.poses.iter().cycle().take(args.poses.max(10)).copied().collect();
    let single = vec![format!("object={}", args.asset)];
    let composed = vec![format!("composed={}", args.scene)];
    let both: Vec<String> = single.iter().chain(&composed).cloned().collect();
    let rt = tokio::runtime::Runtime::new()?;
    let nats = start_nats()?;
    let mut runs = Vec::new();

    eprintln!("one object, in-process worker ...");
    runs.push(summarise("object", "in-process", &rt.block_on(stream(&single, "object", None, &trace, size))?));
    {
        eprintln!("one object, 1 NATS worker ...");
        let _w1 = spawn_worker(&nats, "bench-1", &both)?;
        runs.push(summarise("object", "nats x1", &rt.block_on(stream(&single, "object", Some(nats.settings()), &trace, size))?));
        eprintln!("one object, 2 NATS workers ...");
        let _w2 = spawn_worker(&nats, "bench-2", &both)?;
        runs.push(summarise("object", "nats x2", &rt.block_on(stream(&single, "object", Some(nats.settings()), &trace, size))?));
        eprintln!("composed scene, 2 NATS workers ...");
        runs.push(summarise("composed", "nats x2", &rt.block_on(stream(&composed, "composed", Some(nats.settings()), &trace, size))?));
    }
    eprintln!("composed scene, in-process worker ...");
    runs.push(summarise("composed", "in-process", &rt.block_on(stream(&composed, "composed", None, &trace, size))?));

    // Failover: two workers, one killed every few seconds (and restarted before the next).
    eprintln!("failover: {} kills ...", args.kills);
    let mut failover = trace.clone();
    let period = Duration::from_secs(3);
    // Long enough for every kill (one every 4.5 s) and 3 s after the last.
    let total = ((args.kills as f64 * 4.5 + 3.0) * 50.0) as usize;
    failover.poses = trace.poses.iter().cycle().take(total).copied().collect();
    let mut workers = vec![Some(spawn_worker(&nats, "fo-a", &single)?), Some(spawn_worker(&nats, "fo-b", &single)?)];
    let (report, kill_times) = rt.block_on(async {
        let run = tokio::spawn({
            let (single, settings, failover) = (single.clone(), nats.settings(), failover.clone());
            async move { stream(&single, "object", Some(settings), &failover, size).await }
        });
        // The master discovers its workers for 1.5 s, then replay starts.
        tokio::time::sleep(Duration::from_millis(1500)).await;
        let started = Instant::now();
        let mut kills = Vec::new();
        for k in 0..args.kills {
            tokio::time::sleep(period).await;
            let victim = k % 2;
            workers[victim].take();
            kills.push(started.elapsed().as_secs_f64() * 1e3);
            tokio::time::sleep(Duration::from_millis(1500)).await;
            workers[victim] = Some(spawn_worker(&nats, &format!("fo-{k}"), &single)?);
        }
        Ok::<_, anyhow::Error>((run.await??, kills))
    })?;
    // Decode times are from the first pose, which the replay sent right after the master's
    // 1.5 s discovery wait, as the kill times are.
    let times = &report.decoded_at_ms;
    let gaps: Vec<f64> = kill_times.iter().map(|&t| times.iter().find(|&&d| d > t).map_or(f64::INFINITY, |d| d - t)).collect();
    let frame_gaps: Vec<f64> = kill_times
        .iter()
        .map(|&t| times.windows(2).filter(|w| w[1] >= t && w[0] <= t + 2000.0).map(|w| w[1] - w[0]).fold(0.0, f64::max))
        .collect();
    let sessions_lost = usize::from(report.frames_decoded == 0);
    let failover_gap_ms = gaps.iter().copied().fold(0.0, f64::max);
    let report = FarmReport { width: size.0, height: size.1, runs, failover_gaps_ms: gaps, failover_gap_ms, frame_gaps_ms: frame_gaps, sessions_lost };
    crate::emit(args.json, &format_report(&report), &report)?;
    Ok(())
}

pub fn format_report(r: &FarmReport) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let _ = writeln!(out, "{}x{}, render scale 1, one replay client at 25 fps; NATS and the workers share this machine's cores\n", r.width, r.height);
    let _ = writeln!(out, "| scene | farm | fps | pose→decoded p50 / p99 ms | frame ms | max T_i ms | Σ T_i ms | NATS hop ms | compose ms | MB / frame | hop ms / MB | hop share |");
    let _ = writeln!(out, "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for u in &r.runs {
        let _ = writeln!(
            out,
            "| {} | {} | {:.1} | {:.0} / {:.0} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.2} | {:.1} | {:.1}% |",
            u.scene,
            u.farm,
            u.fps,
            u.latency_p50_ms,
            u.latency_p99_ms,
            u.frame_ms,
            u.render_max_ms,
            u.render_sum_ms,
            u.hop_ms,
            u.compose_ms,
            u.result_mb_per_frame,
            u.hop_ms_per_mb,
            100.0 * u.hop_share
        );
    }
    let _ = writeln!(out, "\nNEPHELE Eq. 9, T_frame = max T_i + Σ D_i / BW + C, as measured (p50s; BW from the NATS runs' hop ms per MB):");
    let bw_ms_per_mb = r.runs.iter().filter(|u| u.farm.starts_with("nats") && u.scene == "object").map(|u| u.hop_ms_per_mb).fold(f64::NAN, f64::min);
    for u in r.runs.iter().filter(|u| u.scene == "composed") {
        let remote = u.farm.starts_with("nats");
        let transfer = if remote { u.result_mb_per_frame * bw_ms_per_mb } else { 0.0 };
        // One in-process worker renders the objects one after the other: Σ T_i, not max.
        let render = if remote { u.render_max_ms } else { u.render_sum_ms };
        let predicted = render + transfer + u.compose_ms;
        let _ = writeln!(
            out,
            "  {} ({}): {:.1} + {:.1} + {:.1} = {:.1} ms predicted, {:.1} ms measured; the composed frame costs {:.2}x the sum of its objects' renders ({:.1} ms)",
            u.farm,
            if remote { "objects on different workers: max T_i" } else { "one worker: Σ T_i" },
            render,
            transfer,
            u.compose_ms,
            predicted,
            u.frame_ms,
            u.frame_ms / u.render_sum_ms.max(1e-9),
            u.render_sum_ms
        );
    }
    let round = |v: &[f64]| v.iter().map(|g| g.round()).collect::<Vec<_>>();
    let _ = writeln!(
        out,
        "\nfailover: a worker killed {} times mid-stream; from each kill to the next decoded frame: {:?} ms (longest {:.0} ms); longest frame interval around each kill: {:?} ms; sessions lost: {}",
        r.failover_gaps_ms.len(),
        round(&r.failover_gaps_ms),
        r.failover_gap_ms,
        round(&r.frame_gaps_ms),
        r.sessions_lost
    );
    out
}
