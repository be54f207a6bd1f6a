//! One join specification (`nephele_protocol::JoinSpec`): for joins that break each rule (and
//! some that keep them all), the page's check (`web/join.js`, run by Node with the limits the
//! server publishes at `GET /limits`), signaling's hub and the master's core say the same
//! words, or all three accept.

use std::{process::Command, time::Instant};

use nephele_signaling::{
    ConnId, Hub, HubConfig, Mode, QuiltSpec, ToClient,
    protocol::{JoinLimits, JoinSpec, ToPeer},
};

fn spec(scene: &str, mode: Mode, width: u32, height: u32, fps: u32, quilt: Option<QuiltSpec>) -> JoinSpec {
    JoinSpec { scene: scene.into(), mode, width, height, fps, quilt, depth: false }
}

/// Good joins and one per rule of `JoinSpec::check` (and a few edges).
fn cases() -> Vec<JoinSpec> {
    let q = |cols, rows, cone_deg| Some(QuiltSpec { cols, rows, cone_deg });
    vec![
        spec("lego", Mode::Viewer, 640, 480, 50, None),
        spec("lego", Mode::Vr, 2160, 3840, 120, None),
        spec("lego", Mode::Quilt, 600, 1440, 30, None),
        spec("lego", Mode::Quilt, 420, 560, 30, q(7, 7, 35.5)),
        spec("", Mode::Viewer, 640, 480, 50, None),
        spec("lego world", Mode::Viewer, 640, 480, 50, None),
        spec(&"x".repeat(65), Mode::Viewer, 640, 480, 50, None),
        spec("lego", Mode::Ar, 640, 480, 50, q(5, 9, 40.0)),
        spec("lego", Mode::Viewer, 0, 480, 50, None),
        spec("lego", Mode::Viewer, 3841, 480, 50, None),
        spec("lego", Mode::Viewer, 3000, 3000, 50, None),
        spec("lego", Mode::Viewer, 640, 480, 0, None),
        spec("lego", Mode::Viewer, 640, 480, 121, None),
        spec("lego", Mode::Quilt, 640, 480, 30, None),
        spec("lego", Mode::Quilt, 600, 1440, 30, q(0, 9, 40.0)),
        spec("lego", Mode::Quilt, 1100, 600, 30, q(11, 10, 40.0)),
        spec("lego", Mode::Quilt, 600, 1440, 30, q(5, 9, 0.0)),
        spec("lego", Mode::Quilt, 600, 1440, 30, q(5, 9, 120.5)),
    ]
}

/// What `web/join.js` says of each case, given the published limits.
fn page_says(cases: &[JoinSpec], limits: &JoinLimits) -> Vec<Option<String>> {
    let js = nephele_e2e::repo().join("web/join.js");
    let script = format!(
        "import {{ checkJoin }} from {url};\nconst [cases, limits] = JSON.parse(process.argv[1]);\nconsole.log(JSON.stringify(cases.map((c) => checkJoin(c, limits))));",
        url = serde_json::to_string(&format!("file://{}", js.display())).unwrap()
    );
    let input = serde_json::to_string(&(cases, limits)).unwrap();
    let o = Command::new("node").args(["--input-type=module", "-e", &script, &input]).output().expect("node runs (tests/run installs Node.js)");
    assert!(o.status.success(), "node failed: {}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&o.stdout)))
}

/// What signaling answers to each case (over a hub with one master serving `lego`).
fn signaling_says(cases: &[JoinSpec]) -> Vec<Option<String>> {
    let now = Instant::now();
    cases
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let mut hub = Hub::new(HubConfig::default());
            let (master, client) = (ConnId(1), ConnId(2 + i as u64));
            hub.connect(master, now);
            hub.handle_text(master, r#"{"type":"register","name":"m","capacity":4,"scenes":["lego"]}"#, now);
            hub.connect(client, now);
            let join = serde_json::json!({ "type": "join", "scene": c.scene, "mode": c.mode, "width": c.width, "height": c.height, "fps": c.fps, "quilt": c.quilt });
            let mut join = join;
            if c.quilt.is_none() {
                join.as_object_mut().unwrap().remove("quilt");
            }
            let out = hub.handle_text(client, &join.to_string(), now);
            out.into_iter().find(|o| o.to == client).and_then(|o| match o.msg {
                ToPeer::Client(ToClient::Error { message, .. }) => Some(message),
                ToPeer::Client(ToClient::Joined { .. }) => None,
                other => panic!("unexpected answer to {c:?}: {other:?}"),
            })
        })
        .collect()
}

#[test]
fn page_signaling_and_master_say_the_same_words() {
    let cases = cases();
    let limits = JoinLimits::current();
    let rust: Vec<Option<String>> = cases.iter().map(|c| c.check().err().map(|e| e.to_string())).collect();
    assert_eq!(rust.iter().filter(|r| r.is_none()).count(), 4, "the four good joins pass: {rust:#?}");
    assert!(rust.iter().skip(4).all(Option::is_some), "every other case breaks a rule: {rust:#?}");
    let page = page_says(&cases, &limits);
    let signaling = signaling_says(&cases);
    for (i, c) in cases.iter().enumerate() {
        assert_eq!(page[i], rust[i], "web/join.js on {c:?}");
        assert_eq!(signaling[i], rust[i], "signaling on {c:?}");
    }
    // The master's core runs the same `JoinSpec::check` (its refusal text is asserted in
    // `server/core/src/tests.rs`); here: the published limits are the ones it enforces.
    assert_eq!((limits.min_fps, limits.max_fps), (nephele_limits::MIN_FPS, nephele_limits::MAX_FPS));
    assert_eq!((limits.max_long_edge_px, limits.max_short_edge_px), (nephele_limits::MAX_STREAM_LONG_EDGE_PX, nephele_limits::MAX_STREAM_SHORT_EDGE_PX));
}

/// `GET /limits` on a running server publishes `JoinLimits::current()`.
#[tokio::test]
async fn limits_are_published() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(nephele_signaling::serve(listener, HubConfig::default()));
    let body = nephele_e2e::http_get(addr, "/limits").await;
    let published: JoinLimits = serde_json::from_str(&body).unwrap_or_else(|e| panic!("{e}: {body}"));
    assert_eq!(published, JoinLimits::current());
}
