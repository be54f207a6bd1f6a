//! Synthetic datasets with exact ground truth, for tests and evaluation. Analytic scenes are
//! ray-traced (no neural parts) and written in the NeRF-synthetic layout that
//! [`crate::dataset`] reads: `transforms_{train,val,test}.json` plus 8-bit straight-alpha RGBA
//! PNGs under `train/`, `val/`, `test/`.
//!
//! Scenes (world space, +z up, everything inside [-1.5, 1.5]³):
//! - `diffuse`: a Lambertian box with a 3D checker pattern, turned about +z;
//! - `glossy`: a sphere with a Blinn–Phong highlight (it moves with the view);
//! - `translucent`: a tilted torus drawn as one transparent layer of constant opacity
//!   [`TORUS_OPACITY`]: a ray that meets it takes its colour at the nearest crossing with that
//!   opacity, however many times it crosses (not a volume);
//! - `mixed`: all three, smaller, composited front to back.
//!
//! Box and sphere are intersected in closed form, the torus by sphere tracing its exact SDF in
//! f64. Each pixel averages a fixed 4×4 stratified grid of rays (premultiplied), so edge alpha
//! is fractional and exact up to that sampling; [`render_view`] gives the same values for any
//! camera. Cameras sit on a sphere of radius 4 looking at the origin, spread by a Fibonacci
//! spiral from 72° above the horizon to 17° below it, with a per-split azimuth phase drawn
//! from the seed.

use std::{
    f64::consts::TAU,
    fmt,
    fs::File,
    io::BufWriter,
    path::{Path, PathBuf},
    str::FromStr,
};

use glam::{DQuat, DVec3};
use nephele_renderer::{
    camera::{MAX_EDGE_PX, View},
    render::to_unorm8,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::dataset::{Split, intrinsics_from_angle_x};

/// Horizontal field of view of every camera, radians (the NeRF-synthetic value).
pub const CAMERA_ANGLE_X: f64 = 0.6911112070083618;
/// Distance of every camera from the origin, scene units.
pub const CAMERA_DISTANCE: f64 = 4.0;
/// Anti-aliasing: each pixel averages this many × this many stratified rays.
pub const SUBSAMPLES_PER_EDGE: u32 = 4;
/// Opacity of the translucent torus.
pub const TORUS_OPACITY: f32 = 0.5;

/// Which analytic scene to render.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SynthScene {
    Diffuse,
    Glossy,
    Translucent,
    Mixed,
}

impl SynthScene {
    pub const ALL: [SynthScene; 4] = [SynthScene::Diffuse, SynthScene::Glossy, SynthScene::Translucent, SynthScene::Mixed];

    pub fn name(self) -> &'static str {
        match self {
            SynthScene::Diffuse => "diffuse",
            SynthScene::Glossy => "glossy",
            SynthScene::Translucent => "translucent",
            SynthScene::Mixed => "mixed",
        }
    }
}

impl fmt::Display for SynthScene {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for SynthScene {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        SynthScene::ALL
            .into_iter()
            .find(|v| v.name() == s)
            .ok_or_else(|| format!("unknown synthetic scene {s:?} (diffuse, glossy, translucent, mixed)"))
    }
}

/// What [`generate`] writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SynthConfig {
    pub scene: SynthScene,
    /// Image size in pixels.
    pub width: u32,
    pub height: u32,
    /// Images per split.
    pub n_train: usize,
    pub n_val: usize,
    pub n_test: usize,
    /// Picks the azimuth phase of each split's camera spiral.
    pub seed: u64,
}

impl SynthConfig {
    /// 200×200 pixels, 100 train, 20 val and 20 test views.
    pub fn new(scene: SynthScene) -> Self {
        Self { scene, width: 200, height: 200, n_train: 100, n_val: 20, n_test: 20, seed: 0 }
    }

    pub fn count(&self, split: Split) -> usize {
        match split {
            Split::Train => self.n_train,
            Split::Val => self.n_val,
            Split::Test => self.n_test,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error("bad synthetic dataset config: {0}")]
    BadConfig(String),
    #[error("cannot write {path}: {message}")]
    Write { path: PathBuf, message: String },
}

/// The cameras of one split, in file order. Deterministic in `cfg`.
pub fn cameras(cfg: &SynthConfig, split: Split) -> Vec<View> {
    const Z_TOP: f64 = 0.95; // sin 72°
    const Z_BOTTOM: f64 = -0.3; // sin −17.5°
    let golden_angle = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let salt: u64 = match split {
        Split::Train => 1,
        Split::Val => 2,
        Split::Test => 3,
    };
    let phase = (splitmix64(cfg.seed ^ salt.wrapping_mul(0x9e37_79b9_7f4a_7c15)) >> 11) as f64 / (1u64 << 53) as f64 * TAU;
    let intrinsics = intrinsics_from_angle_x(cfg.width, cfg.height, CAMERA_ANGLE_X);
    let n = cfg.count(split);
    (0..n)
        .map(|i| {
            let z = Z_TOP - (Z_TOP - Z_BOTTOM) * (i as f64 + 0.5) / n as f64;
            let azimuth = phase + i as f64 * golden_angle;
            let r = (1.0 - z * z).sqrt();
            let eye = CAMERA_DISTANCE * DVec3::new(r * azimuth.cos(), r * azimuth.sin(), z);
            View::look_at(eye, DVec3::ZERO, DVec3::Z, intrinsics)
        })
        .collect()
}

/// Exact ground truth of `scene` seen from `view`: straight RGBA in 0..1, row-major from the
/// top row, each pixel the premultiplied mean of [`SUBSAMPLES_PER_EDGE`]² stratified rays.
pub fn render_view(scene: SynthScene, view: &View) -> Vec<f32> {
    let objects = objects(scene);
    let (width, height) = (view.intrinsics.width as usize, view.intrinsics.height as usize);
    let n = SUBSAMPLES_PER_EDGE;
    let mut rgba = vec![0.0f32; 4 * width * height];
    rgba.par_chunks_mut(4 * width.max(1)).enumerate().for_each(|(y, row)| {
        for (x, out) in row.chunks_exact_mut(4).enumerate() {
            let mut sum = [0.0f64; 4];
            for j in 0..n {
                for i in 0..n {
                    let x_px = x as f64 + (i as f64 + 0.5) / n as f64;
                    let y_px = y as f64 + (j as f64 + 0.5) / n as f64;
                    let (origin, dir) = view.ray_in_world(x_px, y_px);
                    let s = trace(&objects, origin, dir);
                    for c in 0..4 {
                        sum[c] += s[c];
                    }
                }
            }
            let alpha = sum[3] / (n * n) as f64;
            let unpremultiply = if sum[3] > 0.0 { 1.0 / sum[3] } else { 0.0 };
            out.copy_from_slice(&[
                (sum[0] * unpremultiply) as f32,
                (sum[1] * unpremultiply) as f32,
                (sum[2] * unpremultiply) as f32,
                alpha as f32,
            ]);
        }
    });
    rgba
}

/// Renders every split of `cfg` and writes a NeRF-synthetic folder at `out_dir` (created if
/// needed; existing files of the same names are replaced).
pub fn generate(cfg: &SynthConfig, out_dir: &Path) -> Result<(), SynthError> {
    let SynthConfig { width, height, n_train, .. } = *cfg;
    if width == 0 || height == 0 || width > MAX_EDGE_PX || height > MAX_EDGE_PX {
        return Err(SynthError::BadConfig(format!("image size {width}x{height} must be 1..={MAX_EDGE_PX} per edge")));
    }
    if n_train == 0 {
        return Err(SynthError::BadConfig("n_train must be at least 1".into()));
    }
    let write_error = |path: &Path, e: &dyn fmt::Display| SynthError::Write { path: path.to_path_buf(), message: e.to_string() };
    for split in Split::ALL {
        let dir = out_dir.join(split.name());
        std::fs::create_dir_all(&dir).map_err(|e| write_error(&dir, &e))?;
        let views = cameras(cfg, split);
        views.par_iter().enumerate().try_for_each(|(i, view)| {
            let path = dir.join(format!("r_{i}.png"));
            write_rgba8_png(&path, width, height, &render_view(cfg.scene, view)).map_err(|e| write_error(&path, &e))
        })?;
        let frames: Vec<serde_json::Value> = views
            .iter()
            .enumerate()
            .map(|(i, view)| {
                let rows: Vec<[f64; 4]> = (0..4).map(|r| view.world_from_camera.row(r).to_array()).collect();
                serde_json::json!({ "file_path": format!("./{split}/r_{i}"), "transform_matrix": rows })
            })
            .collect();
        let json = serde_json::json!({ "camera_angle_x": CAMERA_ANGLE_X, "frames": frames });
        let path = out_dir.join(format!("transforms_{split}.json"));
        let text = serde_json::to_string_pretty(&json).map_err(|e| write_error(&path, &e))?;
        std::fs::write(&path, text).map_err(|e| write_error(&path, &e))?;
    }
    tracing::debug!(scene = %cfg.scene, dir = %out_dir.display(), "synthetic dataset written");
    Ok(())
}

/// Straight RGBA f32 → 8-bit RGBA PNG (colour 0 where alpha is 0).
fn write_rgba8_png(path: &Path, width: u32, height: u32, rgba: &[f32]) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    let bytes: Vec<u8> = rgba.iter().map(|&v| to_unorm8(v)).collect();
    let mut encoder = png::Encoder::new(BufWriter::new(File::create(path)?), width, height);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header()?;
    writer.write_image_data(&bytes)?;
    writer.finish()?;
    Ok(())
}

fn splitmix64(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

/// Direction towards the light, world space.
fn light_dir_in_world() -> DVec3 {
    DVec3::new(0.35, -0.45, 0.82).normalize()
}
const AMBIENT: f64 = 0.3;

#[derive(Debug, Clone, Copy)]
enum Shape {
    Sphere {
        radius: f64,
    },
    /// Half extents along the object's own axes.
    Box {
        half: DVec3,
    },
    /// Ring in the object's xy-plane around its z axis.
    Torus {
        major: f64,
        minor: f64,
    },
}

#[derive(Debug, Clone, Copy)]
enum Material {
    /// Lambertian, two colours alternating over cubes of `1 / cells_per_unit`.
    Checker { colour_a: DVec3, colour_b: DVec3, cells_per_unit: f64 },
    /// Lambertian plus a white Blinn–Phong highlight.
    Glossy { albedo: DVec3, specular: f64, shininess: f64 },
    /// Lambertian layer of opacity [`TORUS_OPACITY`].
    Translucent { albedo: DVec3 },
}

#[derive(Debug, Clone, Copy)]
struct Object {
    shape: Shape,
    material: Material,
    center_in_world: DVec3,
    world_from_object: DQuat,
}

fn objects(scene: SynthScene) -> Vec<Object> {
    let checker = Material::Checker { colour_a: DVec3::new(0.95, 0.55, 0.1), colour_b: DVec3::new(0.15, 0.3, 0.8), cells_per_unit: 2.5 };
    let glossy = Material::Glossy { albedo: DVec3::new(0.6, 0.08, 0.06), specular: 0.8, shininess: 48.0 };
    let translucent = Material::Translucent { albedo: DVec3::new(0.1, 0.75, 0.85) };
    let yaw = DQuat::from_rotation_z(25f64.to_radians());
    let tilt = DQuat::from_rotation_x(35f64.to_radians());
    let object = |shape, material, center_in_world, world_from_object| Object { shape, material, center_in_world, world_from_object };
    let cube = |half: f64, at| object(Shape::Box { half: DVec3::new(half, 0.8 * half, 0.65 * half) }, checker, at, yaw);
    let ball = |radius, at| object(Shape::Sphere { radius }, glossy, at, DQuat::IDENTITY);
    let ring = |major, minor, at| object(Shape::Torus { major, minor }, translucent, at, tilt);
    match scene {
        SynthScene::Diffuse => vec![cube(0.8, DVec3::ZERO)],
        SynthScene::Glossy => vec![ball(0.9, DVec3::ZERO)],
        SynthScene::Translucent => vec![ring(0.9, 0.3, DVec3::ZERO)],
        SynthScene::Mixed => vec![
            cube(0.4, DVec3::new(-0.55, 0.35, -0.25)),
            ball(0.45, DVec3::new(0.6, 0.3, 0.05)),
            ring(0.45, 0.16, DVec3::new(0.0, -0.62, 0.15)),
        ],
    }
}

/// Where a ray meets an object.
#[derive(Debug, Clone, Copy)]
struct Hit {
    /// Distance along the unit ray, scene units.
    t: f64,
    normal_in_world: DVec3,
    point_in_object: DVec3,
}

impl Object {
    /// Nearest crossing of the ray (origin, unit direction) with t > 0.
    fn intersect(&self, origin_in_world: DVec3, dir_in_world: DVec3) -> Option<Hit> {
        let object_from_world = self.world_from_object.inverse();
        let o = object_from_world * (origin_in_world - self.center_in_world);
        let d = object_from_world * dir_in_world;
        let (t, normal_in_object) = match self.shape {
            Shape::Sphere { radius } => {
                let t = sphere_entry(o, d, radius)?;
                (t, (o + t * d) / radius)
            }
            Shape::Box { half } => box_entry(o, d, half)?,
            Shape::Torus { major, minor } => torus_entry(o, d, major, minor)?,
        };
        Some(Hit { t, normal_in_world: self.world_from_object * normal_in_object, point_in_object: o + t * d })
    }

    /// Shaded colour at a hit and its opacity.
    fn shade(&self, hit: &Hit, dir_in_world: DVec3) -> (DVec3, f64) {
        let n = hit.normal_in_world;
        let light = light_dir_in_world();
        let n_dot_l = n.dot(light).max(0.0);
        let lambert = AMBIENT + (1.0 - AMBIENT) * n_dot_l;
        let (colour, opacity) = match self.material {
            Material::Checker { colour_a, colour_b, cells_per_unit } => {
                let cell = (hit.point_in_object * cells_per_unit).floor();
                let odd = (cell.x + cell.y + cell.z).rem_euclid(2.0) > 0.5;
                (if odd { colour_a } else { colour_b } * lambert, 1.0)
            }
            Material::Glossy { albedo, specular, shininess } => {
                let half_vector = (light - dir_in_world).normalize();
                let highlight = if n_dot_l > 0.0 { specular * n.dot(half_vector).max(0.0).powf(shininess) } else { 0.0 };
                (albedo * lambert + DVec3::splat(highlight), 1.0)
            }
            Material::Translucent { albedo } => (albedo * lambert, TORUS_OPACITY as f64),
        };
        (colour.clamp(DVec3::ZERO, DVec3::ONE), opacity)
    }
}

/// Premultiplied RGB and alpha along one ray.
fn trace(objects: &[Object], origin_in_world: DVec3, dir_in_world: DVec3) -> [f64; 4] {
    let mut layers: Vec<(f64, DVec3, f64)> = objects
        .iter()
        .filter_map(|o| {
            let hit = o.intersect(origin_in_world, dir_in_world)?;
            let (colour, opacity) = o.shade(&hit, dir_in_world);
            Some((hit.t, colour, opacity))
        })
        .collect();
    layers.sort_by(|a, b| a.0.total_cmp(&b.0));
    composite_front_to_back(layers.iter().map(|&(_, c, a)| (c, a)))
}

/// "Over" compositing of (straight colour, opacity) layers, nearest first.
fn composite_front_to_back(layers: impl Iterator<Item = (DVec3, f64)>) -> [f64; 4] {
    let mut premultiplied = DVec3::ZERO;
    let mut transmittance = 1.0;
    for (colour, opacity) in layers {
        premultiplied += transmittance * opacity * colour;
        transmittance *= 1.0 - opacity;
        if transmittance == 0.0 {
            break;
        }
    }
    [premultiplied.x, premultiplied.y, premultiplied.z, 1.0 - transmittance]
}

/// Both crossings of a centred sphere, or None.
fn sphere_span(o: DVec3, d: DVec3, radius: f64) -> Option<(f64, f64)> {
    let b = o.dot(d);
    let disc = b * b - (o.length_squared() - radius * radius);
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    Some((-b - s, -b + s))
}

fn sphere_entry(o: DVec3, d: DVec3, radius: f64) -> Option<f64> {
    let (t0, t1) = sphere_span(o, d, radius)?;
    [t0, t1].into_iter().find(|t| *t > 0.0)
}

/// Slab test against a centred box; the normal is that of the face crossed.
fn box_entry(o: DVec3, d: DVec3, half: DVec3) -> Option<(f64, DVec3)> {
    let (mut t_near, mut t_far) = (f64::NEG_INFINITY, f64::INFINITY);
    for axis in 0..3 {
        if d[axis] == 0.0 {
            if o[axis].abs() > half[axis] {
                return None;
            }
            continue;
        }
        let ta = (-half[axis] - o[axis]) / d[axis];
        let tb = (half[axis] - o[axis]) / d[axis];
        t_near = t_near.max(ta.min(tb));
        t_far = t_far.min(ta.max(tb));
    }
    if t_far < t_near || t_far <= 0.0 {
        return None;
    }
    let t = if t_near > 0.0 { t_near } else { t_far };
    let p = (o + t * d) / half;
    let axis = if p.x.abs() >= p.y.abs() && p.x.abs() >= p.z.abs() {
        0
    } else if p.y.abs() >= p.z.abs() {
        1
    } else {
        2
    };
    let mut normal = DVec3::ZERO;
    normal[axis] = p[axis].signum();
    Some((t, normal))
}

/// Sphere tracing of the torus's exact distance function inside its bounding sphere.
fn torus_entry(o: DVec3, d: DVec3, major: f64, minor: f64) -> Option<(f64, DVec3)> {
    const MAX_STEPS: usize = 1000;
    const SURFACE_EPS: f64 = 1e-9;
    let sdf = |p: DVec3| (DVec3::new(p.x, p.y, 0.0).length() - major).hypot(p.z) - minor;
    let (t_enter, t_exit) = sphere_span(o, d, major + minor)?;
    let mut t = t_enter.max(0.0);
    for _ in 0..MAX_STEPS {
        if t > t_exit {
            return None;
        }
        let p = o + t * d;
        let distance = sdf(p);
        if distance < SURFACE_EPS {
            let ring_point = DVec3::new(p.x, p.y, 0.0).normalize_or(DVec3::X) * major;
            return Some((t, (p - ring_point).normalize_or(DVec3::Z)));
        }
        t += distance;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view_from(eye: DVec3, size: u32) -> View {
        View::look_at(eye, DVec3::ZERO, DVec3::Z, intrinsics_from_angle_x(size, size, CAMERA_ANGLE_X))
    }

    #[test]
    fn objects_fit_in_the_box_and_in_every_frame() {
        // A ball of this radius about the origin is wholly inside the horizontal field of view
        // of every camera (4 units out, 0.69 rad), so image corners are always background.
        let in_frame = CAMERA_DISTANCE * (0.5 * CAMERA_ANGLE_X).sin() - 0.05;
        for scene in SynthScene::ALL {
            for o in objects(scene) {
                let (reach, radius) = match o.shape {
                    Shape::Sphere { radius } => (DVec3::splat(radius), radius),
                    Shape::Box { half } => {
                        let m = glam::DMat3::from_quat(o.world_from_object);
                        (m.x_axis.abs() * half.x + m.y_axis.abs() * half.y + m.z_axis.abs() * half.z, half.length())
                    }
                    Shape::Torus { major, minor } => (DVec3::splat(major + minor), major + minor),
                };
                let (lo, hi) = (o.center_in_world - reach, o.center_in_world + reach);
                assert!(lo.min_element() >= -1.5 && hi.max_element() <= 1.5, "{scene}: {lo} .. {hi}");
                assert!(o.center_in_world.length() + radius <= in_frame, "{scene}: {}", o.center_in_world.length() + radius);
            }
        }
    }

    #[test]
    fn compositing_is_front_to_back_over() {
        let (red, blue) = (DVec3::X, DVec3::Z);
        let [r, g, b, a] = composite_front_to_back([(red, 0.5), (blue, 1.0)].into_iter());
        assert_eq!([r, g, b, a], [0.5, 0.0, 0.5, 1.0]);
        let [r, _, b, a] = composite_front_to_back([(blue, 1.0), (red, 0.5)].into_iter());
        assert_eq!([r, b, a], [0.0, 1.0, 1.0]);
        assert_eq!(composite_front_to_back([(red, 0.5)].into_iter())[3], 0.5);
        assert_eq!(composite_front_to_back(std::iter::empty()), [0.0; 4]);
        // Mixed scene: a ray through the torus tube and on into the box composites both.
        let objects = objects(SynthScene::Mixed);
        let (cube, torus) = (objects[0], objects[2]);
        let tube = torus.center_in_world + torus.world_from_object * DVec3::new(-0.45, 0.0, 0.0);
        let dir = (cube.center_in_world - tube).normalize();
        let origin = tube - 3.0 * dir;
        let (torus_hit, cube_hit) = (torus.intersect(origin, dir).unwrap(), cube.intersect(origin, dir).unwrap());
        assert!(torus_hit.t < cube_hit.t);
        let (torus_colour, _) = torus.shade(&torus_hit, dir);
        let (cube_colour, _) = cube.shade(&cube_hit, dir);
        let expected = 0.5 * torus_colour + 0.5 * cube_colour;
        let [r, g, b, a] = trace(&objects, origin, dir);
        assert!((DVec3::new(r, g, b) - expected).length() < 1e-12 && a == 1.0);
        // The same tube point seen against the empty sky: alpha is the torus opacity.
        let up = DVec3::new(0.0, 0.3, 1.0).normalize();
        assert_eq!(trace(&objects, tube - 3.0 * up, up)[3], TORUS_OPACITY as f64);
    }

    #[test]
    fn closed_form_intersections() {
        let t = sphere_entry(DVec3::new(0.0, 0.0, 5.0), -DVec3::Z, 1.0).unwrap();
        assert!((t - 4.0).abs() < 1e-12);
        assert!(sphere_entry(DVec3::new(2.0, 0.0, 5.0), -DVec3::Z, 1.0).is_none());
        let (t, n) = box_entry(DVec3::new(0.1, 0.2, 5.0), -DVec3::Z, DVec3::new(1.0, 1.0, 0.5)).unwrap();
        assert!((t - 4.5).abs() < 1e-12 && n == DVec3::Z);
        // Axis-parallel ray beside the box (zero direction components).
        assert!(box_entry(DVec3::new(1.5, 0.0, 5.0), -DVec3::Z, DVec3::ONE).is_none());
        // Torus in the xy-plane, seen from above through its tube and through its hole.
        let (t, n) = torus_entry(DVec3::new(1.0, 0.0, 5.0), -DVec3::Z, 1.0, 0.25).unwrap();
        assert!((t - 4.75).abs() < 1e-8 && (n - DVec3::Z).length() < 1e-6, "{t} {n}");
        assert!(torus_entry(DVec3::new(0.0, 0.0, 5.0), -DVec3::Z, 1.0, 0.25).is_none());
        // Edge-on through both sides of the ring: the nearest crossing.
        let (t, _) = torus_entry(DVec3::new(-5.0, 0.0, 0.0), DVec3::X, 1.0, 0.25).unwrap();
        assert!((t - 3.75).abs() < 1e-8, "{t}");
    }

    #[test]
    fn sphere_silhouette_and_alpha_are_exact() {
        // Glossy sphere of radius 0.9: a pixel whose whole footprint is inside the silhouette is
        // opaque, one wholly outside is transparent, and edges are fractional.
        let view = view_from(DVec3::new(1.0, -3.0, 2.0).normalize() * CAMERA_DISTANCE, 48);
        let rgba = render_view(SynthScene::Glossy, &view);
        let footprint = 0.75 * (CAMERA_DISTANCE + 0.9) / view.intrinsics.fx as f64; // half-diagonal of a pixel at the far side
        let (mut inside, mut outside, mut edge) = (0, 0, 0);
        for y in 0..48u32 {
            for x in 0..48u32 {
                let (o, d) = view.ray_in_world(x as f64 + 0.5, y as f64 + 0.5);
                let miss_distance = (o - d * o.dot(d)).length();
                let alpha = rgba[4 * (y * 48 + x) as usize + 3];
                if miss_distance < 0.9 - footprint {
                    assert_eq!(alpha, 1.0, "({x}, {y})");
                    inside += 1;
                } else if miss_distance > 0.9 + footprint {
                    assert_eq!(alpha, 0.0, "({x}, {y})");
                    outside += 1;
                } else if alpha > 0.0 && alpha < 1.0 {
                    edge += 1;
                }
            }
        }
        assert!(inside > 300 && outside > 300 && edge > 40, "{inside} {outside} {edge}");
    }

    #[test]
    fn highlight_follows_the_half_vector() {
        // The brightest pixel of the glossy sphere sits where the normal is the half vector
        // between light and viewer, so it moves with the camera.
        let mut normals = Vec::new();
        for eye in [DVec3::new(0.0, -4.0, 0.5), DVec3::new(3.0, 2.0, 1.5)] {
            let view = view_from(eye.normalize() * CAMERA_DISTANCE, 64);
            let rgba = render_view(SynthScene::Glossy, &view);
            let brightest = (0..64 * 64).max_by(|&a, &b| {
                let sum = |i: usize| rgba[4 * i] + rgba[4 * i + 1] + rgba[4 * i + 2];
                sum(a).total_cmp(&sum(b))
            });
            let i = brightest.unwrap() as u32;
            let (o, d) = view.ray_in_world((i % 64) as f64 + 0.5, (i / 64) as f64 + 0.5);
            let t = sphere_entry(o, d, 0.9).unwrap();
            let normal = (o + t * d).normalize();
            let half_vector = (light_dir_in_world() - d).normalize();
            assert!(normal.dot(half_vector) > 0.99, "{normal} vs {half_vector}");
            normals.push(normal);
        }
        assert!(normals[0].dot(normals[1]) < 0.9, "the highlight did not move");
    }

    #[test]
    fn translucent_torus_has_its_opacity() {
        let view = view_from(DVec3::new(0.5, -2.0, 3.0).normalize() * CAMERA_DISTANCE, 48);
        let rgba = render_view(SynthScene::Translucent, &view);
        let alphas: Vec<f32> = rgba.chunks_exact(4).map(|p| p[3]).collect();
        assert!(alphas.iter().all(|&a| (0.0..=TORUS_OPACITY).contains(&a)));
        let full = alphas.iter().filter(|&&a| a == TORUS_OPACITY).count();
        let empty = alphas.iter().filter(|&&a| a == 0.0).count();
        assert!(full > 200 && empty > 300, "{full} {empty}");
        // The hole in the middle shows the background.
        assert_eq!(alphas[24 * 48 + 24], 0.0);
    }

    #[test]
    fn cameras_are_deterministic_and_spread() {
        let cfg = SynthConfig { n_train: 40, ..SynthConfig::new(SynthScene::Diffuse) };
        let train = cameras(&cfg, Split::Train);
        assert_eq!(train, cameras(&cfg, Split::Train));
        assert_eq!(train.len(), 40);
        let test = cameras(&cfg, Split::Test);
        assert_eq!(test.len(), 20);
        assert_ne!(train[0].world_from_camera, test[0].world_from_camera);
        let other_seed = cameras(&SynthConfig { seed: 7, ..cfg }, Split::Train);
        assert_ne!(train[0].world_from_camera, other_seed[0].world_from_camera);
        let mut below = 0;
        for v in &train {
            assert_eq!(v.validate(), Ok(()));
            let eye = v.world_from_camera.w_axis.truncate();
            assert!((eye.length() - CAMERA_DISTANCE).abs() < 1e-12);
            // Looks at the origin: the camera's −z axis points from the eye to the origin.
            let forward = -v.world_from_camera.z_axis.truncate();
            assert!(forward.dot(-eye.normalize()) > 1.0 - 1e-12);
            below += (eye.z < 0.0) as usize;
        }
        assert!(below > 3 && below < 20, "{below} of 40 below the horizon");
    }

    #[test]
    fn bad_configs_are_refused() {
        let dir = std::env::temp_dir().join(format!("nephele-synth-bad-{}", std::process::id()));
        for cfg in [
            SynthConfig { width: 0, ..SynthConfig::new(SynthScene::Mixed) },
            SynthConfig { height: MAX_EDGE_PX + 1, ..SynthConfig::new(SynthScene::Mixed) },
            SynthConfig { n_train: 0, ..SynthConfig::new(SynthScene::Mixed) },
        ] {
            assert!(matches!(generate(&cfg, &dir), Err(SynthError::BadConfig(_))));
        }
        assert!(!dir.exists());
        assert_eq!("glossy".parse::<SynthScene>(), Ok(SynthScene::Glossy));
        assert!("shiny".parse::<SynthScene>().is_err());
    }

    /// Unused in the scenes but kept honest: a ray starting inside the sphere exits.
    #[test]
    fn rays_from_inside_exit() {
        let t = sphere_entry(DVec3::ZERO, DVec3::X, 1.0).unwrap();
        assert!((t - 1.0).abs() < 1e-12);
        let (t, n) = box_entry(DVec3::ZERO, DVec3::Y, DVec3::ONE).unwrap();
        assert!((t - 1.0).abs() < 1e-12 && n == DVec3::Y);
    }
}
