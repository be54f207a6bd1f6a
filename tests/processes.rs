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

