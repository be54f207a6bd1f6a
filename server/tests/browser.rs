//! A real browser: headless Chromium (Debian's `/usr/bin/chromium`, driven by
//! `playwright-core`) opens the viewer and the AR page served by this process, decodes the
//! H.264 stream (getStats), and a mouse drag changes the picture. See
//! `tests/browser/viewer.mjs`. Missing Chromium, Node or `npm ci` fails loudly: `tests/run`
//! installs them.

use std::{path::PathBuf, process::Command, sync::Arc};

use nephele::{farm::Farm, master::MasterConfig, rtc::RtcConfig, session::RenderScale, web};
use nephele_renderer::{CpuBackend, RenderSettings};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn chromium_streams_the_viewer_and_a_drag_changes_the_picture() {
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    let script = repo().join("tests/browser/viewer.mjs");
    assert!(PathBuf::from(&chromium).exists(), "Chromium not found at {chromium}: install the `chromium` package (tests/run does)");
    assert!(
        repo().join("tests/browser/node_modules/playwright-core").exists(),
        "playwright-core is missing: run `npm ci --prefix tests/browser` (tests/run does)"
    );
    let asset = repo().join("examples/assets/trio-small.nolf");
    let farm = Arc::new(Farm::load(&[format!("trio={}", asset.display())], &CpuBackend, RenderSettings::default()).unwrap());
    let cfg = MasterConfig { name: "browser-test".into(), capacity: 4, token: None, rtc: RtcConfig { loopback_only: true, public_ips: vec![] }, render_scale: RenderScale::Fixed(1.0) };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = web::spawn_local(listener, farm, cfg).await.unwrap();

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
