//! The render farm across processes on NATS (a `nats-server` per test on a free loopback
//! port, with a token): `nephele worker` processes render for a master; a worker killed
//! mid-stream has its tasks re-issued and the stream carries on; workers with bad assets
//! or without credentials refuse in words; garbage from a worker and replies to re-issued
//! tasks are ignored; NATS itself going away is told to the users, and the stream comes
//! back with it; a composed scene renders its objects on the farm.

use std::time::Duration;

use bytes::Bytes;
use futures_util::StreamExt;
use nephele_client::{Receive, replay::{ReplayOptions, ReplayReport, Trace, replay}};
use nephele_farm::protocol::{self, WorkerAnnouncement};
use nephele_e2e::{NatsServer, TempDir, core_config, fixture_scene, nephele, spawn_worker, start_nats_master};
use nephele_signaling::Mode;

fn opts(url: String, scene: &str, size: (u32, u32), fps: u32) -> ReplayOptions {
    ReplayOptions {
        client: nephele_client::ClientOptions {
            signal_url: url,
            scene: scene.into(),
            mode: Mode::Viewer,
            width: size.0,
            height: size.1,
            fps,
            token: None,
            receive: Receive::Decode,
            quilt: None,
            depth: false,
        },
        anchor: None,
        quality_every: 0,
        save_dir: None,
        drain: Duration::from_secs(2),
        start_at: None,
        stereo_baseline: None,
    }
}

fn orbit(poses: usize) -> Trace {
    let mut t = Trace::builtin("orbit").unwrap();
    while t.poses.len() < poses {
        let again = t.poses.clone();
        t.poses.extend(again);
    }
    t.poses.truncate(poses);
    t
}

fn assert_clean(report: &ReplayReport) {
    assert_eq!(report.frames_unknown_pose + report.frames_without_pose, 0, "frames that answer no sent pose");
    assert!(report.errors.is_empty(), "{:?}", report.errors);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_worker_has_its_tasks_re_issued_and_the_stream_carries_on() {
    let nats = NatsServer::start();
    let scenes = [fixture_scene()];
    let mut first = Some(spawn_worker(&nats, "w-first", "light", &scenes));
    let _second = spawn_worker(&nats, "w-second", "light", &scenes);
    let (server, _) = start_nats_master(&scenes, core_config(4), &nats).await;
    // 6 s of poses; the first worker is killed (SIGKILL) once both workers have rendered
    // (the master's own count, not a guess of how long that takes).
    let trace = orbit(300);
    let run = tokio::spawn({
        let o = opts(server.signal_url(), "trio", (160, 120), 25);
        async move { replay(&trace, &o, None).await }
    });
    let rendered_by = |worker: &str| -> u64 {
        let label = nephele_master::metrics::WorkerLabel { worker: worker.into() };
        server.metrics.tasks_rendered.get_or_create(&label).get()
    };
    let both = nephele_e2e::wait_until(Duration::from_secs(20), || rendered_by("w-first") > 0 && rendered_by("w-second") > 0 && server.metrics.frames.get() >= 25).await;
    assert!(both, "both workers never rendered: {}", server.metrics.encode());
    let frames_at_kill = server.metrics.frames.get();
    let first_before = rendered_by("w-first");
    first.take(); // kill -9 and reap
    let report = run.await.unwrap().unwrap();
    println!("{report}");
    assert_clean(&report);
    // The stream went on: at least 20 frames after the kill and its re-issues settled.
    assert!(report.frames_decoded as u64 >= frames_at_kill + 20, "{} frames, {frames_at_kill} before the kill: {report}", report.frames_decoded);
    // Both workers served, the killed one was lost and served no more, the other carried on.
    // (A live worker too slow to say `working` in time is also taken out for a while, so
    // "at least one".)
    assert!(server.metrics.workers_lost.get() >= 1, "{}", server.metrics.encode());
    // The killed worker's count stops (a result already on the wire at the kill may land).
    assert!(rendered_by("w-first") <= first_before + 1, "a dead worker rendered: {}", server.metrics.encode());
    assert!(rendered_by("w-second") >= 20, "{}", server.metrics.encode());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn workers_with_bad_assets_or_no_credentials_refuse_in_words() {
    let nats = NatsServer::start();
    let dir = TempDir::new("bad-assets");
    let corrupt = dir.0.join("corrupt.nolf");
    std::fs::write(&corrupt, b"this is not a safetensors file").unwrap();
    for (scene, words) in [
        ("x=/nonexistent/thing.nolf".to_string(), "this worker cannot serve its scenes"),
        (format!("x={}", corrupt.display()), "this worker cannot serve its scenes"),
    ] {
        let out = nephele()
            .args(["worker", "--nats", &nats.url, "--backend", "cpu", "--scene", &scene])
            .env("NEPHELE_NATS_TOKEN", &nats.token)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(words) && !err.contains("panicked"), "{scene}: {err}");
    }
    // No token: NATS refuses, and the worker says so.
    let out = nephele().args(["worker", "--nats", &nats.url, "--backend", "cpu", "--scene", &fixture_scene()]).env_remove("NEPHELE_NATS_TOKEN").output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("refused us: authorization violation"), "{err}");
    // And none of them ever announced itself.
    let client = async_nats::ConnectOptions::with_token(nats.token.clone()).connect(&nats.url).await.unwrap();
    let inbox = client.new_inbox();
    let mut answers = client.subscribe(inbox.clone()).await.unwrap();
    client.publish_with_reply(format!("$SRV.INFO.{}", protocol::SERVICE_NAME), inbox, Bytes::new()).await.unwrap();
    // (NATS answers a request nobody listens to with a "no responders" status.)
    if let Ok(Some(answer)) = tokio::time::timeout(Duration::from_millis(500), answers.next()).await {
        assert_eq!(answer.status, Some(async_nats::StatusCode::NO_RESPONDERS), "a refusing worker announced itself: {answer:?}");
    }
}

/// A worker of our own on the farm that answers every task with garbage (and, late, with
/// a reply to the attempt it was given after that attempt was re-issued).
async fn garbage_worker(nats: &NatsServer, asset: &str) -> tokio::task::JoinHandle<usize> {
    use async_nats::service::ServiceExt;
    let client = async_nats::ConnectOptions::with_token(nats.token.clone()).connect(&nats.url).await.unwrap();
    let a = WorkerAnnouncement {
        id: "w-garbage".into(),
        farm: protocol::Farm::Light,
        scenes: vec!["trio".into()],
        assets: vec![asset.into()],
        backend: "cpu".into(),
        rays_per_s: 1e9,
        slots: 2,
    };
    let service = client.service_builder().metadata(a.to_metadata()).start(protocol::SERVICE_NAME, protocol::SERVICE_VERSION).await.unwrap();
    let group = service.group_with_queue_group("nephele.render.light", "light");
    let mut light = group.endpoint(asset.to_string()).await.unwrap();
    let mut direct = service.endpoint_builder().name("direct").queue_group("w-garbage").add(protocol::worker_subject("w-garbage")).await.unwrap();
    tokio::spawn(async move {
        let _service = service;
        let mut seen = 0;
        loop {
            let req = tokio::select! { r = light.next() => r, r = direct.next() => r };
            let Some(req) = req else { return seen };
            seen += 1;
            let Some(reply) = req.message.reply.clone() else { continue };
            let mut h = async_nats::HeaderMap::new();
            h.insert(protocol::KIND, "chunk");
            h.insert(protocol::WORKER, "w-garbage");
            h.insert(protocol::CHUNK, "0/1");
            h.insert(protocol::VIEWS, "[[7,7]]");
            client.publish_with_headers(reply.clone(), h, Bytes::from_static(b"garbage")).await.unwrap();
            // Later: a well-formed-looking reply to an attempt that was re-issued meanwhile.
            let c = client.clone();
            tokio::spawn(async move {
                tokio::time::sleep(Duration::from_millis(400)).await;
                let mut h = async_nats::HeaderMap::new();
                h.insert(protocol::KIND, "error");
                let _ = c.publish_with_headers(reply, h, Bytes::from_static(b"too late")).await;
            });
        }
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn garbage_and_late_replies_are_refused_and_the_stream_carries_on() {
    let nats = NatsServer::start();
    let scenes = [fixture_scene()];
    let _good = spawn_worker(&nats, "w-good", "light", &scenes);
    let garbage = garbage_worker(&nats, "trio-small").await;
    let (server, _) = start_nats_master(&scenes, core_config(4), &nats).await;
    let report = replay(&orbit(150), &opts(server.signal_url(), "trio", (160, 120), 25), None).await.unwrap();
    println!("{report}");
    assert_clean(&report);
    assert!(report.frames_decoded >= 30, "{report}");
    garbage.abort();
    // A malformed task straight to the good worker gets an error reply, in words; the worker
    // stays up.
    let client = async_nats::ConnectOptions::with_token(nats.token.clone()).connect(&nats.url).await.unwrap();
    let inbox = client.new_inbox();
    let mut answers = client.subscribe(inbox.clone()).await.unwrap();
    client.publish_with_reply(protocol::worker_subject("w-good"), inbox, Bytes::from_static(b"{\"attempt\": 0, \"task\": 17}")).await.unwrap();
    let answer = tokio::time::timeout(Duration::from_secs(5), answers.next()).await.expect("an answer").unwrap();
    assert_eq!(answer.headers.as_ref().and_then(|h| h.get(protocol::KIND)).map(|v| v.as_str()), Some("error"));
    assert!(String::from_utf8_lossy(&answer.payload).contains("unreadable task"), "{:?}", answer.payload);
    let again = replay(&orbit(50), &opts(server.signal_url(), "trio", (160, 120), 25), None).await.unwrap();
    assert_clean(&again);
    assert!(again.frames_decoded >= 10);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_going_away_is_told_and_the_stream_comes_back() {
    let mut nats = NatsServer::start();
    let scenes = [fixture_scene()];
    let _worker = spawn_worker(&nats, "w-1", "light", &scenes);
    let (server, _) = start_nats_master(&scenes, core_config(4), &nats).await;
    let trace = orbit(400); // 8 s
    let run = tokio::spawn({
        let o = opts(server.signal_url(), "trio", (160, 120), 25);
        async move { replay(&trace, &o, None).await }
    });
    // NATS goes away once the stream runs (the master's own count), for 2 s.
    let streaming = nephele_e2e::wait_until(Duration::from_secs(20), || server.metrics.frames.get() >= 25).await;
    assert!(streaming, "the stream never started");
    nats.stop();
    tokio::time::sleep(Duration::from_millis(2000)).await;
    nats.restart();
    let report = run.await.unwrap().expect("the session survived NATS going away");
    println!("{report}");
    assert_eq!(report.frames_unknown_pose + report.frames_without_pose, 0);
    // The frame rendering when NATS went may fail, in words; nothing else does.
    assert!(report.errors.iter().all(|e| e.starts_with("frame_failed: render:")), "{:?}", report.errors);
    assert!(report.notices.iter().any(|n| n.starts_with("farm_unavailable: the render farm is unreachable")), "{:?}", report.notices);
    assert!(report.notices.iter().any(|n| n.starts_with("farm_back")), "{:?}", report.notices);
    // Frames for poses sent after NATS came back (pose 200 was sent at 4 s).
    let after = report.decoded_pose_seqs.iter().filter(|s| **s > 250).count();
    assert!(after >= 20, "only {after} frames after NATS came back");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_composed_scene_renders_its_objects_on_the_farm() {
    let nats = NatsServer::start();
    let dir = TempDir::new("farm-pair");
    let scenes = [nephele_e2e::pair_scene(&dir.0)];
    let _heavy = spawn_worker(&nats, "w-heavy", "heavy", &scenes);
    let _light = spawn_worker(&nats, "w-light", "light", &scenes);
    let (server, catalog) = start_nats_master(&scenes, core_config(4), &nats).await;
    let mut trace = Trace::builtin("orbit").unwrap();
    trace.poses = trace.poses.iter().step_by(12).copied().collect();
    trace.period_ms = 150.0;
    let mut o = opts(server.signal_url(), "pair", (640, 480), 10);
    o.quality_every = 1;
    o.client.receive = Receive::Pixels;
    let reference = |view, instance, _bg| catalog.render_scene("pair", view, instance, glam::Vec3::new(0.9, 0.95, 1.0));
    let report = replay(&trace, &o, Some(&reference)).await.unwrap();
    println!("{report}");
    assert_clean(&report);
    assert!(report.quality.len() >= 8, "{} frames compared", report.quality.len());
    let min = report.min_psnr().unwrap();
    assert!(min >= 35.0, "composed on the farm vs direct: min PSNR {min:.2} dB");
    let metrics = reqwest_free_get(server.addr, "/metrics").await;
    assert!(metrics.contains("nephele_frames_total"), "{metrics}");
}

/// A plain HTTP/1.1 GET; returns the body.
async fn reqwest_free_get(addr: std::net::SocketAddr, path: &str) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").as_bytes()).await.unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).await.unwrap();
    out
}
