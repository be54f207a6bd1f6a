//! `/metrics` as Prometheus and a log shipper meet it, on a real farm of processes
//! (signal, master, worker, NATS) with a session streaming through it: every role answers
//! OpenMetrics (its content type; a strict parser; base units, `_total` counters,
//! `nephele_build_info`), the series show the session's work, and none of the session's
//! series is left once it has gone. `--log-format json` writes JSON lines only.

use std::{
    io::{BufRead, BufReader},
    net::SocketAddr,
    process::Stdio,
    time::{Duration, Instant},
};

use nephele_client::{ClientOptions, Receive, StreamClient, replay::Trace};
use nephele_e2e::{NatsServer, Reap, check_openmetrics, fixture_scene, nephele};
use nephele_signaling::Mode;

/// GET `path`: (status, content type, body).
async fn get(addr: SocketAddr, path: &str) -> (u16, String, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").as_bytes()).await.unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).await.unwrap();
    let (head, body) = out.split_once("\r\n\r\n").unwrap_or((&out, ""));
    let status = head.split(' ').nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    let content_type = head.lines().find_map(|l| l.to_ascii_lowercase().strip_prefix("content-type: ").map(str::to_owned)).unwrap_or_default();
    (status, content_type, body.to_owned())
}

fn free_addr() -> SocketAddr {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap()
}

/// The value of the first sample line starting with `prefix` (name and labels).
fn sample(text: &str, prefix: &str) -> Option<f64> {
    text.lines().find(|l| l.starts_with(prefix)).and_then(|l| l.rsplit(' ').next()).and_then(|v| v.parse().ok())
}

async fn wait_ready(addr: SocketAddr, what: &str) {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        if tokio::net::TcpStream::connect(addr).await.is_ok() && get(addr, "/readyz").await.0 == 200 {
            return;
        }
        assert!(Instant::now() < deadline, "{what} never became ready");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_role_serves_openmetrics_by_convention_and_forgets_sessions() {
    let nats = NatsServer::start();
    let scene = fixture_scene();
    let dir = nephele_e2e::TempDir::new("metrics");
    let (signal_metrics, master_metrics, worker_metrics) = (free_addr(), free_addr(), free_addr());

    let mut signal = nephele()
        .args(["--log-format", "json", "signal", "--listen", "127.0.0.1:0", "--metrics-listen", &signal_metrics.to_string()])
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(dir.0.join("signal.log")).unwrap())
        .spawn()
        .unwrap();
    let mut line = String::new();
    let mut out = BufReader::new(signal.stdout.take().unwrap());
    out.read_line(&mut line).unwrap();
    // Keep reading, so signal never writes into a closed pipe.
    std::thread::spawn(move || std::io::copy(&mut out, &mut std::io::sink()));
    let addr = line.split("ws://").nth(1).and_then(|s| s.split('/').next()).unwrap_or_else(|| panic!("signal printed {line:?}")).to_owned();
    let _signal = Reap(signal);

    let master_log = dir.0.join("master.log");
    let _master = Reap(
        nephele()
            .args(["--log-format", "json", "master", "--signal", &format!("ws://{addr}/signal"), "--nats", &nats.url, "--scene", &scene])
            .args(["--loopback-only", "--render-scale", "1", "--admission", "open", "--metrics-listen", &master_metrics.to_string()])
            .env("NEPHELE_NATS_TOKEN", &nats.token)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&master_log).unwrap())
            .spawn()
            .unwrap(),
    );
    let _worker = Reap(
        nephele()
            .args(["worker", "--nats", &nats.url, "--farm", "light", "--id", "w-metrics", "--backend", "cpu", "--scene", &scene])
            .args(["--metrics-listen", &worker_metrics.to_string()])
            .env("NEPHELE_NATS_TOKEN", &nats.token)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    wait_ready(worker_metrics, "the worker").await;
    wait_ready(master_metrics, "the master").await;

    // A session streams, then leaves.
    let opts = ClientOptions { signal_url: format!("ws://{addr}/signal"), scene: "trio".into(), mode: Mode::Viewer, width: 96, height: 64, fps: 25, token: None, receive: Receive::AccessUnits, quilt: None, depth: false };
    let mut client = StreamClient::connect(&opts).await.expect("a client connects");
    let trace = Trace::builtin("orbit").unwrap();
    let mut frames = 0;
    for seq in 1..=200u32 {
        client.send_pose(&trace.pose_message(seq, 96, 64)).await.unwrap();
        while let Ok(Some(_)) = tokio::time::timeout(Duration::from_millis(20), client.frames.recv()).await {
            frames += 1;
        }
        if frames >= 10 {
            break;
        }
    }
    assert!(frames >= 10, "only {frames} frames");
    let (_, _, during) = get(master_metrics, "/metrics").await;
    assert!(during.contains("nephele_user_target_fps{session="), "no per-session series while streaming:\n{during}");
    drop(client);

    // The master forgets the session's series once it has gone.
    let deadline = Instant::now() + Duration::from_secs(20);
    let master_text = loop {
        let (_, _, text) = get(master_metrics, "/metrics").await;
        if !text.contains("session=") && sample(&text, "nephele_users ") == Some(0.0) {
            break text;
        }
        assert!(Instant::now() < deadline, "a session's series outlived it:\n{text}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };

    for (role, at) in [("signal", signal_metrics), ("master", master_metrics), ("worker", worker_metrics)] {
        let (status, content_type, text) = get(at, "/metrics").await;
        assert_eq!(status, 200, "{role}: {text}");
        assert_eq!(content_type, "application/openmetrics-text; version=1.0.0; charset=utf-8", "{role}");
        let families = check_openmetrics(&text, role);
        println!("{role}: {} metric families", families.len());
    }
    // Signaling's public listener answers /metrics too (loopback is the operator).
    let (status, content_type, public) = get(addr.parse().unwrap(), "/metrics").await;
    assert_eq!((status, content_type.as_str()), (200, "application/openmetrics-text; version=1.0.0; charset=utf-8"), "{public}");
    check_openmetrics(&public, "signal");
    assert!(sample(&public, "nephele_signal_sessions_started_total").is_some_and(|n| n >= 1.0), "{public}");
    assert_eq!(sample(&public, "nephele_signal_masters "), Some(1.0), "{public}");

    // What the session made the master and the worker do, in base units.
    assert!(sample(&master_text, "nephele_frames_total").is_some_and(|n| n >= 10.0), "{master_text}");
    assert!(sample(&master_text, "nephele_render_seconds_count").is_some_and(|n| n >= 1.0), "{master_text}");
    let render_s = sample(&master_text, "nephele_render_seconds_sum").unwrap() / sample(&master_text, "nephele_render_seconds_count").unwrap();
    assert!(render_s > 0.0 && render_s < 10.0, "a render of 96x64 took {render_s} s? (seconds, not ms)");
    for farm in ["heavy", "light"] {
        assert!(master_text.contains(&format!("nephele_task_queue_depth{{farm=\"{farm}\"}}")), "no {farm} queue:\n{master_text}");
    }
    let (_, _, worker_text) = get(worker_metrics, "/metrics").await;
    assert!(sample(&worker_text, "nephele_worker_tasks_total{outcome=\"rendered\"}").is_some_and(|n| n >= 1.0), "{worker_text}");
    assert!(sample(&worker_text, "nephele_worker_result_bytes_total").is_some_and(|n| n > 0.0), "{worker_text}");
    assert_eq!(sample(&worker_text, "nephele_worker_tasks_running "), Some(0.0), "{worker_text}");

    // `--log-format json`: every line the master wrote is one JSON object with a level and a
    // message, but for the one warning OpenH264's C code prints itself as the encoder starts
    // (before any option can quiet it).
    let log = std::fs::read_to_string(&master_log).unwrap();
    let lines: Vec<&str> = log.lines().filter(|l| !l.trim().is_empty() && !l.starts_with("[OpenH264]")).collect();
    assert!(lines.len() >= 2, "the master logged nothing: {log:?}");
    for l in &lines {
        let v: serde_json::Value = serde_json::from_str(l).unwrap_or_else(|e| panic!("not a JSON line ({e}): {l}"));
        assert!(v["level"].is_string() && v["message"].is_string(), "{l}");
    }
    println!("master: {} JSON log lines, e.g. {}", lines.len(), lines[0]);
}
