//! Cameras, instance transforms and primary rays.
//!
//! Poses are camera-to-world 4×4 matrices in the OpenGL convention (camera looks down −z,
//! y up), as in NeRF-synthetic `transform_matrix` and Three.js. Poses come from the network,
//! so [`View::validate`] rejects anything that is not a finite rigid transform with sane
//! intrinsics and size.
//!
//! Rays use an *offset form* that keeps f32 precision when the camera is very far from the
//! object: on the host (f64) the camera origin is moved along the optical axis to just
//! outside the object's bounding sphere (`origin_near`, distance `t_shift`); each pixel's
//! origin is then `origin_near + t_shift · R·Δ`, where `Δ = d_pixel − d_axis` is computed
//! without cancellation. Every point before `t_shift` lies outside the bounding sphere, so
//! nothing is skipped. The CPU reference and the WGSL kernels evaluate the same formulas.

use glam::{DMat3, DMat4, DQuat, DVec3, Vec3};
use serde::{Deserialize, Serialize};

/// Largest accepted image edge, in pixels (the shared render limit).
pub const MAX_EDGE_PX: u32 = nephele_limits::MAX_RENDER_EDGE_PX;
/// Largest accepted image area, in pixels (8K UHD, the shared render limit).
pub const MAX_PIXELS: u64 = nephele_limits::MAX_RENDER_PIXELS;
/// Largest accepted distance of a camera from the scene origin, in scene units.
pub const MAX_CAMERA_DISTANCE: f64 = 1e9;

/// Why a pose or view was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PoseError {
    #[error("pose has a non-finite entry (NaN or infinity)")]
    NonFinite,
    #[error("pose is not rigid: rotation part deviates from orthonormal by {deviation:.3e}")]
    NotRigid { deviation: f64 },
    #[error("pose is mirrored (rotation determinant {det:.3})")]
    Mirrored { det: f64 },
    #[error("pose bottom row must be [0, 0, 0, 1]")]
    NotAffine,
    #[error("camera is {distance:.3e} units from the origin; the limit is {MAX_CAMERA_DISTANCE:e}")]
    TooFar { distance: f64 },
    #[error("image size {width}x{height} is outside 1..={MAX_EDGE_PX} per edge / {MAX_PIXELS} pixels")]
    BadSize { width: u32, height: u32 },
    #[error("intrinsics must be finite with positive focal lengths (fx={fx}, fy={fy}, cx={cx}, cy={cy})")]
    BadIntrinsics { fx: f32, fy: f32, cx: f32, cy: f32 },
    #[error("instance transform must be finite with a positive scale")]
    BadInstance,
}

/// Pinhole intrinsics in pixels, with the image size.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
}

impl Intrinsics {
    /// Square pixels, principal point at the centre, horizontal field of view in radians.
    pub fn from_fov_x(width: u32, height: u32, fov_x_rad: f32) -> Self {
        let fx = 0.5 * width as f32 / (0.5 * fov_x_rad).tan();
        Self { fx, fy: fx, cx: 0.5 * width as f32, cy: 0.5 * height as f32, width, height }
    }

    /// The same camera at another resolution (the "resolution scale" knob).
    pub fn scaled(&self, scale: f32) -> Self {
        let width = ((self.width as f32 * scale).round() as u32).max(1);
        let height = ((self.height as f32 * scale).round() as u32).max(1);
        let (sx, sy) = (width as f32 / self.width as f32, height as f32 / self.height as f32);
        Self { fx: self.fx * sx, fy: self.fy * sy, cx: self.cx * sx, cy: self.cy * sy, width, height }
    }

    pub fn pixel_count(&self) -> u64 {
        self.width as u64 * self.height as u64
    }

    pub fn validate(&self) -> Result<(), PoseError> {
        let Self { fx, fy, cx, cy, width, height } = *self;
        if !nephele_limits::render_size_ok(width, height) {
            return Err(PoseError::BadSize { width, height });
        }
        let ok = [fx, fy, cx, cy].iter().all(|v| v.is_finite() && v.abs() < 1e12) && fx > 0.0 && fy > 0.0;
        if !ok {
            return Err(PoseError::BadIntrinsics { fx, fy, cx, cy });
        }
        Ok(())
    }
}

/// Largest entry of |RᵀR − I|: 0 for a rotation (or reflection), grows with scale and shear.
pub fn rotation_deviation(r: &DMat3) -> f64 {
    (r.transpose() * *r - DMat3::IDENTITY).to_cols_array().iter().fold(0.0f64, |a, v| a.max(v.abs()))
}

/// A camera: pose plus intrinsics.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct View {
    /// Camera-to-world, OpenGL convention.
    pub world_from_camera: DMat4,
    pub intrinsics: Intrinsics,
}

impl View {
    /// A camera on a sphere around `target`, looking at it. World up is +z, as in
    /// NeRF-synthetic; azimuth turns about +z from +x, elevation rises towards +z.
    pub fn orbit(target: DVec3, distance: f64, azimuth_deg: f64, elevation_deg: f64, intrinsics: Intrinsics) -> Self {
        let (az, el) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
        let eye = target + distance * DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        Self::look_at(eye, target, DVec3::Z, intrinsics)
    }

    /// Camera at `eye` looking at `target`; `up` need not be orthogonal to the view.
    pub fn look_at(eye: DVec3, target: DVec3, up: DVec3, intrinsics: Intrinsics) -> Self {
        let back = (eye - target).normalize_or(DVec3::Z);
        let up = if back.cross(up).length_squared() < 1e-12 { DVec3::Y } else { up };
        let right = up.cross(back).normalize();
        let up = back.cross(right);
        let world_from_camera = DMat4::from_cols(right.extend(0.0), up.extend(0.0), back.extend(0.0), eye.extend(1.0));
        Self { world_from_camera, intrinsics }
    }

    /// World-space ray through the image point (`x_px`, `y_px`), in continuous pixel units:
    /// pixel (x, y) covers [x, x+1) × [y, y+1), so its centre is (x + ½, y + ½); row 0 is the
    /// top. Returns (origin = eye, unit direction). Same formulas as [`RayFrame::ray`] without
    /// the origin shift.
    pub fn ray_in_world(&self, x_px: f64, y_px: f64) -> (DVec3, DVec3) {
        let k = &self.intrinsics;
        let x = (x_px - k.cx as f64) / k.fx as f64;
        let y = -(y_px - k.cy as f64) / k.fy as f64;
        let dir_in_camera = DVec3::new(x, y, -1.0).normalize();
        let m = &self.world_from_camera;
        (m.w_axis.truncate(), m.transform_vector3(dir_in_camera))
    }

    /// Rejects non-finite, non-rigid, mirrored or far-away poses and absurd sizes.
    pub fn validate(&self) -> Result<(), PoseError> {
        let m = &self.world_from_camera;
        if !m.is_finite() {
            return Err(PoseError::NonFinite);
        }
        let row3 = m.row(3);
        if (row3 - glam::DVec4::W).abs().max_element() > 1e-6 {
            return Err(PoseError::NotAffine);
        }
        let r = DMat3::from_mat4(*m);
        let deviation = rotation_deviation(&r);
        if deviation > 1e-3 {
            return Err(PoseError::NotRigid { deviation });
        }
        let det = r.determinant();
        if det <= 0.0 {
            return Err(PoseError::Mirrored { det });
        }
        let distance = m.w_axis.truncate().length();
        if distance > MAX_CAMERA_DISTANCE {
            return Err(PoseError::TooFar { distance });
        }
        self.intrinsics.validate()
    }
}

/// Places an asset in a scene: rotation, translation and uniform scale.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Instance {
    pub rotation: DQuat,
    pub translation: DVec3,
    pub scale: f64,
}

impl Default for Instance {
    fn default() -> Self {
        Self { rotation: DQuat::IDENTITY, translation: DVec3::ZERO, scale: 1.0 }
    }
}

impl Instance {
    pub fn validate(&self) -> Result<(), PoseError> {
        let ok = self.rotation.is_finite() && self.translation.is_finite() && self.scale.is_finite();
        if !ok || self.scale <= 1e-9 || (self.rotation.length() - 1.0).abs() > 1e-3 {
            return Err(PoseError::BadInstance);
        }
        Ok(())
    }

    pub fn world_from_object(&self) -> DMat4 {
        DMat4::from_scale_rotation_translation(DVec3::splat(self.scale), self.rotation, self.translation)
    }

    /// `self ∘ inner`: place something placed by `inner` with `self` (e.g. an AR anchor
    /// around a scene object's own placement).
    pub fn then_inside(&self, inner: &Instance) -> Instance {
        Instance {
            rotation: (self.rotation * inner.rotation).normalize(),
            translation: self.translation + self.rotation.mul_vec3(inner.translation * self.scale),
            scale: self.scale * inner.scale,
        }
    }
}

/// Per-view ray set-up in the object's space, prepared on the host in f64.
/// The GPU twin is `gpu::ViewUniform`; both feed [`RayFrame::ray`]'s formulas.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayFrame {
    /// Camera origin moved along the optical axis to near the object, object space.
    pub origin_near_in_object: Vec3,
    /// How far `origin_near` was moved, in object units.
    pub t_shift: f32,
    /// object_from_camera rotation, as columns.
    pub object_from_camera: [Vec3; 3],
    /// Scene units per object unit.
    pub scale: f32,
    pub intrinsics: Intrinsics,
}

impl RayFrame {
    /// `bound_center`/`bound_radius`: the object's bounding sphere, object space.
    pub fn new(view: &View, instance: &Instance, bound_center: Vec3, bound_radius: f32) -> Self {
        let object_from_world = instance.world_from_object().inverse();
        let object_from_camera = object_from_world * view.world_from_camera;
        // Rotation without the instance's scale: columns have length 1/scale.
        let r = DMat3::from_mat4(object_from_camera) * instance.scale;
        let origin = object_from_camera.w_axis.truncate();
        let axis = -r.z_axis.normalize();
        let distance = (origin - bound_center.as_dvec3()).length();
        let t_shift = (distance - 2.0 * bound_radius as f64).max(0.0);
        let origin_near = origin + t_shift * axis;
        Self {
            origin_near_in_object: origin_near.as_vec3(),
            t_shift: t_shift as f32,
            object_from_camera: [r.x_axis.as_vec3(), r.y_axis.as_vec3(), r.z_axis.as_vec3()],
            scale: instance.scale as f32,
            intrinsics: view.intrinsics,
        }
    }

    /// Object-space ray through the centre of pixel (`x_px`, `y_px`): (origin, unit direction).
    /// Points on it are `origin + t·dir`; their scene depth is `(t_shift + t)·scale`.
    pub fn ray(&self, x_px: u32, y_px: u32) -> (Vec3, Vec3) {
        let k = &self.intrinsics;
        let x = (x_px as f32 + 0.5 - k.cx) / k.fx;
        let y = -(y_px as f32 + 0.5 - k.cy) / k.fy;
        let r2 = x * x + y * y;
        let len = (1.0 + r2).sqrt();
        let [c0, c1, c2] = self.object_from_camera;
        let rotate = |v: Vec3| c0 * v.x + c1 * v.y + c2 * v.z;
        let dir = rotate(Vec3::new(x, y, -1.0) / len);
        let offset = rotate(Vec3::new(x / len, y / len, r2 / (len * (len + 1.0))));
        (self.origin_near_in_object + self.t_shift * offset, dir)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k() -> Intrinsics {
        Intrinsics::from_fov_x(64, 48, 0.8)
    }

    #[test]
    fn placements_compose_like_their_matrices() {
        let anchor = Instance { rotation: DQuat::from_rotation_z(0.4), translation: DVec3::new(1.0, -2.0, 0.5), scale: 0.5 };
        let object = Instance { rotation: DQuat::from_rotation_x(1.1), translation: DVec3::new(0.3, 0.2, -0.7), scale: 3.0 };
        let both = anchor.then_inside(&object);
        let expected = anchor.world_from_object() * object.world_from_object();
        assert!((both.world_from_object() - expected).to_cols_array().iter().all(|d| d.abs() < 1e-12));
        assert_eq!(Instance::default().then_inside(&object), Instance { rotation: object.rotation.normalize(), ..object });
    }

    #[test]
    fn offset_form_matches_plain_rays() {
        let view = View::orbit(DVec3::ZERO, 4.0, 30.0, 20.0, k());
        let frame = RayFrame::new(&view, &Instance::default(), Vec3::ZERO, 0.5);
        assert!(frame.t_shift > 2.0);
        for (x, y) in [(0, 0), (63, 47), (10, 30)] {
            let (o, d) = frame.ray(x, y);
            // The shifted origin lies on the plain ray from the eye.
            let eye = view.world_from_camera.w_axis.truncate().as_vec3();
            let along = (o - eye).normalize();
            assert!((along - d).length() < 1e-5, "{along} vs {d}");
            assert!((d.length() - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn far_cameras_keep_precision() {
        // 10^6 units away with a telephoto lens: the shifted origin is near the object.
        let mut intr = k();
        intr.fx = 1e6 * 32.0 / 1.5;
        intr.fy = intr.fx;
        let view = View::orbit(DVec3::ZERO, 1e6, 10.0, 5.0, intr);
        let frame = RayFrame::new(&view, &Instance::default(), Vec3::ZERO, 1.0);
        let (o, d) = frame.ray(32, 24);
        assert!(o.length() < 3.0, "origin {o}");
        // Distance of the central ray from the object centre is tiny.
        let closest = o - d * o.dot(d);
        assert!(closest.length() < 0.05, "{closest}");
        let (o2, _) = frame.ray(63, 24);
        let spread = (o2 - d * o2.dot(d) - closest).length();
        assert!(spread > 0.5 && spread < 2.0, "edge ray offset {spread}");
    }

    #[test]
    fn validation_rejects_bad_poses() {
        let good = View::orbit(DVec3::ZERO, 4.0, 0.0, 0.0, k());
        assert_eq!(good.validate(), Ok(()));
        let mut v = good;
        v.world_from_camera.x_axis.x = f64::NAN;
        assert_eq!(v.validate(), Err(PoseError::NonFinite));
        let mut v = good;
        v.world_from_camera.z_axis.y = f64::INFINITY;
        assert_eq!(v.validate(), Err(PoseError::NonFinite));
        let mut v = good;
        v.world_from_camera.x_axis *= 2.0;
        assert!(matches!(v.validate(), Err(PoseError::NotRigid { .. })));
        let mut v = good;
        v.world_from_camera.x_axis = -v.world_from_camera.x_axis;
        assert!(matches!(v.validate(), Err(PoseError::Mirrored { .. })));
        let mut v = good;
        v.world_from_camera.x_axis.w = 1.0;
        assert_eq!(v.validate(), Err(PoseError::NotAffine));
        let mut v = good;
        v.world_from_camera.w_axis.x = 1e12;
        assert!(matches!(v.validate(), Err(PoseError::TooFar { .. })));
        for (w, h) in [(0, 10), (10, 0), (100_000, 10), (8192, 8192)] {
            let mut v = good;
            v.intrinsics.width = w;
            v.intrinsics.height = h;
            assert!(matches!(v.validate(), Err(PoseError::BadSize { .. })), "{w}x{h}");
        }
        let mut v = good;
        v.intrinsics.fx = -1.0;
        assert!(matches!(v.validate(), Err(PoseError::BadIntrinsics { .. })));
        let mut v = good;
        v.intrinsics.cy = f32::NAN;
        assert!(matches!(v.validate(), Err(PoseError::BadIntrinsics { .. })));
    }
}
