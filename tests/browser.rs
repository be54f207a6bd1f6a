//! A real browser: headless Chromium (Debian's `/usr/bin/chromium`, driven by
//! `playwright-core`) opens the viewer and the AR page served by this process, decodes the
//! H.264 stream (getStats), and a mouse drag changes the picture. See
//! `tests/browser/viewer.mjs`. Missing Chromium, Node or `npm ci` fails loudly: `tests/run`
//! installs them.

use std::{path::PathBuf, process::Command};

use nephele_e2e::{Reap, core_config, nephele, repo};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn chromium_streams_the_viewer_and_a_drag_changes_the_picture() {
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    let script = repo().join("tests/browser/viewer.mjs");
    assert!(PathBuf::from(&chromium).exists(), "Chromium not found at {chromium}: install the `chromium` package (tests/run does)");
    assert!(
        repo().join("tests/browser/node_modules/playwright-core").exists(),
        "playwright-core is missing: run `npm ci --prefix tests/browser` (tests/run does)"
    );
    let (server, _) = nephele_e2e::start_server(core_config(4)).await;
    let addr = server.addr;

    let url = format!("http://{addr}/");
    let output = tokio::task::spawn_blocking(move || Command::new("node").arg(script).arg(url).env("CHROMIUM", chromium).output())
        .await
        .unwrap()
        .expect("running node (install nodejs; tests/run does)");
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    println!("{stdout}\n{stderr}");
    let last = stdout.lines().last().unwrap_or_default();
    let report: serde_json::Value = serde_json::from_str(last).unwrap_or_else(|_| panic!("no JSON report from the browser check: {stdout} {stderr}"));
    assert!(output.status.success() && report["ok"] == true, "browser check failed: {report}");
    assert!(report["framesDecoded"].as_u64().unwrap() >= 10, "{report}");
    assert!(report["arFramesDecoded"].as_u64().unwrap() >= 5, "{report}");
    assert!(report["meanAbsDiff"].as_f64().unwrap() > 2.0, "{report}");
}

/// Starts `nephele serve` on `addr` and waits for its "open http://…" line.
fn serve(addr: &str) -> Reap {
    use std::io::{BufRead, BufReader};
    let scene = nephele_e2e::fixture_scene();
    let mut child = nephele()
        .args(["serve", "--listen", addr, "--scene", &scene, "--backend", "cpu", "--loopback-only"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("starting nephele serve");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    assert!(line.contains("open http://"), "serve printed {line:?}");
    Reap(child)
}

#[test]
fn the_viewer_reconnects_after_the_server_restarts() {
    use std::io::{BufRead, BufReader};
    assert!(repo().join("tests/browser/node_modules/playwright-core").exists(), "run `npm ci --prefix tests/browser` (tests/run does)");
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let server = serve(&addr);
    let mut node = Command::new("node")
        .arg(repo().join("tests/browser/reconnect.mjs"))
        .arg(format!("http://{addr}/"))
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("running node");
    let mut out = BufReader::new(node.stdout.take().unwrap());
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    assert_eq!(line.trim(), "READY", "the viewer did not stream before the restart: {line}");
    drop(server);
    std::thread::sleep(std::time::Duration::from_secs(2));
    let _server = serve(&addr);
    let mut rest = String::new();
    while out.read_line(&mut rest).unwrap() > 0 {}
    let status = node.wait().unwrap();
    let report: serde_json::Value = serde_json::from_str(rest.lines().last().unwrap_or_default()).unwrap_or_else(|_| panic!("no JSON report: {rest}"));
    assert!(status.success() && report["ok"] == true, "reconnect check failed: {report}");
    assert!(report["banner"].as_str().is_some_and(|b| !b.is_empty()), "the lost connection was not shown in words: {report}");
}
