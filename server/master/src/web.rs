//! The HTTP side of `nephele serve`: the pages of `web/` (compiled into the binary, so the
//! server runs from anywhere), `GET /scenes`, `GET /metrics` (the master's Prometheus
//! metrics), and signaling's `/signal` and `/status`.

use std::sync::Arc;

use axum::{
    Json, Router,
    http::{HeaderValue, StatusCode, header},
    response::{IntoResponse, Response},
    routing::get,
};

use nephele_farm::catalog::Catalog;

use crate::{MasterConfig, metrics::MasterMetrics};

/// A running in-process server.
#[derive(Clone)]
pub struct LocalServer {
    pub addr: std::net::SocketAddr,
    pub metrics: Arc<MasterMetrics>,
    pub signaling: nephele_signaling::SignalState,
}

impl LocalServer {
    /// The signaling websocket URL.
    pub fn signal_url(&self) -> String {
        format!("ws://{}/signal", self.addr)
    }
}

/// Runs signaling, the pages and one master on `listener` in this process (the embedded
/// default). Returns once the master is registered and its render workers have measured
/// their throughput; everything runs on spawned tasks.
pub async fn spawn_local(listener: tokio::net::TcpListener, catalog: Arc<Catalog>, cfg: MasterConfig) -> std::io::Result<LocalServer> {
    spawn_local_with(listener, catalog, cfg, nephele_signaling::HubConfig::default()).await
}

/// [`spawn_local`] with signaling's secrets. The in-process master registers with a
/// masters' secret of its own (made here unless `hub` has one), so no one else can.
pub async fn spawn_local_with(listener: tokio::net::TcpListener, catalog: Arc<Catalog>, cfg: MasterConfig, hub: nephele_signaling::HubConfig) -> std::io::Result<LocalServer> {
    Ok(spawn_local_until(listener, catalog, cfg, hub, crate::Lifecycle::default()).await?.0)
}

/// [`spawn_local_with`] that drains and stops when `life.stop` resolves (`/readyz` from
/// `life.health`); the handle ends when the master has drained.
pub async fn spawn_local_until(
    listener: tokio::net::TcpListener,
    catalog: Arc<Catalog>,
    mut cfg: MasterConfig,
    mut hub: nephele_signaling::HubConfig,
    life: crate::Lifecycle,
) -> std::io::Result<(LocalServer, tokio::task::JoinHandle<anyhow::Result<()>>)> {
    let addr = listener.local_addr()?;
    let master_token = hub.master_token.clone().unwrap_or_else(random_secret);
    hub.master_token = Some(master_token.clone());
    cfg.token = Some(master_token);
    let signaling = nephele_signaling::SignalState::new(hub);
    signaling.spawn_tick_task();
    let metrics = Arc::new(MasterMetrics::serving(&signaling));
    let app = router(signaling.clone(), Arc::clone(&catalog), Arc::clone(&metrics)).merge(life.health.routes());
    let gate = signaling.gate();
    tokio::spawn(async move {
        if let Err(e) = nephele_signaling::serve_limited(listener, app, gate).await {
            tracing::error!("HTTP server failed: {e}");
        }
    });
    let m = Arc::clone(&metrics);
    let farm_is_remote = cfg.nats.is_some();
    let master = tokio::spawn(async move {
        let ended = crate::run_with(format!("ws://{addr}/signal"), cfg, catalog, m, life).await;
        if let Err(e) = &ended {
            tracing::error!("master stopped: {e:#}");
        }
        ended
    });
    // Ready when the master has registered (a join before that would find no master) and a
    // worker has calibrated (before that nothing renders).
    let ready = |what: &str, secs: u64| std::io::Error::other(format!("the local master {what} within {secs} s"));
    wait_for(5, || !signaling.stats().masters.is_empty()).await.ok_or_else(|| ready("did not register with signaling", 5))?;
    // A NATS farm may grow later; in-process workers come up within moments.
    if !farm_is_remote {
        wait_for(120, || metrics.farm_rays_per_s.get() > 0.0).await.ok_or_else(|| ready("had no render worker up", 120))?;
    }
    Ok((LocalServer { addr, metrics, signaling }, master))
}

/// 128 random bits from the OS, hex.
fn random_secret() -> String {
    let mut bytes = [0u8; 16];
    getrandom::fill(&mut bytes).expect("the OS random source");
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

async fn wait_for(secs: u64, done: impl Fn() -> bool) -> Option<()> {
    let until = std::time::Instant::now() + std::time::Duration::from_secs(secs);
    while std::time::Instant::now() < until {
        if done() {
            return Some(());
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    None
}

/// (URL path, content type, body) of every page file.
const PAGES: &[(&str, &str, &str)] = &[
    ("/index.html", "text/html; charset=utf-8", include_str!("../../../web/index.html")),
    ("/ar.html", "text/html; charset=utf-8", include_str!("../../../web/ar.html")),
    ("/vr.html", "text/html; charset=utf-8", include_str!("../../../web/vr.html")),
    ("/quilt.html", "text/html; charset=utf-8", include_str!("../../../web/quilt.html")),
    ("/camera.js", "text/javascript; charset=utf-8", include_str!("../../../web/camera.js")),
    ("/pose.js", "text/javascript; charset=utf-8", include_str!("../../../web/pose.js")),
    ("/connection.js", "text/javascript; charset=utf-8", include_str!("../../../web/connection.js")),
    ("/join.js", "text/javascript; charset=utf-8", include_str!("../../../web/join.js")),
    ("/hud.js", "text/javascript; charset=utf-8", include_str!("../../../web/hud.js")),
    ("/presented.js", "text/javascript; charset=utf-8", include_str!("../../../web/presented.js")),
    ("/glass.js", "text/javascript; charset=utf-8", include_str!("../../../web/glass.js")),
    ("/viewer.js", "text/javascript; charset=utf-8", include_str!("../../../web/viewer.js")),
    ("/ar.js", "text/javascript; charset=utf-8", include_str!("../../../web/ar.js")),
    ("/vr.js", "text/javascript; charset=utf-8", include_str!("../../../web/vr.js")),
    ("/quilt.js", "text/javascript; charset=utf-8", include_str!("../../../web/quilt.js")),
    ("/style.css", "text/css; charset=utf-8", include_str!("../../../web/style.css")),
];

/// Pages plus `/scenes` and `/metrics`, merged with signaling's routes.
pub fn router(signaling: nephele_signaling::SignalState, catalog: Arc<Catalog>, metrics: Arc<MasterMetrics>) -> Router {
    let scenes = serde_json::json!({ "scenes": catalog.names(), "default": catalog.default_scene });
    let gate = signaling.clone();
    with_pages(nephele_signaling::app(signaling))
        .route("/scenes", get(move || async move { Json(scenes.clone()) }))
        .route("/metrics", operator_metrics(gate, move || metrics.encode()))
        .fallback(|| async { (StatusCode::NOT_FOUND, "not found\n") })
}

/// `GET /metrics` on a public listener: for the operator only (their token, or loopback).
fn operator_metrics(gate: nephele_signaling::SignalState, scrape: impl Fn() -> String + Clone + Send + Sync + 'static) -> axum::routing::MethodRouter {
    get(move |request: axum::extract::Request| async move {
        if gate.operator_allowed(&request) {
            nephele_signaling::metrics::response(scrape())
        } else {
            (StatusCode::UNAUTHORIZED, "operator pages need the operator token (Authorization: Bearer …) or a loopback address\n").into_response()
        }
    })
}

/// Signaling's metrics as OpenMetrics text (`nephele signal`).
pub fn signaling_metrics(signaling: &nephele_signaling::SignalState) -> impl Fn() -> String + Clone + Send + Sync + 'static {
    let mut registry = nephele_signaling::metrics::registry("signal");
    nephele_signaling::metrics::register_signaling(&mut registry, signaling);
    let registry = Arc::new(registry);
    move || nephele_signaling::metrics::encode_text(&registry)
}

/// `nephele signal` alone: signaling's routes, the pages, `/metrics` (operator only), and
/// `/scenes` as the registered masters offer them (the first master's first scene is the
/// default).
pub fn signaling_router(signaling: nephele_signaling::SignalState) -> Router {
    let metrics = operator_metrics(signaling.clone(), signaling_metrics(&signaling));
    let state = signaling.clone();
    let scenes = move || {
        let stats = state.stats();
        let mut names: Vec<String> = stats.masters.iter().flat_map(|m| m.scenes.iter().cloned()).collect();
        let default = names.first().cloned();
        names.sort();
        names.dedup();
        Json(serde_json::json!({ "scenes": names, "default": default }))
    };
    with_pages(nephele_signaling::app(signaling)).route("/scenes", get(move || std::future::ready(scenes()))).route("/metrics", metrics).fallback(|| async { (StatusCode::NOT_FOUND, "not found\n") })
}

/// Browser libraries from npm, bundled by `server/build.rs` (or a script that says what to
/// install when the build had no npm).
const VENDOR: &[(&str, &[u8])] = &[
    ("/vendor/aframe.min.js", include_bytes!(concat!(env!("OUT_DIR"), "/vendor/aframe.min.js"))),
    ("/vendor/holoplay-core.min.js", include_bytes!(concat!(env!("OUT_DIR"), "/vendor/holoplay-core.min.js"))),
];

fn with_pages(mut router: Router) -> Router {
    for &(path, mime, body) in PAGES {
        router = router.route(path, get(move || async move { page(mime, body) }));
    }
    for &(path, body) in VENDOR {
        router = router.route(
            path,
            get(move || async move {
                let mut r = body.into_response();
                r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("text/javascript; charset=utf-8"));
                r.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("max-age=86400"));
                r
            }),
        );
    }
    let (_, mime, index) = PAGES[0];
    router.route("/", get(move || async move { page(mime, index) }))
}

fn page(mime: &'static str, body: &'static str) -> Response {
    let mut r = body.into_response();
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(mime));
    r.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    r
}

/// `GET /metrics`, `/healthz` and `/readyz` on `listener` (`--metrics-listen` of master,
/// signal and worker: an internal address, no token), until the process ends.
pub async fn serve_metrics(listener: tokio::net::TcpListener, scrape: impl Fn() -> String + Clone + Send + Sync + 'static, health: nephele_signaling::Health) -> std::io::Result<()> {
    let app = Router::new().route("/metrics", get(move || std::future::ready(nephele_signaling::metrics::response(scrape())))).merge(health.routes());
    axum::serve(listener, app).await
}
