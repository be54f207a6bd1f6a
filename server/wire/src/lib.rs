//! The protocol a streaming client and a master share, and nothing of either side's
//! internals: the `pose` data channel's format (docs/architecture.md §5 "Pose channel") here,
//! the pose-sequence SEI in [`sei`], each mode's background colour. The master's core
//! (`nephele-core`), its edge (`nephele-master`) and the headless client (`nephele-client`)
//! all build on this crate; the WebRTC set-up they share is `nephele-rtc`.
//!
//! Client → master: one binary pose message every 20 ms, little-endian, 104 bytes, or 168
//! with an AR plane anchor:
//!
//! | bytes     | field                                                              |
//! |-----------|--------------------------------------------------------------------|
//! | 0..4      | ASCII `NPO1` (format and version)                                  |
//! | 4..8      | `u32` sequence number, +1 per message                              |
//! | 8..16     | `f64` client timestamp, ms on the client's own clock               |
//! | 16..80    | `f32`×16 world_from_camera, column-major, OpenGL camera (looks −z) |
//! | 80..96    | `f32`×4 fx, fy, cx, cy in pixels                                   |
//! | 96..104   | `u32`×2 viewport width, height in pixels                           |
//! | 104..168  | optional `f32`×16 world_from_anchor (rotation, translation, scale) |
//! | last 72   | optional prediction: `f64` horizon ms, `f32`×16 the present world_from_camera |
//!
//! (so 104, 168, 176 or 240 bytes). With a prediction, the camera at 16..80 is the one the
//! client predicts for the moment this frame will be shown, `horizon` ms after
//! `t_client_ms`, and the master renders it; the present camera is checked (rigid, at most
//! [`MAX_PREDICTED_TURN_DEG`] from the predicted one, horizon within
//! `nephele_limits::MAX_PREDICTION_MS`) and the horizon echoed in the frame info.
//!
//! or, for several views in one frame (a headset's two eyes), version 2: 32 + 144·n bytes,
//! or 64 more with an anchor:
//!
//! | bytes     | field                                                              |
//! |-----------|--------------------------------------------------------------------|
//! | 0..4      | ASCII `NPO2`                                                       |
//! | 4..8      | `u32` sequence number                                              |
//! | 8..16     | `f64` client timestamp, ms                                         |
//! | 16..24    | `u32`×2 frame width, height (the session's size)                   |
//! | 24..28    | `u32` view count n, 1..=[`MAX_VIEWS_PER_POSE`]                     |
//! | 28..32    | `u32` flags: bit 0 = an anchor follows the views; bit 1 = a prediction follows; others 0 |
//! | per view  | `f32`×16 world_from_camera; `f32`×16 clip_from_camera (the GL/WebXR projection, column-major: perspective, maybe asymmetric, no skew); `u32`×4 viewport x, y, width, height in frame pixels, origin top-left |
//! | then 64   | optional `f32`×16 world_from_anchor                                |
//! | last 8+64n| optional prediction: `f64` horizon ms, then per view `f32`×16 its present world_from_camera (the views' cameras are then the predicted ones) |
//!
//! Viewports lie inside the frame and do not overlap; each view is rendered at its
//! viewport's size (projection → pinhole: `nephele_renderer::views`). In `quilt` mode the
//! client sends version 1 for the centre camera at the tile size and the master expands it
//! into the quilt's views ([`FrameLayout::Quilt`]).
//!
//! Master → client: JSON text messages ([`ToViewer`]): the session description once, frame
//! info for every encoded frame (so latency is measured on the client's clock by echoing
//! `t_client_ms`), and refusals with a reason.

pub mod depth;
pub mod sei;

use glam::{DMat3, DMat4, DQuat, DVec3, Mat4, Vec3};
use nephele_limits::MAX_VIEWS_PER_POSE;
use nephele_renderer::{
    Instance, Intrinsics, View,
    camera::rotation_deviation,
    views::{QuiltLayout, focal_distance, intrinsics_from_projection},
};
use serde::{Deserialize, Serialize};

/// Background behind the object in viewer mode (linear RGB).
pub const VIEWER_BACKGROUND: Vec3 = Vec3::ONE;
/// AR mode renders over pure green, keyed out by the client.
pub const AR_BACKGROUND: Vec3 = Vec3::new(0.0, 1.0, 0.0);

/// The background a mode renders over.
pub fn background_of(mode: nephele_protocol::Mode) -> Vec3 {
    if mode == nephele_protocol::Mode::Ar { AR_BACKGROUND } else { VIEWER_BACKGROUND }
}

/// Magic and version at the start of every pose message.
pub const POSE_MAGIC: &[u8; 4] = b"NPO1";
/// Length of a pose message without an anchor.
pub const POSE_LEN: usize = 104;
/// Length of a pose message with an AR plane anchor.
pub const POSE_WITH_ANCHOR_LEN: usize = 168;
/// Magic and version of a multi-view pose message.
pub const POSE_V2_MAGIC: &[u8; 4] = b"NPO2";
/// Header of a multi-view pose message, bytes.
pub const POSE_V2_HEADER_LEN: usize = 32;
/// One view of a multi-view pose message, bytes.
pub const POSE_V2_VIEW_LEN: usize = 144;

/// Bytes a prediction adds to an `NPO1` message.
pub const POSE_PREDICTION_LEN: usize = 72;
/// Largest turn a master accepts between a client's present and predicted camera, degrees.
pub const MAX_PREDICTED_TURN_DEG: f64 = 90.0;

/// One decoded pose message. Not yet validated as a camera: see [`PoseMessage::view`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseMessage {
    pub seq: u32,
    pub t_client_ms: f64,
    /// The camera to render: the predicted one when `predicted` is there.
    pub world_from_camera: Mat4,
    pub intrinsics: Intrinsics,
    pub world_from_anchor: Option<Mat4>,
    pub predicted: Option<Predicted>,
}

/// What a predicting client adds to its pose: how far ahead it predicted, and where the
/// camera is now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Predicted {
    pub horizon_ms: f64,
    pub present_world_from_camera: Mat4,
}

/// Why a pose message was refused; sent back to the client as `bad_pose`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PoseRejection {
    #[error("pose message is {len} bytes; expected {expected}")]
    Length { len: usize, expected: String },
    #[error("pose message does not start with \"NPO1\" or \"NPO2\"")]
    Magic,
    #[error("pose message has {count} views; 1..={MAX_VIEWS_PER_POSE} are allowed")]
    ViewCount { count: u64 },
    #[error("pose message flags {flags:#x} are not known (only bit 0, anchor, and bit 1, prediction, are)")]
    Flags { flags: u32 },
    #[error("view {index}: viewport {x},{y} {width}x{height} {why}")]
    ViewportRect { index: usize, x: u32, y: u32, width: u32, height: u32, why: String },
    #[error("view {index}: projection: {why}")]
    Projection { index: usize, why: String },
    #[error("quilt mode takes one centre camera (an NPO1 message at the tile size {tile_width}x{tile_height}), not {views} views")]
    QuiltCamera { views: usize, tile_width: u32, tile_height: u32 },
    #[error("pose timestamp is not finite")]
    Timestamp,
    #[error("viewport {width}x{height} differs from the session's {session_width}x{session_height}")]
    Viewport { width: u32, height: u32, session_width: u32, session_height: u32 },
    #[error("camera: {0}")]
    Camera(String),
    #[error("plane anchor: {0}")]
    Anchor(String),
    #[error("prediction: {0}")]
    Prediction(String),
}

impl PoseMessage {
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(POSE_WITH_ANCHOR_LEN);
        out.extend_from_slice(POSE_MAGIC);
        out.extend_from_slice(&self.seq.to_le_bytes());
        out.extend_from_slice(&self.t_client_ms.to_le_bytes());
        for v in self.world_from_camera.to_cols_array() {
            out.extend_from_slice(&v.to_le_bytes());
        }
        let k = &self.intrinsics;
        for v in [k.fx, k.fy, k.cx, k.cy] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&k.width.to_le_bytes());
        out.extend_from_slice(&k.height.to_le_bytes());
        if let Some(a) = self.world_from_anchor {
            for v in a.to_cols_array() {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        if let Some(p) = self.predicted {
            out.extend_from_slice(&p.horizon_ms.to_le_bytes());
            for v in p.present_world_from_camera.to_cols_array() {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        out
    }

    /// Parses the byte layout only (length, magic); values are checked by [`Self::view`].
    pub fn decode(bytes: &[u8]) -> Result<Self, PoseRejection> {
        let (anchor, predicted) = match bytes.len() {
            POSE_LEN => (false, false),
            POSE_WITH_ANCHOR_LEN => (true, false),
            n if n == POSE_LEN + POSE_PREDICTION_LEN => (false, true),
            n if n == POSE_WITH_ANCHOR_LEN + POSE_PREDICTION_LEN => (true, true),
            len => {
                let expected = format!("{POSE_LEN}, {POSE_WITH_ANCHOR_LEN}, {} or {} (with a prediction)", POSE_LEN + POSE_PREDICTION_LEN, POSE_WITH_ANCHOR_LEN + POSE_PREDICTION_LEN);
                return Err(PoseRejection::Length { len, expected });
            }
        };
        if &bytes[0..4] != POSE_MAGIC {
            return Err(PoseRejection::Magic);
        }
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let f32_at = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let mat_at = |o: usize| Mat4::from_cols_array(&std::array::from_fn(|i| f32_at(o + 4 * i)));
        Ok(Self {
            seq: u32_at(4),
            t_client_ms: f64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes")),
            world_from_camera: mat_at(16),
            intrinsics: Intrinsics {
                fx: f32_at(80),
                fy: f32_at(84),
                cx: f32_at(88),
                cy: f32_at(92),
                width: u32_at(96),
                height: u32_at(100),
            },
            world_from_anchor: anchor.then(|| mat_at(104)),
            predicted: predicted.then(|| {
                let at = if anchor { POSE_WITH_ANCHOR_LEN } else { POSE_LEN };
                Predicted { horizon_ms: f64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes")), present_world_from_camera: mat_at(at + 8) }
            }),
        })
    }

    /// The camera and asset placement this pose asks for, validated for a session of
    /// `session_size`. f32 on the wire: rotations are re-orthonormalised when they are
    /// within the renderer's rigidity tolerance, so a browser's float rounding passes.
    pub fn view(&self, session_size: (u32, u32)) -> Result<(View, Instance), PoseRejection> {
        if !self.t_client_ms.is_finite() {
            return Err(PoseRejection::Timestamp);
        }
        let k = self.intrinsics;
        if (k.width, k.height) != session_size {
            return Err(PoseRejection::Viewport {
                width: k.width,
                height: k.height,
                session_width: session_size.0,
                session_height: session_size.1,
            });
        }
        let view = checked_camera(self.world_from_camera, k)?;
        if let Some(p) = self.predicted {
            check_prediction(p.horizon_ms, p.present_world_from_camera, &view)?;
        }
        Ok((view, checked_anchor(self.world_from_anchor)?))
    }

    /// How far ahead the camera was predicted, ms (0 without a prediction).
    pub fn predicted_ms(&self) -> f64 {
        self.predicted.map_or(0.0, |p| p.horizon_ms)
    }
}

/// A prediction a master accepts: a horizon within the limit, a present camera that is a
/// camera, not further than [`MAX_PREDICTED_TURN_DEG`] from the predicted one.
fn check_prediction(horizon_ms: f64, present_world_from_camera: Mat4, predicted: &View) -> Result<(), PoseRejection> {
    let max = nephele_limits::MAX_PREDICTION_MS;
    if !horizon_ms.is_finite() || !(0.0..=max).contains(&horizon_ms) {
        return Err(PoseRejection::Prediction(format!("horizon {horizon_ms} ms is outside 0..={max} ms")));
    }
    let present = checked_camera(present_world_from_camera, predicted.intrinsics).map_err(|e| PoseRejection::Prediction(format!("present camera: {e}")))?;
    let (a, b) = (DQuat::from_mat4(&present.world_from_camera), DQuat::from_mat4(&predicted.world_from_camera));
    let turn = a.angle_between(b).to_degrees();
    if turn > MAX_PREDICTED_TURN_DEG {
        return Err(PoseRejection::Prediction(format!("the predicted camera turns {turn:.0}° from the present one; at most {MAX_PREDICTED_TURN_DEG}°")));
    }
    Ok(())
}


/// A rectangle of the streamed frame, pixels, origin top-left.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Viewport {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

impl Viewport {
    pub fn full(width: u32, height: u32) -> Self {
        Self { x: 0, y: 0, width, height }
    }

    fn overlaps(&self, o: &Viewport) -> bool {
        let (a0, a1) = (u64::from(self.x), u64::from(self.x) + u64::from(self.width));
        let (b0, b1) = (u64::from(o.x), u64::from(o.x) + u64::from(o.width));
        let (c0, c1) = (u64::from(self.y), u64::from(self.y) + u64::from(self.height));
        let (d0, d1) = (u64::from(o.y), u64::from(o.y) + u64::from(o.height));
        a0 < b1 && b0 < a1 && c0 < d1 && d0 < c1
    }
}

/// One view of a multi-view pose message, as sent.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseView {
    pub world_from_camera: Mat4,
    /// GL projection, column-major (WebXR's `projectionMatrix`).
    pub clip_from_camera: [f32; 16],
    pub viewport: Viewport,
}

/// A decoded `NPO2` message. Not yet validated: see [`check_pose`].
#[derive(Debug, Clone, PartialEq)]
pub struct MultiViewPose {
    pub seq: u32,
    pub t_client_ms: f64,
    pub frame_width: u32,
    pub frame_height: u32,
    pub views: Vec<PoseView>,
    pub world_from_anchor: Option<Mat4>,
    /// With a prediction: the horizon, ms, and each view's present camera (one per view).
    pub predicted: Option<(f64, Vec<Mat4>)>,
}

impl MultiViewPose {
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(POSE_V2_HEADER_LEN + POSE_V2_VIEW_LEN * self.views.len() + 64);
        out.extend_from_slice(POSE_V2_MAGIC);
        out.extend_from_slice(&self.seq.to_le_bytes());
        out.extend_from_slice(&self.t_client_ms.to_le_bytes());
        let flags = u32::from(self.world_from_anchor.is_some()) | (u32::from(self.predicted.is_some()) << 1);
        for v in [self.frame_width, self.frame_height, self.views.len() as u32, flags] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for v in &self.views {
            for x in v.world_from_camera.to_cols_array().into_iter().chain(v.clip_from_camera) {
                out.extend_from_slice(&x.to_le_bytes());
            }
            for x in [v.viewport.x, v.viewport.y, v.viewport.width, v.viewport.height] {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        if let Some(a) = self.world_from_anchor {
            for v in a.to_cols_array() {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        if let Some((horizon_ms, present)) = &self.predicted {
            out.extend_from_slice(&horizon_ms.to_le_bytes());
            for v in present.iter().flat_map(|m| m.to_cols_array()) {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        out
    }

    /// Parses the byte layout only (magic, count, flags, length).
    pub fn decode(bytes: &[u8]) -> Result<Self, PoseRejection> {
        if bytes.len() < POSE_V2_HEADER_LEN {
            return Err(PoseRejection::Length { len: bytes.len(), expected: format!("at least {POSE_V2_HEADER_LEN} for NPO2") });
        }
        if &bytes[0..4] != POSE_V2_MAGIC {
            return Err(PoseRejection::Magic);
        }
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let f32_at = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let count = u32_at(24);
        if count == 0 || count as usize > MAX_VIEWS_PER_POSE {
            return Err(PoseRejection::ViewCount { count: u64::from(count) });
        }
        let flags = u32_at(28);
        if flags & !3 != 0 {
            return Err(PoseRejection::Flags { flags });
        }
        let n = count as usize;
        let prediction_len = 8 + 64 * n;
        let expected = POSE_V2_HEADER_LEN + POSE_V2_VIEW_LEN * n + if flags & 1 == 1 { 64 } else { 0 } + if flags & 2 == 2 { prediction_len } else { 0 };
        if bytes.len() != expected {
            return Err(PoseRejection::Length { len: bytes.len(), expected: format!("{expected} for NPO2 with {n} views (flags {flags})") });
        }
        let mat_at = |o: usize| Mat4::from_cols_array(&std::array::from_fn(|i| f32_at(o + 4 * i)));
        let views = (0..n)
            .map(|i| {
                let o = POSE_V2_HEADER_LEN + POSE_V2_VIEW_LEN * i;
                PoseView {
                    world_from_camera: mat_at(o),
                    clip_from_camera: std::array::from_fn(|j| f32_at(o + 64 + 4 * j)),
                    viewport: Viewport { x: u32_at(o + 128), y: u32_at(o + 132), width: u32_at(o + 136), height: u32_at(o + 140) },
                }
            })
            .collect();
        let anchor_at = POSE_V2_HEADER_LEN + POSE_V2_VIEW_LEN * n;
        Ok(Self {
            seq: u32_at(4),
            t_client_ms: f64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes")),
            frame_width: u32_at(16),
            frame_height: u32_at(20),
            views,
            world_from_anchor: (flags & 1 == 1).then(|| mat_at(anchor_at)),
            predicted: (flags & 2 == 2).then(|| {
                let at = anchor_at + if flags & 1 == 1 { 64 } else { 0 };
                let horizon = f64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes"));
                (horizon, (0..n).map(|i| mat_at(at + 8 + 64 * i)).collect())
            }),
        })
    }
}

/// How a session's frame is made of views.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FrameLayout {
    /// One camera filling the frame (`NPO1`) or the views of an `NPO2` message.
    Views { width: u32, height: u32 },
    /// A Looking Glass quilt: the client's one centre camera (`NPO1` at the tile size)
    /// becomes `cols × rows` views, with the focal plane through `focal_target`.
    Quilt { width: u32, height: u32, layout: QuiltLayout, focal_target: DVec3, min_focal: f64 },
}

impl FrameLayout {
    pub fn size(&self) -> (u32, u32) {
        match *self {
            Self::Views { width, height } | Self::Quilt { width, height, .. } => (width, height),
        }
    }
}

/// One camera of a frame, validated: where it is, its lens at its viewport's size, and
/// where its pixels go in the frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameView {
    pub view: View,
    pub viewport: Viewport,
}

/// A pose message of either version, validated for a session's frame layout.
#[derive(Debug, Clone, PartialEq)]
pub struct CheckedPose {
    pub seq: u32,
    pub t_client_ms: f64,
    /// How far ahead the client predicted the camera, ms (0: the present camera).
    pub predicted_ms: f64,
    pub views: Vec<FrameView>,
    pub instance: Instance,
}

/// Decodes and validates a pose message (`NPO1` or `NPO2`) for a session laid out as
/// `layout`: rigid finite cameras, sane lenses, viewports inside the frame and apart.
pub fn check_pose(bytes: &[u8], layout: &FrameLayout) -> Result<CheckedPose, PoseRejection> {
    let (width, height) = layout.size();
    if bytes.len() >= 4 && &bytes[0..4] == POSE_V2_MAGIC {
        let m = MultiViewPose::decode(bytes)?;
        if let FrameLayout::Quilt { layout: q, .. } = layout {
            return Err(PoseRejection::QuiltCamera { views: m.views.len(), tile_width: width / q.cols, tile_height: height / q.rows });
        }
        if !m.t_client_ms.is_finite() {
            return Err(PoseRejection::Timestamp);
        }
        if (m.frame_width, m.frame_height) != (width, height) {
            return Err(PoseRejection::Viewport { width: m.frame_width, height: m.frame_height, session_width: width, session_height: height });
        }
        let mut views: Vec<FrameView> = Vec::with_capacity(m.views.len());
        for (index, v) in m.views.iter().enumerate() {
            let r = v.viewport;
            let rect = |why: &str| PoseRejection::ViewportRect { index, x: r.x, y: r.y, width: r.width, height: r.height, why: why.into() };
            if r.width == 0 || r.height == 0 {
                return Err(rect("is empty"));
            }
            if u64::from(r.x) + u64::from(r.width) > u64::from(width) || u64::from(r.y) + u64::from(r.height) > u64::from(height) {
                return Err(rect(&format!("is not inside the {width}x{height} frame")));
            }
            if let Some(j) = views.iter().position(|o| o.viewport.overlaps(&r)) {
                return Err(rect(&format!("overlaps view {j}'s")));
            }
            let intrinsics = intrinsics_from_projection(&v.clip_from_camera, r.width, r.height).map_err(|e| PoseRejection::Projection { index, why: e.to_string() })?;
            let view = checked_camera(v.world_from_camera, intrinsics).map_err(|e| match e {
                PoseRejection::Camera(why) => PoseRejection::Camera(format!("view {index}: {why}")),
                other => other,
            })?;
            views.push(FrameView { view, viewport: r });
        }
        let instance = checked_anchor(m.world_from_anchor)?;
        let mut predicted_ms = 0.0;
        if let Some((horizon_ms, present)) = &m.predicted {
            for (index, (p, v)) in present.iter().zip(&views).enumerate() {
                check_prediction(*horizon_ms, *p, &v.view).map_err(|e| match e {
                    PoseRejection::Prediction(why) => PoseRejection::Prediction(format!("view {index}: {why}")),
                    other => other,
                })?;
            }
            predicted_ms = *horizon_ms;
        }
        return Ok(CheckedPose { seq: m.seq, t_client_ms: m.t_client_ms, predicted_ms, views, instance });
    }
    let m = PoseMessage::decode(bytes)?;
    match *layout {
        FrameLayout::Views { .. } => {
            let (view, instance) = m.view((width, height))?;
            Ok(CheckedPose { seq: m.seq, t_client_ms: m.t_client_ms, predicted_ms: m.predicted_ms(), views: vec![FrameView { view, viewport: Viewport::full(width, height) }], instance })
        }
        FrameLayout::Quilt { layout: q, focal_target, min_focal, .. } => {
            let (tile_w, tile_h) = (width / q.cols, height / q.rows);
            let (centre, instance) = m.view((tile_w, tile_h))?;
            let f = focal_distance(&centre, focal_target, min_focal);
            let views = q
                .cameras(&centre, f)
                .into_iter()
                .enumerate()
                .map(|(i, view)| {
                    // A centre camera near a limit may push a side view past it.
                    view.validate().map_err(|e| PoseRejection::Camera(format!("quilt view {i}: {e}")))?;
                    let (x, y) = q.tile_origin(i as u32, tile_w, tile_h);
                    Ok(FrameView { view, viewport: Viewport { x, y, width: tile_w, height: tile_h } })
                })
                .collect::<Result<_, PoseRejection>>()?;
            Ok(CheckedPose { seq: m.seq, t_client_ms: m.t_client_ms, predicted_ms: m.predicted_ms(), views, instance })
        }
    }
}

/// A camera from the wire: validated, rotation re-orthonormalised (f32 rounding passes).
fn checked_camera(world_from_camera: Mat4, intrinsics: Intrinsics) -> Result<View, PoseRejection> {
    let view = View { world_from_camera: world_from_camera.as_dmat4(), intrinsics };
    view.validate().map_err(|e| PoseRejection::Camera(e.to_string()))?;
    Ok(View { world_from_camera: orthonormalise(view.world_from_camera), intrinsics })
}

fn checked_anchor(anchor: Option<Mat4>) -> Result<Instance, PoseRejection> {
    match anchor {
        None => Ok(Instance::default()),
        Some(a) => anchor_instance(a.as_dmat4()).map_err(PoseRejection::Anchor),
    }
}

/// Gram–Schmidt on the rotation columns (z kept, then y, then x = y × z).
fn orthonormalise(m: DMat4) -> DMat4 {
    let r = DMat3::from_mat4(m);
    let z = r.z_axis.normalize();
    let y = (r.y_axis - z * z.dot(r.y_axis)).normalize();
    let x = y.cross(z);
    DMat4::from_cols(x.extend(0.0), y.extend(0.0), z.extend(0.0), m.w_axis)
}

/// Splits an anchor matrix into rotation, translation and one uniform scale.
fn anchor_instance(m: DMat4) -> Result<Instance, String> {
    if !m.is_finite() {
        return Err("matrix is not finite".into());
    }
    if (m.row(3) - glam::DVec4::W).abs().max_element() > 1e-6 {
        return Err("last row must be 0 0 0 1".into());
    }
    let r = DMat3::from_mat4(m);
    let scales = DVec3::new(r.x_axis.length(), r.y_axis.length(), r.z_axis.length());
    let scale = scales.element_sum() / 3.0;
    if !(1e-6..=1e6).contains(&scale) {
        return Err(format!("scale {scale} is outside 1e-6..1e6"));
    }
    if (scales - DVec3::splat(scale)).abs().max_element() > 1e-3 * scale {
        return Err(format!("scale is not uniform ({:.4} {:.4} {:.4})", scales.x, scales.y, scales.z));
    }
    let rot = r * (1.0 / scale);
    let deviation = rotation_deviation(&rot);
    if deviation > 1e-3 {
        return Err(format!("not a rotation times a scale (deviation {deviation:.2e})"));
    }
    if rot.determinant() <= 0.0 {
        return Err("mirrored".into());
    }
    let instance = Instance { rotation: DQuat::from_mat3(&rot).normalize(), translation: m.w_axis.truncate(), scale };
    instance.validate().map_err(|e| e.to_string())?;
    Ok(instance)
}

/// Master → client messages on the pose channel (JSON text, tagged by `type`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ToViewer {
    /// Sent once when the channel opens: what is being streamed and where to look.
    Session {
        scene: String,
        mode: nephele_protocol::Mode,
        /// Centre of the asset's bounds, scene units.
        center: [f32; 3],
        /// Radius of the asset's bounding sphere, scene units.
        radius: f32,
        /// World up (+z, as in NeRF-synthetic).
        up: [f32; 3],
        width: u32,
        height: u32,
        fps: u32,
        /// Quilt mode: the layout, and the tile size the centre camera's pose must have.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        quilt: Option<QuiltInfo>,
    },
    /// One encoded frame.
    Frame(FrameInfo),
    /// A refused message; the session keeps its last good pose.
    Error { code: String, message: String },
    /// Something the user should know that is not its own error (the render farm went
    /// away, or came back).
    Notice { code: String, message: String },
}

/// A quilt session's layout (view 0 bottom-left; see `nephele_renderer::views`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct QuiltInfo {
    pub cols: u32,
    pub rows: u32,
    pub cone_deg: f32,
    pub tile_width: u32,
    pub tile_height: u32,
}

/// What one frame answered and where its time went.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FrameInfo {
    /// Frame number in this session, from 1.
    pub frame: u64,
    /// Sequence number of the pose this frame shows.
    pub pose_seq: u32,
    /// That pose's client timestamp, echoed: latency = client now − this.
    pub t_client_ms: f64,
    pub width: u32,
    pub height: u32,
    /// Time from pose receipt to the start of rendering (waiting for the frame slot).
    pub queue_ms: f64,
    /// Stage times and size, flattened into this object on the wire.
    #[serde(flatten)]
    pub times: FrameTimes,
    /// Fraction of the stream size that was rendered before upscaling (1 = exact).
    pub render_scale: f32,
    /// Views in the render task that made this frame (several users batched in one pass),
    /// 0 when the frame was not rendered but reused.
    #[serde(default)]
    pub batch_views: u32,
    /// Reused: the user's own last frame (camera at rest) or an identical request of
    /// another user from the history table.
    #[serde(default)]
    pub reused: bool,
    /// Views in the frame (2 for stereo, cols × rows for a quilt).
    #[serde(default = "one")]
    pub views: u32,
    /// How far ahead the client predicted the camera this frame shows, ms (0: none).
    #[serde(default)]
    pub predicted_ms: f64,
}

fn one() -> u32 {
    1
}

/// Where one frame's time went after it left the queue, and what it weighed.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct FrameTimes {
    /// The longest render task of the frame's objects (NEPHELE Eq. 9's max T_i).
    pub render_ms: f64,
    /// All render tasks of the frame's objects, summed.
    #[serde(default)]
    pub render_total_ms: f64,
    /// Getting tasks to remote workers and results back, the longest of the frame's
    /// objects (0 in process).
    #[serde(default)]
    pub transfer_ms: f64,
    /// Result bytes that crossed the network for this frame (Eq. 9's Σ D_i).
    #[serde(default)]
    pub transfer_bytes: u64,
    /// Depth composition of several objects (0 for one; Eq. 9's C).
    #[serde(default)]
    pub compose_ms: f64,
    /// From the frame's start to its pixels being ready (rendered, gathered, composed).
    #[serde(default)]
    pub ready_ms: f64,
    /// Where the frame sits on the stream's 90 kHz RTP clock: its RTP timestamp minus the
    /// first frame's (wrapping). The page matches each presented video frame to its pose by
    /// it (`requestVideoFrameCallback` reports the RTP timestamp).
    #[serde(default)]
    pub rtp_ticks: u32,
    /// RGBA → I420.
    pub convert_ms: f64,
    pub encode_ms: f64,
    /// Handing the access unit to the RTP track (packetise, SRTP, socket).
    pub send_ms: f64,
    /// Bytes of the access unit.
    pub bytes: usize,
    pub idr: bool,
    /// Bytes of the frame's depth message (0: none sent).
    #[serde(default)]
    pub depth_bytes: usize,
    /// Building and coding the depth message.
    #[serde(default)]
    pub depth_ms: f64,
}

impl ToViewer {
    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("viewer messages always serialize")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> PoseMessage {
        let view = View::orbit(DVec3::ZERO, 4.0, 30.0, 20.0, Intrinsics::from_fov_x(64, 48, 0.8));
        PoseMessage {
            seq: 7,
            t_client_ms: 1234.5,
            world_from_camera: view.world_from_camera.as_mat4(),
            intrinsics: view.intrinsics,
            world_from_anchor: None,
            predicted: None,
        }
    }

    #[test]
    fn a_predicted_pose_round_trips_and_implausible_ones_are_refused() {
        let p = sample();
        let present = (p.world_from_camera.as_dmat4() * DMat4::from_rotation_y(-0.2)).as_mat4();
        let anchor = Mat4::from_scale(glam::Vec3::splat(2.0));
        for world_from_anchor in [None, Some(anchor)] {
            let q = PoseMessage { world_from_anchor, predicted: Some(Predicted { horizon_ms: 80.0, present_world_from_camera: present }), ..p };
            let bytes = q.encode();
            assert_eq!(bytes.len(), if world_from_anchor.is_some() { 240 } else { 176 });
            assert_eq!(PoseMessage::decode(&bytes).unwrap(), q);
            let checked = check_pose(&bytes, &FrameLayout::Views { width: 64, height: 48 }).unwrap();
            assert_eq!(checked.predicted_ms, 80.0);
            // The predicted camera is the one rendered.
            assert!((checked.views[0].view.world_from_camera - p.world_from_camera.as_dmat4()).to_cols_array().iter().all(|x| x.abs() < 1e-5));
        }
        let refuse = |predicted: Predicted| PoseMessage { predicted: Some(predicted), ..p }.view((64, 48)).unwrap_err().to_string();
        let with = |horizon_ms: f64, present_world_from_camera: Mat4| Predicted { horizon_ms, present_world_from_camera };
        assert!(refuse(with(f64::NAN, present)).contains("horizon NaN ms is outside 0..=500 ms"));
        assert!(refuse(with(-1.0, present)).contains("outside"));
        assert!(refuse(with(1e6, present)).contains("outside"));
        assert!(refuse(with(50.0, Mat4::from_cols_array(&[f32::NAN; 16]))).starts_with("prediction: present camera"));
        assert!(refuse(with(50.0, present * Mat4::from_scale(glam::Vec3::new(1.0, 3.0, 1.0)))).starts_with("prediction: present camera"));
        let behind = (p.world_from_camera.as_dmat4() * DMat4::from_rotation_y(2.5)).as_mat4();
        assert!(refuse(with(50.0, behind)).contains("turns 143° from the present one; at most 90°"), "{}", refuse(with(50.0, behind)));
    }

    #[test]
    fn round_trip_with_and_without_anchor() {
        let p = sample();
        let bytes = p.encode();
        assert_eq!(bytes.len(), POSE_LEN);
        assert_eq!(PoseMessage::decode(&bytes).unwrap(), p);
        let anchor = Mat4::from_scale_rotation_translation(glam::Vec3::splat(0.5), glam::Quat::from_rotation_z(0.3), glam::Vec3::new(1.0, 2.0, 0.0));
        let q = PoseMessage { world_from_anchor: Some(anchor), ..p };
        let bytes = q.encode();
        assert_eq!(bytes.len(), POSE_WITH_ANCHOR_LEN);
        let back = PoseMessage::decode(&bytes).unwrap();
        assert_eq!(back, q);
        let (_, inst) = back.view((64, 48)).unwrap();
        assert!((inst.scale - 0.5).abs() < 1e-6);
        assert!((inst.translation - DVec3::new(1.0, 2.0, 0.0)).length() < 1e-6);
    }

    #[test]
    fn refusals_name_the_problem() {
        let good = sample().encode();
        for len in [0, 1, 103, 105, 167, 169, 1000] {
            let mut b = good.clone();
            b.resize(len, 0);
            assert!(matches!(PoseMessage::decode(&b), Err(PoseRejection::Length { .. })), "{len}");
        }
        let mut b = good.clone();
        b[0] = b'X';
        assert_eq!(PoseMessage::decode(&b), Err(PoseRejection::Magic));
        let session = (64, 48);
        for (offset, value) in [(16, f32::NAN), (60, f32::INFINITY), (16, 3.0), (80, -1.0), (80, f32::NAN)] {
            let mut b = good.clone();
            b[offset..offset + 4].copy_from_slice(&value.to_le_bytes());
            let err = PoseMessage::decode(&b).unwrap().view(session).unwrap_err();
            assert!(matches!(err, PoseRejection::Camera(_)), "{offset} {value}: {err}");
        }
        let mut b = good.clone();
        b[8..16].copy_from_slice(&f64::NAN.to_le_bytes());
        assert_eq!(PoseMessage::decode(&b).unwrap().view(session).unwrap_err(), PoseRejection::Timestamp);
        let err = PoseMessage::decode(&good).unwrap().view((640, 480)).unwrap_err();
        assert!(err.to_string().contains("64x48"), "{err}");
        // Non-uniformly scaled anchor.
        let skew = PoseMessage { world_from_anchor: Some(Mat4::from_scale(glam::Vec3::new(1.0, 2.0, 1.0))), ..sample() };
        assert!(matches!(skew.view(session), Err(PoseRejection::Anchor(_))));
    }

    #[test]
    fn f32_rounding_of_a_rotation_is_accepted_and_repaired() {
        let p = sample();
        let (view, _) = p.view((64, 48)).unwrap();
        let dev = rotation_deviation(&DMat3::from_mat4(view.world_from_camera));
        assert!(dev < 1e-12, "{dev}");
    }

    fn stereo(anchor: bool) -> MultiViewPose {
        let k = Intrinsics { fx: 40.0, fy: 40.0, cx: 30.0, cy: 24.0, width: 64, height: 48 };
        let proj = nephele_renderer::views::projection_from_intrinsics(&k, 0.05, 100.0);
        let centre = View::orbit(DVec3::ZERO, 4.0, 30.0, 20.0, k);
        let eye = |dx: f64, x: u32| PoseView {
            world_from_camera: (centre.world_from_camera * DMat4::from_translation(DVec3::new(dx, 0.0, 0.0))).as_mat4(),
            clip_from_camera: proj,
            viewport: Viewport { x, y: 0, width: 64, height: 48 },
        };
        MultiViewPose {
            seq: 9,
            t_client_ms: 5.0,
            frame_width: 128,
            frame_height: 48,
            views: vec![eye(-0.03, 0), eye(0.03, 64)],
            world_from_anchor: anchor.then(|| Mat4::from_scale(glam::Vec3::splat(2.0))),
            predicted: None,
        }
    }

    #[test]
    fn multi_view_predictions_round_trip_and_are_checked_per_view() {
        for anchor in [false, true] {
            let p = stereo(anchor);
            let present: Vec<Mat4> = p.views.iter().map(|v| (v.world_from_camera.as_dmat4() * DMat4::from_rotation_y(0.1)).as_mat4()).collect();
            let q = MultiViewPose { predicted: Some((60.0, present.clone())), ..p.clone() };
            let bytes = q.encode();
            assert_eq!(bytes.len(), 32 + 2 * 144 + if anchor { 64 } else { 0 } + 8 + 2 * 64);
            assert_eq!(MultiViewPose::decode(&bytes).unwrap(), q);
            assert_eq!(check_pose(&bytes, &STEREO).unwrap().predicted_ms, 60.0);
            // One eye's present camera turned away, a horizon past the limit, a cut message.
            let mut wild = present.clone();
            wild[1] = (p.views[1].world_from_camera.as_dmat4() * DMat4::from_rotation_y(2.0)).as_mat4();
            let err = check_pose(&MultiViewPose { predicted: Some((60.0, wild)), ..p.clone() }.encode(), &STEREO).unwrap_err().to_string();
            assert!(err.starts_with("prediction: view 1: the predicted camera turns 115°"), "{err}");
            let err = check_pose(&MultiViewPose { predicted: Some((600.0, present.clone())), ..p.clone() }.encode(), &STEREO).unwrap_err().to_string();
            assert!(err.contains("horizon 600 ms is outside 0..=500 ms"), "{err}");
            assert!(matches!(check_pose(&bytes[..bytes.len() - 64], &STEREO), Err(PoseRejection::Length { .. })));
        }
    }

    const STEREO: FrameLayout = FrameLayout::Views { width: 128, height: 48 };

    #[test]
    fn multi_view_poses_round_trip_and_become_cameras() {
        for anchor in [false, true] {
            let p = stereo(anchor);
            let bytes = p.encode();
            assert_eq!(bytes.len(), 32 + 2 * 144 + if anchor { 64 } else { 0 });
            assert_eq!(MultiViewPose::decode(&bytes).unwrap(), p);
            let checked = check_pose(&bytes, &STEREO).unwrap();
            assert_eq!(checked.views.len(), 2);
            assert_eq!(checked.views[1].viewport, Viewport { x: 64, y: 0, width: 64, height: 48 });
            let k = checked.views[0].view.intrinsics;
            assert!((k.fx - 40.0).abs() < 1e-3 && (k.cx - 30.0).abs() < 1e-3 && (k.cy - 24.0).abs() < 1e-3, "{k:?}");
            assert_eq!(checked.instance.scale, if anchor { 2.0 } else { 1.0 });
        }
        // Version 1 still works, as one view filling the frame.
        let one = check_pose(&sample().encode(), &FrameLayout::Views { width: 64, height: 48 }).unwrap();
        assert_eq!(one.views[0].viewport, Viewport::full(64, 48));
    }

    #[test]
    fn bad_multi_view_poses_are_refused_in_words() {
        let good = stereo(false);
        let refuse = |p: &MultiViewPose| check_pose(&p.encode(), &STEREO).unwrap_err().to_string();
        // Zero views and 10^4 views (the count field, whatever the length).
        let mut bytes = good.encode();
        bytes[24..28].copy_from_slice(&0u32.to_le_bytes());
        assert!(check_pose(&bytes, &STEREO).unwrap_err().to_string().contains("0 views"));
        bytes[24..28].copy_from_slice(&10_000u32.to_le_bytes());
        assert!(check_pose(&bytes, &STEREO).unwrap_err().to_string().contains("10000 views; 1..=8"));
        let many = MultiViewPose { views: vec![good.views[0]; 9], ..good.clone() };
        assert!(refuse(&many).contains("9 views"));
        // Truncated, unknown flags.
        let bytes = good.encode();
        assert!(matches!(check_pose(&bytes[..bytes.len() - 1], &STEREO), Err(PoseRejection::Length { .. })));
        let mut flagged = bytes.clone();
        flagged[28] = 4;
        assert!(matches!(check_pose(&flagged, &STEREO), Err(PoseRejection::Flags { .. })));
        // Frame size differs from the session's.
        assert!(refuse(&MultiViewPose { frame_width: 256, ..good.clone() }).contains("differs from the session's 128x48"));
        // Out of the frame, overlapping, empty.
        let mut p = good.clone();
        p.views[1].viewport.x = 100;
        assert!(refuse(&p).contains("is not inside the 128x48 frame"));
        let mut p = good.clone();
        p.views[1].viewport.x = 32;
        assert!(refuse(&p).contains("overlaps view 0"));
        let mut p = good.clone();
        p.views[0].viewport.width = 0;
        assert!(refuse(&p).contains("is empty"));
        let mut p = good.clone();
        p.views[1].viewport.x = u32::MAX;
        assert!(refuse(&p).contains("not inside"));
        // Projections: NaN, far before near, skew.
        let mut p = good.clone();
        p.views[1].clip_from_camera[0] = f32::NAN;
        assert!(refuse(&p).starts_with("view 1: projection: projection has a non-finite entry"));
        let mut p = good.clone();
        let k = Intrinsics { fx: 40.0, fy: 40.0, cx: 30.0, cy: 24.0, width: 64, height: 48 };
        p.views[0].clip_from_camera = nephele_renderer::views::projection_from_intrinsics(&k, 10.0, 1.0);
        assert!(refuse(&p).starts_with("view 0: projection"), "{}", refuse(&p));
        let mut p = good.clone();
        p.views[0].clip_from_camera[4] = 0.5;
        assert!(refuse(&p).contains("skew"));
        // A non-rigid camera names its view.
        let mut p = good.clone();
        p.views[1].world_from_camera.x_axis *= 3.0;
        assert!(refuse(&p).starts_with("camera: view 1: pose is not rigid"), "{}", refuse(&p));
        // Quilt sessions take one centre camera, not views.
        let quilt = FrameLayout::Quilt { width: 320, height: 432, layout: QuiltLayout::default(), focal_target: DVec3::ZERO, min_focal: 0.1 };
        assert!(check_pose(&good.encode(), &quilt).unwrap_err().to_string().contains("tile size 64x48"));
    }

    #[test]
    fn a_quilt_pose_becomes_every_view_in_its_tile() {
        let quilt = FrameLayout::Quilt { width: 320, height: 432, layout: QuiltLayout::default(), focal_target: DVec3::ZERO, min_focal: 0.1 };
        let p = sample(); // a 64x48 centre camera: the tile size
        let checked = check_pose(&p.encode(), &quilt).unwrap();
        assert_eq!(checked.views.len(), 45);
        assert_eq!(checked.views[0].viewport, Viewport { x: 0, y: 384, width: 64, height: 48 });
        assert_eq!(checked.views[44].viewport, Viewport { x: 256, y: 0, width: 64, height: 48 });
        // The wrong tile size is refused with the size it must have.
        let err = check_pose(&p.encode(), &FrameLayout::Quilt { width: 640, height: 432, layout: QuiltLayout::default(), focal_target: DVec3::ZERO, min_focal: 0.1 }).unwrap_err();
        assert!(err.to_string().contains("128x48"), "{err}");
    }
}
