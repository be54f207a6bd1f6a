//! A real browser: headless Chromium (Debian's `/usr/bin/chromium`, driven by
//! `playwright-core`) opens the viewer and the AR page served by this process, decodes the
//! H.264 stream (getStats), and a mouse drag changes the picture. See
//! `tests/browser/viewer.mjs`. Missing Chromium, Node or `npm ci` fails loudly: `tests/run`
//! installs them.

use std::path::PathBuf;

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
    let output = browser_check(script, url, chromium).await;
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

/// The viewer reprojects each frame by its depth (tests/browser/glass.mjs): depth messages
/// decode in the page, a still camera's warp is the frame itself, and after a turn the warped
/// picture is nearer the server's render of the turned camera than the stale frame.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn chromium_reprojects_the_viewer_by_depth() {
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    assert!(PathBuf::from(&chromium).exists(), "Chromium not found at {chromium}: install the `chromium` package (tests/run does)");
    let (server, _) = nephele_e2e::start_server(core_config(4)).await;
    let output = browser_check(repo().join("tests/browser/glass.mjs"), format!("http://{}/", server.addr), chromium).await;
    let stdout = String::from_utf8_lossy(&output.stdout);
    println!("{stdout}\n{}", String::from_utf8_lossy(&output.stderr));
    let last = stdout.lines().last().unwrap_or_default();
    let report: serde_json::Value = serde_json::from_str(last).unwrap_or_else(|_| panic!("no JSON report from the browser check: {stdout}"));
    assert!(output.status.success() && report["ok"] == true, "browser check failed: {report}");
    assert!(report["warpedDb"].as_f64().unwrap() >= report["staleDb"].as_f64().unwrap() + 1.0, "{report}");
}

/// Runs `node SCRIPT URL` with Chromium at `chromium` to its end (node and the browser are
/// ended as one process group however it goes) and returns its output.
async fn browser_check(script: PathBuf, url: String, chromium: String) -> std::process::Output {
    tokio::task::spawn_blocking(move || {
        let mut cmd = nephele_e2e::node(&script);
        cmd.arg(url).env("CHROMIUM", chromium);
        nephele_e2e::node_output(cmd)
    })
    .await
    .unwrap()
    .expect("running node (install nodejs; tests/run does)")
}

/// Starts `nephele serve` on `addr` and waits for its "open http://…" line.
fn serve(addr: &str) -> Reap {
    serve_with(addr, &[])
}

/// [`serve`] with `extra` arguments.
fn serve_with(addr: &str, extra: &[&str]) -> Reap {
    use std::io::{BufRead, BufReader};
    let scene = nephele_e2e::fixture_scene();
    let mut child = nephele()
        .args(["serve", "--listen", addr, "--scene", &scene, "--backend", "cpu", "--loopback-only"])
        .args(extra)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("starting nephele serve");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    assert!(line.contains("open http://"), "serve printed {line:?}");
    Reap(child)
}

/// Runs `node tests/browser/<script> <url>`, waits for its `READY` line, calls `meanwhile`,
/// and returns its exit status and last (JSON) line.
fn node_around(script: &str, url: &str, meanwhile: impl FnOnce()) -> (bool, serde_json::Value) {
    use std::io::{BufRead, BufReader};
    let mut node = nephele_e2e::node(&repo().join("tests/browser").join(script)).arg(url).stdout(std::process::Stdio::piped()).spawn().expect("running node");
    // Node and its Chromium end with this function, even if an assertion fails.
    let _group = nephele_e2e::NodeGroup(node.id());
    let mut out = BufReader::new(node.stdout.take().unwrap());
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    assert_eq!(line.trim(), "READY", "{script}: the viewer did not stream first: {line}");
    meanwhile();
    let mut rest = String::new();
    while out.read_line(&mut rest).unwrap() > 0 {}
    let status = node.wait().unwrap();
    let report = serde_json::from_str(rest.lines().last().unwrap_or_default()).unwrap_or_else(|_| panic!("{script}: no JSON report: {rest}"));
    (status.success(), report)
}

#[test]
fn the_viewer_reconnects_after_the_server_restarts() {
    assert!(repo().join("tests/browser/node_modules/playwright-core").exists(), "run `npm ci --prefix tests/browser` (tests/run does)");
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let server = serve(&addr);
    let mut restarted = None;
    let (ok, report) = node_around("reconnect.mjs", &format!("http://{addr}/"), || {
        drop(server);
        std::thread::sleep(std::time::Duration::from_secs(2));
        restarted = Some(serve(&addr));
    });
    drop(restarted);
    assert!(ok && report["ok"] == true, "reconnect check failed: {report}");
    assert!(report["banner"].as_str().is_some_and(|b| !b.is_empty()), "the lost connection was not shown in words: {report}");
}

/// Failure of the middle, in the browser: signaling (`nephele signal`, which also serves the
/// page) is killed while the viewer streams from a `nephele master`, and started again on
/// the same address 1 s later. The page stays connected, frames keep coming (the media is
/// peer to peer and the session belongs to the master), and it tells the user that
/// signaling went away and the stream goes on (see `tests/browser/signal_restart.mjs`).
#[test]
fn the_viewer_keeps_streaming_through_a_signaling_restart() {
    assert!(repo().join("tests/browser/node_modules/playwright-core").exists(), "run `npm ci --prefix tests/browser` (tests/run does)");
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let signal = nephele_e2e::spawn_signal_at(&addr);
    let _master = nephele_e2e::spawn_fixture_master(&addr);
    let mut restarted = None;
    let (ok, report) = node_around("signal_restart.mjs", &format!("http://{addr}/"), || {
        drop(signal);
        std::thread::sleep(std::time::Duration::from_secs(1));
        restarted = Some(nephele_e2e::spawn_signal_at(&addr));
    });
    drop(restarted);
    println!("{report}");
    assert!(ok && report["ok"] == true, "signaling-restart check failed: {report}");
    let gap = report["maxGapMs"].as_f64().unwrap();
    assert!(gap < 1000.0, "the picture froze for {gap} ms while signaling restarted: {report}");
    assert!(report["framesDuring"].as_u64().unwrap() >= 20, "{report}");
    assert!(report["told"].as_array().is_some_and(|t| !t.is_empty()), "the page did not say signaling went away: {report}");
}

/// The headset page in headless Chromium with `iwer` as the WebXR runtime (a Meta Quest 3,
/// stereo): it enters an immersive session, sends both eyes per pose, and each half of the
/// decoded frame matches a direct render of that eye's camera (PSNR ≥ 30 dB), with the
/// parallax the right way round. Then the quilt page streams. See `tests/browser/xr.mjs`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_headset_page_streams_both_eyes_in_webxr() {
    use base64::Engine;
    use nephele_wire::{FrameLayout, background_of, check_pose};
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    assert!(PathBuf::from(&chromium).exists(), "Chromium not found at {chromium}: install the `chromium` package (tests/run does)");
    assert!(repo().join("tests/browser/node_modules/iwer").exists(), "iwer is missing: run `npm ci --prefix tests/browser` (tests/run does)");
    let (server, catalog) = nephele_e2e::start_server(core_config(4)).await;
    let url = format!("http://{}/", server.addr);
    let script = repo().join("tests/browser/xr.mjs");
    let output = browser_check(script, url, chromium).await;
    let stdout = String::from_utf8_lossy(&output.stdout);
    let last = stdout.lines().last().unwrap_or_default();
    let report: serde_json::Value = serde_json::from_str(last).unwrap_or_else(|_| panic!("no JSON report: {stdout} {}", String::from_utf8_lossy(&output.stderr)));
    let brief: serde_json::Value = report.as_object().unwrap().iter().filter(|(k, _)| !k.ends_with("B64")).map(|(k, v)| (k.clone(), v.clone())).collect();
    println!("{brief}");
    assert!(output.status.success() && report["ok"] == true, "xr check failed: {brief}");
    assert_eq!(report["xrActive"], true);
    let views = report["viewsPerPose"].as_array().unwrap();
    assert!(!views.is_empty() && views.iter().all(|v| v == 2), "every pose in the session carries two views: {views:?}");
    assert!(report["quiltFramesDecoded"].as_u64().unwrap() >= 3, "{brief}");

    let b64 = base64::engine::general_purpose::STANDARD;
    let pose = b64.decode(report["poseB64"].as_str().unwrap()).unwrap();
    let rgba = b64.decode(report["rgbaB64"].as_str().unwrap()).unwrap();
    let (w, h) = (report["width"].as_u64().unwrap() as u32, report["height"].as_u64().unwrap() as u32);
    assert_eq!(rgba.len(), (w * h * 4) as usize);
    let pose = check_pose(&pose, &FrameLayout::Views { width: w, height: h }).expect("the page's pose is valid");
    assert_eq!(pose.views.len(), 2);
    let mut centroids = Vec::new();
    for (i, v) in pose.views.iter().enumerate() {
        let direct = catalog.render_scene("trio", v.view, pose.instance, background_of(nephele_signaling::Mode::Vr)).unwrap();
        let r = v.viewport;
        let half: Vec<u8> = (r.y..r.y + r.height).flat_map(|y| rgba[(4 * (y * w + r.x)) as usize..(4 * (y * w + r.x + r.width)) as usize].to_vec()).collect();
        let psnr = nephele_renderer::render::psnr_rgb(&half, &direct.rgba);
        println!("eye {i}: viewport {r:?}, PSNR {psnr:.2} dB against a direct render");
        // Measured 43.2 and 44.4 dB (AMD Zen 4); 3 dB below.
        assert!(psnr >= 40.0, "eye {i}: {psnr:.2} dB < 40");
        // Mean x of the object's pixels in this eye's image.
        let (mut sum, mut n) = (0.0, 0.0);
        for (j, p) in half.chunks_exact(4).enumerate() {
            if p[..3].iter().any(|&c| c < 200) {
                sum += (j as u32 % r.width) as f64;
                n += 1.0;
            }
        }
        assert!(n > 50.0, "eye {i} sees the object ({n} pixels)");
        centroids.push(sum / n);
    }
    // Eye 0 is the left one (its camera sits left of eye 1's): the object, in front of
    // both, appears further right to it.
    let d = pose.views[1].view.world_from_camera.w_axis - pose.views[0].view.world_from_camera.w_axis;
    assert!(d.truncate().dot(pose.views[0].view.world_from_camera.x_axis.truncate()) > 0.0, "eye 1 is right of eye 0");
    assert!(centroids[0] > centroids[1] + 1.0, "parallax: object at x {:.1} (left eye) vs {:.1} (right eye)", centroids[0], centroids[1]);
}

/// The viewer forced through TURN (`?relay=1`) in headless Chromium: `nephele serve` hands
/// the page a real coturn with a credential minted for its session from the shared secret,
/// and the video arrives over the browser's relay candidate, without a camera request
/// (see `tests/browser/relay.mjs`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn chromium_streams_the_viewer_through_turn() {
    assert!(repo().join("tests/browser/node_modules/playwright-core").exists(), "run `npm ci --prefix tests/browser` (tests/run does)");
    let turn = nephele_e2e::Coturn::start("browser-secret");
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let turn_url = format!("turn:127.0.0.1:{}?transport=udp", turn.port);
    let _server = serve_with(&addr, &["--ice-server", &turn_url, "--turn-secret", "browser-secret"]);
    let chromium = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    let output = browser_check(repo().join("tests/browser/relay.mjs"), format!("http://{addr}/"), chromium).await;
    let stdout = String::from_utf8_lossy(&output.stdout);
    println!("{stdout}\n{}", String::from_utf8_lossy(&output.stderr));
    let report: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap_or_default()).unwrap_or_else(|_| panic!("no JSON report: {stdout}"));
    assert!(output.status.success() && report["ok"] == true, "relay check failed: {report}");
    assert_eq!(report["path"]["local"], "relay", "{report}");
}
