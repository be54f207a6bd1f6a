//! Signaling wire protocol: the JSON messages exchanged over the `/signal` websocket.
//!
//! Every message is one JSON object in one text frame, tagged by `"type"` in
//! snake_case, e.g. `{"type":"offer","sdp":"v=0..."}`. Clients (the browser page,
//! the replay client) and masters (render nodes) share the endpoint; the first
//! accepted message decides a connection's role: `join` makes it a client,
//! `register` makes it a master.
//!
//! WebRTC roles: the client creates the offer (recvonly video plus a data channel),
//! the master answers; ICE candidates are trickled both ways.
//!
//! These types are the single definition of the protocol: the master node and the
//! replay client serialize/deserialize them, the web page mirrors them by hand.

pub mod ice;

use serde::{Deserialize, Serialize};
use serde_json::Value;

pub use ice::IceServer;

/// The rule for scene and master names: 1..=64 characters from `[A-Za-z0-9_-]`.
pub fn is_valid_name(name: &str) -> bool {
    let ok_char = |c: char| c.is_ascii_alphanumeric() || c == '_' || c == '-';
    !name.is_empty() && name.len() <= 64 && name.chars().all(ok_char)
}

/// How the client will display the stream; decides what the master renders.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// A single view on a flat screen.
    Viewer,
    /// Side-by-side stereo for a headset.
    Vr,
    /// Object over pure green, keyed out by the client over its camera view.
    Ar,
    /// Looking Glass quilt of horizontally offset views.
    Quilt,
}

/// A Looking Glass quilt's layout, asked for in a `quilt` mode join (defaults: 5×9 views
/// over 40°, the 16"/32" Gen2 displays). The frame must split into equal tiles
/// (`nephele_limits::check_quilt`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct QuiltSpec {
    pub cols: u32,
    pub rows: u32,
    /// Full horizontal view cone, degrees.
    pub cone_deg: f32,
}

impl Default for QuiltSpec {
    fn default() -> Self {
        Self { cols: 5, rows: 9, cone_deg: 40.0 }
    }
}

/// What a client asks for when it joins: the one definition of the join's fields and of the
/// rules they must keep ([`JoinSpec::check`]). Signaling checks it before pairing, the master's
/// core checks it again (a master may sit behind another signaling server), and the pages
/// check it against the same rules as published at `GET /limits` ([`JoinLimits`]); all three
/// say the same words for the same fault.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JoinSpec {
    /// Scene name: 1..=64 characters from `[A-Za-z0-9_-]`.
    pub scene: String,
    /// Display mode.
    pub mode: Mode,
    /// Frame width in pixels (`nephele_limits::check_stream_size`).
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// Frame rate in frames per second, `MIN_FPS..=MAX_FPS` (1..=120).
    pub fps: u32,
    /// Quilt layout (mode `quilt` only; [`QuiltSpec::default`] when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quilt: Option<QuiltSpec>,
    /// Send each frame's depth and camera (`nephele_wire::depth`), for reprojection on the
    /// client (docs/architecture.md §5 "Depth").
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub depth: bool,
}

/// Why a join breaks its specification; the text is what the client is told.
#[derive(Clone, Debug, PartialEq)]
pub enum JoinError {
    /// The scene name is not 1..=64 characters of `[A-Za-z0-9_-]`.
    SceneName,
    /// A quilt layout with a mode other than `quilt`.
    QuiltWithoutQuiltMode,
    /// A size, rate or quilt layout outside `nephele_limits`.
    Limit(nephele_limits::LimitError),
}

impl std::fmt::Display for JoinError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::SceneName => write!(f, "scene must be 1 to 64 characters of A-Z a-z 0-9 _ -"),
            Self::QuiltWithoutQuiltMode => write!(f, "a quilt layout is only for mode \"quilt\""),
            Self::Limit(e) => write!(f, "{e}"),
        }
    }
}

impl std::error::Error for JoinError {}

impl JoinSpec {
    /// The join as it will be served: mode `quilt` without a layout gets the default one.
    pub fn with_defaults(mut self) -> Self {
        if self.mode == Mode::Quilt && self.quilt.is_none() {
            self.quilt = Some(QuiltSpec::default());
        }
        self
    }

    /// Checks every rule, in a fixed order (name, quilt with its mode, size, rate, quilt
    /// layout): the first broken one is the error.
    pub fn check(&self) -> Result<(), JoinError> {
        if !is_valid_name(&self.scene) {
            return Err(JoinError::SceneName);
        }
        if self.quilt.is_some() && self.mode != Mode::Quilt {
            return Err(JoinError::QuiltWithoutQuiltMode);
        }
        let quilt = match (self.mode, self.quilt) {
            (Mode::Quilt, q) => Some(q.unwrap_or_default()),
            _ => None,
        };
        nephele_limits::check_stream_size(self.width, self.height)
            .and_then(|()| nephele_limits::check_fps(self.fps))
            .and_then(|()| match quilt {
                Some(q) => nephele_limits::check_quilt(q.cols, q.rows, q.cone_deg, self.width, self.height),
                None => Ok(()),
            })
            .map_err(JoinError::Limit)
    }

    /// Pixels per second this join asks for at full resolution.
    pub fn pixel_rate(&self) -> f64 {
        f64::from(self.width) * f64::from(self.height) * f64::from(self.fps)
    }
}

/// The rules of [`JoinSpec::check`] as numbers, for clients that check a join before sending
/// it (the pages fetch them from `GET /limits`; `web/join.js` applies them with the same
/// words). Built from `nephele_limits`, never kept by hand.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JoinLimits {
    pub modes: Vec<Mode>,
    pub name_max_chars: usize,
    pub min_fps: u32,
    pub max_fps: u32,
    pub max_long_edge_px: u32,
    pub max_short_edge_px: u32,
    pub max_quilt_views: u32,
    pub max_quilt_cone_deg: f32,
    pub default_quilt: QuiltSpec,
}

impl JoinLimits {
    /// The limits this build enforces.
    pub fn current() -> Self {
        Self {
            modes: vec![Mode::Viewer, Mode::Ar, Mode::Vr, Mode::Quilt],
            name_max_chars: 64,
            min_fps: nephele_limits::MIN_FPS,
            max_fps: nephele_limits::MAX_FPS,
            max_long_edge_px: nephele_limits::MAX_STREAM_LONG_EDGE_PX,
            max_short_edge_px: nephele_limits::MAX_STREAM_SHORT_EDGE_PX,
            max_quilt_views: nephele_limits::MAX_QUILT_VIEWS,
            max_quilt_cone_deg: nephele_limits::MAX_QUILT_CONE_DEG,
            default_quilt: QuiltSpec::default(),
        }
    }
}

/// Any message sent *to* signaling, by a client or by a master.
///
/// The hub checks that each message suits the sender's role.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ToSignal {
    /// Client: ask for a session on a master with room.
    Join {
        /// What the client asks for ([`JoinSpec`]: scene, mode, size, rate, quilt).
        #[serde(flatten)]
        spec: JoinSpec,
        /// Shared secret; required when signaling is configured with a token.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        token: Option<String>,
    },
    /// Client: the WebRTC offer for its session (after `joined`).
    Offer {
        /// SDP of the client's offer.
        sdp: String,
    },
    /// Client or master: one trickled ICE candidate.
    Ice {
        /// Master only: the session the candidate belongs to. Clients omit it.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        session: Option<String>,
        /// The `RTCIceCandidateInit` JSON as the browser gives it
        /// (`{"candidate":..., "sdpMid":..., "sdpMLineIndex":...}`), relayed verbatim.
        candidate: Value,
    },
    /// Client: end its session; the connection may `join` again.
    Leave {},
    /// Master: offer rendering capacity.
    Register {
        /// Human-readable master name: 1..=64 characters from `[A-Za-z0-9_-]`.
        name: String,
        /// Maximum number of concurrent sessions this master accepts.
        capacity: u32,
        /// The scenes this master renders; joins for other scenes never reach it.
        scenes: Vec<String>,
        /// Shared secret; required when signaling is configured with a token.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        token: Option<String>,
    },
    /// Master: liveness, its authoritative count of live sessions and the room it has left.
    Heartbeat {
        /// Sessions the master is currently serving.
        sessions: u32,
        /// Predicted rays per second the farm can still render after serving every admitted
        /// user at its lowest render scale (NEPHELE Algorithm 1's capacity, measured online).
        #[serde(default)]
        free_rays_per_s: f64,
        /// Some admitted user is behind its frame rate: the master refuses new joins.
        #[serde(default)]
        saturated: bool,
    },
    /// Master: the WebRTC answer to a client's offer.
    Answer {
        /// Session id from the `join` the master received.
        session: String,
        /// SDP of the master's answer.
        sdp: String,
    },
    /// Master: the session's video connected (it no longer counts as a pending join of its
    /// client's address).
    Connected {
        /// Session id from the `join`.
        session: String,
    },
    /// Master: refuse a session (e.g. unknown scene); the client gets `error rejected`.
    Reject {
        /// Session id being refused.
        session: String,
        /// Why, shown to the user.
        reason: String,
    },
    /// Master: end a running session; the client gets `ended`.
    End {
        /// Session id being ended.
        session: String,
        /// Why, shown to the user.
        reason: String,
    },
}

/// Messages signaling sends to a client.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ToClient {
    /// The join was accepted; the client should now send its `offer`.
    Joined {
        /// Session id assigned by signaling.
        session: String,
        /// Id of the master serving the session.
        master: String,
        /// STUN and TURN servers for the client's peer connection (TURN with credentials
        /// for this session); absent when the deployment has none.
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        ice_servers: Vec<IceServer>,
    },
    /// The master's WebRTC answer.
    Answer {
        /// SDP of the master's answer.
        sdp: String,
    },
    /// One ICE candidate from the master (`RTCIceCandidateInit` JSON).
    Ice {
        /// Candidate, relayed verbatim.
        candidate: Value,
    },
    /// A request failed, or the session was lost; see [`ErrorCode`].
    Error {
        /// Machine-readable reason.
        code: ErrorCode,
        /// Human-readable explanation.
        message: String,
    },
    /// The master ended the session; the client may `join` again.
    Ended {
        /// Why, from the master.
        reason: String,
    },
}

/// Messages signaling sends to a master.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ToMaster {
    /// Registration accepted.
    Registered {
        /// Id assigned to this master: its name, made unique if already taken.
        master: String,
    },
    /// A client was paired with this master; expect its `offer` next.
    Join {
        /// Session id; quote it in every message about this session.
        session: String,
        /// The join as checked by signaling, with the quilt default filled in.
        #[serde(flatten)]
        spec: JoinSpec,
    },
    /// The client's WebRTC offer.
    Offer {
        /// Session id.
        session: String,
        /// SDP of the client's offer.
        sdp: String,
    },
    /// One ICE candidate from the client (`RTCIceCandidateInit` JSON).
    Ice {
        /// Session id.
        session: String,
        /// Candidate, relayed verbatim.
        candidate: Value,
    },
    /// The client left or disconnected; tear the session down.
    Leave {
        /// Session id.
        session: String,
    },
    /// A request from the master failed; see [`ErrorCode`].
    Error {
        /// Machine-readable reason.
        code: ErrorCode,
        /// Human-readable explanation.
        message: String,
    },
}

/// Machine-readable error reasons, sent as snake_case strings.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// Not valid JSON, or not a known message.
    BadMessage,
    /// Message longer than the configured limit.
    TooLarge,
    /// Missing or wrong token; the connection is closed.
    Unauthorized,
    /// No master has room for another session.
    NoCapacity,
    /// Well-formed but unacceptable (absurd size, bad scene name, already joined...).
    BadRequest,
    /// The session's master disconnected or stopped sending heartbeats.
    MasterLost,
    /// No registered master serves the requested scene.
    UnknownScene,
    /// The master refused the session.
    Rejected,
    /// A message that the sender's role may not send.
    WrongRole,
    /// A session message before `join` (or a master message before `register`).
    NotJoined,
    /// Too many messages too fast; the connection is closed.
    RateLimited,
}

impl ErrorCode {
    /// The code as it travels (snake_case), also the `code` label of refusal metrics.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::BadMessage => "bad_message",
            Self::TooLarge => "too_large",
            Self::Unauthorized => "unauthorized",
            Self::NoCapacity => "no_capacity",
            Self::BadRequest => "bad_request",
            Self::MasterLost => "master_lost",
            Self::UnknownScene => "unknown_scene",
            Self::Rejected => "rejected",
            Self::WrongRole => "wrong_role",
            Self::NotJoined => "not_joined",
            Self::RateLimited => "rate_limited",
        }
    }
}

/// A message to either kind of peer; serializes exactly like the inner message.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(untagged)]
pub enum ToPeer {
    /// To a client (or to a connection without a role yet).
    Client(ToClient),
    /// To a master.
    Master(ToMaster),
}

impl ToPeer {
    /// The JSON text frame for this message.
    pub fn to_json(&self) -> String {
        // Serializing these plain enums of strings, numbers and `Value` cannot fail.
        serde_json::to_string(self).expect("signaling messages always serialize")
    }
}
