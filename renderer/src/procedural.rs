//! Procedural assets from analytic shapes, so the renderer, tests and streaming can run before
//! any training. Each shape is a signed distance function with a material; density is a thin
//! solid shell (or a soft volume for the translucent shape), and only what the scene needs is
//! stored: density bricks around surfaces, diffuse bricks around reachable hit points, PSH
//! vertices next to surfaces.
//!
//! The specular MLP gets fixed weights that draw a moving highlight: hidden unit `j` stands for
//! one view direction `v_j` (Fibonacci sphere) and fires when the ray direction is near `v_j`
//! AND the surface normal (stored as PSH features) is near the half vector `h_j = norm(L − v_j)`
//! — a ReLU "and" of two dot products. The last hidden unit passes `α_c` through to α.

use std::str::FromStr;

use glam::{UVec3, Vec3};
use serde::{Deserialize, Serialize};

use crate::{
    asset::{Asset, MarchMeta},
    cubes::{Aabb, TextureCubes},
    mlp::{HIDDEN, SpecularMlp},
    psh::{PshError, SpatialHash},
    sh::SH_COEFFS,
};

/// Which analytic scene to build.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Scene {
    /// A checkered rounded box: opaque, purely diffuse.
    Diffuse,
    /// A dark red sphere with a white moving highlight.
    Shiny,
    /// A soft cyan torus, semi-transparent.
    Translucent,
    /// All three side by side.
    Trio,
}

impl FromStr for Scene {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "diffuse" => Ok(Self::Diffuse),
            "shiny" => Ok(Self::Shiny),
            "translucent" => Ok(Self::Translucent),
            "trio" => Ok(Self::Trio),
            _ => Err(format!("unknown procedural scene {s:?} (diffuse, shiny, translucent, trio)")),
        }
    }
}

/// Resolution and density settings of a generated asset.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProceduralConfig {
    pub scene: Scene,
    pub density_grid: u32,
    pub density_brick: u32,
    pub diffuse_grid: u32,
    pub diffuse_brick: u32,
    pub psh_grid: u32,
    /// Multiplies every density (0 gives an empty-looking but valid asset; huge saturates f16).
    pub sigma_scale: f32,
}

impl ProceduralConfig {
    /// Full quality: used for the embedded default scene.
    pub fn default_quality(scene: Scene) -> Self {
        Self { scene, density_grid: 64, density_brick: 8, diffuse_grid: 64, diffuse_brick: 4, psh_grid: 256, sigma_scale: 1.0 }
    }
    /// Small and quick: test fixtures.
    pub fn small(scene: Scene) -> Self {
        Self { scene, density_grid: 32, density_brick: 4, diffuse_grid: 32, diffuse_brick: 2, psh_grid: 64, sigma_scale: 1.0 }
    }
}

/// Light direction (towards the light), object space.
fn light_dir() -> Vec3 {
    Vec3::new(0.35, -0.45, 0.82).normalize()
}

#[derive(Clone, Copy)]
enum Kind {
    RoundBox { half: Vec3, round: f32 },
    Sphere { radius: f32 },
    Torus { major: f32, minor: f32 },
}

#[derive(Clone, Copy)]
struct Shape {
    kind: Kind,
    center: Vec3,
    /// Translucent shapes are a soft volume of this σ (per object unit); solid ones a shell.
    volume_sigma: Option<f32>,
    shiny: bool,
}

impl Shape {
    fn sdf(&self, p: Vec3) -> f32 {
        let q = p - self.center;
        match self.kind {
            Kind::RoundBox { half, round } => {
                let d = q.abs() - (half - Vec3::splat(round));
                d.max(Vec3::ZERO).length() + d.max_element().min(0.0) - round
            }
            Kind::Sphere { radius } => q.length() - radius,
            Kind::Torus { major, minor } => {
                let ring = Vec3::new(q.x, q.y, 0.0).length() - major;
                (ring * ring + q.z * q.z).sqrt() - minor
            }
        }
    }

    /// Diffuse RGB and specular tint.
    fn material(&self, p: Vec3) -> [f32; 4] {
        match (self.kind, self.shiny) {
            (_, true) => [0.55, 0.06, 0.05, 1.0],
            (Kind::Torus { .. }, _) => [0.1, 0.75, 0.85, 0.0],
            _ => {
                let cell = (p * 3.5).floor();
                let odd = (cell.x + cell.y + cell.z).rem_euclid(2.0) > 0.5;
                if odd { [0.95, 0.55, 0.1, 0.0] } else { [0.15, 0.3, 0.8, 0.0] }
            }
        }
    }
}

fn shapes(scene: Scene) -> Vec<Shape> {
    let boxy = |c| Shape { kind: Kind::RoundBox { half: Vec3::splat(0.45), round: 0.1 }, center: c, volume_sigma: None, shiny: false };
    let ball = |c| Shape { kind: Kind::Sphere { radius: 0.55 }, center: c, volume_sigma: None, shiny: true };
    let ring = |c| Shape { kind: Kind::Torus { major: 0.55, minor: 0.22 }, center: c, volume_sigma: Some(3.5), shiny: false };
    match scene {
        Scene::Diffuse => vec![boxy(Vec3::ZERO)],
        Scene::Shiny => vec![ball(Vec3::ZERO)],
        Scene::Translucent => vec![ring(Vec3::ZERO)],
        Scene::Trio => vec![boxy(Vec3::new(-0.7, 0.55, -0.3)), ball(Vec3::new(0.65, 0.35, 0.0)), ring(Vec3::new(-0.15, -0.75, -0.2))],
    }
}

/// Nearest shape and its signed distance.
fn nearest(shapes: &[Shape], p: Vec3) -> (f32, &Shape) {
    shapes.iter().map(|s| (s.sdf(p), s)).min_by(|a, b| a.0.total_cmp(&b.0)).unwrap()
}

fn normal(shapes: &[Shape], p: Vec3) -> Vec3 {
    let e = 1e-3;
    let f = |q: Vec3| nearest(shapes, q).0;
    Vec3::new(
        f(p + Vec3::X * e) - f(p - Vec3::X * e),
        f(p + Vec3::Y * e) - f(p - Vec3::Y * e),
        f(p + Vec3::Z * e) - f(p - Vec3::Z * e),
    )
    .normalize_or_zero()
}

/// Points on the unit sphere, evenly spread.
fn fibonacci_sphere(n: usize) -> Vec<Vec3> {
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let phi = i as f32 * std::f32::consts::PI * (3.0 - 5f32.sqrt());
            let r = (1.0 - z * z).sqrt();
            Vec3::new(r * phi.cos(), r * phi.sin(), z)
        })
        .collect()
}

/// PSH features per vertex: normal (3) and shininess mask (1).
pub const FEATURES: u32 = 4;

fn highlight_mlp() -> SpecularMlp {
    let f = FEATURES as usize;
    let input = f + SH_COEFFS + 1;
    let mut mlp = SpecularMlp::zeros(input);
    let (cos_n, cos_v) = (0.95f32, 0.94f32);
    let sh1 = 0.488_602_51f32;
    let views = fibonacci_sphere(HIDDEN - 1);
    for (j, v) in views.iter().enumerate() {
        let h = (light_dir() - *v).normalize_or_zero();
        let row = &mut mlp.w0[j * input..(j + 1) * input];
        for a in 0..3 {
            row[a] = h[a] / (1.0 - cos_n);
        }
        row[3] = 4.0;
        // d = (−sh[3], −sh[1], sh[2]) / sh1.
        let kv = 1.0 / (sh1 * (1.0 - cos_v));
        row[f + 1] = -v.y * kv;
        row[f + 2] = v.z * kv;
        row[f + 3] = -v.x * kv;
        mlp.b0[j] = -cos_n / (1.0 - cos_n) - cos_v / (1.0 - cos_v) - 1.0 - 4.0;
    }
    let last = HIDDEN - 1;
    mlp.w0[last * input + input - 1] = 1.0;
    for j in 0..HIDDEN {
        mlp.w1[j * HIDDEN + j] = 1.0;
    }
    for c in 0..3 {
        for j in 0..last {
            mlp.w2[c * HIDDEN + j] = 16.0;
        }
        mlp.b2[c] = -6.0;
    }
    mlp.w2[3 * HIDDEN + last] = 20.0;
    mlp.b2[3] = -14.5;
    mlp
}

/// Builds an asset for `cfg`. Deterministic.
pub fn generate(cfg: &ProceduralConfig) -> Result<Asset, PshError> {
    let bounds = Aabb::cube(1.5);
    let shapes = shapes(cfg.scene);
    let step = bounds.size().x / (cfg.density_grid * cfg.density_brick) as f32;
    // Solid shell: σ rises from 0 to `solid` over `shell` object units across the surface.
    let shell = 2.0 * step;
    let solid = 3.0 / step;
    let sigma = |p: Vec3| -> f32 {
        let (d, s) = nearest(&shapes, p);
        let ramp = (0.5 - d / shell).clamp(0.0, 1.0);
        cfg.sigma_scale * s.volume_sigma.unwrap_or(solid) * ramp
    };
    // A cell is needed if a surface (or a translucent interior) passes within its reach.
    let near_surface = |cell: UVec3, grid: u32, extra: f32| {
        let size = bounds.size() / grid as f32;
        let center = bounds.min + (cell.as_vec3() + 0.5) * size;
        let reach = 0.5 * size.length() + extra;
        let (d, s) = nearest(&shapes, center);
        if s.volume_sigma.is_some() { d < reach } else { d.abs() < reach }
    };
    let density = TextureCubes::bake(
        bounds,
        cfg.density_grid,
        cfg.density_brick,
        1,
        |c| near_surface(c, cfg.density_grid, shell + step),
        |p, out| out[0] = sigma(p).min(65504.0),
    );
    let diffuse = TextureCubes::bake(
        bounds,
        cfg.diffuse_grid,
        cfg.diffuse_brick,
        4,
        |c| near_surface(c, cfg.diffuse_grid, shell + 2.0 * step),
        |p, out| {
            // Baked diffuse radiance: albedo under the key light plus ambient (Lambert).
            let m = nearest(&shapes, p).1.material(p);
            let lambert = 0.35 + 0.65 * normal(&shapes, p).dot(light_dir()).max(0.0);
            out.copy_from_slice(&[m[0] * lambert, m[1] * lambert, m[2] * lambert, m[3]]);
        },
    );
    let n = cfg.psh_grid;
    let vertex_size = bounds.size() / n as f32;
    let vertex_pos = |v: UVec3| bounds.min + v.as_vec3() * vertex_size;
    let reach = 1.5 * vertex_size.length() + shell;
    let mut points = Vec::new();
    for z in 0..=n {
        for y in 0..=n {
            for x in 0..=n {
                let v = UVec3::new(x, y, z);
                let (d, s) = nearest(&shapes, vertex_pos(v));
                if d.abs() < reach || (s.volume_sigma.is_some() && d < 0.0) {
                    points.push(v);
                }
            }
        }
    }
    let psh = SpatialHash::build(
        bounds,
        n,
        FEATURES,
        &points,
        |v, out| {
            let p = vertex_pos(v);
            let nrm = normal(&shapes, p);
            out[..3].copy_from_slice(&nrm.to_array());
            out[3] = if nearest(&shapes, p).1.shiny { 1.0 } else { 0.0 };
        },
        0x5eed,
    )?;
    Ok(Asset {
        name: format!("procedural-{:?}", cfg.scene).to_lowercase(),
        bounds,
        march: MarchMeta { step, alpha_min: 0.02, hits: Default::default(), early_stop: crate::model::DEFAULT_EARLY_STOP },
        density,
        diffuse,
        psh,
        mlp: highlight_mlp(),
        provenance: serde_json::json!({ "generator": "nephele procedural", "config": cfg }),
    })
}
