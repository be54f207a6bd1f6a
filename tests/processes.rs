//! Streaming end to end through separate processes, as a deployment runs: `nephele signal`,
//! `nephele master` registering with it, and `nephele replay` replaying a shipped pose trace
//! through them (real WebRTC, real OpenH264 both ways), compared with direct renders.


use nephele_e2e::{Reap, nephele, repo};

/// Starts `nephele signal` on a free port; returns it with its `host:port`.
fn spawn_signal() -> (Reap, String) {
    use std::io::{BufRead, BufReader};
    let mut child = nephele()
        .args(["signal", "--listen", "127.0.0.1:0"])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let addr = line.split("ws://").nth(1).and_then(|s| s.split('/').next()).expect("prints its address").to_string();
    (Reap(child), addr)
}

#[test]
fn signal_serves_status() {
    use std::io::{Read, Write};
    let (_signal, addr) = spawn_signal();
    let mut s = std::net::TcpStream::connect(&addr).unwrap();
    write!(s, "GET /status HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").unwrap();
    let mut body = String::new();
    s.read_to_string(&mut body).unwrap();
    assert!(body.starts_with("HTTP/1.1 200") && body.contains("\"masters\":[]"), "{body}");
}

#[test]
fn split_deployment_signal_master_and_replay_of_a_shipped_trace() {
    let root = repo();
    let asset = root.join("examples/assets/trio-small.nolf");
    let trace = root.join("examples/traces/shake.json");
    let (_signal, addr) = spawn_signal();
    let url = format!("ws://{addr}/signal");
    let scene = format!("trio={}", asset.display());
    let _master = Reap(
        nephele()
            .args(["master", "--signal", &url, "--scene", &scene, "--backend", "cpu", "--loopback-only", "--render-scale", "1"])
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap(),
    );
    // The master registers within a moment; until then signaling answers no_capacity.
    let mut last = String::new();
    for _ in 0..20 {
        let o = nephele()
            .args([
                "replay", "--trace", trace.to_str().unwrap(), "--signal", &url, "--size", "320x240",
                "--reference", asset.to_str().unwrap(), "--quality-every", "3", "--json",
            ])
            .output()
            .unwrap();
        last = format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
        if o.status.success() {
            let report: serde_json::Value = serde_json::from_slice(&o.stdout).expect("JSON report");
            assert!(report["frames_decoded"].as_u64().unwrap() >= 5, "{report}");
            assert_eq!(report["frames_unknown_pose"], 0, "{report}");
            assert_eq!(report["frames_without_pose"], 0, "{report}");
            let psnr: Vec<f64> = report["quality"].as_array().unwrap().iter().map(|q| q["psnr_db"].as_f64().unwrap()).collect();
            let min = psnr.iter().copied().fold(f64::INFINITY, f64::min);
            assert!(!psnr.is_empty() && min >= 30.0, "min PSNR {min:.2} dB over {} frames: {psnr:?}", psnr.len());
            return;
        }
        assert!(last.contains("NoCapacity") || last.contains("UnknownScene"), "replay failed: {last}");
        std::thread::sleep(std::time::Duration::from_millis(250));
    }
    panic!("the master never took a session: {last}");
}


/// A master that stops answering (SIGSTOP) is dropped by signaling within ~3 s (one
/// heartbeat a second, 3 s of silence), so joins stop going to it; it used to take ~16 s.
#[test]
fn a_stopped_master_is_noticed_within_seconds() {
    use std::io::{Read, Write};
    let root = repo();
    let asset = root.join("examples/assets/trio-small.nolf");
    let (_signal, addr) = spawn_signal();
    let url = format!("ws://{addr}/signal");
    let scene = format!("trio={}", asset.display());
    let master = Reap(nephele().args(["master", "--signal", &url, "--scene", &scene, "--backend", "cpu"]).stderr(std::process::Stdio::null()).spawn().unwrap());
    let masters = || {
        let mut s = std::net::TcpStream::connect(&addr).unwrap();
        write!(s, "GET /status HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").unwrap();
        let mut body = String::new();
        s.read_to_string(&mut body).unwrap();
        let json: serde_json::Value = serde_json::from_str(body.split("\r\n\r\n").nth(1).unwrap()).unwrap();
        json["masters"].as_array().unwrap().len()
    };
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while masters() == 0 {
        assert!(std::time::Instant::now() < deadline, "the master never registered");
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    // Registered and heart-beating; now it stops.
    std::thread::sleep(std::time::Duration::from_millis(1500));
    let pid = master.0.id().to_string();
    assert!(std::process::Command::new("kill").args(["-STOP", &pid]).status().unwrap().success());
    let stopped = std::time::Instant::now();
    while masters() > 0 {
        assert!(stopped.elapsed() < std::time::Duration::from_secs(10), "the stopped master is still listed");
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    let noticed = stopped.elapsed();
    let _ = std::process::Command::new("kill").args(["-CONT", &pid]).status();
    println!("stopped master dropped after {:.2} s", noticed.as_secs_f64());
    // Silence of 3 s, checked four times per timeout: at most ~3.75 s (+ one heartbeat).
    assert!(noticed <= std::time::Duration::from_millis(4800), "noticed after {noticed:?}");
}
