//! `nephele bench tradeoff`: the speed/accuracy trade of NEPHELE's ablation (Table 5) and of
//! its distance sweep (Fig. 14), measured here, side by side in one run on one backend (the
//! CPU: the only one every variant has) and one size.
//!
//! From one trained i-NGP checkpoint (the teacher) it builds the geometry once, trains the
//! students the rows need (same steps and settings otherwise), and then, for each row, scores
//! held-out views (PSNR / SSIM over white at the dataset's size) and times frames at the
//! benchmark size. Each row of the paper's ablation changes one thing:
//!
//! | row | hit point | diffuse | E_s | student |
//! |---|---|---|---|---|
//! | i-NGP | volume rendering of the field | — | — | — |
//! | i-NOLF base | density network | none (one colour net) | hash grid | A |
//! | + density cubes | cubes | none | hash grid | A |
//! | + diffuse MLP | cubes | net at the hit | hash grid | B |
//! | + diffuse cubes | cubes | B's net baked | hash grid | B |
//! | + PSH 256 | cubes | cubes | PSH 256 | C |
//! | + trained on the bake lattice (the asset) | cubes | cubes | PSH 256 | D |
//! | PSH 128 / 512 | cubes | cubes | PSH N | D at N |
//!
//! The hash grid is the teacher's own encoding (i-NGP's); "trained on the bake lattice" is
//! what `nephele train` does (see [`distill`]).
//!
//! Then the adaptive multi-hit rule (docs/architecture.md §3, beyond the paper): the asset's settings
//! (`nephele train`'s default, PSH 128) trained and rendered with each `--taus` value (τ = 1:
//! one hit), each with its own geometry (the rule decides which bricks and PSH vertices are
//! reachable). Every row reports the network queries per hit ray. `tradeoff_psnr_ms.png`
//! plots PSNR against frame time, one marker per row, its size growing with the model's MB
//! (NEPHELE's Fig. 13).
//!
//! Oracle rows put the ceiling of each structure beside the students: the teacher's own
//! march collapsed by a student's rule (one hit; multi-hit at each τ with each segment's
//! colour at its peak, or averaged over it by weight), scored on the same views.
//!
//! The distance sweep renders an orbit view from far to filling the screen with i-NGP and
//! the asset and plots ms/frame to a PNG.

use std::{
    fmt::Write as _,
    path::{Path, PathBuf},
    sync::Arc,
    time::Instant,
};

use anyhow::{Context, Result, bail};
use glam::{DVec3, Vec3};
use indicatif::ProgressBar;
use serde::{Deserialize, Deserializer, Serialize};

use nephele_renderer::{
    Asset, Backend, FastCpuBackend, Intrinsics, RenderSettings, RenderStats, View, ViewRequest,
    gpu::{GpuBackend, ngp::GpuNgp},
    cubes::TextureCubes,
    model::HitRule,
};
use nephele_train::{
    Trainer,
    dataset::{Dataset, LoadOptions, Split},
    distill::{self, DistillConfig, Distiller, Geometry, Student},
    trainer::eval::{psnr, ssim},
    variants::{self, OracleRule, VariantFrame},
};

use crate::plot::{Dot, DotSeries, Labels, Series, line_chart, scatter_chart};

/// The speed/accuracy table (NEPHELE Table 5) and distance sweep (Fig. 14) from a trained
/// i-NGP checkpoint: trains the i-NOLF variants, scores held-out views, times frames.
#[derive(clap::Args, Debug, Clone)]
pub struct TradeoffArgs {
    #[arg(required_unless_present = "replot")]
    dataset: Option<PathBuf>,
    /// The teacher: an i-NGP checkpoint (e.g. DIR.train/ngp.ckpt from `nephele train`).
    #[arg(long, required_unless_present = "replot")]
    teacher: Option<PathBuf>,
    #[arg(long, default_value_t = 2)]
    downscale: u32,
    /// Held-out views as in `train --holdout-every` (needed without a test split).
    #[arg(long)]
    holdout_every: Option<usize>,
    /// Appearance steps per student.
    #[arg(long, default_value_t = 2000)]
    nolf_steps: u64,
    /// PSH grid sizes (must include 256).
    #[arg(long, default_value = "128,256,512", value_delimiter = ',')]
    psh: Vec<u32>,
    /// Frame size for the timings.
    #[arg(long, default_value = "800x800")]
    size: String,
    /// Held-out views scored.
    #[arg(long, default_value_t = 10)]
    views: usize,
    /// Camera distances in the sweep.
    #[arg(long, default_value_t = 7)]
    distances: usize,
    /// Where the plot and JSON go.
    #[arg(long, default_value = "tradeoff")]
    out: PathBuf,
    /// Also time i-NGP and the asset on wgpu (one frame each; slow on software Vulkan).
    #[arg(long)]
    gpu: bool,
    /// Multi-hit thresholds τ of the rows of `nephele train`'s settings (1 = one hit).
    #[arg(long, default_value = "1,0.2,0.1,0.05", value_delimiter = ',')]
    taus: Vec<f32>,
    /// Most network queries per ray in those rows.
    #[arg(long, default_value_t = 3)]
    max_hits: u32,
    /// Print the report as JSON on stdout (the table goes to stderr; `OUT/tradeoff.json` is
    /// written either way).
    #[arg(long)]
    pub json: bool,
    /// Redraw the charts of an earlier run from its `tradeoff.json` (into its folder) and
    /// print its table, without training or timing anything.
    #[arg(long, value_name = "TRADEOFF_JSON")]
    pub replot: Option<PathBuf>,
}

/// Runs `nephele bench tradeoff`.
pub fn run_args(args: TradeoffArgs) -> Result<()> {
    let TradeoffArgs { dataset, teacher, downscale, holdout_every, nolf_steps, psh, size, views, distances, out, gpu, taus, max_hits, json, replot } = args;
    if let Some(path) = replot {
        let text = std::fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))?;
        let mut report: Report = serde_json::from_str(&text).with_context(|| format!("{} is not a bench tradeoff report", path.display()))?;
        let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
        draw_charts(&mut report, dir)?;
        return crate::emit(json, &format_report(&report), &report);
    }
    let (Some(dataset), Some(teacher)) = (dataset, teacher) else { bail!("bench tradeoff needs a dataset and --teacher (or --replot)") };
    let size = nephele_farm::assets::parse_size(&size)?;
    let report = run(&TradeoffOptions { dataset, teacher, downscale, holdout_every, nolf_steps, psh_grids: psh, size, views, distances, out, gpu, taus, max_hits })?;
    crate::emit(json, &format_report(&report), &report)
}

#[derive(Debug, Clone)]
pub struct TradeoffOptions {
    pub dataset: PathBuf,
    pub teacher: PathBuf,
    pub downscale: u32,
    pub holdout_every: Option<usize>,
    pub nolf_steps: u64,
    pub psh_grids: Vec<u32>,
    pub size: (u32, u32),
    pub views: usize,
    pub distances: usize,
    pub out: PathBuf,
    /// Also time i-NGP and the asset on the wgpu backend at the benchmark size.
    pub gpu: bool,
    /// Multi-hit thresholds of the τ rows (1 = one hit) and their most queries per ray.
    pub taus: Vec<f32>,
    pub max_hits: u32,
}

/// i-NGP and the i-NOLF asset on the wgpu backend, one frame each at the benchmark size.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct GpuRow {
    pub adapter: String,
    pub ngp_ms: f64,
    pub nolf_ms: f64,
    pub nolf_march_ms: f64,
}

/// JSON has no NaN (`serde_json` writes `null`): read `null` back as NaN.
fn nan_if_null<'de, D: Deserializer<'de>>(d: D) -> std::result::Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// The chart series a row is drawn in.
pub const SERIES_NGP: &str = "i-NGP";
pub const SERIES_ONE_HIT: &str = "i-NOLF, one hit";
pub const SERIES_MULTI_HIT: &str = "i-NOLF, multi-hit";

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Row {
    pub variant: String,
    /// Its marker's label in the PSNR-against-ms chart.
    pub tag: String,
    /// Its series in that chart ([`SERIES_NGP`], …); `None`: not drawn (oracles, untimed).
    pub series: Option<String>,
    #[serde(deserialize_with = "nan_if_null")]
    pub psnr: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub ssim: f64,
    /// Bytes of what the variant needs stored (f32 networks as trained, f16 cubes and PSH).
    pub model_bytes: u64,
    /// Bytes the CPU renderer holds beyond that (f32 copies of f16 data, occupancy grid,
    /// transposed weights).
    pub runtime_extra_bytes: u64,
    #[serde(deserialize_with = "nan_if_null")]
    pub march_ms: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub total_ms: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub fps: f64,
    /// Network queries per hit ray (1 without multi-hit; NaN where not counted).
    #[serde(deserialize_with = "nan_if_null")]
    pub queries_per_hit: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SweepPoint {
    pub distance: f64,
    pub coverage: f64,
    pub ngp_ms: f64,
    pub nolf_ms: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Report {
    pub dataset: String,
    pub eval_views: usize,
    pub eval_size: (u32, u32),
    pub bench_size: (u32, u32),
    pub rows: Vec<Row>,
    pub sweep: Vec<SweepPoint>,
    pub plot: String,
    /// PSNR against ms per frame, one marker per row.
    pub trade_plot: String,
    pub gpu: Option<GpuRow>,
}

fn f32_bytes(n: usize) -> u64 {
    4 * n as u64
}

/// Rays of a view (world space, f32), row-major.
fn view_rays(view: &View) -> Vec<(Vec3, Vec3)> {
    let k = view.intrinsics;
    (0..k.height)
        .flat_map(|y| (0..k.width).map(move |x| (x, y)))
        .map(|(x, y)| {
            let (o, d) = view.ray_in_world(x as f64 + 0.5, y as f64 + 0.5);
            (o.as_vec3(), d.as_vec3())
        })
        .collect()
}

/// Bytes the CPU adds by keeping cube values (f16 or unorm8 when stored) as f32.
fn widened(c: &TextureCubes) -> u64 {
    (4 - c.storage.bytes_per_value()) * c.values.len() as u64
}

fn asset_memory(asset: &Asset) -> (u64, u64) {
    let stored = asset.memory().stored_bytes();
    // Cube and PSH values as f32, and a transposed copy of the MLP.
    let extra = widened(&asset.density) + widened(&asset.diffuse) + 2 * asset.psh.values.len() as u64
        + f32_bytes(asset.mlp.w0.len() + asset.mlp.w1.len() + asset.mlp.w2.len());
    (stored, extra)
}

/// Bytes of the specular net and its encoding (what a student needs beside its diffuse).
fn specular_bytes(s: &Student) -> u64 {
    s.encoding.stored_bytes() + f32_bytes(s.specular_mlp.params().len())
}

fn bar(prefix: &'static str, len: u64) -> ProgressBar {
    let bar = ProgressBar::new(len);
    let style = indicatif::ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {msg} (ETA {eta})").map(|s| s.progress_chars("=> "));
    bar.set_style(style.unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()));
    bar.set_prefix(prefix);
    bar
}

/// Median wall time of `runs` calls (one if a call takes over 2 s).
fn timed<T>(runs: usize, mut f: impl FnMut() -> T) -> (T, f64) {
    let mut times = Vec::new();
    let mut last;
    loop {
        let t = Instant::now();
        last = f();
        times.push(t.elapsed().as_secs_f64() * 1e3);
        if times.len() >= runs || times[0] > 2000.0 {
            break;
        }
    }
    times.sort_by(f64::total_cmp);
    (last, times[times.len() / 2])
}

/// How a row of the table finds hits and shades them.
enum Shading<'a> {
    Ngp,
    /// Hits from the teacher's density network.
    Base(&'a Student),
    /// Hits from the density cubes; diffuse from the student's net or from baked cubes.
    Cubes(&'a Student, Option<&'a TextureCubes>),
    /// The baked asset on the CPU backend.
    Asset(Arc<Asset>),
}

struct Variant<'a> {
    name: String,
    /// Marker label in the PSNR-against-ms plot.
    tag: String,
    shading: Shading<'a>,
    model_bytes: u64,
    runtime_extra_bytes: u64,
}

/// One trained student of the table.
struct Trained {
    label: String,
    distiller: Distiller,
}

fn train_student(label: &str, cfg: DistillConfig, geometry: &Geometry, data: &Dataset) -> Result<Trained> {
    let steps = cfg.steps;
    let mut d = Distiller::new(geometry.with_psh_grid(cfg.psh_grid, cfg.psh_dilation), cfg).context("building the PSH")?;
    let b = bar("nolf", steps);
    b.set_message(label.to_string());
    let t = Instant::now();
    let mut last = 0.0;
    while d.step < steps {
        last = d.train_step(data).psnr();
        b.set_position(d.step);
        b.set_message(format!("{label}: batch PSNR {last:.2} dB"));
    }
    b.finish_and_clear();
    eprintln!("{label}: {steps} steps in {:.0} s, last batch PSNR {last:.2} dB, {:.2} MB of parameters", t.elapsed().as_secs_f64(), d.student.stored_bytes() as f64 / 1048576.0);
    Ok(Trained { label: label.to_string(), distiller: d })
}

pub fn run(opts: &TradeoffOptions) -> Result<Report> {
    if opts.psh_grids.is_empty() || !opts.psh_grids.contains(&256) {
        bail!("--psh must include 256 (the grid of the ablation rows)");
    }
    let (teacher, _) = Trainer::load_checkpoint(&opts.teacher, None).with_context(|| format!("loading {}", opts.teacher.display()))?;
    let load = |split| LoadOptions { split, downscale: opts.downscale, holdout_every: opts.holdout_every, max_images: None };
    let train = Dataset::load(&opts.dataset, &load(Split::Train)).with_context(|| format!("loading {}", opts.dataset.display()))?;
    let mut test = Dataset::load(&opts.dataset, &load(Split::Test)).context("loading the test split (held-out views; use --holdout-every N for a dataset without one)")?;
    test.images.truncate(opts.views.max(1));
    std::fs::create_dir_all(&opts.out).with_context(|| format!("creating {}", opts.out.display()))?;
    eprintln!("teacher step {}; {} train and {} held-out views", teacher.step, train.images.len(), test.images.len());

    // The ablation rows are NEPHELE's i-NOLF: one hit per ray (the τ rows below add multi-hit).
    let base_cfg = DistillConfig { psh_grid: 256, hits: HitRule::default(), ..DistillConfig::default_for(opts.nolf_steps) };
    let t = Instant::now();
    let geometry: Geometry = distill::geometry(&teacher, &train, &base_cfg).map_err(anyhow::Error::msg)?;
    eprintln!("geometry: {} density bricks, {} hits in {:.1} s", geometry.density.brick_count(), geometry.hits.rays.len(), t.elapsed().as_secs_f64());

    // The students: each ablation step of the paper changes one thing, in its order; then
    // this pipeline's addition (the diffuse net trained on its bake lattice) and the PSH sizes.
    // E_s as a hash grid uses the teacher's own encoding (i-NGP's multi-resolution grid).
    let grid = Some(teacher.config.field.grid);
    let at_hit = DistillConfig { train_on_bake_lattice: false, ..base_cfg.clone() };
    let plain = train_student("hash-grid E_s, no diffuse net", DistillConfig { diffuse_net: false, specular_hash_grid: grid, ..at_hit.clone() }, &geometry, &train)?;
    let split = train_student("hash-grid E_s, diffuse net", DistillConfig { specular_hash_grid: grid, ..at_hit.clone() }, &geometry, &train)?;
    let psh_at_hit = train_student("PSH 256, diffuse net at the hit", at_hit, &geometry, &train)?;
    let mut sized = Vec::new();
    let mut grids = opts.psh_grids.clone();
    grids.sort_by_key(|&n| (n != 256, n));
    for n in grids {
        sized.push(train_student(&format!("PSH {n}, diffuse net on its bake lattice"), DistillConfig { psh_grid: n, ..base_cfg.clone() }, &geometry, &train)?);
    }
    let split_diffuse = split.distiller.bake_diffuse();
    let bake = |s: &Trained| -> Result<Arc<Asset>> {
        let asset = s.distiller.bake(geometry.density.clone(), geometry.step, &train.name, serde_json::json!({ "bench": "tradeoff", "student": s.label })).map_err(anyhow::Error::msg)?;
        Ok(Arc::new(asset))
    };
    let (alpha_min, step) = (base_cfg.alpha_min, geometry.step);

    let ngp_model = f32_bytes(teacher.field.parameter_count());
    let ngp_extra = teacher.occupancy.cell_count() as u64 * 4 + teacher.occupancy.cell_count() as u64 / 8 + f32_bytes(teacher.field.density_mlp.params().len() + teacher.field.colour_mlp.params().len());
    let density_stored = geometry.density.stored_bytes();
    let density_extra = widened(&geometry.density);
    let mut variants = vec![
        Variant { name: "i-NGP".into(), tag: "NGP".into(), shading: Shading::Ngp, model_bytes: ngp_model, runtime_extra_bytes: ngp_extra },
        Variant {
            name: "i-NOLF base (density network; hash-grid E_s, no diffuse net)".into(),
            tag: "base".into(),
            shading: Shading::Base(&plain.distiller.student),
            model_bytes: ngp_model + plain.distiller.student.stored_bytes(),
            runtime_extra_bytes: ngp_extra,
        },
        Variant {
            name: "+ density cubes".into(),
            tag: "DT".into(),
            shading: Shading::Cubes(&plain.distiller.student, None),
            model_bytes: density_stored + plain.distiller.student.stored_bytes(),
            runtime_extra_bytes: density_extra,
        },
        Variant {
            name: "+ diffuse MLP".into(),
            tag: "DMLP".into(),
            shading: Shading::Cubes(&split.distiller.student, None),
            model_bytes: density_stored + split.distiller.student.stored_bytes(),
            runtime_extra_bytes: density_extra,
        },
        Variant {
            name: "+ diffuse cubes".into(),
            tag: "DIFT".into(),
            shading: Shading::Cubes(&split.distiller.student, Some(&split_diffuse)),
            model_bytes: density_stored + split_diffuse.stored_bytes() + specular_bytes(&split.distiller.student),
            runtime_extra_bytes: density_extra + widened(&split_diffuse),
        },
    ];
    let mut asset_row = |name: String, tag: String, asset: Arc<Asset>| {
        let (model_bytes, runtime_extra_bytes) = asset_memory(&asset);
        variants.push(Variant { name, tag, shading: Shading::Asset(asset), model_bytes, runtime_extra_bytes });
    };
    asset_row("+ PSH 256 (an asset)".into(), "PSH".into(), bake(&psh_at_hit)?);
    let main = bake(&sized[0])?;
    asset_row("+ diffuse net trained on its bake lattice, PSH 256 (the asset)".into(), "L256".into(), main.clone());
    for s in &sized[1..] {
        asset_row(format!("PSH {} (the asset at another N)", s.distiller.config.psh_grid), format!("L{}", s.distiller.config.psh_grid), bake(s)?);
    }
    // The multi-hit rule: `nephele train`'s settings at each τ, each with its own geometry.
    for &tau in &opts.taus {
        let hits = HitRule { tau, max_hits: if tau < 1.0 { opts.max_hits } else { 1 }, ..HitRule::default() };
        let cfg = DistillConfig { hits, ..DistillConfig::default_for(opts.nolf_steps) };
        let label = if hits.one_hit() { "one hit (τ = 1)".to_string() } else { format!("τ = {tau}, up to {} hits", hits.max_hits) };
        let geometry = distill::geometry(&teacher, &train, &cfg).map_err(anyhow::Error::msg)?;
        let student = train_student(&format!("PSH {}, {label}", cfg.psh_grid), cfg.clone(), &geometry, &train)?;
        let asset = student.distiller.bake(geometry.density.clone(), geometry.step, &train.name, serde_json::json!({ "bench": "tradeoff", "student": student.label })).map_err(anyhow::Error::msg)?;
        asset_row(format!("`nephele train` default (PSH {}), {label}", cfg.psh_grid), format!("T{tau}"), Arc::new(asset));
    }
    let render = |v: &Variant<'_>, rays: &[(Vec3, Vec3)]| -> VariantFrame {
        match &v.shading {
            Shading::Ngp => variants::render_ngp(&teacher, rays, Vec3::ONE),
            Shading::Base(s) => variants::render_base(&teacher, s, step, alpha_min, rays, Vec3::ONE),
            Shading::Cubes(s, diffuse) => variants::render_cubes(s, &geometry.density, *diffuse, step, alpha_min, base_cfg.early_stop, rays, Vec3::ONE),
            Shading::Asset(_) => unreachable!("assets render on the backend"),
        }
    };

    // Oracles: the teacher's own march collapsed by each student rule (the ceiling of each
    // structure), scored on the same views; no times (they cost a teacher march).
    let mut oracle_rules = vec![(OracleRule::OneHit, "oracle: the teacher's colour at its max-weight sample (ideal one-hit student)".to_string())];
    for &tau in opts.taus.iter().filter(|&&t| t < 1.0) {
        let rule = HitRule { tau, max_hits: opts.max_hits, ..HitRule::default() };
        oracle_rules.push((OracleRule::MultiHit { rule, averaged: false }, format!("oracle: multi-hit τ = {tau}, colour at each segment's peak")));
        oracle_rules.push((OracleRule::MultiHit { rule, averaged: true }, format!("oracle: multi-hit τ = {tau}, each segment's colour averaged by weight")));
    }
    let rules: Vec<OracleRule> = oracle_rules.iter().map(|r| r.0).collect();
    let gap_t = HitRule::default().gap_steps * step;
    let b = bar("oracles", test.images.len() as u64);
    let mut oracle_sums = vec![(0.0, 0.0, 0usize, 0usize); rules.len()];
    for im in &test.images {
        let truth = im.composite_over(Vec3::ONE);
        for (sum, frame) in oracle_sums.iter_mut().zip(variants::render_oracles(&teacher, &im.rays().collect::<Vec<_>>(), Vec3::ONE, gap_t, alpha_min, &rules)) {
            sum.0 += psnr(&truth, &frame.rgb);
            sum.1 += ssim(&truth, &frame.rgb, im.width as usize, im.height as usize, 3);
            sum.2 += frame.hits;
            sum.3 += frame.queries;
        }
        b.inc(1);
    }
    b.finish_and_clear();
    let oracle_rows: Vec<Row> = oracle_rules
        .iter()
        .zip(&oracle_sums)
        .map(|((_, name), &(p, s, hits, queries))| {
            let n = test.images.len() as f64;
            Row {
                variant: name.clone(),
                tag: String::new(),
                series: None,
                psnr: p / n,
                ssim: s / n,
                model_bytes: ngp_model,
                runtime_extra_bytes: ngp_extra,
                march_ms: f64::NAN,
                total_ms: f64::NAN,
                fps: f64::NAN,
                queries_per_hit: queries as f64 / hits.max(1) as f64,
            }
        })
        .collect();

    // Quality on held-out views.
    let b = bar("eval", (variants.len() * test.images.len()) as u64);
    let mut scores = Vec::new();
    for v in &variants {
        let (mut p, mut s) = (0.0, 0.0);
        for im in &test.images {
            let truth = im.composite_over(Vec3::ONE);
            let out = match &v.shading {
                Shading::Asset(asset) => distill::render_image(asset, im, Vec3::ONE),
                _ => render(v, &im.rays().collect::<Vec<_>>()).rgb,
            };
            p += psnr(&truth, &out);
            s += ssim(&truth, &out, im.width as usize, im.height as usize, 3);
            b.inc(1);
        }
        let n = test.images.len() as f64;
        scores.push((p / n, s / n));
    }
    b.finish_and_clear();

    // Speed at the benchmark size, from the first held-out camera.
    let first = &test.images[0];
    let k = first.view.intrinsics;
    let (w, h) = opts.size;
    let intrinsics = Intrinsics { fx: k.fx * w as f32 / k.width as f32, fy: k.fy * h as f32 / k.height as f32, cx: k.cx * w as f32 / k.width as f32, cy: k.cy * h as f32 / k.height as f32, width: w, height: h };
    let view = View { world_from_camera: first.view.world_from_camera, intrinsics };
    let rays = view_rays(&view);
    let settings = RenderSettings::default();
    let time_on = |backend: &dyn Backend, asset: &Arc<Asset>, view: &View| -> Result<RenderStats> {
        let prepared = backend.prepare(asset.clone())?;
        let req = [ViewRequest::new(*view).with_background(Vec3::ONE)];
        prepared.render(&req, &settings)?;
        let mut runs = Vec::new();
        for _ in 0..3 {
            runs.push(prepared.render(&req, &settings)?);
        }
        runs.sort_by(|a, b| a.stats.total_ms.total_cmp(&b.stats.total_ms));
        Ok(runs[1].stats)
    };
    let backend = FastCpuBackend;
    let time_asset = |asset: &Arc<Asset>, view: &View| time_on(&backend, asset, view);
    let b = bar("time", variants.len() as u64);
    let mut rows = Vec::new();
    for (v, &(psnr, ssim)) in variants.iter().zip(&scores) {
        let (march_ms, total_ms, queries_per_hit) = match &v.shading {
            Shading::Asset(asset) => {
                let s = time_asset(asset, &view)?;
                (s.march_ms, s.total_ms, s.queries as f64 / s.hits.max(1) as f64)
            }
            // The slow network variants once, the rest the median of three.
            Shading::Ngp => {
                let (f, ms) = timed(1, || render(v, &rays));
                (f.march_ms, ms, f64::NAN)
            }
            Shading::Base(_) => {
                let (f, ms) = timed(1, || render(v, &rays));
                (f.march_ms, ms, 1.0)
            }
            Shading::Cubes(..) => {
                let (f, ms) = timed(3, || render(v, &rays));
                (f.march_ms, ms, 1.0)
            }
        };
        let multi = matches!(&v.shading, Shading::Asset(a) if !a.march.hits.one_hit());
        let series = match v.shading {
            Shading::Ngp => SERIES_NGP,
            _ if multi => SERIES_MULTI_HIT,
            _ => SERIES_ONE_HIT,
        };
        rows.push(Row {
            variant: v.name.clone(),
            tag: v.tag.clone(),
            series: Some(series.into()),
            psnr,
            ssim,
            model_bytes: v.model_bytes,
            runtime_extra_bytes: v.runtime_extra_bytes,
            march_ms,
            total_ms,
            fps: 1e3 / total_ms,
            queries_per_hit,
        });
        b.inc(1);
    }
    b.finish_and_clear();
    rows.extend(oracle_rows);
    // Distance sweep: an orbit at the first held-out camera's direction, far → filling the screen.
    let centre = main.bounds.center().as_dvec3();
    let eye = first.view.world_from_camera.w_axis.truncate();
    let dir = (eye - centre).normalize();
    let radius = main.bounds.radius() as f64;
    let (near, far) = (1.2 * radius, 8.0 * radius);
    let n = opts.distances.max(2);
    let b = bar("sweep", n as u64);
    let mut sweep = Vec::new();
    for i in 0..n {
        let distance = far * (near / far).powf(i as f64 / (n - 1) as f64);
        let v = View::look_at(centre + distance * dir, centre, DVec3::Z, intrinsics);
        let s = time_asset(&main, &v)?;
        let (nolf_ms, coverage) = (s.total_ms, s.hits as f64 / s.rays.max(1) as f64);
        let (_, ngp_ms) = timed(1, || variants::render_ngp(&teacher, &view_rays(&v), Vec3::ONE));
        sweep.push(SweepPoint { distance, coverage, ngp_ms, nolf_ms });
        b.inc(1);
    }
    b.finish_and_clear();
    let gpu = if opts.gpu {
        let gpu_backend = GpuBackend::new().context("--gpu: no wgpu adapter")?;
        let adapter = gpu_backend.ctx.describe();
        let ngp = GpuNgp::new(gpu_backend.ctx.clone(), &teacher)?;
        ngp.render(&rays[..64.min(rays.len())], Vec3::ONE)?; // compiles the kernel
        let (_, ngp_ms) = ngp.render(&rays, Vec3::ONE)?;
        let s = time_on(&gpu_backend, &main, &view)?;
        let (nolf_march_ms, nolf_ms) = (s.march_ms, s.total_ms);
        Some(GpuRow { adapter, ngp_ms, nolf_ms, nolf_march_ms })
    } else {
        None
    };
    let mut report = Report {
        dataset: opts.dataset.display().to_string(),
        eval_views: test.images.len(),
        eval_size: (first.width, first.height),
        bench_size: opts.size,
        rows,
        sweep,
        plot: String::new(),
        trade_plot: String::new(),
        gpu,
    };
    draw_charts(&mut report, &opts.out)?;
    std::fs::write(opts.out.join("tradeoff.json"), serde_json::to_string_pretty(&report)?)?;
    Ok(report)
}

/// Draws the distance sweep and the PSNR-against-ms trade (marker size from the model's MB)
/// into `dir` and records their paths in `r`.
fn draw_charts(r: &mut Report, dir: &Path) -> Result<()> {
    let (w, h) = r.bench_size;
    let plot = dir.join("tradeoff_distance.png");
    let title = format!("{w}x{h} frame time as the camera approaches, CPU");
    line_chart(
        &plot,
        &Labels { title: &title, x: "camera distance (scene units)", y: "ms per frame (log)" },
        &[
            Series { name: "i-NGP".into(), rgb: [214, 39, 40], points: r.sweep.iter().map(|p| (p.distance, p.ngp_ms)).collect() },
            Series { name: "i-NOLF".into(), rgb: [31, 119, 180], points: r.sweep.iter().map(|p| (p.distance, p.nolf_ms)).collect() },
        ],
        true,
    )?;
    let trade_plot = dir.join("tradeoff_psnr_ms.png");
    let dots = |series: &str| -> Vec<Dot> {
        r.rows
            .iter()
            .filter(|row| row.series.as_deref() == Some(series) && row.total_ms.is_finite() && row.psnr.is_finite())
            .map(|row| Dot { x: row.total_ms, y: row.psnr, radius_px: 2 + (row.model_bytes as f64 / 1048576.0).sqrt().round() as i64, label: row.tag.clone() })
            .collect()
    };
    let title = format!("held-out PSNR against {w}x{h} CPU frame time; marker size: model MB");
    scatter_chart(
        &trade_plot,
        &Labels { title: &title, x: "ms per frame (log)", y: "PSNR dB" },
        &[
            DotSeries { name: SERIES_NGP.into(), rgb: [214, 39, 40], dots: dots(SERIES_NGP) },
            DotSeries { name: SERIES_ONE_HIT.into(), rgb: [31, 119, 180], dots: dots(SERIES_ONE_HIT) },
            DotSeries { name: SERIES_MULTI_HIT.into(), rgb: [44, 160, 44], dots: dots(SERIES_MULTI_HIT) },
        ],
        true,
    )?;
    r.plot = plot.display().to_string();
    r.trade_plot = trade_plot.display().to_string();
    Ok(())
}

pub fn format_report(r: &Report) -> String {
    let mut s = String::new();
    let (w, h) = r.bench_size;
    let _ = writeln!(
        s,
        "Table 5 here: {} held-out views at {}x{} (PSNR/SSIM over white); times at {w}x{h}, CPU backend, same run\n",
        r.eval_views, r.eval_size.0, r.eval_size.1
    );
    let _ = writeln!(s, "| variant | PSNR dB | SSIM | model MB | extra runtime MB | queries per hit ray | ray-march ms | total ms | FPS | speed-up vs i-NGP |");
    let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let base = r.rows.first().map_or(f64::NAN, |x| x.total_ms);
    for x in &r.rows {
        let march = if x.march_ms.is_finite() { format!("{:.1}", x.march_ms) } else { "—".into() };
        let queries = if x.queries_per_hit.is_finite() { format!("{:.2}", x.queries_per_hit) } else { "—".into() };
        let timed = if x.total_ms.is_finite() { format!("{:.1} | {:.2} | {:.1}×", x.total_ms, x.fps, base / x.total_ms) } else { "— | — | —".into() };
        let _ = writeln!(
            s,
            "| {} | {:.2} | {:.4} | {:.2} | {:.2} | {queries} | {march} | {timed} |",
            x.variant,
            x.psnr,
            x.ssim,
            x.model_bytes as f64 / 1048576.0,
            x.runtime_extra_bytes as f64 / 1048576.0,
        );
    }
    if let Some(g) = &r.gpu {
        let _ = writeln!(
            s,
            "\nwgpu ({}), {w}x{h}, same view: i-NGP {:.0} ms, i-NOLF asset {:.0} ms (ray march {:.0} ms): {:.1}× faster\n",
            g.adapter,
            g.ngp_ms,
            g.nolf_ms,
            g.nolf_march_ms,
            g.ngp_ms / g.nolf_ms
        );
    }
    let _ = writeln!(s, "\nFig. 13 here: PSNR against ms per frame, one marker per row, size from the model's MB: {}", r.trade_plot);
    let _ = writeln!(s, "\nFig. 14 here: ms per {w}x{h} frame as the camera approaches (red i-NGP, blue i-NOLF; plot {})\n", r.plot);
    let _ = writeln!(s, "| distance | screen coverage | i-NGP ms | i-NOLF ms | speed-up |");
    let _ = writeln!(s, "|---:|---:|---:|---:|---:|");
    for p in &r.sweep {
        let _ = writeln!(s, "| {:.2} | {:.1}% | {:.1} | {:.1} | {:.1}× |", p.distance, 100.0 * p.coverage, p.ngp_ms, p.nolf_ms, p.ngp_ms / p.nolf_ms);
    }
    s
}
