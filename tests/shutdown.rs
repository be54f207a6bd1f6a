//! Graceful stops, as a container runtime or an operator's Ctrl-C asks for them: every role
//! drains on SIGTERM and exits 0; the clients of a stopping `serve` hear why at once; a
//! second signal stops at once; `/healthz` and `/readyz` answer.

use std::{
    io::{BufRead, BufReader},
    process::{Child, ExitStatus, Stdio},
    time::{Duration, Instant},
};

use futures_util::{SinkExt, StreamExt};
use nephele_client::{ClientOptions, Receive, StreamClient, replay::Trace};
use nephele_e2e::{NatsServer, Reap, fixture_scene, http_get, http_request, nephele};
use nephele_signaling::{Mode, ToClient};
use tokio_tungstenite::tungstenite::Message;

fn sigterm(child: &Child) {
    let ok = std::process::Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap().success();
    assert!(ok, "kill -TERM {}", child.id());
}

/// Waits up to `limit` for the child to exit.
fn exit_within(child: &mut Child, limit: Duration) -> Option<(ExitStatus, Duration)> {
    let start = Instant::now();
    while start.elapsed() < limit {
        if let Some(status) = child.try_wait().unwrap() {
            return Some((status, start.elapsed()));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    None
}

/// Starts a child whose first stdout line names its address after `marker`; returns the
/// child and `host:port`.
fn spawn_printing(args: &[&str], marker: &str) -> (Reap, String) {
    let mut child = nephele().args(args).stdout(Stdio::piped()).stderr(Stdio::null()).spawn().unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let addr = line.split(marker).nth(1).and_then(|s| s.split('/').next()).unwrap_or_else(|| panic!("no address in {line:?}")).to_string();
    (Reap(child), addr)
}

fn opts(addr: &str) -> ClientOptions {
    ClientOptions { signal_url: format!("ws://{addr}/signal"), scene: "trio".into(), mode: Mode::Viewer, width: 96, height: 64, fps: 25, token: None, receive: Receive::AccessUnits, quilt: None, depth: false }
}

/// `serve` with three streaming clients: SIGTERM tells each of them why within a second
/// (`ended` with the reason), and the process exits 0 well inside its drain deadline.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_on_serve_tells_every_client_and_exits_0() {
    let scene = fixture_scene();
    let (mut serve, addr) = spawn_printing(
        &["serve", "--listen", "127.0.0.1:0", "--scene", &scene, "--backend", "cpu", "--loopback-only", "--render-scale", "1", "--admission", "open", "--drain-seconds", "5"],
        "open http://",
    );
    let sock: std::net::SocketAddr = addr.parse().unwrap();
    assert!(http_get(sock, "/healthz").await.ends_with("ok\n"));
    assert!(http_get(sock, "/readyz").await.ends_with("ready\n"), "{}", http_get(sock, "/readyz").await);
    let trace = Trace::builtin("orbit").unwrap();
    let mut clients = Vec::new();
    for _ in 0..3 {
        let mut c = StreamClient::connect(&opts(&addr)).await.expect("a client connects");
        for seq in 1..=5 {
            c.send_pose(&trace.pose_message(seq, 96, 64)).await.unwrap();
        }
        tokio::time::timeout(Duration::from_secs(10), c.frames.recv()).await.expect("a frame").expect("a frame");
        clients.push(c);
    }
    let stopped_at = Instant::now();
    sigterm(&serve.0);
    for (k, c) in clients.iter_mut().enumerate() {
        let told = tokio::time::timeout(Duration::from_secs(1), async {
            loop {
                match c.signaling.recv().await {
                    Some(ToClient::Ended { reason }) => return reason,
                    Some(_) => continue,
                    None => panic!("client {k}: signaling closed without a word"),
                }
            }
        })
        .await;
        let reason = told.unwrap_or_else(|_| panic!("client {k} was not told within 1 s of SIGTERM"));
        assert!(reason.contains("shutting down"), "client {k} was told {reason:?}");
    }
    let told_ms = stopped_at.elapsed().as_millis();
    let (status, took) = exit_within(&mut serve.0, Duration::from_secs(8)).expect("serve exits within its 5 s drain deadline");
    assert!(status.success(), "serve exited with {status}");
    println!("3 clients told within {told_ms} ms of SIGTERM; serve exited 0 after {:.2} s", took.as_secs_f64());
}

/// `signal` waits for a session that is still connecting before it goes (its client never
/// offers), refusing new joins in the meantime; a second SIGTERM stops it at once (status 1).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn signal_drains_refuses_joins_and_a_second_signal_stops_it_at_once() {
    let (mut signal, addr) = spawn_printing(&["signal", "--listen", "127.0.0.1:0", "--drain-seconds", "30"], "ws://");
    let _master = nephele_e2e::spawn_fixture_master(&addr);
    let sock: std::net::SocketAddr = addr.parse().unwrap();
    let deadline = Instant::now() + Duration::from_secs(60);
    while !http_get(sock, "/status").await.contains("\"master\":") {
        assert!(Instant::now() < deadline, "the master never registered");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // A join that never goes on to connect.
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/signal")).await.unwrap();
    ws.send(Message::text(r#"{"type":"join","scene":"trio","mode":"viewer","width":96,"height":64,"fps":25}"#)).await.unwrap();
    let joined = ws.next().await.unwrap().unwrap().into_text().unwrap();
    assert!(joined.contains("\"joined\""), "{joined}");

    sigterm(&signal.0);
    // Draining: not ready, and a new join is refused in words.
    let mut readyz = (0, String::new());
    for _ in 0..100 {
        readyz = http_request(sock, "/readyz").await;
        if readyz.1.contains("draining") {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(readyz.0 == 503 && readyz.1.contains("draining"), "{readyz:?}");
    let (mut late, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/signal")).await.unwrap();
    late.send(Message::text(r#"{"type":"join","scene":"trio","mode":"viewer","width":96,"height":64,"fps":25}"#)).await.unwrap();
    let refused = late.next().await.unwrap().unwrap().into_text().unwrap();
    assert!(refused.contains("no_capacity") && refused.contains("shutting down"), "{refused}");
    assert!(signal.0.try_wait().unwrap().is_none(), "signal left while a session was still connecting");

    sigterm(&signal.0);
    let (status, took) = exit_within(&mut signal.0, Duration::from_secs(2)).expect("a second SIGTERM stops signal at once");
    assert_eq!(status.code(), Some(1), "a second signal exits 1 ({status})");
    println!("second SIGTERM: signal stopped after {:.0} ms", took.as_secs_f64() * 1e3);
}

/// A worker with its health listener: ready once it serves; on SIGTERM it stops taking
/// tasks, stops its NATS service and exits 0.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_on_a_worker_exits_0_after_its_tasks() {
    let nats = NatsServer::start();
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let health = format!("127.0.0.1:{port}");
    let mut worker = spawn_worker_with(&nats, &["--metrics-listen", &health]);
    let sock: std::net::SocketAddr = health.parse().unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        if tokio::net::TcpStream::connect(sock).await.is_ok() && http_request(sock, "/readyz").await == (200, "ready\n".to_string()) {
            break;
        }
        assert!(Instant::now() < deadline, "the worker never became ready");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    sigterm(&worker.0);
    let (status, took) = exit_within(&mut worker.0, Duration::from_secs(10)).expect("the worker exits");
    assert!(status.success(), "worker exited with {status}");
    println!("worker drained and exited 0 after {:.2} s", took.as_secs_f64());
}

/// `nephele worker` for the fixture scene with extra arguments; returns once it serves.
fn spawn_worker_with(nats: &NatsServer, extra: &[&str]) -> Reap {
    let scene = fixture_scene();
    let mut child = nephele()
        .args(["worker", "--nats", &nats.url, "--farm", "light", "--id", "w-drain", "--backend", "cpu", "--scene", &scene])
        .args(extra)
        .env("NEPHELE_NATS_TOKEN", &nats.token)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut out = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    while out.read_line(&mut line).unwrap() > 0 && !line.contains(" serves ") {
        line.clear();
    }
    assert!(line.contains(" serves "), "the worker did not start: {line:?}");
    // Keep reading: its last words at exit go to stdout too.
    std::thread::spawn(move || for _ in out.lines() {});
    Reap(child)
}
