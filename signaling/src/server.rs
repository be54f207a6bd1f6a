//! The IO edge of signaling: axum routes, one task per websocket, a heartbeat tick.
//!
//! `GET /signal` upgrades to a websocket whose text frames are fed to the [`Hub`]
//! (served by [`crate::serve_limited`] under the connection caps; a websocket must speak
//! within the hello timeout and then answer pings, or it is closed);
//! the hub's [`Outgoing`] messages are delivered through a bounded per-connection
//! channel to that connection's task, which owns the socket. `GET /status` returns
//! [`HubStats`](crate::HubStats) as JSON. The hub sits behind a `std::sync::Mutex`:
//! every hub call is short and synchronous, and no lock is held across an `.await`.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use axum::Router;
use axum::extract::{ConnectInfo, State};
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tracing::Instrument;

use nephele_limits::ConnLimits;

use crate::hub::{ConnId, Hub, HubConfig, Outgoing};
use crate::net::{ConnGate, ConnPermit};

/// Messages queued for a client before a non-reading client is disconnected…
const SEND_QUEUE_LEN: usize = 64;
/// …and for a master, which hears every client of its sessions (hundreds of clients may
/// each send a burst of ICE candidates at once). A master is never disconnected for a full
/// queue: the client whose message filled it is, or (for a message of signaling's own) the
/// message is dropped.
const MASTER_SEND_QUEUE_LEN: usize = 4096;

/// A peer that does not accept a frame within this time is disconnected.
const SEND_TIMEOUT: Duration = Duration::from_secs(10);

/// What a connection task is asked to do with its socket.
#[derive(Debug)]
enum Frame {
    Text(String),
    Close,
}

/// Shared state of the signaling routes; cheap to clone.
#[derive(Clone)]
pub struct SignalState {
    inner: Arc<Shared>,
}

struct Shared {
    core: Mutex<Core>,
    operator_token: Option<String>,
    next_conn: AtomicU64,
    max_message_bytes: usize,
    heartbeat_timeout: Duration,
    limits: ConnLimits,
    gate: ConnGate,
}

struct Core {
    hub: Hub,
    senders: HashMap<ConnId, mpsc::Sender<Frame>>,
}

impl SignalState {
    /// A fresh hub with `cfg`. Remember to [`spawn_tick_task`](Self::spawn_tick_task).
    pub fn new(cfg: HubConfig) -> Self {
        let (max_message_bytes, heartbeat_timeout, limits) = (cfg.max_message_bytes, cfg.heartbeat_timeout, cfg.limits);
        let operator_token = cfg.operator_token.clone();
        // Session ids of this run must differ from those of a signaling that ran before
        // (its sessions may still stream): the start time makes the prefix.
        let started_ms = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis());
        let core = Core {
            hub: Hub::new(cfg).with_session_prefix(&format!("s{:x}-", started_ms & 0xffff_ffff_ffff)),
            senders: HashMap::new(),
        };
        Self {
            inner: Arc::new(Shared {
                core: Mutex::new(core),
                operator_token,
                next_conn: AtomicU64::new(1),
                max_message_bytes,
                heartbeat_timeout,
                limits,
                gate: ConnGate::new(limits),
            }),
        }
    }

    /// The connection caps this state's server applies ([`crate::serve_limited`]).
    pub fn gate(&self) -> ConnGate {
        self.inner.gate.clone()
    }

    /// Spawn the task that drops masters whose heartbeat is older than the timeout.
    /// It checks four times per timeout and runs until aborted.
    pub fn spawn_tick_task(&self) -> JoinHandle<()> {
        let state = self.clone();
        let period = (self.inner.heartbeat_timeout / 4).max(Duration::from_millis(10));
        tokio::spawn(async move {
            let mut interval = tokio::time::interval(period);
            interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                interval.tick().await;
                state.with_hub(None, |hub| hub.tick(Instant::now()));
            }
        })
    }

    /// Whether `request` may read operator pages (`/status`, `/metrics`): it carries the
    /// operator token as `Authorization: Bearer …`, or, with no operator token configured,
    /// it comes from a loopback address (the server must be served with connect info).
    pub fn operator_allowed(&self, request: &axum::extract::Request) -> bool {
        match &self.inner.operator_token {
            Some(expected) => request
                .headers()
                .get(axum::http::header::AUTHORIZATION)
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.strip_prefix("Bearer "))
                .is_some_and(|given| crate::hub::secrets_match(given, expected)),
            None => request.extensions().get::<axum::extract::ConnectInfo<std::net::SocketAddr>>().is_some_and(|c| c.0.ip().is_loopback()),
        }
    }

    /// Refuse joins from now on (shutting down); see [`crate::Hub::drain`].
    pub fn drain(&self) {
        self.lock().hub.drain();
    }

    /// Sessions paired whose peers have not connected yet.
    pub fn connecting(&self) -> usize {
        self.lock().hub.connecting()
    }

    /// Closes every websocket after what is already queued for it (an `ended`, say), and
    /// returns once all are closed or `limit` has passed (shutting down).
    pub async fn close_all(&self, limit: Duration) {
        let deadline = tokio::time::Instant::now() + limit;
        let senders: Vec<mpsc::Sender<Frame>> = self.lock().senders.values().cloned().collect();
        for sender in senders {
            let _ = tokio::time::timeout_at(deadline, sender.send(Frame::Close)).await;
        }
        while !self.lock().senders.is_empty() && tokio::time::Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }

    /// Current masters and load.
    pub fn stats(&self) -> crate::HubStats {
        let mut stats = self.lock().hub.stats();
        (stats.connections, stats.connections_refused, stats.connections_evicted) = self.inner.gate.snapshot();
        stats
    }

    fn lock(&self) -> MutexGuard<'_, Core> {
        // A panic inside the hub is a bug; the state is still the best we have.
        self.inner
            .core
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// Run `f` on the hub for a message from `from` (`None`: the tick) and deliver what it
    /// returns. A recipient whose queue is full loses the message; if someone else's
    /// message filled it, that *sender* is disconnected (a client flooding its master must
    /// not cost the master, and every session on it, its connection); a recipient that
    /// does not read its own replies is disconnected.
    fn with_hub(&self, from: Option<ConnId>, f: impl FnOnce(&mut Hub) -> Vec<Outgoing>) {
        let mut core = self.lock();
        let out = f(&mut core.hub);
        for Outgoing { to, msg, close } in out {
            let to_master = core.hub.is_master(to);
            let Some(tx) = core.senders.get(&to) else {
                continue;
            };
            let limit = if to_master { MASTER_SEND_QUEUE_LEN } else { SEND_QUEUE_LEN };
            let queued = tx.max_capacity() - tx.capacity();
            let mut ok = queued < limit && tx.try_send(Frame::Text(msg.to_json())).is_ok();
            if close {
                ok &= tx.try_send(Frame::Close).is_ok();
            }
            let culprit = match from {
                Some(sender) if !ok && sender != to => Some(sender),
                _ if !ok && to_master => None,
                _ => Some(to),
            };
            if !ok {
                match culprit {
                    Some(c) => tracing::warn!(conn = %c, recipient = %to, "a send queue is full; disconnecting the connection that filled it"),
                    None => tracing::warn!(recipient = %to, "a master's send queue is full; dropping a message of signaling's own"),
                }
            }
            if close && ok {
                // Dropping the sender ends the connection task once its queue drains.
                core.senders.remove(&to);
            } else if let (false, Some(c)) = (ok, culprit) {
                core.senders.remove(&c);
            }
        }
    }
}

/// The signaling routes (`GET /signal`, `GET /status`, `GET /limits`) with state applied,
/// ready to `merge` into a bigger app. The tick task is separate: see
/// [`SignalState::spawn_tick_task`].
pub fn app(state: SignalState) -> Router {
    Router::new()
        .route("/signal", get(upgrade))
        .route("/status", get(status))
        .route("/limits", get(limits))
        .with_state(state)
}

/// `GET /limits`: the rules a join must keep ([`crate::protocol::JoinLimits`]), which the
/// pages check a join against before sending it. Public: they are no secret.
async fn limits() -> axum::Json<crate::protocol::JoinLimits> {
    axum::Json(crate::protocol::JoinLimits::current())
}

/// Serve signaling alone on `listener` (with its tick task) until the server fails.
pub async fn serve(listener: tokio::net::TcpListener, cfg: HubConfig) -> std::io::Result<()> {
    let state = SignalState::new(cfg);
    let tick = state.spawn_tick_task();
    let gate = state.gate();
    let result = crate::serve_limited(listener, app(state), gate).await;
    tick.abort();
    result
}

async fn status(State(state): State<SignalState>, request: axum::extract::Request) -> Response {
    if !state.operator_allowed(&request) {
        return (axum::http::StatusCode::UNAUTHORIZED, "operator pages need the operator token (Authorization: Bearer …) or a loopback address\n").into_response();
    }
    axum::Json(state.stats()).into_response()
}

async fn upgrade(State(state): State<SignalState>, ws: WebSocketUpgrade, request: axum::extract::Request) -> Response {
    // Frames up to 4x the hub limit reach the hub (which answers `too_large` and keeps
    // the connection); anything bigger is a protocol violation that drops the socket.
    let hard_limit_bytes = state.inner.max_message_bytes.saturating_mul(4).max(1024);
    let buffer = state.inner.limits.ws_buffer_bytes.max(1024);
    let peer = request.extensions().get::<ConnectInfo<SocketAddr>>().map(|c| c.0.ip());
    // Served by `serve_limited`, the socket holds its place under the caps until it closes.
    let permit = request.extensions().get::<Arc<ConnPermit>>().cloned();
    ws.max_message_size(hard_limit_bytes)
        .max_frame_size(hard_limit_bytes)
        .read_buffer_size(buffer)
        .write_buffer_size(buffer)
        .max_write_buffer_size(hard_limit_bytes.saturating_add(buffer))
        .on_upgrade(move |socket| {
            let conn = ConnId(state.inner.next_conn.fetch_add(1, Ordering::Relaxed));
            async move {
                run_connection(state, conn, peer, socket, permit).await;
            }
            .instrument(tracing::info_span!("signal", %conn))
        })
}

async fn run_connection(state: SignalState, conn: ConnId, peer: Option<IpAddr>, mut socket: WebSocket, permit: Option<Arc<ConnPermit>>) {
    let (tx, mut rx) = mpsc::channel(MASTER_SEND_QUEUE_LEN);
    {
        let mut core = state.lock();
        core.senders.insert(conn, tx);
        match peer {
            Some(ip) => core.hub.connect_from(conn, ip, Instant::now()),
            None => core.hub.connect(conn, Instant::now()),
        }
    }
    tracing::debug!("connected");
    // Silence: the first message must come within the hello timeout; after it, any message
    // or pong within the idle timeout (we ping every quarter of it; browsers answer).
    let limits = state.inner.limits;
    let idle = Duration::from_millis(limits.idle_timeout_ms.max(40));
    let mut deadline = tokio::time::Instant::now() + Duration::from_millis(limits.hello_timeout_ms.max(1));
    let mut greeted = false;
    let mut ping = tokio::time::interval_at(tokio::time::Instant::now() + idle / 4, idle / 4);
    let evicted = async {
        match &permit {
            Some(p) => p.evicted().await,
            None => std::future::pending().await,
        }
    };
    tokio::pin!(evicted);
    loop {
        // Room may be made by closing this connection while it holds no role.
        if let Some(p) = &permit {
            p.set_evictable(!state.lock().hub.holds_role(conn));
        }
        tokio::select! {
            () = &mut evicted => {
                tracing::debug!("closing a websocket without a role to make room for a newer connection");
                let _ = tokio::time::timeout(Duration::from_secs(1), socket.send(Message::Close(None))).await;
                break;
            }
            _ = tokio::time::sleep_until(deadline) => {
                let what = if greeted { "silent for the idle timeout" } else { "sent nothing within the hello timeout" };
                tracing::debug!("closing a websocket that {what}");
                let _ = tokio::time::timeout(Duration::from_secs(1), socket.send(Message::Close(None))).await;
                break;
            }
            _ = ping.tick() => {
                if tokio::time::timeout(SEND_TIMEOUT, socket.send(Message::Ping(Default::default()))).await.is_err() {
                    break;
                }
            }
            incoming = socket.recv() => match incoming {
                Some(Ok(Message::Text(text))) => {
                    (greeted, deadline) = (true, tokio::time::Instant::now() + idle);
                    state.with_hub(Some(conn), |hub| hub.handle_text(conn, text.as_str(), Instant::now()));
                    // Condemned (rate-limited, unauthorized, flooding a master): say why and
                    // go, without reading whatever else it has already sent.
                    if !state.lock().senders.contains_key(&conn) {
                        while let Ok(Frame::Text(text)) = rx.try_recv() {
                            let _ = tokio::time::timeout(Duration::from_secs(1), socket.send(Message::Text(text.into()))).await;
                        }
                        let _ = tokio::time::timeout(Duration::from_secs(1), socket.send(Message::Close(None))).await;
                        break;
                    }
                }
                // JSON in a binary frame is tolerated; anything else is a bad message.
                Some(Ok(Message::Binary(bytes))) => {
                    (greeted, deadline) = (true, tokio::time::Instant::now() + idle);
                    let text = String::from_utf8_lossy(&bytes);
                    state.with_hub(Some(conn), |hub| hub.handle_text(conn, &text, Instant::now()));
                }
                Some(Ok(Message::Ping(_) | Message::Pong(_))) => {
                    if greeted {
                        deadline = tokio::time::Instant::now() + idle;
                    }
                }
                // Answer the close handshake, so clients see a clean close and not 1006:
                // tungstenite queued the reply, and the next read flushes it.
                Some(Ok(Message::Close(_))) => {
                    let _ = tokio::time::timeout(Duration::from_secs(1), socket.recv()).await;
                    break;
                }
                None => break,
                Some(Err(err)) => {
                    tracing::debug!(%err, "websocket read failed");
                    break;
                }
            },
            frame = rx.recv() => match frame {
                Some(Frame::Text(text)) => {
                    let sent = tokio::time::timeout(SEND_TIMEOUT, socket.send(Message::Text(text.into()))).await;
                    if !matches!(sent, Ok(Ok(()))) {
                        tracing::debug!(?sent, "websocket write failed or timed out");
                        break;
                    }
                }
                Some(Frame::Close) | None => {
                    let _ = tokio::time::timeout(SEND_TIMEOUT, socket.send(Message::Close(None))).await;
                    break;
                }
            },
        }
    }
    state.lock().senders.remove(&conn);
    state.with_hub(None, |hub| hub.disconnect(conn, Instant::now()));
    tracing::debug!("disconnected");
}
