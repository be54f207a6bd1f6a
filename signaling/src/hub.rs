//! The signaling hub: a sans-IO state machine that pairs clients with masters and
//! routes SDP/ICE between them.
//!
//! Inputs are connection events and text frames with the current time passed in;
//! outputs are [`Outgoing`] messages addressed by [`ConnId`]. The hub never touches
//! sockets, clocks or tasks (see `server.rs` for the IO edge), so tests drive it on
//! simulated time.
//!
//! Pairing: a join goes only to masters that serve its scene (a scene nobody serves is
//! refused at once, naming the scenes on offer); among those with a free session slot
//! (`sessions < capacity`) that do not report themselves saturated, to the one with the
//! most free rays per second, as its last heartbeat said, less the pixel rate
//! (`width × height × fps`) of every join paired there since (ties: fewer sessions, then
//! the smaller id). Each master's session count is kept by the hub (join +1; leave, end,
//! reject, disconnect -1) and raised to the master's own count whenever a heartbeat arrives
//! (never below the sessions the hub has paired there: a heartbeat can be older than the
//! latest join).

use std::collections::BTreeMap;
use std::net::IpAddr;
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::protocol::{ErrorCode, JoinSpec, ToClient, ToMaster, ToPeer, ToSignal};

/// Identifies one websocket connection; chosen by the IO edge.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct ConnId(pub u64);

impl std::fmt::Display for ConnId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "c{}", self.0)
    }
}

/// Hub settings.
#[derive(Clone, Debug)]
pub struct HubConfig {
    /// The clients' secret: `join` must carry it; `None` lets anyone join.
    pub token: Option<String>,
    /// The masters' secret: `register` must carry it (never the clients' token); `None`
    /// lets anyone register a master — only for signaling that nobody else can reach.
    pub master_token: Option<String>,
    /// The operators' secret for `GET /status` (and a server's `/metrics`), as
    /// `Authorization: Bearer …`; `None` serves them to loopback addresses only.
    pub operator_token: Option<String>,
    /// A master silent for longer than this is dropped and its clients told `master_lost`.
    pub heartbeat_timeout: Duration,
    /// Longest accepted text message in bytes; longer ones get `error too_large`.
    pub max_message_bytes: usize,
    /// Messages per second a client connection may send on average (a session needs a
    /// join, an offer, a dozen ICE candidates and a leave)…
    pub client_messages_per_s: f64,
    /// …and in one burst. Beyond that the client gets `rate_limited` and is disconnected,
    /// before its relayed messages can fill its master's queue.
    pub client_message_burst: f64,
    /// Connection limits (the hub applies `max_pending_joins_per_address`; the server the
    /// rest).
    pub limits: nephele_limits::ConnLimits,
    /// STUN/TURN servers handed to each client in `joined` (TURN credentials minted per
    /// session when from a secret).
    pub ice: nephele_protocol::ice::IceConfig,
}

impl Default for HubConfig {
    fn default() -> Self {
        Self {
            token: None,
            master_token: None,
            operator_token: None,
            heartbeat_timeout: Duration::from_millis(nephele_limits::MASTER_SILENCE_TIMEOUT_MS),
            max_message_bytes: nephele_limits::MAX_SIGNAL_MESSAGE_BYTES,
            client_messages_per_s: nephele_limits::CLIENT_SIGNAL_MESSAGES_PER_S,
            client_message_burst: nephele_limits::CLIENT_SIGNAL_MESSAGE_BURST,
            limits: nephele_limits::ConnLimits::default(),
            ice: nephele_protocol::ice::IceConfig::default(),
        }
    }
}

/// One message for the IO edge to deliver.
#[derive(Clone, Debug, PartialEq)]
pub struct Outgoing {
    /// Receiving connection.
    pub to: ConnId,
    /// The message (serialize with [`ToPeer::to_json`]).
    pub msg: ToPeer,
    /// Close the connection after sending this message.
    pub close: bool,
}

impl Outgoing {
    fn client(to: ConnId, msg: ToClient) -> Self {
        Self {
            to,
            msg: ToPeer::Client(msg),
            close: false,
        }
    }
    fn master(to: ConnId, msg: ToMaster) -> Self {
        Self {
            to,
            msg: ToPeer::Master(msg),
            close: false,
        }
    }
}

/// Why a message was refused; becomes an `error` message to its sender only.
#[derive(Debug, thiserror::Error)]
pub enum SignalError {
    /// Not JSON or not a known message type.
    #[error("not a valid signaling message: {0}")]
    BadMessage(String),
    /// Over the size limit.
    #[error("message is {len_bytes} bytes, the limit is {max_bytes} bytes")]
    TooLarge { len_bytes: usize, max_bytes: usize },
    /// Token missing or wrong.
    #[error("missing or wrong token")]
    Unauthorized,
    /// No master registered at all.
    #[error("no master is registered; try again later")]
    NoMaster,
    /// All registered masters serving the scene are at capacity or saturated.
    #[error(
        "all {masters} masters serving scene {scene:?} are busy: {saturated} report users behind their frame rates, {full} have every session slot taken; try again later"
    )]
    AllFull { masters: usize, scene: String, saturated: usize, full: usize },
    /// No registered master serves the scene.
    #[error("no master serves scene {scene:?}; scenes on offer: {offered}")]
    UnknownScene { scene: String, offered: String },
    /// Acceptable syntax, unacceptable content.
    #[error("{0}")]
    BadRequest(String),
    /// Message not allowed for the connection's role.
    #[error("`{kind}` is not allowed on a {role} connection")]
    WrongRole {
        kind: &'static str,
        role: &'static str,
    },
    /// Session message before a successful `join`/`register`.
    #[error("`{0}` needs a session: send `join` (clients) or `register` (masters) first")]
    NotJoined(&'static str),
    /// A client sent messages faster than its allowance; the connection is closed.
    #[error("more than {burst} messages at once or {per_s} per second on average; disconnected")]
    RateLimited { burst: f64, per_s: f64 },
    /// An address started more sessions than its allowance.
    #[error("your address started more than {burst} sessions at once or {per_min} per minute; try again in {wait_s:.0} s")]
    JoinRate { burst: u32, per_min: u32, wait_s: f64 },
    /// Too many sessions from one address are joined but not connected yet.
    #[error("{pending} sessions from your address are still connecting (limit {limit}); finish or leave one first")]
    PendingJoins { pending: usize, limit: usize },
    /// This signaling server is shutting down.
    #[error("this signaling server is shutting down; try again in a moment")]
    Draining,
}

impl SignalError {
    /// The wire error code.
    pub fn code(&self) -> ErrorCode {
        match self {
            Self::BadMessage(_) => ErrorCode::BadMessage,
            Self::TooLarge { .. } => ErrorCode::TooLarge,
            Self::Unauthorized => ErrorCode::Unauthorized,
            Self::NoMaster | Self::AllFull { .. } | Self::Draining => ErrorCode::NoCapacity,
            Self::UnknownScene { .. } => ErrorCode::UnknownScene,
            Self::BadRequest(_) => ErrorCode::BadRequest,
            Self::WrongRole { .. } => ErrorCode::WrongRole,
            Self::NotJoined(_) => ErrorCode::NotJoined,
            Self::RateLimited { .. } | Self::PendingJoins { .. } | Self::JoinRate { .. } => ErrorCode::RateLimited,
        }
    }
}

/// One master's load, for `/status`.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MasterStats {
    /// Master id.
    pub master: String,
    /// Maximum concurrent sessions.
    pub capacity: u32,
    /// Current sessions.
    pub sessions: u32,
    /// Scenes it serves.
    pub scenes: Vec<String>,
    /// Free rays per second, as last reported less the joins paired since (null before the
    /// first heartbeat).
    pub free_rays_per_s: Option<f64>,
    /// It reported users behind their frame rates.
    pub saturated: bool,
}

/// Snapshot of the hub, for `/status`.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct HubStats {
    /// Registered masters, ordered by id.
    pub masters: Vec<MasterStats>,
    /// Connections in the client role.
    pub clients: usize,
    /// Sessions paired with a master.
    pub sessions: usize,
    /// Open HTTP/websocket connections (filled in by the server).
    pub connections: usize,
    /// Connections closed at accept because a cap was reached, since start.
    pub connections_refused: u64,
    /// Connections without a role closed to make room for newer ones (the server's count).
    pub connections_evicted: u64,
    /// Sessions paired since start.
    pub sessions_started: u64,
    /// Messages refused since start, by wire error code.
    pub refused: BTreeMap<String, u64>,
}

#[derive(Debug)]
struct Master {
    id: String,
    capacity: u32,
    sessions: u32,
    scenes: Vec<String>,
    /// Last reported free rays/s, less the pixel rate of joins paired since (unknown, i.e.
    /// unbounded, before the first heartbeat).
    free_rays_per_s: Option<f64>,
    saturated: bool,
    last_seen: Instant,
}

#[derive(Debug)]
enum Peer {
    /// Connected; role not decided yet.
    Fresh,
    /// A client, with its session if paired.
    Client {
        session: Option<String>,
    },
    Master(Master),
}

#[derive(Debug)]
struct Session {
    client: ConnId,
    master: ConnId,
    /// The master said its video connected.
    connected: bool,
}

/// The signaling state machine. See the module docs.
#[derive(Debug)]
pub struct Hub {
    cfg: HubConfig,
    peers: BTreeMap<ConnId, Peer>,
    /// Message allowance of each connection that is not a master: (tokens, last refill).
    allowance: BTreeMap<ConnId, (f64, Instant)>,
    /// The peer address of each connection the IO edge told us.
    addresses: BTreeMap<ConnId, IpAddr>,
    /// New-session allowance of each address that joined lately: (tokens, last refill).
    join_allowance: BTreeMap<IpAddr, (f64, Instant)>,
    sessions: BTreeMap<String, Session>,
    next_session: u64,
    /// Starts every session id; unique per hub so that ids never repeat across a restart
    /// (sessions outlive signaling: their masters still hold the old ids).
    session_prefix: String,
    /// Set by [`Hub::drain`]: joins are refused.
    draining: bool,
    /// Messages refused since start, by wire error code (for `/metrics`).
    refused: BTreeMap<String, u64>,
}

type Res = Result<Vec<Outgoing>, SignalError>;

impl Hub {
    /// An empty hub.
    pub fn new(cfg: HubConfig) -> Self {
        Self {
            cfg,
            peers: BTreeMap::new(),
            allowance: BTreeMap::new(),
            addresses: BTreeMap::new(),
            join_allowance: BTreeMap::new(),
            sessions: BTreeMap::new(),
            next_session: 1,
            session_prefix: "s".into(),
            draining: false,
            refused: BTreeMap::new(),
        }
    }

    /// Refuse every join from now on (the server is shutting down); sessions already
    /// paired carry on, their media being their masters'.
    pub fn drain(&mut self) {
        self.draining = true;
    }

    /// Sessions paired but whose peers have not connected yet.
    pub fn connecting(&self) -> usize {
        self.sessions.values().filter(|s| !s.connected).count()
    }

    /// Session ids start with `prefix` (`[A-Za-z0-9_-]`; the default is `s`).
    pub fn with_session_prefix(mut self, prefix: &str) -> Self {
        self.session_prefix = prefix.chars().filter(|c| c.is_ascii_alphanumeric() || *c == '-' || *c == '_').take(24).collect();
        self
    }

    /// Whether `conn` is a registered master.
    pub fn is_master(&self, conn: ConnId) -> bool {
        matches!(self.peers.get(&conn), Some(Peer::Master(_)))
    }

    /// The configuration.
    pub fn config(&self) -> &HubConfig {
        &self.cfg
    }

    /// A new connection was accepted.
    pub fn connect(&mut self, conn: ConnId, now: Instant) {
        self.peers.insert(conn, Peer::Fresh);
        self.allowance.insert(conn, (self.cfg.client_message_burst, now));
    }

    /// A new connection from `address` (its pending joins count against the address).
    pub fn connect_from(&mut self, conn: ConnId, address: IpAddr, now: Instant) {
        self.connect(conn, now);
        self.addresses.insert(conn, address);
    }

    /// Takes one message from a non-master connection's allowance (a token bucket).
    fn allowed(&mut self, conn: ConnId, now: Instant) -> bool {
        if matches!(self.peers.get(&conn), Some(Peer::Master(_))) {
            return true;
        }
        let (burst, rate) = (self.cfg.client_message_burst, self.cfg.client_messages_per_s);
        let (tokens, last) = self.allowance.entry(conn).or_insert((burst, now));
        *tokens = (*tokens + now.saturating_duration_since(*last).as_secs_f64() * rate).min(burst);
        *last = now;
        if *tokens >= 1.0 {
            *tokens -= 1.0;
            true
        } else {
            false
        }
    }

    /// One text frame from `conn`. Refused messages produce an `error` to `conn` only.
    pub fn handle_text(&mut self, conn: ConnId, text: &str, now: Instant) -> Vec<Outgoing> {
        if !self.peers.contains_key(&conn) {
            return Vec::new();
        }
        let result = if !self.allowed(conn, now) {
            Err(SignalError::RateLimited { burst: self.cfg.client_message_burst, per_s: self.cfg.client_messages_per_s })
        } else if text.len() > self.cfg.max_message_bytes {
            Err(SignalError::TooLarge {
                len_bytes: text.len(),
                max_bytes: self.cfg.max_message_bytes,
            })
        } else {
            serde_json::from_str::<ToSignal>(text)
                .map_err(|e| SignalError::BadMessage(e.to_string()))
                .and_then(|msg| self.dispatch(conn, msg, now))
        };
        result.unwrap_or_else(|err| {
            tracing::debug!(%conn, %err, "refused signaling message");
            let (code, message) = (err.code(), err.to_string());
            *self.refused.entry(code.as_str().to_owned()).or_default() += 1;
            let msg = match self.peers.get(&conn) {
                Some(Peer::Master(_)) => ToPeer::Master(ToMaster::Error { code, message }),
                _ => ToPeer::Client(ToClient::Error { code, message }),
            };
            vec![Outgoing {
                to: conn,
                msg,
                close: matches!(err, SignalError::Unauthorized | SignalError::RateLimited { .. }),
            }]
        })
    }

    /// Whether `conn` holds a role: a registered master, or a client paired in a session.
    pub fn holds_role(&self, conn: ConnId) -> bool {
        matches!(self.peers.get(&conn), Some(Peer::Master(_) | Peer::Client { session: Some(_) }))
    }

    /// `conn` is gone: its master hears `leave` (unless the session's video is connected:
    /// the stream is peer to peer and belongs to the master now, which ends it when the peer
    /// connection closes), or its clients hear `master_lost`.
    pub fn disconnect(&mut self, conn: ConnId, _now: Instant) -> Vec<Outgoing> {
        self.allowance.remove(&conn);
        self.addresses.remove(&conn);
        match self.peers.remove(&conn) {
            Some(Peer::Client {
                session: Some(session),
            }) if self.sessions.get(&session).is_some_and(|s| s.connected) => {
                // The master still counts it (and says so in its next heartbeat).
                self.sessions.remove(&session);
                tracing::info!(%session, "the client's signaling connection closed; its stream lives on with the master");
                Vec::new()
            }
            Some(Peer::Client {
                session: Some(session),
            }) => self.end_session(&session).1.into_iter().collect(),
            Some(Peer::Master(m)) => self.lose_master(conn, &m.id, "disconnected"),
            _ => Vec::new(),
        }
    }

    /// Refills `address`'s new-session allowance; an error if it has no whole session left.
    fn refill_joins(&mut self, address: IpAddr, now: Instant) -> Result<(), SignalError> {
        let (burst, per_min) = self.join_bucket();
        let per_s = f64::from(per_min) / 60.0;
        let (tokens, last) = self.join_allowance.entry(address).or_insert((f64::from(burst), now));
        *tokens = (*tokens + now.saturating_duration_since(*last).as_secs_f64() * per_s).min(f64::from(burst));
        *last = now;
        if *tokens >= 1.0 {
            Ok(())
        } else {
            Err(SignalError::JoinRate { burst, per_min, wait_s: ((1.0 - *tokens) / per_s).ceil() })
        }
    }

    /// The new-session bucket per address: (burst, sessions per minute), each at least 1.
    fn join_bucket(&self) -> (u32, u32) {
        let limits = &self.cfg.limits;
        (limits.join_burst_per_address.max(1), limits.joins_per_address_per_minute.max(1))
    }

    /// Drop masters silent for longer than `heartbeat_timeout`, and forget addresses whose
    /// new-session allowance is full again.
    pub fn tick(&mut self, now: Instant) -> Vec<Outgoing> {
        let (burst, per_min) = self.join_bucket();
        let refill = Duration::from_secs_f64(f64::from(burst) * 60.0 / f64::from(per_min));
        self.join_allowance.retain(|_, (_, last)| now.saturating_duration_since(*last) < refill);
        let timeout = self.cfg.heartbeat_timeout;
        let stale: Vec<(ConnId, String)> = self
            .peers
            .iter()
            .filter_map(|(conn, peer)| match peer {
                Peer::Master(m) if now.saturating_duration_since(m.last_seen) > timeout => {
                    Some((*conn, m.id.clone()))
                }
                _ => None,
            })
            .collect();
        let mut out = Vec::new();
        for (conn, id) in stale {
            tracing::warn!(master = %id, timeout_secs = timeout.as_secs_f64(), "master missed its heartbeat");
            self.peers.remove(&conn);
            let message = format!("no heartbeat for {:.1} s", timeout.as_secs_f64());
            out.push(Outgoing {
                to: conn,
                msg: ToPeer::Master(ToMaster::Error {
                    code: ErrorCode::MasterLost,
                    message,
                }),
                close: true,
            });
            out.extend(self.lose_master(conn, &id, "stopped sending heartbeats"));
        }
        out
    }

    /// Masters and their load.
    pub fn stats(&self) -> HubStats {
        let mut clients = 0;
        let mut masters = Vec::new();
        for peer in self.peers.values() {
            match peer {
                Peer::Client { .. } => clients += 1,
                Peer::Master(m) => masters.push(MasterStats {
                    master: m.id.clone(),
                    capacity: m.capacity,
                    sessions: m.sessions,
                    scenes: m.scenes.clone(),
                    free_rays_per_s: m.free_rays_per_s,
                    saturated: m.saturated,
                }),
                Peer::Fresh => {}
            }
        }
        masters.sort_by(|a, b| a.master.cmp(&b.master));
        HubStats {
            masters,
            clients,
            sessions: self.sessions.len(),
            connections: 0,
            connections_refused: 0,
            connections_evicted: 0,
            sessions_started: self.next_session - 1,
            refused: self.refused.clone(),
        }
    }

    fn dispatch(&mut self, conn: ConnId, msg: ToSignal, now: Instant) -> Res {
        let peer = self.peers.get_mut(&conn).expect("checked by handle_text");
        match (peer, msg) {
            (
                Peer::Fresh | Peer::Client { .. },
                ToSignal::Join { spec, token },
            ) => self.join(conn, spec, token.as_deref(), now),
            (
                Peer::Fresh,
                ToSignal::Register {
                    name,
                    capacity,
                    scenes,
                    token,
                },
            ) => self.register(conn, &name, capacity, scenes, token.as_deref(), now),
            (Peer::Fresh, msg) => Err(SignalError::NotJoined(kind(&msg))),
            (Peer::Client { session }, ToSignal::Offer { sdp }) => {
                let session = session.clone().ok_or(SignalError::NotJoined("offer"))?;
                let master = self.sessions[&session].master;
                Ok(vec![Outgoing::master(
                    master,
                    ToMaster::Offer { session, sdp },
                )])
            }
            (Peer::Client { session }, ToSignal::Ice { candidate, .. }) => {
                let session = session.clone().ok_or(SignalError::NotJoined("ice"))?;
                let master = self.sessions[&session].master;
                Ok(vec![Outgoing::master(
                    master,
                    ToMaster::Ice { session, candidate },
                )])
            }
            (Peer::Client { session }, ToSignal::Leave {}) => match session.take() {
                Some(session) => Ok(self.end_session(&session).1.into_iter().collect()),
                None => Ok(Vec::new()),
            },
            (Peer::Client { .. }, msg) => Err(SignalError::WrongRole {
                kind: kind(&msg),
                role: "client",
            }),
            (
                Peer::Master(m),
                ToSignal::Heartbeat {
                    sessions,
                    free_rays_per_s,
                    saturated,
                },
            ) => {
                m.last_seen = now;
                // A heartbeat may have left the master before a join we paired reached it:
                // never count fewer sessions than this hub has paired there and not ended.
                let paired = self.sessions.values().filter(|s| s.master == conn).count() as u32;
                m.sessions = sessions.max(paired);
                m.free_rays_per_s = Some(if free_rays_per_s.is_finite() { free_rays_per_s.max(0.0) } else { 0.0 });
                m.saturated = saturated;
                Ok(Vec::new())
            }
            (Peer::Master(m), ToSignal::Answer { session, sdp }) => {
                m.last_seen = now;
                Ok(self.to_client_of(conn, &session, ToClient::Answer { sdp }))
            }
            (Peer::Master(m), ToSignal::Ice { session, candidate }) => {
                m.last_seen = now;
                let session = session.ok_or_else(|| {
                    SignalError::BadRequest("`ice` from a master needs `session`".into())
                })?;
                Ok(self.to_client_of(conn, &session, ToClient::Ice { candidate }))
            }
            (Peer::Master(m), ToSignal::Connected { session }) => {
                m.last_seen = now;
                if let Some(s) = self.sessions.get_mut(&session).filter(|s| s.master == conn) {
                    s.connected = true;
                }
                Ok(Vec::new())
            }
            (Peer::Master(m), ToSignal::Reject { session, reason }) => {
                m.last_seen = now;
                Ok(self.finish_by_master(
                    conn,
                    &session,
                    ToClient::Error {
                        code: ErrorCode::Rejected,
                        message: reason,
                    },
                ))
            }
            (Peer::Master(m), ToSignal::End { session, reason }) => {
                m.last_seen = now;
                Ok(self.finish_by_master(conn, &session, ToClient::Ended { reason }))
            }
            (Peer::Master(_), msg) => Err(SignalError::WrongRole {
                kind: kind(&msg),
                role: "master",
            }),
        }
    }

    /// `token` against `expected` (the clients' or the masters' secret).
    fn check_token(expected: Option<&str>, token: Option<&str>) -> Result<(), SignalError> {
        match expected {
            Some(expected) if !token.is_some_and(|t| secrets_match(t, expected)) => Err(SignalError::Unauthorized),
            _ => Ok(()),
        }
    }

    fn join(&mut self, conn: ConnId, req: JoinSpec, token: Option<&str>, now: Instant) -> Res {
        Self::check_token(self.cfg.token.as_deref(), token)?;
        if self.draining {
            return Err(SignalError::Draining);
        }
        if let Some(Peer::Client {
            session: Some(session),
        }) = self.peers.get(&conn)
        {
            return Err(SignalError::BadRequest(format!(
                "already in session {session}; send `leave` first"
            )));
        }
        req.check().map_err(|e| SignalError::BadRequest(e.to_string()))?;
        let req = req.with_defaults();
        if let Some(address) = self.addresses.get(&conn) {
            let limit = self.cfg.limits.max_pending_joins_per_address;
            let pending = self.sessions.values().filter(|s| !s.connected && self.addresses.get(&s.client) == Some(address)).count();
            if pending >= limit {
                return Err(SignalError::PendingJoins { pending, limit });
            }
        }
        let address = self.addresses.get(&conn).copied();
        if let Some(address) = address {
            self.refill_joins(address, now)?;
        }
        let master_conn = self.pick_master(&req.scene)?;
        if let Some((tokens, _)) = address.and_then(|a| self.join_allowance.get_mut(&a)) {
            *tokens -= 1.0;
        }
        let session = format!("{}{}", self.session_prefix, self.next_session);
        self.next_session += 1;
        let Some(Peer::Master(master)) = self.peers.get_mut(&master_conn) else {
            unreachable!("picked a master")
        };
        master.sessions += 1;
        master.free_rays_per_s = master.free_rays_per_s.map(|f| (f - req.pixel_rate()).max(0.0));
        let master_id = master.id.clone();
        tracing::info!(%session, master = %master_id, scene = %req.scene, mode = ?req.mode, width = req.width, height = req.height, fps = req.fps, "session paired");
        self.sessions.insert(
            session.clone(),
            Session {
                client: conn,
                master: master_conn,
                connected: false,
            },
        );
        self.peers.insert(
            conn,
            Peer::Client {
                session: Some(session.clone()),
            },
        );
        Ok(vec![
            Outgoing::client(
                conn,
                ToClient::Joined {
                    ice_servers: self.cfg.ice.servers_now(&format!("nephele-{session}")),
                    session: session.clone(),
                    master: master_id,
                },
            ),
            Outgoing::master(
                master_conn,
                ToMaster::Join { session, spec: req },
            ),
        ])
    }

    /// Among the masters serving `scene`, the one with a free slot, not saturated, and the
    /// most free rays per second; ties go to fewer sessions, then the smaller id.
    fn pick_master(&self, scene: &str) -> Result<ConnId, SignalError> {
        let masters: Vec<(ConnId, &Master)> = self
            .peers
            .iter()
            .filter_map(|(c, p)| match p {
                Peer::Master(m) => Some((*c, m)),
                _ => None,
            })
            .collect();
        if masters.is_empty() {
            return Err(SignalError::NoMaster);
        }
        let serving: Vec<&(ConnId, &Master)> = masters
            .iter()
            .filter(|(_, m)| m.scenes.iter().any(|s| s == scene))
            .collect();
        if serving.is_empty() {
            let mut offered: Vec<&str> = masters
                .iter()
                .flat_map(|(_, m)| m.scenes.iter().map(String::as_str))
                .collect();
            offered.sort_unstable();
            offered.dedup();
            return Err(SignalError::UnknownScene {
                scene: scene.to_owned(),
                offered: offered.join(", "),
            });
        }
        serving
            .iter()
            .filter(|(_, m)| m.sessions < m.capacity && !m.saturated)
            .max_by(|(_, a), (_, b)| {
                let free = |m: &Master| m.free_rays_per_s.unwrap_or(f64::INFINITY);
                free(a)
                    .total_cmp(&free(b))
                    .then_with(|| b.sessions.cmp(&a.sessions))
                    .then_with(|| b.id.cmp(&a.id))
            })
            .map(|(c, _)| *c)
            .ok_or_else(|| SignalError::AllFull {
                masters: serving.len(),
                scene: scene.to_owned(),
                saturated: serving.iter().filter(|(_, m)| m.saturated).count(),
                full: serving.iter().filter(|(_, m)| m.sessions >= m.capacity).count(),
            })
    }

    fn register(
        &mut self,
        conn: ConnId,
        name: &str,
        capacity: u32,
        scenes: Vec<String>,
        token: Option<&str>,
        now: Instant,
    ) -> Res {
        Self::check_token(self.cfg.master_token.as_deref(), token)?;
        validate_name("master name", name)?;
        if scenes.len() > MAX_SCENES_PER_MASTER {
            return Err(SignalError::BadRequest(format!(
                "a master may list at most {MAX_SCENES_PER_MASTER} scenes (got {})",
                scenes.len()
            )));
        }
        for scene in &scenes {
            validate_name("scene", scene)?;
        }
        let taken = |id: &str| {
            self.peers
                .values()
                .any(|p| matches!(p, Peer::Master(m) if m.id == id))
        };
        let id = if taken(name) {
            format!("{name}-{}", conn.0)
        } else {
            name.to_owned()
        };
        tracing::info!(master = %id, capacity, "master registered");
        self.peers.insert(
            conn,
            Peer::Master(Master {
                id: id.clone(),
                capacity,
                sessions: 0,
                scenes,
                free_rays_per_s: None,
                saturated: false,
                last_seen: now,
            }),
        );
        Ok(vec![Outgoing::master(
            conn,
            ToMaster::Registered { master: id },
        )])
    }

    /// Forward to the client of `session` if `master` owns it; stale ids are dropped
    /// silently (the client may have just left, and the master hears `leave`).
    fn to_client_of(&self, master: ConnId, session: &str, msg: ToClient) -> Vec<Outgoing> {
        match self.sessions.get(session) {
            Some(s) if s.master == master => vec![Outgoing::client(s.client, msg)],
            _ => {
                tracing::debug!(%master, session, "dropping message for an unknown session");
                Vec::new()
            }
        }
    }

    /// The master ends one of its sessions; its client gets `msg`.
    fn finish_by_master(&mut self, master: ConnId, session: &str, msg: ToClient) -> Vec<Outgoing> {
        let owned = self
            .sessions
            .get(session)
            .is_some_and(|s| s.master == master);
        if !owned {
            tracing::debug!(%master, session, "dropping message for an unknown session");
            return Vec::new();
        }
        let (client, _) = self.end_session(session);
        if let Some(Peer::Client { session }) = self.peers.get_mut(&client) {
            *session = None;
        }
        tracing::info!(session, ?msg, "master finished session");
        vec![Outgoing::client(client, msg)]
    }

    /// Forget `session` and free its slot; returns its client and the master's `leave`.
    fn end_session(&mut self, session: &str) -> (ConnId, Option<Outgoing>) {
        let Some(s) = self.sessions.remove(session) else {
            unreachable!("session {session} is tracked")
        };
        let leave = match self.peers.get_mut(&s.master) {
            Some(Peer::Master(m)) => {
                m.sessions = m.sessions.saturating_sub(1);
                Some(Outgoing::master(
                    s.master,
                    ToMaster::Leave {
                        session: session.to_owned(),
                    },
                ))
            }
            _ => None,
        };
        (s.client, leave)
    }

    /// The master at `conn` (already removed from `peers`) is gone: tell its clients.
    fn lose_master(&mut self, conn: ConnId, id: &str, why: &str) -> Vec<Outgoing> {
        let lost: Vec<String> = self
            .sessions
            .iter()
            .filter(|(_, s)| s.master == conn)
            .map(|(k, _)| k.clone())
            .collect();
        tracing::info!(master = id, sessions = lost.len(), why, "master lost");
        let mut out = Vec::new();
        for session in lost {
            let (client, _) = self.end_session(&session);
            if let Some(Peer::Client { session }) = self.peers.get_mut(&client) {
                *session = None;
            }
            let message = format!("master {id} {why}");
            out.push(Outgoing::client(
                client,
                ToClient::Error {
                    code: ErrorCode::MasterLost,
                    message,
                },
            ));
        }
        out
    }
}

/// Most scenes one master may list at registration.
const MAX_SCENES_PER_MASTER: usize = 256;

fn validate_name(what: &str, name: &str) -> Result<(), SignalError> {
    if !crate::protocol::is_valid_name(name) {
        return Err(SignalError::BadRequest(format!(
            "{what} must be 1 to 64 characters of A-Z a-z 0-9 _ -"
        )));
    }
    Ok(())
}

/// Wire name of a message type, for error texts.
fn kind(msg: &ToSignal) -> &'static str {
    match msg {
        ToSignal::Join { .. } => "join",
        ToSignal::Offer { .. } => "offer",
        ToSignal::Ice { .. } => "ice",
        ToSignal::Leave {} => "leave",
        ToSignal::Register { .. } => "register",
        ToSignal::Heartbeat { .. } => "heartbeat",
        ToSignal::Answer { .. } => "answer",
        ToSignal::Connected { .. } => "connected",
        ToSignal::Reject { .. } => "reject",
        ToSignal::End { .. } => "end",
    }
}

/// Compares secrets in constant time (`subtle`), so timing does not tell how much of a
/// guess was right.
pub fn secrets_match(given: &str, expected: &str) -> bool {
    use subtle::ConstantTimeEq;
    given.as_bytes().ct_eq(expected.as_bytes()).into()
}

#[cfg(test)]
mod tests;
