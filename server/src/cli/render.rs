//! `nephele render` (one view, or a Looking Glass quilt of views, to PNG), `nephele generate` (procedural assets) and
//! `nephele info` (an asset's metadata and memory).

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use glam::{DMat4, DVec3};
use nephele_renderer::{
    Instance, Intrinsics, RenderStats, View, ViewRequest,
    procedural::{self, ProceduralConfig, Scene},
    views::{QuiltLayout, focal_distance},
};

use nephele_farm::{
    assets::{BackendChoice, DEFAULT_ASSET, load_asset, make_backend, parse_color, parse_size},
    catalog::Catalog,
};

#[derive(clap::Args)]
pub struct RenderArgs {
    /// A .nolf file, builtin:<lego|diffuse|shiny|translucent|trio>[-small], or a scene file
    /// (.json: several assets composed by depth).
    #[arg(long, default_value = DEFAULT_ASSET)]
    asset: String,
    /// Deprecated spelling: the asset as a positional argument (use --asset).
    #[arg(hide = true)]
    asset_positional: Option<String>,
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
    #[command(flatten)]
    knobs: nephele_farm::assets::RenderKnobs,
    /// Render a Looking Glass quilt of COLSxROWS views (e.g. 5x9) instead of one view;
    /// `--size` is then one tile. Views are the camera moved sideways with off-axis frusta,
    /// view 0 bottom-left (see `nephele_renderer::views`); all rendered in one batch. The
    /// file name gets the `_qs{cols}x{rows}a{aspect}` suffix displays expect unless it
    /// already has one.
    #[arg(long)]
    quilt: Option<String>,
    /// The quilt's view cone, degrees.
    #[arg(long, default_value_t = 40.0)]
    cone: f32,
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
    /// A .nolf file or builtin:<name>.
    #[arg(long, default_value = DEFAULT_ASSET)]
    asset: String,
    /// Deprecated spelling: the asset as a positional argument (use --asset).
    #[arg(hide = true)]
    asset_positional: Option<String>,
}

/// `--asset` names an asset everywhere; the positional form of `render` and `info` still
/// works, with a warning, until scripts have moved.
fn asset_of(command: &str, asset: String, positional: Option<String>) -> String {
    match positional {
        Some(p) => {
            eprintln!("warning: `nephele {command} ASSET` is deprecated; use `nephele {command} --asset {p}`");
            p
        }
        None => asset,
    }
}

#[derive(serde::Deserialize)]
struct PoseFile {
    transform_matrix: [[f64; 4]; 4],
    camera_angle_x: Option<f64>,
    /// `[fx, fy, cx, cy]` in pixels (an off-centre lens); overrides `camera_angle_x`.
    intrinsics: Option<[f32; 4]>,
}

pub fn render(mut args: RenderArgs) -> Result<()> {
    args.asset = asset_of("render", std::mem::take(&mut args.asset), args.asset_positional.take());
    let settings = args.knobs.settings()?;
    let (w, h) = parse_size(&args.size)?;
    let background = parse_color(&args.background)?;
    let backend = make_backend(args.backend)?;
    let view = match &args.pose {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading pose {}", path.display()))?;
            let pose: PoseFile = serde_json::from_str(&text).with_context(|| format!("parsing pose {}", path.display()))?;
            let fov = pose.camera_angle_x.unwrap_or(args.fov.to_radians());
            let m = DMat4::from_cols_array_2d(&pose.transform_matrix).transpose();
            let intrinsics = match pose.intrinsics {
                Some([fx, fy, cx, cy]) => Intrinsics { fx, fy, cx, cy, width: w, height: h },
                None => Intrinsics::from_fov_x(w, h, fov as f32),
            };
            View { world_from_camera: m, intrinsics }
        }
        None => View::orbit(DVec3::ZERO, args.distance, args.azimuth, args.elevation, Intrinsics::from_fov_x(w, h, args.fov.to_radians() as f32)),
    };
    view.validate().context("the camera")?;
    let quilt = args.quilt.as_deref().map(|q| QuiltLayout::parse(q, args.cone)).transpose().map_err(anyhow::Error::msg)?;
    // A quilt's focal plane goes through the orbit target (the origin).
    let views = match quilt {
        Some(q) => q.cameras(&view, focal_distance(&view, DVec3::ZERO, 1e-3)),
        None => vec![view],
    };
    let is_scene = args.asset.ends_with(".json") || nephele_farm::assets::BUILTIN_SCENE_FILES.iter().any(|(n, _)| args.asset == format!("builtin:{n}"));
    let (frames, s) = if is_scene {
        // A scene: every object rendered and composed by depth (timings summed).
        let catalog = Catalog::load(std::slice::from_ref(&args.asset), backend.as_ref(), settings)?;
        let t = std::time::Instant::now();
        let frames = views.iter().map(|v| catalog.render_scene(&catalog.default_scene, *v, Instance::default(), background)).collect::<Result<Vec<_>>>()?;
        let (rays, hits) = frames.iter().fold((0, 0), |(r, h), f| (r + f.depth.len() as u64, h + f.depth.iter().filter(|d| d.is_finite()).count() as u64));
        (frames, RenderStats { total_ms: t.elapsed().as_secs_f64() * 1e3, rays, hits, ..Default::default() })
    } else {
        let prepared = backend.prepare(load_asset(&args.asset)?)?;
        let requests: Vec<ViewRequest> = views.iter().map(|v| ViewRequest::new(*v).with_background(background)).collect();
        let out = prepared.render(&requests, &settings)?;
        (out.frames, out.stats)
    };
    let (frame, out_path) = match quilt {
        Some(q) => {
            let mut rgba = vec![0u8; (q.views() * w * h * 4) as usize];
            let qw = q.cols * w;
            for (i, f) in frames.iter().enumerate() {
                let (x, y) = q.tile_origin(i as u32, w, h);
                for row in 0..h {
                    let src = &f.rgba[(4 * row * w) as usize..(4 * (row + 1) * w) as usize];
                    let at = (4 * ((y + row) * qw + x)) as usize;
                    rgba[at..at + src.len()].copy_from_slice(src);
                }
            }
            let stem = args.out.file_stem().and_then(|s| s.to_str()).unwrap_or("quilt");
            let out = if stem.contains("_qs") { args.out.clone() } else { args.out.with_file_name(format!("{stem}{}.png", q.file_suffix(w, h))) };
            let (fw, fh) = (qw, q.rows * h);
            (nephele_renderer::Frame { width: fw, height: fh, rgba, depth: vec![f32::INFINITY; (fw * fh) as usize] }, out)
        }
        None => (frames.into_iter().next().expect("one view"), args.out.clone()),
    };
    let args = RenderArgs { out: out_path, ..args };
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
        "wrote {} ({}×{}{}, {}) — march {:.1} ms, network {:.1} ms, total {:.1} ms, {:.1}% of rays hit{}",
        args.out.display(),
        frame.width,
        frame.height,
        quilt.map_or(String::new(), |q| format!(", {} views of {w}×{h}", q.views())),
        backend.name(),
        s.march_ms,
        s.shade_ms,
        s.total_ms,
        100.0 * s.hits as f64 / s.rays.max(1) as f64,
        if s.queries > 0 { format!(", {:.2} network queries per hit ray", s.queries as f64 / s.hits.max(1) as f64) } else { String::new() }
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
    let a = load_asset(&asset_of("info", args.asset, args.asset_positional))?;
    let m = &a.march;
    println!(
        "name: {}\nbounds: {:?}\nstep: {}\nmiss below α_c {}, early stop at T < {}, hits: τ {} and at most {} per ray\nprovenance: {}\n\n{}",
        a.name,
        a.bounds,
        m.step,
        m.alpha_min,
        m.early_stop,
        m.hits.tau,
        m.hits.max_hits,
        a.provenance,
        a.memory()
    );
    Ok(())
}
