//! Every limit of the system, defined once. Signaling checks a `join` against them, the
//! master checks them again (a master may sit behind another signaling server), the encoder
//! and the renderer check the sizes they are given, and every error names the limit it quotes
//! from here. No dependencies, so every crate (renderer, signaling, server) can use it.
//!
//! Two frame limits, on purpose:
//! - a **stream** frame is what our H.264 encoder takes in one picture: OpenH264 encodes at
//!   most 3840×2160 landscape or 2160×3840 portrait (checked in `server/tests/encode.rs`),
//!   within H.264 level 5.1's 36 864 macroblocks per frame;
//! - a **render** image (offline `nephele render`, benchmarks, a tile of a quilt) can be
//!   larger: 8K UHD, 8192 per edge, which also bounds the GPU's per-dispatch buffers.

/// Longest edge of a streamed frame, in pixels.
pub const MAX_STREAM_LONG_EDGE_PX: u32 = 3840;
/// Shortest edge of a streamed frame may be at most this, in pixels.
pub const MAX_STREAM_SHORT_EDGE_PX: u32 = 2160;
/// Largest streamed frame, in pixels (3840×2160).
pub const MAX_STREAM_PIXELS: u64 = MAX_STREAM_LONG_EDGE_PX as u64 * MAX_STREAM_SHORT_EDGE_PX as u64;

/// Largest rendered image, in pixels (8K UHD).
pub const MAX_RENDER_PIXELS: u64 = 7680 * 4320;
/// Largest edge of a rendered image, in pixels.
pub const MAX_RENDER_EDGE_PX: u32 = 8192;

/// Frame rates a client may ask for, frames per second.
pub const MIN_FPS: u32 = 1;
pub const MAX_FPS: u32 = 120;

/// Longest signaling message (one JSON text frame), bytes.
pub const MAX_SIGNAL_MESSAGE_BYTES: usize = 64 * 1024;
/// A master sends signaling a heartbeat this often, milliseconds…
pub const MASTER_HEARTBEAT_EVERY_MS: u64 = 1000;
/// …and signaling drops a master silent for this long (a stopped or cut-off master gets no
/// new joins after ~3 s, and its clients are told), milliseconds.
pub const MASTER_SILENCE_TIMEOUT_MS: u64 = 3000;

/// Signaling messages a client connection may send per second on average, and in one
/// burst (a session needs about 15: join, offer, ICE candidates, leave).
pub const CLIENT_SIGNAL_MESSAGES_PER_S: f64 = 20.0;
pub const CLIENT_SIGNAL_MESSAGE_BURST: f64 = 40.0;
/// Longest message on the pose data channel, bytes; longer ones are refused unread.
pub const MAX_POSE_MESSAGE_BYTES: usize = 4096;

/// Most grid vertices of one frame's depth message (every view together): the grid step
/// grows with the frame so that a 4K frame's depth stays one data-channel message.
pub const MAX_DEPTH_VERTICES: usize = 16_384;
/// Grid step of a depth message, pixels, unless the frame is too large for it (the step
/// then doubles). 16 px: a quarter of 8 px's bytes, and no PSNR lost on the head trace (`nephele
/// bench glass`, docs/benchmarks.md).
pub const DEPTH_STRIDE_PX: u32 = 16;
/// Largest grid step a depth message may declare, pixels.
pub const MAX_DEPTH_STRIDE_PX: u32 = 256;
/// Longest a client may ask the master to predict its pose ahead, ms.
pub const MAX_PREDICTION_MS: f64 = 500.0;

/// Most views one pose message may carry (a headset's two eyes, a CAVE's walls).
pub const MAX_VIEWS_PER_POSE: usize = 8;
/// Most views of a Looking Glass quilt (the largest common layout is 11×6 = 66).
pub const MAX_QUILT_VIEWS: u32 = 100;
/// Widest quilt view cone, degrees.
pub const MAX_QUILT_CONE_DEG: f32 = 120.0;

/// Why a stream size, frame rate or quilt layout was refused; the text names the limit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LimitError {
    StreamSize { width: u32, height: u32 },
    Fps { fps: u32 },
    QuiltViews { cols: u32, rows: u32 },
    QuiltTiles { cols: u32, rows: u32, width: u32, height: u32 },
    QuiltCone { cone_deg: f32 },
}

impl std::fmt::Display for LimitError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Self::StreamSize { width, height } => write!(
                f,
                "frame size {width}x{height} is outside the stream limits: at least 1x1, at most \
                 {MAX_STREAM_LONG_EDGE_PX}x{MAX_STREAM_SHORT_EDGE_PX} (or {MAX_STREAM_SHORT_EDGE_PX}x{MAX_STREAM_LONG_EDGE_PX} portrait)"
            ),
            Self::Fps { fps } => write!(f, "fps {fps} is outside {MIN_FPS}..={MAX_FPS}"),
            Self::QuiltViews { cols, rows } => write!(f, "a {cols}x{rows} quilt is outside 1..={MAX_QUILT_VIEWS} views"),
            Self::QuiltTiles { cols, rows, width, height } => {
                write!(f, "a {width}x{height} frame does not split into {cols}x{rows} equal tiles (each edge must divide evenly)")
            }
            Self::QuiltCone { cone_deg } => write!(f, "quilt view cone {cone_deg} degrees is outside (0, {MAX_QUILT_CONE_DEG}]"),
        }
    }
}

impl std::error::Error for LimitError {}

/// Checks a streamed frame size: both edges at least 1, the long one at most
/// [`MAX_STREAM_LONG_EDGE_PX`], the short one at most [`MAX_STREAM_SHORT_EDGE_PX`].
pub fn check_stream_size(width: u32, height: u32) -> Result<(), LimitError> {
    let (long, short) = (width.max(height), width.min(height));
    if short >= 1 && long <= MAX_STREAM_LONG_EDGE_PX && short <= MAX_STREAM_SHORT_EDGE_PX {
        Ok(())
    } else {
        Err(LimitError::StreamSize { width, height })
    }
}

/// Checks a requested frame rate against [`MIN_FPS`]..=[`MAX_FPS`].
pub fn check_fps(fps: u32) -> Result<(), LimitError> {
    if (MIN_FPS..=MAX_FPS).contains(&fps) { Ok(()) } else { Err(LimitError::Fps { fps }) }
}

/// Checks a quilt layout for a frame: `cols × rows` views within [`MAX_QUILT_VIEWS`], tiles
/// of equal whole pixels, a view cone in (0, [`MAX_QUILT_CONE_DEG`]].
pub fn check_quilt(cols: u32, rows: u32, cone_deg: f32, width: u32, height: u32) -> Result<(), LimitError> {
    if cols == 0 || rows == 0 || u64::from(cols) * u64::from(rows) > u64::from(MAX_QUILT_VIEWS) {
        return Err(LimitError::QuiltViews { cols, rows });
    }
    if width % cols != 0 || height % rows != 0 || width < cols || height < rows {
        return Err(LimitError::QuiltTiles { cols, rows, width, height });
    }
    if !(cone_deg > 0.0 && cone_deg <= MAX_QUILT_CONE_DEG) {
        return Err(LimitError::QuiltCone { cone_deg });
    }
    Ok(())
}

/// Whether a rendered image size is within [`MAX_RENDER_EDGE_PX`] and [`MAX_RENDER_PIXELS`].
pub fn render_size_ok(width: u32, height: u32) -> bool {
    (1..=MAX_RENDER_EDGE_PX).contains(&width)
        && (1..=MAX_RENDER_EDGE_PX).contains(&height)
        && u64::from(width) * u64::from(height) <= MAX_RENDER_PIXELS
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stream_limits_hold_at_their_edges() {
        assert!(check_stream_size(3840, 2160).is_ok());
        assert!(check_stream_size(2160, 3840).is_ok());
        assert!(check_stream_size(3840, 1).is_ok());
        assert!(check_stream_size(1, 1).is_ok());
        for (w, h) in [(0, 1), (1, 0), (3841, 1), (7680, 1080), (3840, 2161), (2161, 2161), (u32::MAX, u32::MAX)] {
            let e = check_stream_size(w, h).unwrap_err();
            assert!(e.to_string().contains(&format!("{w}x{h}")) && e.to_string().contains("3840x2160"), "{e}");
        }
        assert!(check_fps(1).is_ok() && check_fps(120).is_ok());
        assert!(check_fps(0).is_err() && check_fps(1_000_000).unwrap_err().to_string().contains("1..=120"));
        assert!(render_size_ok(7680, 4320) && render_size_ok(8192, 1) && !render_size_ok(8193, 1) && !render_size_ok(8192, 8192));
    }

    #[test]
    fn quilt_layouts_are_checked() {
        assert!(check_quilt(5, 9, 40.0, 1200, 2880).is_ok());
        assert!(check_quilt(11, 6, 35.0, 11, 6).is_ok());
        for (cols, rows, cone, w, h) in [
            (0, 9, 40.0, 1200, 2880),
            (10, 11, 40.0, 1100, 1100),
            (u32::MAX, 2, 40.0, 100, 100),
            (5, 9, 40.0, 1201, 2880),
            (5, 9, 40.0, 4, 2880),
            (5, 9, 0.0, 1200, 2880),
            (5, 9, f32::NAN, 1200, 2880),
            (5, 9, 121.0, 1200, 2880),
        ] {
            let e = check_quilt(cols, rows, cone, w, h).unwrap_err();
            assert!(!e.to_string().is_empty());
        }
    }
}

/// Render tasks queued on one in-process render worker (beyond the one it is rendering): the
/// core hands a worker a task only when it has a free slot, so this is a backstop.
pub const MAX_QUEUED_TASKS_PER_WORKER: usize = 2;

/// What one HTTP/websocket server (signaling and the pages) allows its connections. Every
/// field has a flag on `nephele serve` and `nephele signal` (`--max-connections`, …); the
/// defaults hold on a 2-core machine with a 1024 file-descriptor limit: 5,000 hostile
/// connections cost the server at most `max_connections` sockets and buffers, and a
/// well-behaved viewer keeps streaming.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConnLimits {
    /// Open connections at once. At the cap a newcomer takes the place of the oldest
    /// connection that holds no role (not a master, not a client in a session), so idle
    /// sockets cannot lock anyone out; when every one holds a role, newcomers are closed as
    /// they arrive. Below the usual 1024 file-descriptor limit, which the media sockets and
    /// assets share.
    pub max_connections: usize,
    /// Open connections at once from one IP address.
    pub max_connections_per_address: usize,
    /// An HTTP request's headers must arrive within this (also how long an idle keep-alive
    /// connection is kept), milliseconds.
    pub header_timeout_ms: u64,
    /// A websocket must send its first message (`join` or `register`) within this,
    /// milliseconds.
    pub hello_timeout_ms: u64,
    /// A websocket silent for this long (no message, no answer to our pings, sent every
    /// quarter of it) is closed, milliseconds.
    pub idle_timeout_ms: u64,
    /// Sessions from one IP address that are paired but whose video has not connected yet;
    /// more joins get `rate_limited` (a join that never connects held a slot for 30 s).
    pub max_pending_joins_per_address: usize,
    /// New sessions from one IP address: a burst of this many…
    pub join_burst_per_address: u32,
    /// …then this many per minute (a token bucket; refused joins cost nothing). A join →
    /// pose → leave loop is throttled to it, not only the joins still connecting.
    pub joins_per_address_per_minute: u32,
    /// Bytes a websocket reads into (and buffers for writing) at a time, each way; messages
    /// themselves are bounded by [`MAX_SIGNAL_MESSAGE_BYTES`].
    pub ws_buffer_bytes: usize,
}

impl Default for ConnLimits {
    fn default() -> Self {
        Self {
            max_connections: 768,
            max_connections_per_address: 64,
            header_timeout_ms: 10_000,
            hello_timeout_ms: 10_000,
            idle_timeout_ms: 60_000,
            // One address may be a classroom or an office behind one NAT: 30 people opening
            // the page within seconds all get in. A flood from one address is still held to
            // 40 and then one a second (and its pending joins time out after 30 s).
            max_pending_joins_per_address: 32,
            join_burst_per_address: 40,
            joins_per_address_per_minute: 60,
            ws_buffer_bytes: 16 * 1024,
        }
    }
}
