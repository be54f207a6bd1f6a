//! `nephele render` (one view to PNG), `nephele generate` (procedural assets) and
//! `nephele info` (an asset's metadata and memory).

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use glam::{DMat4, DVec3};
use nephele_renderer::{
    Instance, Intrinsics, RenderSettings, RenderStats, View, ViewRequest,
    procedural::{self, ProceduralConfig, Scene},
};

use crate::{
    assets::{BackendChoice, DEFAULT_ASSET, load_asset, make_backend, parse_color, parse_size},
    catalog::Catalog,
};

#[derive(clap::Args)]
pub struct RenderArgs {
    /// A .nolf file, builtin:<lego|diffuse|shiny|translucent|trio>[-small], or a scene file
    /// (.json: several assets composed by depth).
    #[arg(default_value = DEFAULT_ASSET)]
    asset: String,
    /// Camera pose: JSON with a row-major 4×4 camera-to-world `transform_matrix` (NeRF style)
    /// and optionally `camera_angle_x`. Overrides the orbit options.
    #[arg(long)]
    pose: Option<PathBuf>,
    /// Orbit azimuth in degrees (about +z).
    #[arg(long, default_value_t = 35.0)]
    azimuth: f64,
    /// Orbit elevation in degrees.
    #[arg(long, default_value_t = 25.0)]
    elevation: f64,
    /// Orbit distance from the object centre, scene units.
    #[arg(long, default_value_t = 4.0)]
    distance: f64,
    /// Horizontal field of view in degrees (NeRF-synthetic uses ~39.6).
    #[arg(long, default_value_t = 39.6)]
    fov: f64,
    #[arg(long, default_value = "800x800")]
    size: String,
    #[arg(long, value_enum, default_value = "auto")]
    backend: BackendChoice,
    /// r,g,b in [0,1] or white/black/green.
    #[arg(long, default_value = "white")]
    background: String,
    #[arg(long, default_value = "out/render.png")]
    out: PathBuf,
    /// Also write depth (grey, near = bright) here.
    #[arg(long)]
    depth: Option<PathBuf>,
    /// Also write alpha here.
    #[arg(long)]
    alpha: Option<PathBuf>,
    /// Step-size multiplier (speed/accuracy knob).
    #[arg(long, default_value_t = 1.0)]
    step_scale: f32,
}

#[derive(clap::Args)]
pub struct GenerateArgs {
    /// diffuse, shiny, translucent or trio.
    #[arg(long, default_value = "trio")]
    scene: String,
    /// Small grids (test fixtures) instead of full quality.
    #[arg(long)]
    small: bool,
    #[arg(long)]
    out: PathBuf,
}

#[derive(clap::Args)]
pub struct InfoArgs {
    #[arg(default_value = DEFAULT_ASSET)]
    asset: String,
}

#[derive(serde::Deserialize)]
struct PoseFile {
    transform_matrix: [[f64; 4]; 4],
    camera_angle_x: Option<f64>,
}

pub fn render(args: RenderArgs) -> Result<()> {
    let (w, h) = parse_size(&args.size)?;
    let background = parse_color(&args.background)?;
    let backend = make_backend(args.backend)?;
    let view = match &args.pose {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading pose {}", path.display()))?;
            let pose: PoseFile = serde_json::from_str(&text).with_context(|| format!("parsing pose {}", path.display()))?;
            let fov = pose.camera_angle_x.unwrap_or(args.fov.to_radians());
            let m = DMat4::from_cols_array_2d(&pose.transform_matrix).transpose();
            View { world_from_camera: m, intrinsics: Intrinsics::from_fov_x(w, h, fov as f32) }
        }
        None => View::orbit(DVec3::ZERO, args.distance, args.azimuth, args.elevation, Intrinsics::from_fov_x(w, h, args.fov.to_radians() as f32)),
    };
    let settings = RenderSettings { step_scale: args.step_scale, ..Default::default() };
    let is_scene = args.asset.ends_with(".json") || crate::assets::BUILTIN_SCENE_FILES.iter().any(|(n, _)| args.asset == format!("builtin:{n}"));
    let (frame, s) = if is_scene {
        // A scene: every object rendered and composed by depth (timings summed).
        let catalog = Catalog::load(std::slice::from_ref(&args.asset), backend.as_ref(), settings)?;
        let t = std::time::Instant::now();
        let frame = catalog.render_scene(&catalog.default_scene, view, Instance::default(), background)?;
        let stats = RenderStats { total_ms: t.elapsed().as_secs_f64() * 1e3, rays: frame.depth.len() as u64, hits: frame.depth.iter().filter(|d| d.is_finite()).count() as u64, ..Default::default() };
        (frame, stats)
    } else {
        let prepared = backend.prepare(load_asset(&args.asset)?)?;
        let mut out = prepared.render(&[ViewRequest::new(view).with_background(background)], &settings)?;
        (out.frames.remove(0), out.stats)
    };
    let frame = &frame;
    if let Some(dir) = args.out.parent() {
        std::fs::create_dir_all(dir)?;
    }
    frame.save_png(&args.out)?;
    if let Some(p) = &args.depth {
        frame.save_depth_png(p)?;
    }
    if let Some(p) = &args.alpha {
        frame.save_alpha_png(p)?;
    }
    if s.hits == 0 {
        eprintln!("note: no ray hit the object; check the camera");
    }
    println!(
        "wrote {} ({w}×{h}, {}) — march {:.1} ms, network {:.1} ms, total {:.1} ms, {:.1}% of rays hit",
        args.out.display(),
        backend.name(),
        s.march_ms,
        s.shade_ms,
        s.total_ms,
        100.0 * s.hits as f64 / s.rays.max(1) as f64
    );
    if !args.out.exists() {
        bail!("output was not written");
    }
    Ok(())
}

pub fn generate(args: GenerateArgs) -> Result<()> {
    let scene: Scene = args.scene.parse().map_err(anyhow::Error::msg)?;
    let cfg = if args.small { ProceduralConfig::small(scene) } else { ProceduralConfig::default_quality(scene) };
    let asset = procedural::generate(&cfg)?;
    asset.save(&args.out)?;
    println!("wrote {} ({} bytes)\n{}", args.out.display(), std::fs::metadata(&args.out)?.len(), asset.memory());
    Ok(())
}

pub fn info(args: InfoArgs) -> Result<()> {
    let a = load_asset(&args.asset)?;
    println!("name: {}\nbounds: {:?}\nstep: {}\nprovenance: {}\n\n{}", a.name, a.bounds, a.march.step, a.provenance, a.memory());
    Ok(())
}
