//! The `nephele` command line end to end: render, info, generate and bench print and write
//! what they say, and bad input is a clear error with a non-zero exit.

use std::process::Command;

fn nephele(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_nephele")).args(args).output().expect("runs")
}

fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("nephele-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

#[test]
fn render_writes_pngs() {
    let out = tmp("r.png");
    let depth = tmp("d.png");
    let o = nephele(&["render", "builtin:trio-small", "--size", "63x47", "--backend", "cpu", "--out", out.to_str().unwrap(), "--depth", depth.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("of rays hit"));
    let png = std::fs::read(&out).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    assert!(depth.exists());
}

#[test]
fn render_from_a_nerf_pose_file() {
    let pose = tmp("pose.json");
    // A NeRF-synthetic style camera 4 units out on +y, looking at the origin.
    std::fs::write(&pose, r#"{"camera_angle_x": 0.69, "transform_matrix": [[-1,0,0,0],[0,0,1,4],[0,1,0,0],[0,0,0,1]]}"#).unwrap();
    let out = tmp("pose.png");
    let o = nephele(&["render", "builtin:shiny-small", "--pose", pose.to_str().unwrap(), "--size", "32x32", "--backend", "cpu", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!String::from_utf8_lossy(&o.stderr).contains("no ray hit"));
}

#[test]
fn generate_info_and_bench_print_tables() {
    let asset = tmp("g.nolf");
    let o = nephele(&["generate", "--scene", "diffuse", "--small", "--out", asset.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = nephele(&["info", asset.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("density cubes") && text.contains("dense MiB"), "{text}");
    let o = nephele(&["bench", "render", "--asset", asset.to_str().unwrap(), "--sizes", "32x32,17x9", "--backends", "cpu", "--runs", "1"]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(text.contains("| cpu | 32×32 |") && text.contains("| cpu | 17×9 |"), "{text}");
}

#[test]
fn bad_input_is_a_clear_error() {
    for (args, words) in [
        (vec!["render", "/nonexistent.nolf"], "nonexistent.nolf"),
        (vec!["render", "builtin:teapot"], "unknown procedural scene"),
        (vec!["render", "builtin:trio-small", "--size", "100000x10", "--backend", "cpu"], "outside"),
        (vec!["render", "builtin:trio-small", "--size", "ax3"], "invalid digit"),
        (vec!["render", "builtin:trio-small", "--background", "purple"], "colour"),
        (vec!["synth", "--scene", "teapot", "--out", "/tmp/never"], "unknown synthetic scene"),
        (vec!["dataset-info", "/nonexistent/lego"], "does not exist"),
        (vec!["serve", "--render-scale", "2"], "render scale"),
        (vec!["replay", "--trace", "/nonexistent.json"], "nonexistent.json"),
    ] {
        let o = nephele(&args);
        assert!(!o.status.success(), "{args:?} should fail");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(words), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    }
}

/// Kills a child process when dropped, so a failing assertion leaves no server behind.
struct Reap(std::process::Child);

impl Drop for Reap {
    fn drop(&mut self) {
        self.0.kill().ok();
        self.0.wait().ok();
    }
}

/// Starts `nephele signal` on a free port; returns it with its `host:port`.
fn spawn_signal() -> (Reap, String) {
    use std::io::{BufRead, BufReader};
    let mut child = Command::new(env!("CARGO_BIN_EXE_nephele"))
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
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let asset = root.join("examples/assets/trio-small.nolf");
    let trace = root.join("examples/traces/shake.json");
    let (_signal, addr) = spawn_signal();
    let url = format!("ws://{addr}/signal");
    let scene = format!("trio={}", asset.display());
    let _master = Reap(
        Command::new(env!("CARGO_BIN_EXE_nephele"))
            .args(["master", "--signal", &url, "--scene", &scene, "--backend", "cpu", "--loopback-only", "--render-scale", "1"])
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap(),
    );
    // The master registers within a moment; until then signaling answers no_capacity.
    let mut last = String::new();
    for _ in 0..20 {
        let o = nephele(&[
            "replay", "--trace", trace.to_str().unwrap(), "--signal", &url, "--size", "320x240",
            "--reference", asset.to_str().unwrap(), "--quality-every", "3", "--json",
        ]);
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
        assert!(last.contains("no_capacity") || last.contains("NoCapacity"), "replay failed: {last}");
        std::thread::sleep(std::time::Duration::from_millis(250));
    }
    panic!("the master never took a session: {last}");
}

#[test]
fn synth_writes_a_dataset_that_dataset_info_reads() {
    let dir = tmp("synth");
    let o = nephele(&["synth", "--scene", "glossy", "--size", "32x24", "--train", "3", "--val", "1", "--test", "2", "--out", dir.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = nephele(&["dataset-info", dir.to_str().unwrap(), "--load"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for line in ["train    3 frames, first image Some((32, 24))", "val      1 frames", "test     2 frames", "decoded 3 images"] {
        assert!(out.contains(line), "missing {line:?} in:\n{out}");
    }
}

#[test]
fn shipped_traces_are_the_built_in_ones() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/traces");
    for name in nephele::replay::BUILTIN_TRACES {
        let shipped = nephele::replay::Trace::load(&root.join(format!("{name}.json"))).unwrap();
        assert_eq!(shipped, nephele::replay::Trace::builtin(name).unwrap(), "{name}: regenerate with `nephele traces`");
    }
}
