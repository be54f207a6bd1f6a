//! Every limit of the system, defined once. Signaling checks a `join` against them, the
//! master checks them again (a master may sit behind another signaling server), the encoder
//! and the renderer check the sizes they are given, and every error names the limit it quotes
//! from here. No dependencies, so every crate (renderer, signaling, server) can use it.
//!
//! Two frame limits, on purpose:
//! - a **stream** frame is what one H.264 picture can carry: constrained baseline at level
//!   5.1 allows 36 864 macroblocks per frame, so 3840×2160 (32 400) fits and 4096 per edge is
//!   the most either side may be;
//! - a **render** image (offline `nephele render`, benchmarks, a tile of a quilt) can be
//!   larger: 8K UHD, 8192 per edge, which also bounds the GPU's per-dispatch buffers.

/// Largest streamed frame, in pixels (3840×2160; H.264 level 5.1 holds 36 864 macroblocks).
pub const MAX_STREAM_PIXELS: u64 = 3840 * 2160;
/// Largest edge of a streamed frame, in pixels.
pub const MAX_STREAM_EDGE_PX: u32 = 4096;

/// Largest rendered image, in pixels (8K UHD).
pub const MAX_RENDER_PIXELS: u64 = 7680 * 4320;
/// Largest edge of a rendered image, in pixels.
pub const MAX_RENDER_EDGE_PX: u32 = 8192;

/// Frame rates a client may ask for, frames per second.
pub const MIN_FPS: u32 = 1;
pub const MAX_FPS: u32 = 120;

/// Longest signaling message (one JSON text frame), bytes.
pub const MAX_SIGNAL_MESSAGE_BYTES: usize = 64 * 1024;
/// Longest message on the pose data channel, bytes; longer ones are refused unread.
pub const MAX_POSE_MESSAGE_BYTES: usize = 4096;

/// Why a stream size or frame rate was refused; the text names the limit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LimitError {
    StreamSize { width: u32, height: u32 },
    Fps { fps: u32 },
}

impl std::fmt::Display for LimitError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Self::StreamSize { width, height } => write!(
                f,
                "frame size {width}x{height} is outside the stream limits: 1..={MAX_STREAM_EDGE_PX} pixels per edge and at most \
                 {MAX_STREAM_PIXELS} pixels (3840x2160)"
            ),
            Self::Fps { fps } => write!(f, "fps {fps} is outside {MIN_FPS}..={MAX_FPS}"),
        }
    }
}

impl std::error::Error for LimitError {}

/// Checks a streamed frame size against [`MAX_STREAM_EDGE_PX`] and [`MAX_STREAM_PIXELS`].
pub fn check_stream_size(width: u32, height: u32) -> Result<(), LimitError> {
    let edge_ok = (1..=MAX_STREAM_EDGE_PX).contains(&width) && (1..=MAX_STREAM_EDGE_PX).contains(&height);
    if edge_ok && u64::from(width) * u64::from(height) <= MAX_STREAM_PIXELS {
        Ok(())
    } else {
        Err(LimitError::StreamSize { width, height })
    }
}

/// Checks a requested frame rate against [`MIN_FPS`]..=[`MAX_FPS`].
pub fn check_fps(fps: u32) -> Result<(), LimitError> {
    if (MIN_FPS..=MAX_FPS).contains(&fps) { Ok(()) } else { Err(LimitError::Fps { fps }) }
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
        assert!(check_stream_size(4096, 2025).is_ok());
        assert!(check_stream_size(1, 1).is_ok());
        for (w, h) in [(0, 1), (1, 0), (4097, 1), (7680, 1080), (3840, 2161), (u32::MAX, u32::MAX)] {
            let e = check_stream_size(w, h).unwrap_err();
            assert!(e.to_string().contains(&format!("{w}x{h}")) && e.to_string().contains("4096"), "{e}");
        }
        assert!(check_fps(1).is_ok() && check_fps(120).is_ok());
        assert!(check_fps(0).is_err() && check_fps(1_000_000).unwrap_err().to_string().contains("1..=120"));
        assert!(render_size_ok(7680, 4320) && render_size_ok(8192, 1) && !render_size_ok(8193, 1) && !render_size_ok(8192, 8192));
    }
}
