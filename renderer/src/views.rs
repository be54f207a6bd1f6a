//! Several views of one frame: a GL projection matrix (WebXR's per-eye `projectionMatrix`,
//! an asymmetric frustum) as pinhole intrinsics, and the cameras and tiles of a Looking
//! Glass quilt (NEPHELE §7 renders 45-view quilts).
//!
//! **Projection → pinhole.** For a viewport of W×H pixels (row 0 at the top, as our images)
//! and P the column-major clip_from_camera matrix, a camera-space point (X, Y, Z), Z < 0,
//! lands at NDC x = P00·X/(−Z) − P02 and y = P11·Y/(−Z) − P12, so
//! `fx = W·P00/2`, `cx = W·(1 − P02)/2`, `fy = H·P11/2`, `cy = H·(1 + P12)/2`. Exact for
//! every perspective projection without skew; near and far only clip, which a ray caster
//! does not need (they are still checked: 0 < near < far, far may be infinite).
//!
//! **Quilt convention** (the Looking Glass one, written once here and tested below):
//! N = cols·rows views; view i sits at column `i % cols` and row `⌊i / cols⌋` counted from
//! the **bottom**, so view 0 is the bottom-left tile; in a top-down image its tile starts at
//! `x = (i % cols)·tile_w`, `y = (rows − 1 − ⌊i / cols⌋)·tile_h`. Camera i is the centre
//! camera translated along its own x axis by `x_i = f·tan(cone·((i + ½)/N − ½))` (view 0 is
//! the leftmost), not rotated; its frustum is shifted back so the focal plane at distance
//! `f` stays put: `cx_i = cx + fx·x_i / f`. A point on the focal plane lands on the same pixel
//! in every view; nearer points move right→left as i grows, farther ones left→right.

use glam::{DMat4, DVec3};

use crate::camera::{Intrinsics, View};

/// Why a projection matrix was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProjectionError {
    #[error("projection has a non-finite entry (NaN or infinity)")]
    NonFinite,
    #[error("projection is not a perspective one (expected clip w = −z: m[3,2] = −1, m[3,3] = 0)")]
    NotPerspective,
    #[error("projection has skew or rotation terms (only scale and frustum shift are allowed)")]
    Skewed,
    #[error("projection focal scales must be positive (m[0,0] = {p00}, m[1,1] = {p11})")]
    BadScale { p00: f32, p11: f32 },
    #[error("projection near plane {near} must be positive")]
    BadNear { near: f32 },
    #[error("projection far plane {far} is not beyond the near plane {near}")]
    FarBeforeNear { near: f32, far: f32 },
}

/// Pinhole intrinsics of a W×H viewport seen through a GL projection (column-major, as
/// WebXR's `XRView.projectionMatrix` and three.js). See the module docs for the formulas.
pub fn intrinsics_from_projection(m: &[f32; 16], width: u32, height: u32) -> Result<Intrinsics, ProjectionError> {
    if m.iter().any(|v| !v.is_finite()) {
        return Err(ProjectionError::NonFinite);
    }
    // Column-major: entry (row r, column c) is m[4c + r].
    let at = |r: usize, c: usize| m[4 * c + r];
    let (p00, p11) = (at(0, 0), at(1, 1));
    if !(p00 > 0.0 && p11 > 0.0 && p00 < 1e6 && p11 < 1e6) {
        return Err(ProjectionError::BadScale { p00, p11 });
    }
    let tol = 1e-5 * p00.max(p11).max(1.0);
    if (at(3, 2) + 1.0).abs() > 1e-5 || at(3, 3).abs() > 1e-5 || at(3, 0).abs() > 1e-6 || at(3, 1).abs() > 1e-6 {
        return Err(ProjectionError::NotPerspective);
    }
    let zero = [at(1, 0), at(2, 0), at(0, 1), at(2, 1), at(0, 3), at(1, 3)];
    if zero.iter().any(|v| v.abs() > tol) {
        return Err(ProjectionError::Skewed);
    }
    let (p22, p23) = (f64::from(at(2, 2)), f64::from(at(2, 3)));
    let near = p23 / (p22 - 1.0);
    let far = if (p22 + 1.0).abs() < 1e-7 { f64::INFINITY } else { p23 / (p22 + 1.0) };
    if !(near.is_finite() && near > 0.0) {
        return Err(ProjectionError::BadNear { near: near as f32 });
    }
    if !(far > near) {
        return Err(ProjectionError::FarBeforeNear { near: near as f32, far: far as f32 });
    }
    let (w, h) = (width as f32, height as f32);
    Ok(Intrinsics { fx: 0.5 * w * p00, fy: 0.5 * h * p11, cx: 0.5 * w * (1.0 - at(0, 2)), cy: 0.5 * h * (1.0 + at(1, 2)), width, height })
}

/// The GL projection (column-major) of pinhole intrinsics, with the given clip planes: the
/// inverse of [`intrinsics_from_projection`] (tests, the replay client, headless pages).
pub fn projection_from_intrinsics(k: &Intrinsics, near: f32, far: f32) -> [f32; 16] {
    let (w, h) = (k.width as f32, k.height as f32);
    let mut m = [0.0f32; 16];
    m[0] = 2.0 * k.fx / w;
    m[5] = 2.0 * k.fy / h;
    m[8] = 1.0 - 2.0 * k.cx / w;
    m[9] = 2.0 * k.cy / h - 1.0;
    m[10] = -(far + near) / (far - near);
    m[11] = -1.0;
    m[14] = -2.0 * far * near / (far - near);
    m
}

/// A Looking Glass quilt: `cols × rows` views over a horizontal view cone.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QuiltLayout {
    pub cols: u32,
    pub rows: u32,
    /// Full view cone, radians.
    pub cone_rad: f64,
}

impl Default for QuiltLayout {
    /// The 16"/32" Gen2 displays' 5×9 = 45 views over 40° (NEPHELE's case).
    fn default() -> Self {
        Self { cols: 5, rows: 9, cone_rad: 40f64.to_radians() }
    }
}

impl QuiltLayout {
    /// Parses `COLSxROWS` (e.g. `5x9`) with a cone in degrees; checks the shared limits for
    /// a frame of `tile × (cols, rows)`.
    pub fn parse(spec: &str, cone_deg: f32) -> Result<Self, String> {
        let (c, r) = spec.split_once('x').ok_or_else(|| format!("quilt {spec:?}: expected COLSxROWS, e.g. 5x9"))?;
        let cols: u32 = c.trim().parse().map_err(|_| format!("quilt {spec:?}: bad column count"))?;
        let rows: u32 = r.trim().parse().map_err(|_| format!("quilt {spec:?}: bad row count"))?;
        nephele_limits::check_quilt(cols, rows, cone_deg, cols, rows).map_err(|e| e.to_string())?;
        Ok(Self { cols, rows, cone_rad: f64::from(cone_deg).to_radians() })
    }

    pub fn views(&self) -> u32 {
        self.cols * self.rows
    }

    /// Top-left pixel of view `i`'s tile in a top-down image (view 0 bottom-left).
    pub fn tile_origin(&self, i: u32, tile_w: u32, tile_h: u32) -> (u32, u32) {
        let (col, row_from_bottom) = (i % self.cols, i / self.cols);
        (col * tile_w, (self.rows - 1 - row_from_bottom) * tile_h)
    }

    /// Camera offset of view `i` along the centre camera's x axis, scene units, for a focal
    /// plane at `focal_distance`.
    pub fn offset(&self, i: u32, focal_distance: f64) -> f64 {
        let n = f64::from(self.views());
        focal_distance * (self.cone_rad * ((f64::from(i) + 0.5) / n - 0.5)).tan()
    }

    /// View `i`: the centre camera moved by [`Self::offset`] along its x axis, its frustum
    /// shifted back so the focal plane stays put.
    pub fn camera(&self, centre: &View, focal_distance: f64, i: u32) -> View {
        let x = self.offset(i, focal_distance);
        let world_from_camera = centre.world_from_camera * DMat4::from_translation(DVec3::new(x, 0.0, 0.0));
        let mut intrinsics = centre.intrinsics;
        intrinsics.cx = (f64::from(intrinsics.cx) + f64::from(intrinsics.fx) * x / focal_distance) as f32;
        View { world_from_camera, intrinsics }
    }

    /// Every view, in quilt order.
    pub fn cameras(&self, centre: &View, focal_distance: f64) -> Vec<View> {
        (0..self.views()).map(|i| self.camera(centre, focal_distance, i)).collect()
    }

    /// The file-name suffix displays expect: `_qs{cols}x{rows}a{aspect}` (aspect = tile
    /// width / height, e.g. `_qs5x9a0.75`).
    pub fn file_suffix(&self, tile_w: u32, tile_h: u32) -> String {
        let aspect = f64::from(tile_w) / f64::from(tile_h);
        let aspect = format!("{aspect:.4}");
        let aspect = aspect.trim_end_matches('0').trim_end_matches('.');
        format!("_qs{}x{}a{aspect}", self.cols, self.rows)
    }
}

/// Focal distance of a quilt whose centre camera looks at `target`: the depth of `target`
/// along the optical axis, at least `min_distance` (a target behind the camera would
/// otherwise flip the views).
pub fn focal_distance(centre: &View, target: DVec3, min_distance: f64) -> f64 {
    let m = &centre.world_from_camera;
    let forward = -m.z_axis.truncate().normalize_or_zero();
    forward.dot(target - m.w_axis.truncate()).max(min_distance)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k() -> Intrinsics {
        Intrinsics { fx: 70.0, fy: 65.0, cx: 30.0, cy: 27.0, width: 64, height: 48 }
    }

    #[test]
    fn projections_round_trip_through_intrinsics() {
        let m = projection_from_intrinsics(&k(), 0.1, 100.0);
        let back = intrinsics_from_projection(&m, 64, 48).unwrap();
        for (a, b) in [(back.fx, 70.0), (back.fy, 65.0), (back.cx, 30.0), (back.cy, 27.0)] {
            assert!((a - b).abs() < 1e-4, "{back:?}");
        }
        // A pixel's ray through the matrix lands where the intrinsics say.
        let view = View { world_from_camera: DMat4::IDENTITY, intrinsics: back };
        let (_, dir) = view.ray_in_world(10.5, 40.5);
        let p = glam::Vec4::new(dir.x as f32, dir.y as f32, dir.z as f32, 1.0);
        let clip = glam::Mat4::from_cols_array(&m) * p;
        let (ndc_x, ndc_y) = (clip.x / clip.w, clip.y / clip.w);
        let (u, v) = ((ndc_x + 1.0) * 0.5 * 64.0, (1.0 - ndc_y) * 0.5 * 48.0);
        assert!((u - 10.5).abs() < 1e-3 && (v - 40.5).abs() < 1e-3, "{u} {v}");
        // An infinite far plane is fine.
        let mut inf = m;
        inf[10] = -1.0;
        inf[14] = -0.2;
        assert!(intrinsics_from_projection(&inf, 64, 48).is_ok());
    }

    #[test]
    fn bad_projections_are_named() {
        let good = projection_from_intrinsics(&k(), 0.1, 100.0);
        let with = |i: usize, v: f32| {
            let mut m = good;
            m[i] = v;
            intrinsics_from_projection(&m, 64, 48).unwrap_err()
        };
        assert_eq!(with(0, f32::NAN), ProjectionError::NonFinite);
        assert_eq!(with(11, 0.0), ProjectionError::NotPerspective);
        assert_eq!(with(15, 1.0), ProjectionError::NotPerspective);
        assert_eq!(with(4, 0.3), ProjectionError::Skewed);
        assert!(matches!(with(5, -1.0), ProjectionError::BadScale { .. }));
        // Far nearer than near: swap the planes.
        let swapped = projection_from_intrinsics(&k(), 100.0, 0.1);
        assert!(matches!(intrinsics_from_projection(&swapped, 64, 48), Err(ProjectionError::BadNear { .. } | ProjectionError::FarBeforeNear { .. })));
        let behind = projection_from_intrinsics(&k(), -1.0, 10.0);
        assert!(matches!(intrinsics_from_projection(&behind, 64, 48), Err(ProjectionError::BadNear { .. })));
    }

    #[test]
    fn quilt_tiles_and_cameras_follow_the_convention() {
        let q = QuiltLayout::default();
        assert_eq!(q.views(), 45);
        // View 0 bottom-left, view 4 bottom-right, view 5 one row up, view 44 top-right.
        assert_eq!(q.tile_origin(0, 10, 20), (0, 160));
        assert_eq!(q.tile_origin(4, 10, 20), (40, 160));
        assert_eq!(q.tile_origin(5, 10, 20), (0, 140));
        assert_eq!(q.tile_origin(44, 10, 20), (40, 0));
        assert_eq!(q.file_suffix(240, 320), "_qs5x9a0.75");
        assert_eq!(q.file_suffix(420, 560), "_qs5x9a0.75");
        let centre = View::orbit(DVec3::ZERO, 4.0, 30.0, 20.0, Intrinsics::from_fov_x(48, 64, 0.7));
        let f = focal_distance(&centre, DVec3::ZERO, 0.1);
        assert!((f - 4.0).abs() < 1e-9);
        let cams = q.cameras(&centre, f);
        let right = centre.world_from_camera.x_axis.truncate();
        let eye = centre.world_from_camera.w_axis.truncate();
        let mut last = f64::NEG_INFINITY;
        for (i, c) in cams.iter().enumerate() {
            // Translated along the camera's x axis by f·tan(cone·((i+½)/N − ½)), not rotated.
            let d = c.world_from_camera.w_axis.truncate() - eye;
            let expected = 4.0 * (40f64.to_radians() * ((i as f64 + 0.5) / 45.0 - 0.5)).tan();
            assert!((d - right * expected).length() < 1e-12, "view {i}");
            assert!(d.dot(right) > last);
            last = d.dot(right);
            assert_eq!(glam::DMat3::from_mat4(c.world_from_camera), glam::DMat3::from_mat4(centre.world_from_camera));
            // The focal point (the orbit target) lands on the same pixel in every view.
            let p = c.world_from_camera.inverse().transform_point3(DVec3::ZERO);
            let k = c.intrinsics;
            let u = f64::from(k.cx) + f64::from(k.fx) * p.x / -p.z;
            assert!((u - 24.0).abs() < 1e-4, "view {i}: {u}");
        }
        assert!((cams[0].world_from_camera.w_axis.truncate() - eye).dot(right) < 0.0, "view 0 is the leftmost");
    }

    #[test]
    fn quilt_specs_are_parsed_and_limited() {
        assert_eq!(QuiltLayout::parse("8x6", 35.0).unwrap().views(), 48);
        for bad in ["5", "0x9", "x9", "5x", "11x11", "axb"] {
            assert!(QuiltLayout::parse(bad, 40.0).is_err(), "{bad}");
        }
        assert!(QuiltLayout::parse("5x9", 0.0).is_err());
    }
}
