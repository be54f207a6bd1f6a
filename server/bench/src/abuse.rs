//! `nephele bench abuse`: a well-behaved viewer against four attacks at once on one
//! `nephele serve` process (a child, so its memory is its own): thousands of idle
//! connections from many loopback addresses, a relay flood (join, then ICE candidates as fast
//! as the socket takes them), a 4K join → pose → leave loop, and an empty-pose-message loop.
//! Prints the viewer's frame rate before, during and after, the server's peak memory and
//! what the limits refused.

use std::{
    net::{IpAddr, Ipv4Addr, SocketAddr},
    sync::{
        Arc,
        atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering},
    },
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail};
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use nephele_protocol::Mode;
use tokio_tungstenite::tungstenite::Message;

use nephele_client::{ClientNet, ClientOptions, Receive, StreamClient, replay::Trace};
use nephele_wire::PoseMessage;

/// What to throw at the server.
#[derive(clap::Args, Debug, Clone)]
pub struct AbuseArgs {
    /// The scene the server serves and the viewer watches.
    #[arg(long, default_value = "trio=builtin:trio-small")]
    pub scene: String,
    /// Idle connections to attempt, spread over this many loopback source addresses…
    #[arg(long, default_value_t = 5000)]
    pub connections: usize,
    /// …(127.0.1.1, 127.0.1.2, …).
    #[arg(long, default_value_t = 100)]
    pub addresses: usize,
    /// Seconds of each phase (before, during, after the attack).
    #[arg(long, default_value_t = 10)]
    pub seconds: u64,
    /// The viewer's frame size and rate.
    #[arg(long, default_value = "320x240")]
    pub size: String,
    #[arg(long, default_value_t = 25)]
    pub fps: u32,
    /// Which attacks run (all four by default).
    #[arg(long, value_delimiter = ',', default_value = "idle,flood,rejoin,empty")]
    pub attacks: Vec<Attack>,
    /// Frame size of the join → pose → leave loop.
    #[arg(long, default_value = "3840x2160")]
    pub rejoin_size: String,
    /// The server's render scale and admission (its defaults: what a user runs).
    #[arg(long, default_value = "auto")]
    pub render_scale: String,
    #[arg(long, value_enum, default_value = "load")]
    pub admission: nephele_core::Admission,
    /// Niceness of the attacking process (a child of this one): on a real deployment the
    /// attackers are other machines; 0 lets them compete with the server for this one's CPU.
    #[arg(long, default_value_t = 19)]
    pub attacker_nice: i32,
    /// Internal: be the attacker against this signaling URL for `--seconds`, then print the
    /// counts as JSON.
    #[arg(long, hide = true)]
    pub attack_url: Option<String>,
    /// Print the report as JSON on stdout (the table goes to stderr).
    #[arg(long)]
    pub json: bool,
}

/// What the attacker did.
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
struct AttackCounts {
    held: usize,
    flood_sent: u64,
    flood_connections: u64,
    rejoins: u64,
    rejoins_refused: u64,
    /// Refused rejoins by the reason signaling or the master gave.
    rejoin_refusals: std::collections::BTreeMap<String, u64>,
    empties: u64,
}

/// The attacks of `bench abuse`.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Attack {
    /// Thousands of websockets that never speak.
    Idle,
    /// Join, then ICE candidates as fast as the socket takes them, on new connections.
    Flood,
    /// 4K join → pose → leave, again and again.
    Rejoin,
    /// Sessions that send an empty pose message.
    Empty,
}

/// What happened.
#[derive(Debug, Clone, serde::Serialize)]
pub struct AbuseReport {
    pub fps_before: f64,
    pub fps_during: f64,
    pub fps_after: f64,
    pub longest_gap_during_ms: f64,
    pub rss_before_mb: f64,
    pub rss_peak_mb: f64,
    pub rss_after_mb: f64,
    pub connections_attempted: usize,
    pub connections_held: usize,
    pub connections_refused_by_server: u64,
    /// Sockets without a role the server closed to make room for newer ones.
    pub connections_evicted_by_server: u64,
    /// Most connections the server had open at once (its `/status`, sampled every 100 ms).
    pub server_connections_peak: u64,
    pub flood_messages_sent: u64,
    pub flood_connections: u64,
    pub rejoin_cycles: u64,
    pub rejoins_refused: u64,
    pub rejoin_refusals: std::collections::BTreeMap<String, u64>,
    pub empty_message_cycles: u64,
    pub viewer_errors: Vec<String>,
}

impl AbuseReport {
    /// The viewer kept this fraction of its frame rate under attack.
    pub fn kept(&self) -> f64 {
        if self.fps_before > 0.0 { self.fps_during / self.fps_before } else { 0.0 }
    }
}

pub fn run(args: AbuseArgs) -> Result<()> {
    if let Some(url) = &args.attack_url {
        let counts = tokio::runtime::Runtime::new()?.block_on(attack(url, &args))?;
        println!("{}", serde_json::to_string(&counts)?);
        return Ok(());
    }
    let report = tokio::runtime::Runtime::new()?.block_on(abuse(&args, &std::env::current_exe()?))?;
    crate::emit(args.json, &format_report(&args, &report), &report)
}

pub fn format_report(args: &AbuseArgs, r: &AbuseReport) -> String {
    let mut s = String::new();
    s.push_str(&format!(
        "viewer {} at {} fps on {} (server: render scale {}, admission {}); each phase {} s; attacks {:?} from a child process at nice {}\n\n",
        args.size, args.fps, args.scene, args.render_scale, format!("{:?}", args.admission).to_lowercase(), args.seconds, args.attacks, args.attacker_nice
    ));
    s.push_str("| phase | viewer fps | server RSS MB |\n|---|---:|---:|\n");
    s.push_str(&format!("| before | {:.1} | {:.0} |\n", r.fps_before, r.rss_before_mb));
    s.push_str(&format!("| during the attacks | {:.1} ({:.0}% kept; longest gap {:.0} ms) | {:.0} peak |\n", r.fps_during, 100.0 * r.kept(), r.longest_gap_during_ms, r.rss_peak_mb));
    s.push_str(&format!("| after | {:.1} | {:.0} |\n\n", r.fps_after, r.rss_after_mb));
    s.push_str(&format!(
        "idle connections: {} attempted from {} addresses ({} open at once as the attacker saw it); the server had {} connections open at most, closed {} idle ones to make room for newer ones and {} at accept\n",
        r.connections_attempted, args.addresses, r.connections_held, r.server_connections_peak, r.connections_evicted_by_server, r.connections_refused_by_server
    ));
    s.push_str(&format!("relay flood: {} ice messages on {} connections (each rate-limited and dropped)\n", r.flood_messages_sent, r.flood_connections));
    s.push_str(&format!(
        "{} join → pose → leave cycles: {} (and {} joins refused{}); empty-pose-message sessions: {}\n",
        args.rejoin_size,
        r.rejoin_cycles,
        r.rejoins_refused,
        if r.rejoin_refusals.is_empty() { String::new() } else { format!(": {:?}", r.rejoin_refusals) },
        r.empty_message_cycles
    ));
    s.push_str("sources: idle sockets 127.0.1.x…, relay flood 127.0.2.1, join/leave loop 127.0.3.1, empty messages 127.0.4.1, viewer 127.0.0.1\n");
    if !r.viewer_errors.is_empty() {
        s.push_str(&format!("viewer heard: {:?}\n", r.viewer_errors));
    }
    s
}

/// A `nephele serve` child killed on drop.
struct Server {
    child: std::process::Child,
    addr: SocketAddr,
}

impl Drop for Server {
    fn drop(&mut self) {
        self.child.kill().ok();
        self.child.wait().ok();
    }
}

impl Server {
    fn start(exe: &std::path::Path, scene: &str, render_scale: &str, admission: nephele_core::Admission) -> Result<Self> {
        use std::io::{BufRead, BufReader};
        let mut child = std::process::Command::new(exe)
            .args(["serve", "--listen", "127.0.0.1:0", "--scene", scene, "--backend", "cpu", "--admission", if admission == nephele_core::Admission::Load { "load" } else { "open" }, "--render-scale", render_scale])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::null())
            .spawn()
            .context("starting nephele serve")?;
        let mut out = BufReader::new(child.stdout.take().expect("piped"));
        let mut line = String::new();
        out.read_line(&mut line)?;
        let addr = line.split("http://").nth(1).and_then(|s| s.split('/').next()).and_then(|a| a.parse().ok());
        std::thread::spawn(move || std::io::copy(&mut out, &mut std::io::sink()));
        match addr {
            Some(addr) => Ok(Self { child, addr }),
            None => bail!("nephele serve printed {line:?}"),
        }
    }

    /// Resident memory, MB.
    fn rss_mb(&self) -> f64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).unwrap_or_default();
        status.lines().find_map(|l| l.strip_prefix("VmRSS:")).and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok()).map_or(0.0, |kb| kb / 1024.0)
    }

    fn url(&self) -> String {
        format!("ws://{}/signal", self.addr)
    }
}

fn pose(seq: u32, width: u32, height: u32) -> PoseMessage {
    Trace::builtin("orbit").expect("a built-in trace").pose_message(seq, width, height)
}

fn opts(url: &str, width: u32, height: u32, fps: u32) -> ClientOptions {
    ClientOptions { signal_url: url.into(), scene: "trio".into(), mode: Mode::Viewer, width, height, fps, token: None, receive: Receive::Decode, quilt: None, depth: false }
}

/// Runs the three phases against a fresh server started from `exe`.
pub async fn abuse(args: &AbuseArgs, exe: &std::path::Path) -> Result<AbuseReport> {
    let (width, height) = nephele_farm::assets::parse_size(&args.size)?;
    let scene = args.scene.split_once('=').map_or(args.scene.clone(), |(_, a)| format!("trio={a}"));
    let server = Server::start(exe, &scene, &args.render_scale, args.admission)?;
    let url = server.url();

    // The viewer: a pose every 20 ms, decoded frames timed.
    let mut viewer = StreamClient::connect(&opts(&url, width, height, args.fps)).await.context("the viewer connects")?;
    let arrivals = Arc::new(std::sync::Mutex::new(Vec::<Instant>::new()));
    let mut frames = std::mem::replace(&mut viewer.frames, tokio::sync::mpsc::unbounded_channel().1);
    let seen = Arc::clone(&arrivals);
    tokio::spawn(async move {
        while let Some(f) = frames.recv().await {
            seen.lock().expect("arrivals").push(f.decoded_at);
        }
    });
    let mut said = std::mem::replace(&mut viewer.signaling, tokio::sync::mpsc::unbounded_channel().1);
    let mut messages = std::mem::replace(&mut viewer.messages, tokio::sync::mpsc::unbounded_channel().1);
    let errors = Arc::new(std::sync::Mutex::new(Vec::new()));
    let (e1, e2) = (Arc::clone(&errors), Arc::clone(&errors));
    tokio::spawn(async move {
        while let Some(m) = said.recv().await {
            e1.lock().expect("errors").push(format!("signaling: {m:?}"));
        }
    });
    tokio::spawn(async move {
        while let Some(m) = messages.recv().await {
            if let nephele_wire::ToViewer::Error { code, message } = m {
                e2.lock().expect("errors").push(format!("{code}: {message}"));
            }
        }
    });
    let viewer = Arc::new(viewer);
    let posing = {
        let viewer = Arc::clone(&viewer);
        tokio::spawn(async move {
            for seq in 1.. {
                if viewer.send_pose(&pose(seq, width, height)).await.is_err() {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        })
    };
    let phase = Duration::from_secs(args.seconds.max(1));
    let fps_over = |from: Instant, to: Instant| {
        let a = arrivals.lock().expect("arrivals");
        a.iter().filter(|t| **t >= from && **t < to).count() as f64 / to.duration_since(from).as_secs_f64()
    };
    tokio::time::sleep(Duration::from_secs(2)).await; // warm up
    let t0 = Instant::now();
    tokio::time::sleep(phase).await;
    let t1 = Instant::now();
    let rss_before_mb = server.rss_mb();

    // The attacks, from a child process at low priority, for one phase.
    let mut attacker = std::process::Command::new("nice")
        .arg("-n")
        .arg(args.attacker_nice.to_string())
        .arg(exe)
        .args(["bench", "abuse", "--attack-url", &url, "--seconds", &args.seconds.to_string()])
        .args(["--connections", &args.connections.to_string(), "--addresses", &args.addresses.to_string(), "--rejoin-size", &args.rejoin_size])
        .arg("--attacks")
        .arg(args.attacks.iter().map(|a| format!("{a:?}").to_lowercase()).collect::<Vec<_>>().join(","))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .context("starting the attacker (nice)")?;
    let mut rss_peak_mb = rss_before_mb;
    let mut connections_peak = 0;
    let give_up = Instant::now() + phase + Duration::from_secs(30);
    while attacker.try_wait()?.is_none() {
        rss_peak_mb = rss_peak_mb.max(server.rss_mb());
        if let Some(open) = http_get(server.addr, "/status").await.and_then(|s| serde_json::from_str::<serde_json::Value>(&s).ok()).and_then(|v| v["connections"].as_u64()) {
            connections_peak = connections_peak.max(open);
        }
        if Instant::now() > give_up {
            attacker.kill().ok();
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let t2 = (t1 + phase).min(Instant::now());
    let mut out = String::new();
    std::io::Read::read_to_string(&mut attacker.stdout.take().expect("piped"), &mut out)?;
    let counts: AttackCounts = serde_json::from_str(out.lines().last().unwrap_or_default()).with_context(|| format!("the attacker said {out:?}"))?;
    let status = http_get(server.addr, "/status").await.unwrap_or_default();
    let status: serde_json::Value = serde_json::from_str(&status).unwrap_or_default();
    let (refused, evicted) = (status["connections_refused"].as_u64().unwrap_or(0), status["connections_evicted"].as_u64().unwrap_or(0));
    // Give the server a moment to let go, then the calm phase.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let t3 = Instant::now();
    tokio::time::sleep(phase).await;
    let t4 = Instant::now();
    let rss_after_mb = server.rss_mb();
    posing.abort();
    let longest_gap_during_ms = {
        let a = arrivals.lock().expect("arrivals");
        let during: Vec<Instant> = a.iter().copied().filter(|t| *t >= t1 && *t < t2).collect();
        let mut edges = vec![t1];
        edges.extend(during);
        edges.push(t2);
        edges.windows(2).map(|w| w[1].duration_since(w[0]).as_secs_f64() * 1e3).fold(0.0, f64::max)
    };
    let viewer_errors = errors.lock().expect("errors").clone();
    Ok(AbuseReport {
        fps_before: fps_over(t0, t1),
        fps_during: fps_over(t1, t2),
        fps_after: fps_over(t3, t4),
        longest_gap_during_ms,
        rss_before_mb,
        rss_peak_mb,
        rss_after_mb,
        connections_attempted: args.connections,
        connections_held: counts.held,
        connections_refused_by_server: refused,
        connections_evicted_by_server: evicted,
        server_connections_peak: connections_peak,
        flood_messages_sent: counts.flood_sent,
        flood_connections: counts.flood_connections,
        rejoin_cycles: counts.rejoins,
        rejoins_refused: counts.rejoins_refused,
        rejoin_refusals: counts.rejoin_refusals,
        empty_message_cycles: counts.empties,
        viewer_errors,
    })
}

/// The attacker's side: every chosen attack against `url` for `args.seconds`.
async fn attack(url: &str, args: &AbuseArgs) -> Result<AttackCounts> {
    let server: SocketAddr = url.trim_start_matches("ws://").split('/').next().unwrap_or_default().parse().context("the attack URL's address")?;
    let on = |a: Attack| args.attacks.contains(&a);
    let stop = Arc::new(AtomicBool::new(false));
    let held = Arc::new(AtomicUsize::new(0));
    let mut tasks = Vec::new();
    let sockets_task = {
        let n = if on(Attack::Idle) { args.connections } else { 0 };
        let (stop, held, addresses) = (Arc::clone(&stop), Arc::clone(&held), args.addresses.max(1));
        tokio::spawn(async move { idle_connections(server, n, addresses, &stop, &held).await })
    };
    let (flood_sent, flood_conns, rejoins, empties) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let rejoins_refused = Arc::new(AtomicU64::new(0));
    let refusals = Arc::new(std::sync::Mutex::new(std::collections::BTreeMap::new()));
    if on(Attack::Flood) {
        let (stop, url, sent, conns) = (Arc::clone(&stop), url.to_owned(), Arc::clone(&flood_sent), Arc::clone(&flood_conns));
        tasks.push(tokio::spawn(async move {
            while !stop.load(Ordering::Relaxed) {
                conns.fetch_add(1, Ordering::Relaxed);
                relay_flood(&url, &sent).await;
            }
        }));
    }
    if on(Attack::Rejoin) {
        let (rw, rh) = nephele_farm::assets::parse_size(&args.rejoin_size)?;
        let (stop, url, count, refused, why) = (Arc::clone(&stop), url.to_owned(), Arc::clone(&rejoins), Arc::clone(&rejoins_refused), Arc::clone(&refusals));
        tasks.push(tokio::spawn(async move {
            while !stop.load(Ordering::Relaxed) {
                let c = match StreamClient::connect_with(&opts(&url, rw, rh, 25), &from(REJOIN_SOURCE)).await {
                    Ok(c) => c,
                    Err(e) => {
                        refused.fetch_add(1, Ordering::Relaxed);
                        *why.lock().expect("refusals").entry(refusal_reason(&format!("{e:#}"))).or_insert(0) += 1;
                        tokio::time::sleep(Duration::from_millis(100)).await;
                        continue;
                    }
                };
                {
                    let _ = c.send_pose(&pose(1, rw, rh)).await;
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    c.close().await;
                    count.fetch_add(1, Ordering::Relaxed);
                }
            }
        }));
    }
    if on(Attack::Empty) {
        let (stop, url, count) = (Arc::clone(&stop), url.to_owned(), Arc::clone(&empties));
        tasks.push(tokio::spawn(async move {
            while !stop.load(Ordering::Relaxed) {
                if let Ok(c) = StreamClient::connect_with(&opts(&url, 160, 120, 25), &from(EMPTY_SOURCE)).await {
                    let _ = c.send_bytes(Bytes::new()).await;
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    c.close().await;
                    count.fetch_add(1, Ordering::Relaxed);
                } else {
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            }
        }));
    }
    tokio::time::sleep(Duration::from_secs(args.seconds.max(1))).await;
    stop.store(true, Ordering::Relaxed);
    let _ = tokio::time::timeout(Duration::from_secs(5), sockets_task).await;
    for t in tasks {
        let _ = tokio::time::timeout(Duration::from_secs(10), t).await;
    }
    Ok(AttackCounts {
        held: held.load(Ordering::Relaxed),
        flood_sent: flood_sent.load(Ordering::Relaxed),
        flood_connections: flood_conns.load(Ordering::Relaxed),
        rejoins: rejoins.load(Ordering::Relaxed),
        rejoins_refused: rejoins_refused.load(Ordering::Relaxed),
        rejoin_refusals: refusals.lock().expect("refusals").clone(),
        empties: empties.load(Ordering::Relaxed),
    })
}

/// Opens `n` TCP connections from `addresses` loopback source addresses, upgrades each to a
/// websocket that never speaks, and holds them until `stop`. `held`: most open at once.
async fn idle_connections(server: SocketAddr, n: usize, addresses: usize, stop: &AtomicBool, held: &AtomicUsize) {
    let mut open = Vec::new();
    for i in 0..n {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        let k = (i % addresses) as u32 + 1;
        let source = IpAddr::V4(Ipv4Addr::new(127, 0, 1 + (k / 250) as u8, (k % 250) as u8 + 1));
        let Ok(socket) = tokio::net::TcpSocket::new_v4() else { continue };
        if socket.bind(SocketAddr::new(source, 0)).is_err() {
            continue;
        }
        let Ok(Ok(stream)) = tokio::time::timeout(Duration::from_secs(2), socket.connect(server)).await else { continue };
        let url = format!("ws://{server}/signal");
        // The server closes sockets past its caps at once: the handshake fails.
        if let Ok(Ok((ws, _))) = tokio::time::timeout(Duration::from_secs(2), tokio_tungstenite::client_async(url, stream)).await {
            open.push(ws);
            open.retain(|w| w.get_ref().peer_addr().is_ok());
            held.fetch_max(open.len(), Ordering::Relaxed);
        }
    }
    while !stop.load(Ordering::Relaxed) {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Each attack comes from its own loopback address, as separate attackers would (the idle
/// sockets from 127.0.1.x), so one attack's per-address caps do not throttle another's.
const FLOOD_SOURCE: IpAddr = IpAddr::V4(Ipv4Addr::new(127, 0, 2, 1));
const REJOIN_SOURCE: IpAddr = IpAddr::V4(Ipv4Addr::new(127, 0, 3, 1));
const EMPTY_SOURCE: IpAddr = IpAddr::V4(Ipv4Addr::new(127, 0, 4, 1));

/// A client's network with its signaling websocket from `source`.
fn from(source: IpAddr) -> ClientNet {
    ClientNet { source_ip: Some(source), ..ClientNet::default() }
}

/// The error code in a refused join's error text (`NoCapacity`, `Rejected`, …).
fn refusal_reason(error: &str) -> String {
    match error.split_once("refused the join (") {
        Some((_, rest)) => rest.split(')').next().unwrap_or("?").to_string(),
        None if error.contains("refused") || error.contains("rejected") => "master refused".into(),
        None => error.split(':').next().unwrap_or("?").trim().to_string(),
    }
}

/// One connection that joins and then sends ICE candidates as fast as it can.
async fn relay_flood(url: &str, sent: &AtomicU64) {
    let ws = async { tokio_tungstenite::client_async(url, nephele_client::connect_from(FLOOD_SOURCE, url).await.ok()?).await.ok() };
    let Some((mut ws, _)) = ws.await else {
        tokio::time::sleep(Duration::from_millis(200)).await;
        return;
    };
    let join = serde_json::json!({"type":"join","scene":"trio","mode":"viewer","width":160,"height":120,"fps":25});
    if ws.send(Message::text(join.to_string())).await.is_err() {
        return;
    }
    let ice = serde_json::json!({"type":"ice","candidate":{"candidate":"candidate:1 1 udp 1 127.0.0.1 9 typ host","sdpMid":"0","sdpMLineIndex":0}}).to_string();
    for _ in 0..1000 {
        if ws.send(Message::text(ice.clone())).await.is_err() {
            break;
        }
        sent.fetch_add(1, Ordering::Relaxed);
    }
    // Read until the server drops us.
    let _ = tokio::time::timeout(Duration::from_secs(2), async { while let Some(Ok(_)) = ws.next().await {} }).await;
}

async fn http_get(addr: SocketAddr, path: &str) -> Option<String> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.ok()?;
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").as_bytes()).await.ok()?;
    let mut out = String::new();
    s.read_to_string(&mut out).await.ok()?;
    out.split_once("\r\n\r\n").map(|(_, b)| b.to_owned())
}
