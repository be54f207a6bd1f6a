//! The protocol a streaming client and a master share, and nothing of either side's
//! internals: the `pose` data channel's format (DESIGN.md §5 "Pose channel") here, the
//! pose-sequence SEI in [`sei`], the WebRTC media conventions in [`media`]. The master
//! (`crate::master`) and the headless client (`crate::client`) both build on this module.
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
//!
//! Master → client: JSON text messages ([`ToViewer`]): the session description once, frame
//! info for every encoded frame (so latency is measured on the client's clock by echoing
//! `t_client_ms`), and refusals with a reason.

pub mod media;
pub mod sei;

use glam::{DMat3, DMat4, DQuat, DVec3, Mat4};
use nephele_renderer::{Instance, Intrinsics, View, camera::rotation_deviation};
use serde::{Deserialize, Serialize};

/// Magic and version at the start of every pose message.
pub const POSE_MAGIC: &[u8; 4] = b"NPO1";
/// Length of a pose message without an anchor.
pub const POSE_LEN: usize = 104;
/// Length of a pose message with an AR plane anchor.
pub const POSE_WITH_ANCHOR_LEN: usize = 168;

/// One decoded pose message. Not yet validated as a camera: see [`PoseMessage::view`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseMessage {
    pub seq: u32,
    pub t_client_ms: f64,
    pub world_from_camera: Mat4,
    pub intrinsics: Intrinsics,
    pub world_from_anchor: Option<Mat4>,
}

/// Why a pose message was refused; sent back to the client as `bad_pose`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PoseRejection {
    #[error("pose message is {len} bytes; expected {POSE_LEN} or {POSE_WITH_ANCHOR_LEN}")]
    Length { len: usize },
    #[error("pose message does not start with \"NPO1\"")]
    Magic,
    #[error("pose timestamp is not finite")]
    Timestamp,
    #[error("viewport {width}x{height} differs from the session's {session_width}x{session_height}")]
    Viewport { width: u32, height: u32, session_width: u32, session_height: u32 },
    #[error("camera: {0}")]
    Camera(String),
    #[error("plane anchor: {0}")]
    Anchor(String),
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
        out
    }

    /// Parses the byte layout only (length, magic); values are checked by [`Self::view`].
    pub fn decode(bytes: &[u8]) -> Result<Self, PoseRejection> {
        if bytes.len() != POSE_LEN && bytes.len() != POSE_WITH_ANCHOR_LEN {
            return Err(PoseRejection::Length { len: bytes.len() });
        }
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
            world_from_anchor: (bytes.len() == POSE_WITH_ANCHOR_LEN).then(|| mat_at(104)),
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
        let view = View { world_from_camera: self.world_from_camera.as_dmat4(), intrinsics: k };
        view.validate().map_err(|e| PoseRejection::Camera(e.to_string()))?;
        let view = View { world_from_camera: orthonormalise(view.world_from_camera), intrinsics: k };
        let instance = match self.world_from_anchor {
            None => Instance::default(),
            Some(a) => anchor_instance(a.as_dmat4()).map_err(PoseRejection::Anchor)?,
        };
        Ok((view, instance))
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
        mode: nephele_signaling::Mode,
        /// Centre of the asset's bounds, scene units.
        center: [f32; 3],
        /// Radius of the asset's bounding sphere, scene units.
        radius: f32,
        /// World up (+z, as in NeRF-synthetic).
        up: [f32; 3],
        width: u32,
        height: u32,
        fps: u32,
    },
    /// One encoded frame.
    Frame(FrameInfo),
    /// A refused message; the session keeps its last good pose.
    Error { code: String, message: String },
    /// Something the user should know that is not its own error (the render farm went
    /// away, or came back).
    Notice { code: String, message: String },
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
    /// RGBA → I420.
    pub convert_ms: f64,
    pub encode_ms: f64,
    /// Handing the access unit to the RTP track (packetise, SRTP, socket).
    pub send_ms: f64,
    /// Bytes of the access unit.
    pub bytes: usize,
    pub idr: bool,
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
        }
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
}
