//! The HTTP server loop for signaling and the pages, with the connection limits of
//! [`ConnLimits`]: at most `max_connections` open sockets and `max_connections_per_address`
//! per IP (more are closed as they are accepted, before any byte is read), and request
//! headers within `header_timeout_ms` (hyper's header timer, which also ends idle
//! keep-alive connections). Websockets upgrade on the same connection and keep counting
//! against the caps until they close. Requests carry [`ConnectInfo`] of the peer and an
//! `Arc<ConnPermit>` (its place under the caps).

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Router;
use axum::extract::ConnectInfo;
use hyper_util::rt::{TokioIo, TokioTimer};
use nephele_limits::ConnLimits;
use tokio::net::TcpListener;
use tower_service::Service;

/// Open connections, in total and per address.
#[derive(Debug, Default)]
pub struct ConnCounts {
    total: usize,
    per_address: HashMap<IpAddr, usize>,
    refused: u64,
}

/// Counts and limits shared by the accept loop and the connections.
#[derive(Clone, Debug)]
pub struct ConnGate {
    limits: ConnLimits,
    counts: Arc<Mutex<ConnCounts>>,
}

/// Held by an open connection; frees its place when dropped.
#[derive(Debug)]
pub struct ConnPermit {
    gate: ConnGate,
    ip: IpAddr,
}

impl ConnGate {
    pub fn new(limits: ConnLimits) -> Self {
        Self { limits, counts: Arc::default() }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, ConnCounts> {
        self.counts.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A place for a connection from `ip`, or `None` when a cap is reached.
    pub fn admit(&self, ip: IpAddr) -> Option<ConnPermit> {
        let mut c = self.lock();
        let mine = c.per_address.get(&ip).copied().unwrap_or(0);
        if c.total >= self.limits.max_connections || mine >= self.limits.max_connections_per_address {
            c.refused += 1;
            return None;
        }
        c.total += 1;
        *c.per_address.entry(ip).or_insert(0) += 1;
        Some(ConnPermit { gate: self.clone(), ip })
    }

    /// (open connections, connections refused so far).
    pub fn snapshot(&self) -> (usize, u64) {
        let c = self.lock();
        (c.total, c.refused)
    }
}

impl Drop for ConnPermit {
    fn drop(&mut self) {
        let mut c = self.gate.lock();
        c.total -= 1;
        if let Some(n) = c.per_address.get_mut(&self.ip) {
            *n -= 1;
            if *n == 0 {
                c.per_address.remove(&self.ip);
            }
        }
    }
}

/// Serves `app` on `listener` under `gate`'s limits until the listener fails for good.
pub async fn serve_limited(listener: TcpListener, app: Router, gate: ConnGate) -> std::io::Result<()> {
    let header_timeout = Duration::from_millis(gate.limits.header_timeout_ms.max(1));
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(x) => x,
            Err(e) => {
                // Out of file descriptors or a connection reset before accept: wait a moment.
                tracing::warn!("accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Some(permit) = gate.admit(peer.ip()) else {
            tracing::debug!(%peer, "connection refused: a connection cap is reached");
            drop(stream);
            continue;
        };
        let _ = stream.set_nodelay(true);
        let app = app.clone();
        let permit = Arc::new(permit);
        tokio::spawn(async move {
            let held = Arc::clone(&permit);
            let service = hyper::service::service_fn(move |request: hyper::Request<hyper::body::Incoming>| {
                let mut request = request.map(axum::body::Body::new);
                request.extensions_mut().insert(ConnectInfo::<SocketAddr>(peer));
                request.extensions_mut().insert(Arc::clone(&held));
                let mut app = app.clone();
                async move { app.call(request).await }
            });
            let connection = hyper::server::conn::http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(header_timeout)
                .serve_connection(TokioIo::new(stream), service)
                .with_upgrades();
            if let Err(e) = connection.await {
                tracing::debug!(%peer, "connection ended: {e}");
            }
            // The connection is done, or upgraded: a websocket's task holds its own clone of
            // the permit (from the request's extensions) until the socket closes.
            drop(permit);
        });
    }
}
