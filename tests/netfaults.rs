//! A stream survives network faults between a replay client and the server.
//!
//! The server (`nephele serve`, CPU backend, the fixture scene) runs in a network namespace
//! of this test's own, behind a second namespace that routes between it and the client; the
//! client (`nephele_client`, real WebRTC, real OpenH264, poses sent with
//! `send_pose_paced`) stays in the test process, in the root namespace. Faults, one after
//! another on one session, each followed by 3 s of a healed path:
//!
//! - 1 %, 3 % and 5 % random loss of UDP both ways (`iptables -m statistic` in the router's
//!   FORWARD chain);
//! - 50 ms of jitter both ways: every datagram of the client's socket is held an independent
//!   0–50 ms (so packets also arrive out of order), by a socket wrapper of this test given to
//!   the `webrtc` crate as its one UDP socket (this kernel has no `netem`);
//! - a 2 s blackout (all UDP dropped both ways).
//!
//! Checked: the session is never lost (no `ended`/error from signaling or the master, frames
//! at the end), no picture stays frozen longer than 1 s once the path has healed, and frames
//! flow again after every fault. The table printed says which recovery each case used: NACK
//! (holes filled by retransmission; in the jitter case also by reordering), PLI → IDR (a
//! picture given up, P frames dropped until the IDR the PLI asked for), pose probe (the pose
//! channel's SCTP backlog cleared by a paced pose after an outage).
//!
//! Needs root (network namespaces, iptables) and the `ip` and `iptables` commands (Debian
//! packages `iproute2` and `iptables`); it fails, and says so, without them.

use std::{
    net::{IpAddr, Ipv4Addr, SocketAddr},
    process::{Command, Stdio},
    sync::{
        Arc, Mutex,
        atomic::{AtomicBool, AtomicU64, Ordering},
    },
    time::{Duration, Instant},
};

use nephele_client::{ClientNet, ClientOptions, POSE_BACKLOG_FREE, Receive, ReceiveCounts, StreamClient, replay::Trace};
use nephele_wire::ToViewer;
use nephele_e2e::{run_ok as run, Reap, ShowLogOnFailure, fixture_scene, nephele_bin, spawn_serve};
use nephele_signaling::Mode;
use tokio::{net::UdpSocket, sync::mpsc};
use webrtc::{
    api::setting_engine::SettingEngine,
    ice::{
        udp_mux::{UDPMuxDefault, UDPMuxParams},
        udp_network::UDPNetwork,
    },
    util::Conn,
};

const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;
const FPS: u32 = 25;
/// Observed after every fault.
const HEAL_WINDOW: Duration = Duration::from_secs(3);
/// The longest a picture may stay frozen after the path heals.
const MAX_FREEZE: Duration = Duration::from_millis(1000);

// ---------------------------------------------------------------------------------------
// The namespace

/// Fails (never skips) without what the test needs.
fn preflight() {
    nephele_e2e::require_root_and("the network-fault test", &[("ip", "-V", "iproute2"), ("iptables", "-V", "iptables")]);
}

/// Two network namespaces of this test's own: the server's, and a router between it and
/// the client (the root namespace), joined by two veth pairs:
///
/// ```text
/// client (root ns) 10.213.h.l+1 ─veth─ l+2 [router ns] l+5 ─veth─ l+6 [server ns]
/// ```
///
/// Faults are `iptables` rules in the router's FORWARD chain, so packets vanish in the
/// network as on a real path (a DROP in a sender's own OUTPUT chain would fail its
/// `sendmsg` with EPERM instead). Both namespaces, and with them the veth pairs and the
/// root namespace's route, are deleted when this is dropped.
struct Netns {
    server: String,
    router: String,
    root_veth: String,
    client_ip: Ipv4Addr,
    server_ip: Ipv4Addr,
}

impl Netns {
    fn create() -> Self {
        let pid = std::process::id();
        let (server, router) = (format!("nph{pid}s"), format!("nph{pid}r"));
        let [root_veth, router_a, router_b, server_veth] = ["a", "b", "c", "d"].map(|x| format!("nph{pid}{x}"));
        // A /29 of 10.213.0.0/16 picked by the pid, so that runs side by side do not clash.
        let (hi, lo) = (((pid >> 5) & 0xff) as u8, ((pid & 0x1f) << 3) as u8);
        let ip = |n: u8| Ipv4Addr::new(10, 213, hi, lo + n);
        let (client_ip, router_ip_a, router_ip_b, server_ip) = (ip(1), ip(2), ip(5), ip(6));
        // Leftovers of an earlier run with the same pid would make `add` fail.
        for n in [&server, &router] {
            let _ = Command::new("ip").args(["netns", "del", n]).stderr(Stdio::null()).status();
        }
        let _ = Command::new("ip").args(["link", "del", &root_veth]).stderr(Stdio::null()).status();
        run("ip", &["netns", "add", &server]);
        let ns = Self { server, router, root_veth, client_ip, server_ip };
        run("ip", &["netns", "add", &ns.router]);
        run("ip", &["link", "add", &ns.root_veth, "type", "veth", "peer", "name", &router_a, "netns", &ns.router]);
        run("ip", &["netns", "exec", &ns.router, "ip", "link", "add", &router_b, "type", "veth", "peer", "name", &server_veth, "netns", &ns.server]);
        run("ip", &["addr", "add", &format!("{client_ip}/30"), "dev", &ns.root_veth]);
        run("ip", &["link", "set", &ns.root_veth, "up"]);
        run("ip", &["route", "add", &format!("{server_ip}/32"), "via", &router_ip_a.to_string(), "dev", &ns.root_veth]);
        ns.exec(&ns.router, "ip", &["addr", "add", &format!("{router_ip_a}/30"), "dev", &router_a]);
        ns.exec(&ns.router, "ip", &["addr", "add", &format!("{router_ip_b}/30"), "dev", &router_b]);
        for dev in [router_a.as_str(), router_b.as_str(), "lo"] {
            ns.exec(&ns.router, "ip", &["link", "set", dev, "up"]);
        }
        ns.exec(&ns.router, "sysctl", &["-qw", "net.ipv4.ip_forward=1"]);
        ns.exec(&ns.server, "ip", &["addr", "add", &format!("{server_ip}/30"), "dev", &server_veth]);
        for dev in [server_veth.as_str(), "lo"] {
            ns.exec(&ns.server, "ip", &["link", "set", dev, "up"]);
        }
        ns.exec(&ns.server, "ip", &["route", "add", "default", "via", &router_ip_b.to_string()]);
        ns
    }

    /// Runs a command inside namespace `ns`; panics if it fails.
    fn exec(&self, ns: &str, program: &str, args: &[&str]) {
        let mut all = vec!["netns", "exec", ns, program];
        all.extend_from_slice(args);
        run("ip", &all);
    }

    /// Adds (`-A`) or deletes (`-D`) a rule dropping forwarded UDP (both ways) that matches `matches`.
    fn udp_rule(&self, op: &str, matches: &[&str]) {
        let mut args = vec!["-w", op, "FORWARD", "-p", "udp"];
        args.extend_from_slice(matches);
        args.extend_from_slice(&["-j", "DROP"]);
        self.exec(&self.router, "iptables", &args);
    }
}

impl Drop for Netns {
    fn drop(&mut self) {
        for n in [&self.server, &self.router] {
            let _ = Command::new("ip").args(["netns", "del", n]).status();
        }
        let _ = Command::new("ip").args(["link", "del", &self.root_veth]).stderr(Stdio::null()).status();
    }
}

/// `nephele serve` in the server's namespace on its veth address, logging into `log`;
/// returns it with its `host:port`.
fn spawn_server(ns: &Netns, log: &std::path::Path) -> (Reap, String) {
    let listen = format!("{}:0", ns.server_ip);
    let scene = fixture_scene();
    let mut cmd = Command::new("ip");
    cmd.args(["netns", "exec", &ns.server]).arg(nephele_bin());
    cmd.args(["serve", "--listen", &listen, "--scene", &scene, "--backend", "cpu", "--render-scale", "1", "--admission", "open", "--capacity", "2"]);
    spawn_serve(cmd, log)
}


// ---------------------------------------------------------------------------------------
// Jitter: the client's one UDP socket, every datagram held a random 0..=max

/// A UDP socket that holds every datagram, either way, an independent uniform random time
/// in 0..=`max_delay_us` (0: passes them straight on).
struct JitterConn {
    socket: Arc<UdpSocket>,
    inbox: tokio::sync::Mutex<mpsc::UnboundedReceiver<(Vec<u8>, SocketAddr)>>,
    max_delay_us: Arc<AtomicU64>,
    rng: Arc<Mutex<u64>>,
}

/// xorshift64*: random delays, nothing more.
fn next_random(state: &Mutex<u64>) -> u64 {
    let mut s = state.lock().unwrap();
    *s ^= *s >> 12;
    *s ^= *s << 25;
    *s ^= *s >> 27;
    s.wrapping_mul(0x2545_f491_4f6c_dd1d)
}

fn random_delay(max_delay_us: &AtomicU64, rng: &Mutex<u64>) -> Duration {
    let max = max_delay_us.load(Ordering::Relaxed);
    if max == 0 { Duration::ZERO } else { Duration::from_micros(next_random(rng) % (max + 1)) }
}

impl JitterConn {
    fn new(socket: UdpSocket, max_delay_us: Arc<AtomicU64>) -> Self {
        let socket = Arc::new(socket);
        let rng = Arc::new(Mutex::new(0x9e37_79b9_7f4a_7c15 ^ u64::from(std::process::id())));
        let (tx, inbox) = mpsc::unbounded_channel();
        let (reader, delays, rng2) = (Arc::clone(&socket), Arc::clone(&max_delay_us), Arc::clone(&rng));
        tokio::spawn(async move {
            let mut buf = vec![0u8; 2048];
            while let Ok((n, from)) = reader.recv_from(&mut buf).await {
                let datagram = (buf[..n].to_vec(), from);
                let delay = random_delay(&delays, &rng2);
                if delay.is_zero() {
                    if tx.send(datagram).is_err() {
                        return;
                    }
                } else {
                    let tx = tx.clone();
                    tokio::spawn(async move {
                        tokio::time::sleep(delay).await;
                        let _ = tx.send(datagram);
                    });
                }
            }
        });
        Self { socket, inbox: tokio::sync::Mutex::new(inbox), max_delay_us, rng }
    }
}

type UtilResult<T> = Result<T, webrtc::util::Error>;

#[async_trait::async_trait]
impl Conn for JitterConn {
    async fn connect(&self, addr: SocketAddr) -> UtilResult<()> {
        Ok(self.socket.connect(addr).await?)
    }

    async fn recv(&self, buf: &mut [u8]) -> UtilResult<usize> {
        Ok(self.recv_from(buf).await?.0)
    }

    async fn recv_from(&self, buf: &mut [u8]) -> UtilResult<(usize, SocketAddr)> {
        let (datagram, from) = self.inbox.lock().await.recv().await.ok_or(webrtc::util::Error::ErrUseClosedNetworkConn)?;
        let n = datagram.len().min(buf.len());
        buf[..n].copy_from_slice(&datagram[..n]);
        Ok((n, from))
    }

    async fn send(&self, buf: &[u8]) -> UtilResult<usize> {
        Ok(self.socket.send(buf).await?)
    }

    async fn send_to(&self, buf: &[u8], target: SocketAddr) -> UtilResult<usize> {
        let delay = random_delay(&self.max_delay_us, &self.rng);
        if delay.is_zero() {
            return Ok(self.socket.send_to(buf, target).await?);
        }
        let (socket, datagram) = (Arc::clone(&self.socket), buf.to_vec());
        tokio::spawn(async move {
            tokio::time::sleep(delay).await;
            let _ = socket.send_to(&datagram, target).await;
        });
        Ok(buf.len())
    }

    fn local_addr(&self) -> UtilResult<SocketAddr> {
        Ok(self.socket.local_addr()?)
    }

    fn remote_addr(&self) -> Option<SocketAddr> {
        None
    }

    async fn close(&self) -> UtilResult<()> {
        Ok(())
    }

    fn as_any(&self) -> &(dyn std::any::Any + Send + Sync) {
        self
    }
}

// ---------------------------------------------------------------------------------------
// The session

/// Decoded frames (when, and whether IDR), signaling and viewer trouble, as they come.
#[derive(Default)]
struct Log {
    frames: Mutex<Vec<(Instant, bool)>>,
    trouble: Mutex<Vec<String>>,
}

impl Log {
    fn frame_times(&self, from: Instant, to: Instant) -> Vec<Instant> {
        self.frames.lock().unwrap().iter().map(|f| f.0).filter(|t| *t >= from && *t < to).collect()
    }
}

/// The longest time in `from..to` without a new frame (from `from` to the first frame, between
/// frames, from the last frame to `to`).
fn longest_freeze(frames: &[Instant], from: Instant, to: Instant) -> Duration {
    let mut last = from;
    let mut worst = Duration::ZERO;
    for &t in frames {
        worst = worst.max(t - last);
        last = t;
    }
    worst.max(to.saturating_duration_since(last))
}

/// Sends poses of a slow orbit every 20 ms until `stop`.
fn keep_posing(client: Arc<StreamClient>, stop: Arc<AtomicBool>, log: Arc<Log>) -> tokio::task::JoinHandle<()> {
    let trace = Trace::builtin("orbit").unwrap();
    tokio::spawn(async move {
        let mut seq = 0u32;
        let mut tick = tokio::time::interval(Duration::from_millis(20));
        while !stop.load(Ordering::Relaxed) {
            tick.tick().await;
            seq += 1;
            let m = trace.pose_message(seq, WIDTH, HEIGHT);
            if let Err(e) = client.send_pose_paced(&m).await {
                log.trouble.lock().unwrap().push(format!("sending a pose failed: {e:#}"));
                return;
            }
        }
    })
}

#[derive(Debug, Clone, Copy)]
enum Fault {
    None,
    Loss(f64),
    Jitter(Duration),
    Blackout,
}

struct Case {
    name: &'static str,
    fault: Fault,
    lasts: Duration,
}

struct Row {
    name: &'static str,
    frames: usize,
    fps: f64,
    freeze_during_ms: f64,
    frames_after: usize,
    freeze_after_ms: f64,
    backlog_at_heal: usize,
    held_back: u64,
    c: ReceiveCounts,
    recovery: String,
}

fn recovery_of(fault: Fault, c: &ReceiveCounts, backlog_at_heal: usize) -> String {
    let mut used = Vec::new();
    if c.late > 0 {
        used.push(if matches!(fault, Fault::Jitter(_)) { "reordering/NACK" } else { "NACK" });
    }
    if c.gave_up > 0 || c.plis_sent > 0 || c.decode_errors > 0 {
        used.push("PLI→IDR");
    }
    if backlog_at_heal > POSE_BACKLOG_FREE {
        used.push("pose probe");
    }
    if used.is_empty() { "none needed".into() } else { used.join(" + ") }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_stream_survives_loss_jitter_and_a_blackout() {
    preflight();
    let ns = Netns::create();
    let dir = nephele_e2e::TempDir::new("netfaults");
    let server_log = dir.0.join("server.log");
    let (_server, addr) = spawn_server(&ns, &server_log);
    let _show_log = ShowLogOnFailure(server_log);
    println!("server in namespace {} at {addr}, behind router namespace {}; client at {}", ns.server, ns.router, ns.client_ip);

    // The client's one UDP socket, on its end of the veth pair, with the jitter knob.
    let socket = UdpSocket::bind((ns.client_ip, 0)).await.expect("a UDP socket on the veth address");
    let jitter_us = Arc::new(AtomicU64::new(0));
    let mux = UDPMuxDefault::new(UDPMuxParams::new(JitterConn::new(socket, Arc::clone(&jitter_us))));
    let root_ip = IpAddr::V4(ns.client_ip);
    let net = ClientNet {
        any_interface: true,
        settings: Some(Arc::new(move |s: &mut SettingEngine| {
            s.set_udp_network(UDPNetwork::Muxed(mux.clone()));
            s.set_ip_filter(Box::new(move |ip| ip == root_ip));
        })),
        ..ClientNet::default()
    };
    let opts = ClientOptions { signal_url: format!("ws://{addr}/signal"), scene: "trio".into(), mode: Mode::Viewer, width: WIDTH, height: HEIGHT, fps: FPS, token: None, receive: Receive::Decode, quilt: None, depth: false };
    let mut client = StreamClient::connect_with(&opts, &net).await.expect("the client connects to the server in the namespace");

    // Frames, signaling and viewer messages are logged in the background.
    let log = Arc::new(Log::default());
    let (mut frames, mut signaling, mut messages) = (
        std::mem::replace(&mut client.frames, mpsc::unbounded_channel().1),
        std::mem::replace(&mut client.signaling, mpsc::unbounded_channel().1),
        std::mem::replace(&mut client.messages, mpsc::unbounded_channel().1),
    );
    let l = Arc::clone(&log);
    tokio::spawn(async move {
        while let Some(f) = frames.recv().await {
            l.frames.lock().unwrap().push((f.decoded_at, f.idr));
        }
    });
    let l = Arc::clone(&log);
    tokio::spawn(async move {
        while let Some(m) = signaling.recv().await {
            l.trouble.lock().unwrap().push(format!("signaling: {m:?}"));
        }
    });
    let l = Arc::clone(&log);
    tokio::spawn(async move {
        while let Some(m) = messages.recv().await {
            if let ToViewer::Error { .. } = m {
                l.trouble.lock().unwrap().push(format!("viewer message: {m:?}"));
            }
        }
    });
    let client = Arc::new(client);
    let stop = Arc::new(AtomicBool::new(false));
    let posing = keep_posing(Arc::clone(&client), Arc::clone(&stop), Arc::clone(&log));

    // Streaming first.
    let deadline = Instant::now() + Duration::from_secs(30);
    while log.frames.lock().unwrap().len() < 10 {
        assert!(Instant::now() < deadline, "fewer than 10 frames within 30 s of joining: {:?}", client.receive_stats());
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    let cases = [
        Case { name: "no fault", fault: Fault::None, lasts: Duration::from_secs(2) },
        Case { name: "loss 1 %", fault: Fault::Loss(0.01), lasts: Duration::from_secs(5) },
        Case { name: "loss 3 %", fault: Fault::Loss(0.03), lasts: Duration::from_secs(5) },
        Case { name: "loss 5 %", fault: Fault::Loss(0.05), lasts: Duration::from_secs(5) },
        Case { name: "jitter 50 ms", fault: Fault::Jitter(Duration::from_millis(50)), lasts: Duration::from_secs(5) },
        Case { name: "blackout 2 s", fault: Fault::Blackout, lasts: Duration::from_secs(2) },
    ];
    let mut rows = Vec::new();
    let mut last_end = Instant::now();
    for case in &cases {
        let before = client.receive_stats();
        let held_before = client.poses_held_back();
        let start = Instant::now();
        let probability = if let Fault::Loss(p) = case.fault { p.to_string() } else { String::new() };
        let loss_match: Vec<&str> = if probability.is_empty() { vec![] } else { vec!["-m", "statistic", "--mode", "random", "--probability", &probability] };
        match case.fault {
            Fault::None => {}
            Fault::Loss(_) | Fault::Blackout => ns.udp_rule("-A", &loss_match),
            Fault::Jitter(max) => jitter_us.store(max.as_micros() as u64, Ordering::Relaxed),
        }
        tokio::time::sleep(case.lasts).await;
        match case.fault {
            Fault::None => {}
            Fault::Loss(_) | Fault::Blackout => ns.udp_rule("-D", &loss_match),
            Fault::Jitter(_) => jitter_us.store(0, Ordering::Relaxed),
        }
        let healed = Instant::now();
        let backlog_at_heal = client.pose_backlog().await;
        tokio::time::sleep(HEAL_WINDOW.saturating_sub(healed.elapsed())).await;
        let end = Instant::now();
        last_end = end;
        let c = client.receive_stats().since(&before);
        let during = log.frame_times(start, healed);
        let after = log.frame_times(healed, end);
        let row = Row {
            name: case.name,
            frames: during.len(),
            fps: during.len() as f64 / (healed - start).as_secs_f64(),
            freeze_during_ms: longest_freeze(&during, start, healed).as_secs_f64() * 1e3,
            frames_after: after.len(),
            freeze_after_ms: longest_freeze(&after, healed, end).as_secs_f64() * 1e3,
            backlog_at_heal,
            held_back: client.poses_held_back() - held_before,
            recovery: recovery_of(case.fault, &c, backlog_at_heal),
            c,
        };
        println!(
            "{}: {} frames ({:.1} fps), longest freeze {:.0} ms; healed: {} frames, longest freeze {:.0} ms; {:?}",
            row.name, row.frames, row.fps, row.freeze_during_ms, row.frames_after, row.freeze_after_ms, row.c
        );
        rows.push(row);
    }
    stop.store(true, Ordering::Relaxed);
    let _ = posing.await;

    println!();
    println!(
        "| case | fault s | frames | fps | longest freeze during ms | frames in 3 s after | longest freeze after heal ms | RTP pkts | late pkts (filled) | dup | lost (given up) | AUs dropped | IDRs | PLIs sent | pose backlog at heal B | poses held back | recovery |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (row, case) in rows.iter().zip(&cases) {
        let c = &row.c;
        println!(
            "| {} | {:.0} | {} | {:.1} | {:.0} | {} | {:.0} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            row.name,
            case.lasts.as_secs_f64(),
            row.frames,
            row.fps,
            row.freeze_during_ms,
            row.frames_after,
            row.freeze_after_ms,
            c.packets,
            c.late,
            c.duplicates,
            c.lost,
            c.units_dropped,
            c.idrs,
            c.plis_sent,
            row.backlog_at_heal,
            row.held_back,
            row.recovery
        );
    }
    println!();

    let trouble = log.trouble.lock().unwrap().clone();
    assert!(trouble.is_empty(), "the session had trouble: {trouble:#?}");
    for row in &rows {
        assert!(row.frames_after >= 5, "{}: only {} frames in the {} s after the path healed", row.name, row.frames_after, HEAL_WINDOW.as_secs());
        assert!(
            row.freeze_after_ms <= MAX_FREEZE.as_secs_f64() * 1e3,
            "{}: the picture froze for {:.0} ms after the path healed (at most {} ms)",
            row.name,
            row.freeze_after_ms,
            MAX_FREEZE.as_millis()
        );
    }
    let at_the_end = log.frame_times(last_end - Duration::from_secs(1), last_end).len();
    assert!(at_the_end >= 5, "{at_the_end} frames in the last second: the session was lost");
    match Arc::try_unwrap(client) {
        Ok(client) => client.close().await,
        Err(_) => panic!("the client is still shared"),
    }
}
