//! The HTTP server loop for signaling and the pages, with the connection limits of
//! [`ConnLimits`]: at most `max_connections` open sockets and `max_connections_per_address`
//! per IP (more are closed as they are accepted, before any byte is read), and request
//! headers within `header_timeout_ms` (hyper's header timer, which also ends idle
//! keep-alive connections). Websockets upgrade on the same connection and keep counting
//! against the caps until they close. At the total cap, the oldest connection that holds no
//! role (no master, no session) is closed to let a newcomer in ([`ConnPermit`]). Requests
//! carry [`ConnectInfo`] of the peer and an `Arc<ConnPermit>` (its place under the caps).

use std::collections::{HashMap, VecDeque};
use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

use axum::Router;
use axum::extract::ConnectInfo;
use hyper_util::rt::{TokioIo, TokioTimer};
use nephele_limits::ConnLimits;
use tokio::net::TcpListener;
use tokio::sync::Notify;
use tower_service::Service;

/// Open connections, in total and per address, and every open one in the order it came.
#[derive(Debug, Default)]
pub struct ConnCounts {
    total: usize,
    per_address: HashMap<IpAddr, usize>,
    /// Oldest first; dead entries are pruned as they are met.
    open: VecDeque<Weak<ConnPermit>>,
    refused: u64,
    evicted: u64,
}

/// Counts and limits shared by the accept loop and the connections.
#[derive(Clone, Debug)]
pub struct ConnGate {
    limits: ConnLimits,
    counts: Arc<Mutex<ConnCounts>>,
}

/// Held by an open connection; frees its place when dropped.
///
/// A connection is *evictable* until it holds a role (a registered master, a client in a
/// session) and again once it drops it. When `max_connections` is reached, a newcomer is
/// not turned away while an evictable connection is open: the oldest of those is closed
/// instead ([`ConnPermit::evicted`] fires). So thousands of sockets that never join, from
/// however many addresses, cannot lock a viewer out; they only push each other out.
#[derive(Debug)]
pub struct ConnPermit {
    gate: ConnGate,
    ip: IpAddr,
    evictable: AtomicBool,
    evicted: AtomicBool,
    evict: Notify,
}

impl ConnGate {
    pub fn new(limits: ConnLimits) -> Self {
        Self { limits, counts: Arc::default() }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, ConnCounts> {
        self.counts.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A place for a connection from `ip` (evicting the oldest evictable connection when
    /// the total cap is reached), or `None` when its address is at its cap or nothing
    /// can make room.
    pub fn admit(&self, ip: IpAddr) -> Option<Arc<ConnPermit>> {
        let mut c = self.lock();
        let mine = c.per_address.get(&ip).copied().unwrap_or(0);
        if mine >= self.limits.max_connections_per_address || (c.total >= self.limits.max_connections && !Self::evict_oldest(&mut c)) {
            c.refused += 1;
            return None;
        }
        c.total += 1;
        *c.per_address.entry(ip).or_insert(0) += 1;
        let permit = Arc::new(ConnPermit { gate: self.clone(), ip, evictable: AtomicBool::new(true), evicted: AtomicBool::new(false), evict: Notify::new() });
        c.open.push_back(Arc::downgrade(&permit));
        // A closed connection's entry keeps its permit's allocation alive: prune once the dead
        // outnumber the open (amortised O(1) per connection; memory follows open connections).
        if c.open.len() > 2 * c.total + 64 {
            c.open.retain(|w| w.strong_count() > 0);
        }
        Some(permit)
    }

    /// Closes the oldest evictable connection; its place is free at once (its count goes
    /// now, its address's when it is dropped). `false` if there is none.
    fn evict_oldest(c: &mut ConnCounts) -> bool {
        while c.open.front().is_some_and(|w| w.strong_count() == 0) {
            c.open.pop_front();
        }
        let victim = c.open.iter().position(|w| w.upgrade().is_some_and(|p| p.evictable.load(Ordering::Relaxed) && !p.evicted.load(Ordering::Relaxed)));
        let Some(permit) = victim.and_then(|i| c.open.remove(i)).and_then(|w| w.upgrade()) else {
            return false;
        };
        permit.evicted.store(true, Ordering::Release);
        permit.evict.notify_waiters();
        c.total -= 1;
        c.evicted += 1;
        true
    }

    /// (open connections, connections refused so far, connections evicted so far).
    pub fn snapshot(&self) -> (usize, u64, u64) {
        let c = self.lock();
        (c.total, c.refused, c.evicted)
    }
}

impl ConnPermit {
    /// Whether this connection may be closed to make room (it holds no role).
    pub fn set_evictable(&self, evictable: bool) {
        self.evictable.store(evictable, Ordering::Relaxed);
    }

    /// Completes once this connection is chosen to make room for a newcomer.
    pub async fn evicted(&self) {
        let notified = self.evict.notified();
        tokio::pin!(notified);
        notified.as_mut().enable();
        if self.evicted.load(Ordering::Acquire) {
            return;
        }
        notified.await;
    }
}

impl Drop for ConnPermit {
    fn drop(&mut self) {
        let mut c = self.gate.lock();
        if !self.evicted.load(Ordering::Acquire) {
            c.total -= 1;
        }
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
            tokio::select! {
                ended = connection => if let Err(e) = ended {
                    tracing::debug!(%peer, "connection ended: {e}");
                },
                () = permit.evicted() => tracing::debug!(%peer, "connection closed to make room for a newer one"),
            }
            // The connection is done, or upgraded: a websocket's task holds its own clone of
            // the permit (from the request's extensions) until the socket closes.
            drop(permit);
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closed_connections_leave_no_entries_behind() {
        let gate = ConnGate::new(ConnLimits::default());
        let ip: IpAddr = [127, 0, 0, 1].into();
        let resident: Vec<_> = (0..10).map(|_| gate.admit(ip).expect("room")).collect();
        for _ in 0..10_000 {
            drop(gate.admit(ip).expect("room"));
        }
        let c = gate.lock();
        assert_eq!(c.total, resident.len());
        assert!(c.open.len() <= 2 * c.total + 64, "{} entries for {} open connections", c.open.len(), c.total);
    }
}
