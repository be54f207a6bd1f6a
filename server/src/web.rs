//! The HTTP side of `nephele serve`: the pages of `web/` (compiled into the binary, so the
//! server runs from anywhere), `GET /scenes`, and signaling's `/signal` and `/status`.

use std::sync::Arc;

use axum::{
    Json, Router,
    http::{HeaderValue, StatusCode, header},
    response::{IntoResponse, Response},
    routing::get,
};

use crate::{
    farm::Farm,
    master::{self, MasterConfig},
};

/// Runs signaling, the pages and one master on `listener` in this process (the embedded
/// default). Returns the bound address; everything runs on spawned tasks.
pub async fn spawn_local(listener: tokio::net::TcpListener, farm: Arc<Farm>, cfg: MasterConfig) -> std::io::Result<std::net::SocketAddr> {
    let addr = listener.local_addr()?;
    let hub = nephele_signaling::HubConfig { token: cfg.token.clone(), ..Default::default() };
    let signaling = nephele_signaling::SignalState::new(hub);
    signaling.spawn_tick_task();
    let app = router(signaling.clone(), Arc::clone(&farm));
    tokio::spawn(async move {
        if let Err(e) = axum::serve(listener, app).await {
            tracing::error!("HTTP server failed: {e}");
        }
    });
    tokio::spawn(async move {
        if let Err(e) = master::run(format!("ws://{addr}/signal"), cfg, farm).await {
            tracing::error!("master stopped: {e:#}");
        }
    });
    // Ready when the master has registered (a join before that would find no capacity).
    for _ in 0..200 {
        if !signaling.stats().masters.is_empty() {
            return Ok(addr);
        }
        tokio::time::sleep(std::time::Duration::from_millis(25)).await;
    }
    Err(std::io::Error::other("the local master did not register with signaling within 5 s"))
}

/// (URL path, content type, body) of every page file.
const PAGES: &[(&str, &str, &str)] = &[
    ("/index.html", "text/html; charset=utf-8", include_str!("../../web/index.html")),
    ("/ar.html", "text/html; charset=utf-8", include_str!("../../web/ar.html")),
    ("/nephele.js", "text/javascript; charset=utf-8", include_str!("../../web/nephele.js")),
    ("/viewer.js", "text/javascript; charset=utf-8", include_str!("../../web/viewer.js")),
    ("/ar.js", "text/javascript; charset=utf-8", include_str!("../../web/ar.js")),
    ("/style.css", "text/css; charset=utf-8", include_str!("../../web/style.css")),
];

/// Pages plus `/scenes`, merged with signaling's routes.
pub fn router(signaling: nephele_signaling::SignalState, farm: Arc<Farm>) -> Router {
    let mut router = nephele_signaling::app(signaling);
    for &(path, mime, body) in PAGES {
        router = router.route(path, get(move || async move { page(mime, body) }));
    }
    let (_, mime, index) = PAGES[0];
    router = router.route("/", get(move || async move { page(mime, index) }));
    let scenes = serde_json::json!({ "scenes": farm.names(), "default": farm.default_scene });
    router.route("/scenes", get(move || async move { Json(scenes.clone()) })).fallback(|| async { (StatusCode::NOT_FOUND, "not found\n") })
}

fn page(mime: &'static str, body: &'static str) -> Response {
    let mut r = body.into_response();
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(mime));
    r.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    r
}
