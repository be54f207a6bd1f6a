//! `nephele train` and `nephele eval`: the whole pipeline from a posed-image dataset to a
//! `.nolf` asset — the i-NGP field (checkpointed, resumable), then the i-NOLF stages of
//! [`nephele_train::distill`] — each stage with a progress bar; and evaluation of
//! an asset or an i-NGP checkpoint on a dataset split (PSNR, SSIM, side-by-side images).

use std::{
    path::{Path, PathBuf},
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail};
use glam::Vec3;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

use nephele_renderer::Asset;
use nephele_train::{
    TrainConfig, Trainer,
    dataset::{Dataset, LoadOptions, Split},
    distill::{self, DistillConfig, Distiller, geometry},
    variants,
    trainer::eval::{psnr, ssim, write_comparison_png},
};

/// File names inside the work directory.
pub const NGP_CHECKPOINT: &str = "ngp.ckpt";
pub const STUDENT_CHECKPOINT: &str = "student.ckpt";

/// Where training stops.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Until {
    /// After the i-NGP field (the teacher and baseline).
    Ngp,
    /// After the whole pipeline: the `.nolf` asset.
    Asset,
}

#[derive(Debug, Clone, clap::Args)]
pub struct TrainOptions {
    /// NeRF-synthetic folder or instant-ngp transforms.json / folder.
    pub dataset: PathBuf,
    /// The asset to write (A.nolf); with `--until ngp`, any path (the work directory).
    #[arg(long)]
    pub out: PathBuf,
    /// Checkpoints of the stages (default: the asset path with .train).
    #[arg(long)]
    pub work: Option<PathBuf>,
    /// How much training: tiny, fast, default or quality.
    #[arg(long, default_value = "default", value_parser = clap::builder::PossibleValuesParser::new(TrainConfig::PRESETS))]
    pub preset: String,
    /// Steps of the i-NGP stage (default: tiny 500, fast 2000, default 6000, quality 20000).
    #[arg(long)]
    pub steps: Option<u64>,
    /// Steps of the i-NOLF appearance stage (default: tiny 300, fast 1000, default 2000,
    /// quality 6000).
    #[arg(long)]
    pub nolf_steps: Option<u64>,
    /// Stop after the i-NGP stage, or go on to the asset.
    #[arg(long, value_enum, default_value = "asset")]
    pub until: Until,
    /// Stop this run when the i-NGP stage reaches step N (checkpointed; continue with
    /// --resume and the same --steps, which also set the learning-rate schedule).
    #[arg(long)]
    pub stop_at_step: Option<u64>,
    /// Shrink images by 1, 2, 4 or 8.
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// Train on all views but every N-th of the train file (eval then uses
    /// `--split test --holdout-every N`).
    #[arg(long)]
    pub holdout_every: Option<usize>,
    /// Continue from the work directory's checkpoints (same preset and seed); finished
    /// stages are skipped.
    #[arg(long)]
    pub resume: bool,
    /// Write the i-NGP checkpoint every N steps (and at the end).
    #[arg(long, default_value_t = 500)]
    pub checkpoint_every: u64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Print a JSON summary.
    #[arg(long)]
    pub json: bool,
    /// Without a terminal (no progress bar), log progress every N steps.
    #[arg(long, default_value_t = 100)]
    pub log_every: u64,
    /// Score i-NGP and the asset on up to N held-out views for the asset's provenance.
    #[arg(long, default_value_t = 10)]
    pub eval_views: usize,
    /// JSON object overriding i-NOLF settings of the preset, e.g.
    /// '{"psh_grid": 256, "diffuse_dilation": 1}' (an unknown name lists the known ones).
    #[arg(long)]
    pub nolf_config: Option<String>,
}

/// Step counts of a preset: (i-NGP, i-NOLF).
pub fn default_steps(preset: &str) -> (u64, u64) {
    match preset {
        "tiny" => (500, 300),
        "fast" => (2_000, 1_000),
        "default" => (6_000, 2_000),
        _ => (20_000, 6_000),
    }
}

/// The i-NOLF settings of a preset.
pub fn distill_preset(preset: &str, steps: u64) -> DistillConfig {
    match preset {
        "tiny" => DistillConfig::tiny(steps),
        "quality" => DistillConfig::quality(steps),
        _ => DistillConfig::default_for(steps),
    }
}

/// `base` with the fields of the JSON object `overrides` replaced; unknown fields are errors.
pub fn override_config(base: &DistillConfig, overrides: &str) -> Result<DistillConfig> {
    let patch: serde_json::Value = serde_json::from_str(overrides).context("--nolf-config is not JSON")?;
    let Some(patch) = patch.as_object() else { bail!("--nolf-config should be a JSON object, e.g. {{\"psh_grid\": 256}}") };
    let mut value = serde_json::to_value(base)?;
    let fields = value.as_object_mut().expect("a struct serialises to an object");
    for (key, v) in patch {
        if !fields.contains_key(key) {
            bail!("--nolf-config: unknown setting {key:?} (known: {})", fields.keys().cloned().collect::<Vec<_>>().join(", "));
        }
        fields.insert(key.clone(), v.clone());
    }
    let config: DistillConfig = serde_json::from_value(value).context("--nolf-config: a value has the wrong type")?;
    config.validate().map_err(anyhow::Error::msg).context("--nolf-config")?;
    Ok(config)
}

#[derive(Debug, Clone, Serialize)]
pub struct NgpSummary {
    /// The scene box (min, max), world units.
    pub bounds: [[f32; 3]; 2],
    pub resumed_from_step: Option<u64>,
    pub steps: u64,
    /// Batch loss (MSE) and PSNR of the last step taken in this run (None if none was).
    pub final_loss: Option<f64>,
    pub final_batch_psnr: Option<f64>,
    pub seconds: f64,
    pub ms_per_step: f64,
    pub checkpoint: String,
}

#[derive(Debug, Clone, Serialize)]
pub struct NolfSummary {
    pub bounds: [[f32; 3]; 2],
    pub step: f32,
    pub density_bricks: usize,
    pub hit_rays: usize,
    pub total_rays: usize,
    /// Rays the ground truth calls opaque (α ≥ ½) that miss the baked density.
    pub missed_opaque_rays: usize,
    pub psh_entries: usize,
    pub geometry_seconds: f64,
    pub steps: u64,
    pub resumed: bool,
    pub final_batch_psnr: Option<f64>,
    pub train_seconds: f64,
    pub bake_seconds: f64,
    pub asset_bytes: u64,
    pub dense_equivalent_bytes: u64,
}

/// PSNR / SSIM of the teacher and the asset on held-out views (over white).
#[derive(Debug, Clone, Serialize)]
pub struct HeldOut {
    pub split: String,
    pub views: usize,
    pub width: u32,
    pub height: u32,
    pub ngp_psnr: f64,
    pub ngp_ssim: f64,
    pub nolf_psnr: f64,
    pub nolf_ssim: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct TrainSummary {
    pub preset: String,
    pub dataset: String,
    pub train_images: usize,
    pub ngp: NgpSummary,
    pub nolf: Option<NolfSummary>,
    pub held_out: Option<HeldOut>,
    pub asset: Option<String>,
    pub seconds: f64,
}

fn bar_style(template: &str) -> ProgressStyle {
    ProgressStyle::with_template(template).map(|s| s.progress_chars("=> ")).unwrap_or_else(|_| ProgressStyle::default_bar())
}

pub fn progress_bar(prefix: &'static str, total: u64, start: u64) -> ProgressBar {
    let bar = ProgressBar::new(total);
    bar.set_style(bar_style("{prefix} [{bar:30}] {pos}/{len} {msg} (ETA {eta})"));
    bar.set_prefix(prefix);
    bar.set_position(start);
    bar.reset_eta();
    bar
}

fn spinner(prefix: &'static str, msg: &str) -> ProgressBar {
    let bar = ProgressBar::new_spinner();
    bar.set_style(ProgressStyle::with_template("{prefix} {spinner} {msg} ({elapsed})").unwrap_or_else(|_| ProgressStyle::default_spinner()));
    bar.set_prefix(prefix);
    bar.set_message(msg.to_string());
    bar.enable_steady_tick(Duration::from_millis(200));
    bar
}

/// The work directory of a run.
pub fn work_dir(opts: &TrainOptions) -> PathBuf {
    opts.work.clone().unwrap_or_else(|| if opts.out.extension().is_some_and(|e| e == "nolf") { opts.out.with_extension("train") } else { opts.out.clone() })
}

pub fn train(opts: &TrainOptions) -> Result<TrainSummary> {
    let Some(mut config) = TrainConfig::preset(&opts.preset) else {
        bail!("unknown preset {:?} (use one of: {})", opts.preset, TrainConfig::PRESETS.join(", "));
    };
    if opts.until == Until::Asset && opts.out.extension().is_none_or(|e| e != "nolf") {
        bail!("--out {} should name the asset to write, ending in .nolf (or pass --until ngp)", opts.out.display());
    }
    config.seed = opts.seed;
    let (ngp_default, nolf_default) = default_steps(&opts.preset);
    let steps = opts.steps.unwrap_or(ngp_default);
    // Step decay over the last 40% of the run: ×⅓ at 60%, ×⅒ at 85%.
    config.learning_rate_schedule = vec![(steps * 6 / 10, 1.0 / 3.0), (steps * 85 / 100, 0.1)];
    if opts.checkpoint_every == 0 {
        bail!("--checkpoint-every must be at least 1");
    }
    let mut distill = distill_preset(&opts.preset, opts.nolf_steps.unwrap_or(nolf_default));
    distill.seed = opts.seed;
    if let Some(json) = &opts.nolf_config {
        distill = override_config(&distill, json)?;
    }
    distill.validate().map_err(anyhow::Error::msg)?;
    let started = Instant::now();
    let load = LoadOptions { split: Split::Train, downscale: opts.downscale, holdout_every: opts.holdout_every, ..LoadOptions::default() };
    let t = Instant::now();
    let data = Dataset::load(&opts.dataset, &load).with_context(|| format!("loading the train split of {}", opts.dataset.display()))?;
    let (w, h) = data.images.first().map(|i| (i.width, i.height)).unwrap_or((0, 0));
    eprintln!("dataset {}: {} train images of {w}x{h} (downscale {}) in {:.1} s", data.name, data.images.len(), opts.downscale, t.elapsed().as_secs_f64());
    // instant-ngp's `aabb_scale` k grows its unit cube about the centre; with its default
    // scale 0.33 and offset 0.5 (which NeRF-synthetic's [-1.5, 1.5]³ matches), that is the
    // world box [-1.5k, 1.5k]³.
    if let Some(k) = data.aabb_scale {
        if !(1.0..=128.0).contains(&k) {
            bail!("aabb_scale {k} in {} is outside 1..=128", data.transforms_file.display());
        }
        config.bounds = nephele_renderer::cubes::Aabb::cube(1.5 * k as f32);
        eprintln!("aabb_scale {k}: scene box [-{0}, {0}]³", 1.5 * k);
    }
    let work = work_dir(opts);
    std::fs::create_dir_all(&work).with_context(|| format!("creating work directory {}", work.display()))?;
    let provenance = serde_json::json!({
        "dataset": opts.dataset.display().to_string(),
        "dataset_name": data.name,
        "downscale": opts.downscale,
        "preset": opts.preset,
        "holdout_every": opts.holdout_every,
        "seed": opts.seed,
    });
    let (teacher, ngp) = train_ngp(opts, config, steps, &data, &work, &provenance)?;
    let stopped_early = teacher.step < steps;
    let mut summary = TrainSummary {
        preset: opts.preset.clone(),
        dataset: opts.dataset.display().to_string(),
        train_images: data.images.len(),
        ngp,
        nolf: None,
        held_out: None,
        asset: None,
        seconds: 0.0,
    };
    if stopped_early {
        eprintln!("stopped at step {} of {steps} as asked; continue with --resume", teacher.step);
    } else if opts.until == Until::Asset {
        let (asset, nolf) = train_nolf(opts, &teacher, distill.clone(), &data, &work)?;
        let held_out = if opts.eval_views > 0 { held_out_scores(opts, &teacher, &asset)? } else { None };
        let mut asset = asset;
        summary.seconds = started.elapsed().as_secs_f64();
        asset.provenance = serde_json::json!({
            "generator": "nephele train",
            "created_unix_s": std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0),
            "source": provenance,
            "ngp": { "config": teacher.config, "summary": summary.ngp },
            "nolf": { "config": distill, "summary": nolf },
            "held_out": held_out,
            "training_seconds": summary.seconds,
        });
        asset.save(&opts.out).with_context(|| format!("writing {}", opts.out.display()))?;
        summary.nolf = Some(nolf);
        summary.held_out = held_out;
        summary.asset = Some(opts.out.display().to_string());
    }
    summary.seconds = started.elapsed().as_secs_f64();
    if opts.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        print!("{}", format_summary(&summary));
    }
    Ok(summary)
}

fn format_summary(s: &TrainSummary) -> String {
    let n = &s.ngp;
    let mut out = match (n.final_loss, n.final_batch_psnr) {
        (Some(loss), Some(p)) => format!(
            "ngp: step {} in {:.1} s ({:.1} ms/step); final loss {loss:.6} (batch PSNR {p:.2} dB); checkpoint {}\n",
            n.steps, n.seconds, n.ms_per_step, n.checkpoint
        ),
        _ => format!("ngp: already at step {}; checkpoint {}\n", n.steps, n.checkpoint),
    };
    if let Some(v) = &s.nolf {
        out += &format!(
            "nolf: {} density bricks, {} of {} rays hit ({} opaque rays missed), {} PSH entries; {} steps{}; batch PSNR {}\n",
            v.density_bricks,
            v.hit_rays,
            v.total_rays,
            v.missed_opaque_rays,
            v.psh_entries,
            v.steps,
            if v.resumed { " (resumed)" } else { "" },
            v.final_batch_psnr.map_or("-".into(), |p| format!("{p:.2} dB"))
        );
        out += &format!("asset: {} bytes ({:.1}% of dense grids of the same resolution)\n", v.asset_bytes, 100.0 * v.asset_bytes as f64 / v.dense_equivalent_bytes.max(1) as f64);
    }
    if let Some(h) = &s.held_out {
        out += &format!(
            "held out ({} views of {}x{}, {} split, over white): i-NGP {:.2} dB / SSIM {:.4}; i-NOLF {:.2} dB / SSIM {:.4}\n",
            h.views, h.width, h.height, h.split, h.ngp_psnr, h.ngp_ssim, h.nolf_psnr, h.nolf_ssim
        );
    }
    if let Some(a) = &s.asset {
        out += &format!("wrote {a} ({:.1} s in all)\n", s.seconds);
    }
    out
}

fn train_ngp(opts: &TrainOptions, config: TrainConfig, steps: u64, data: &Dataset, work: &Path, provenance: &serde_json::Value) -> Result<(Trainer, NgpSummary)> {
    let ckpt = work.join(NGP_CHECKPOINT);
    let mut trainer = if opts.resume && ckpt.exists() {
        let (trainer, _) = Trainer::load_checkpoint(&ckpt, Some(&config)).with_context(|| format!("resuming from {}", ckpt.display()))?;
        eprintln!("resuming from {} at step {}", ckpt.display(), trainer.step);
        trainer
    } else if opts.resume {
        bail!("--resume: no checkpoint at {}", ckpt.display());
    } else {
        Trainer::new(config)
    };
    let resumed_from_step = opts.resume.then_some(trainer.step);
    eprintln!(
        "stage ngp: preset {}, {} parameters, {} rays per batch, steps {}..{steps}",
        opts.preset,
        trainer.field.parameter_count(),
        trainer.config.rays_per_batch,
        trainer.step
    );
    let start_step = trainer.step;
    let bar = progress_bar("ngp", steps, start_step.min(steps));
    let stop_at = opts.stop_at_step.unwrap_or(steps).min(steps);
    let t = Instant::now();
    let mut last = None;
    let mut window = (Instant::now(), 0usize);
    // (start of the log interval, step then, rays since)
    let mut log = (Instant::now(), start_step, 0usize);
    while trainer.step < stop_at {
        let s = trainer.train_step(data);
        window.1 += s.batch.rays;
        log.2 += s.batch.rays;
        last = Some(s);
        let secs = window.0.elapsed().as_secs_f64();
        if secs > 0.5 || trainer.step == steps {
            bar.set_message(format!("loss {:.5} PSNR {:.2} dB {:.0}k rays/s", s.batch.loss, s.batch.psnr(), window.1 as f64 / secs.max(1e-9) / 1e3));
            window = (Instant::now(), 0);
        }
        bar.set_position(trainer.step);
        if bar.is_hidden() && opts.log_every > 0 && (trainer.step % opts.log_every == 0 || trainer.step == steps) {
            // Rates over the steps since the previous line (early steps, before the occupancy
            // grid prunes empty space, are much slower than later ones).
            let (since, steps_since, rays_since) = (log.0.elapsed().as_secs_f64(), trainer.step - log.1, log.2);
            eprintln!(
                "ngp step {}/{steps}: loss {:.6}, batch PSNR {:.2} dB, {:.0} ms/step, {:.1}k rays/s, {} samples/ray, {:.0} s elapsed",
                trainer.step,
                s.batch.loss,
                s.batch.psnr(),
                since * 1e3 / steps_since.max(1) as f64,
                rays_since as f64 / since.max(1e-9) / 1e3,
                s.batch.samples / s.batch.rays.max(1),
                t.elapsed().as_secs_f64()
            );
            log = (Instant::now(), trainer.step, 0);
        }
        if trainer.step % opts.checkpoint_every == 0 || trainer.step == stop_at {
            trainer.save_checkpoint(&ckpt, provenance.clone())?;
        }
    }
    bar.finish_and_clear();
    if trainer.step == start_step {
        // Nothing to do, but make sure the checkpoint exists.
        trainer.save_checkpoint(&ckpt, provenance.clone())?;
    }
    let seconds = t.elapsed().as_secs_f64();
    let taken = trainer.step - start_step;
    let summary = NgpSummary {
        bounds: [trainer.config.bounds.min.to_array(), trainer.config.bounds.max.to_array()],
        resumed_from_step,
        steps: trainer.step,
        final_loss: last.map(|s| s.batch.loss),
        final_batch_psnr: last.map(|s| s.batch.psnr()),
        seconds,
        ms_per_step: if taken > 0 { seconds * 1e3 / taken as f64 } else { 0.0 },
        checkpoint: ckpt.display().to_string(),
    };
    Ok((trainer, summary))
}

/// Stages 2–4: geometry, appearance nets (or their checkpoint when resuming), bake.
fn train_nolf(opts: &TrainOptions, teacher: &Trainer, cfg: DistillConfig, data: &Dataset, work: &Path) -> Result<(Asset, NolfSummary)> {
    let augmented;
    let data = if cfg.teacher_views > 0 {
        let t = Instant::now();
        let bar = progress_bar("views", cfg.teacher_views as u64, 0);
        bar.set_message("the teacher renders new views for the student");
        augmented = nephele_train::distill::with_teacher_views(teacher, data, cfg.teacher_views as usize, cfg.seed, &|n| bar.set_position(n as u64));
        bar.finish_and_clear();
        eprintln!("stage nolf views: {} teacher views added to {} images in {:.1} s", cfg.teacher_views, data.images.len(), t.elapsed().as_secs_f64());
        &augmented
    } else {
        data
    };
    let t = Instant::now();
    let bar = spinner("nolf", "baking density cubes from the field and marching every training ray");
    let geometry = geometry(teacher, data, &cfg).map_err(anyhow::Error::msg)?;
    bar.finish_and_clear();
    let geometry_seconds = t.elapsed().as_secs_f64();
    let hits = &geometry.hits;
    let (bounds, step, density) = (geometry.bounds, geometry.step, geometry.density.clone());
    eprintln!(
        "stage nolf geometry: box {:.3?}..{:.3?}, step {step:.5}, {} density bricks, {} of {} rays hit ({} opaque rays missed), {} PSH vertices, {geometry_seconds:.1} s",
        bounds.min.to_array(),
        bounds.max.to_array(),
        density.brick_count(),
        hits.rays.len(),
        hits.total_rays,
        hits.missed_opaque,
        geometry.psh_vertices.len()
    );
    let (density_bricks, hit_rays, total_rays, missed) = (density.brick_count(), hits.rays.len(), hits.total_rays, hits.missed_opaque);
    let steps = cfg.steps;
    let mut distiller = Distiller::new(geometry, cfg).context("building the perfect spatial hash")?;
    let ckpt = work.join(STUDENT_CHECKPOINT);
    let t = Instant::now();
    let mut resumed = false;
    let mut last = None;
    if opts.resume && ckpt.exists() {
        let bytes = std::fs::read(&ckpt).with_context(|| format!("reading {}", ckpt.display()))?;
        distiller.load_student(&bytes, teacher.step).map_err(anyhow::Error::msg).with_context(|| format!("resuming from {}", ckpt.display()))?;
        resumed = true;
        eprintln!("stage nolf: resumed the finished appearance nets from {}", ckpt.display());
    }
    if distiller.step < steps && distiller.config.teacher_query_weight > 0.0 {
        // Each query's colour target, from the teacher's march along its ray (the window: the
        // multi-hit rule's segment gap).
        let t = Instant::now();
        let window = distiller.config.hits.gap_steps * step;
        distiller.query_targets = nephele_train::distill::teacher_query_targets(teacher, data, &distiller.hits, window);
        eprintln!("stage nolf targets: the teacher's colour at each query of {} hit rays, {:.1} s", distiller.query_targets.len(), t.elapsed().as_secs_f64());
    }
    if distiller.step < steps {
        eprintln!("stage nolf appearance: {} steps of {} rays", steps, distiller.config.rays_per_batch);
        let bar = progress_bar("nolf", steps, distiller.step);
        let mut log = Instant::now();
        while distiller.step < steps {
            let s = distiller.train_step(data);
            last = Some(s);
            bar.set_position(distiller.step);
            bar.set_message(format!("loss {:.5} PSNR {:.2} dB α-MSE {:.5}", s.rgb_mse, s.psnr(), s.alpha_mse));
            if bar.is_hidden() && opts.log_every > 0 && (distiller.step % opts.log_every == 0 || distiller.step == steps) {
                eprintln!(
                    "nolf step {}/{steps}: batch PSNR {:.2} dB, alpha MSE {:.5}, {:.0} ms/step, {:.0} s elapsed",
                    distiller.step,
                    s.psnr(),
                    s.alpha_mse,
                    log.elapsed().as_secs_f64() * 1e3 / opts.log_every as f64,
                    t.elapsed().as_secs_f64()
                );
                log = Instant::now();
            }
        }
        bar.finish_and_clear();
        let bytes = distiller.student_bytes(teacher.step).map_err(anyhow::Error::msg)?;
        let mut tmp = ckpt.clone().into_os_string();
        tmp.push(".partial");
        std::fs::write(&tmp, bytes).and_then(|_| std::fs::rename(&tmp, &ckpt)).with_context(|| format!("writing {}", ckpt.display()))?;
    }
    let train_seconds = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let bar = spinner("bake", "baking diffuse cubes");
    let asset = distiller.bake(density, step, &data.name, serde_json::Value::Null).map_err(anyhow::Error::msg)?;
    asset.validate().context("the baked asset fails its own checks")?;
    bar.finish_and_clear();
    let psh_entries = asset.psh.len();
    let memory = asset.memory();
    let (asset_bytes, dense_equivalent_bytes) = (memory.stored_bytes(), memory.dense_bytes());
    let summary = NolfSummary {
        bounds: [bounds.min.to_array(), bounds.max.to_array()],
        step,
        density_bricks,
        hit_rays,
        total_rays,
        missed_opaque_rays: missed,
        psh_entries,
        geometry_seconds,
        steps: distiller.step,
        resumed,
        final_batch_psnr: last.map(|s| s.psnr()),
        train_seconds,
        bake_seconds: t.elapsed().as_secs_f64(),
        asset_bytes,
        dense_equivalent_bytes,
    };
    Ok((asset, summary))
}

/// Scores the teacher and the asset on up to `eval_views` views of the test split (the
/// held-out views with `--holdout-every`, else the dataset's own test split), if there is one.
fn held_out_scores(opts: &TrainOptions, teacher: &Trainer, asset: &Asset) -> Result<Option<HeldOut>> {
    let load = LoadOptions { split: Split::Test, downscale: opts.downscale, holdout_every: opts.holdout_every, max_images: Some(opts.eval_views) };
    let Ok(test) = Dataset::load(&opts.dataset, &load) else {
        eprintln!("no test split to score (use --holdout-every N to hold views out)");
        return Ok(None);
    };
    let bar = progress_bar("eval", test.images.len() as u64, 0);
    let (mut np, mut ns, mut ap, mut as_) = (0.0, 0.0, 0.0, 0.0);
    for image in &test.images {
        let truth = image.composite_over(Vec3::ONE);
        let (w, h) = (image.width as usize, image.height as usize);
        let ngp = teacher.render_image(image, Vec3::ONE);
        let nolf = distill::render_image(asset, image, Vec3::ONE);
        np += psnr(&truth, &ngp);
        ns += ssim(&truth, &ngp, w, h, 3);
        ap += psnr(&truth, &nolf);
        as_ += ssim(&truth, &nolf, w, h, 3);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let n = test.images.len().max(1) as f64;
    let (w, h) = test.images.first().map_or((0, 0), |i| (i.width, i.height));
    Ok(Some(HeldOut {
        split: if opts.holdout_every.is_some() { "held out of train".into() } else { "test".into() },
        views: test.images.len(),
        width: w,
        height: h,
        ngp_psnr: np / n,
        ngp_ssim: ns / n,
        nolf_psnr: ap / n,
        nolf_ssim: as_ / n,
    }))
}

#[derive(Debug, Clone)]
pub struct EvalOptions {
    pub checkpoint: PathBuf,
    pub dataset: PathBuf,
    pub split: Split,
    pub downscale: u32,
    pub holdout_every: Option<usize>,
    pub out: Option<PathBuf>,
    pub json: bool,
    /// For an asset: the i-NGP checkpoint it was distilled from, to split the asset's loss
    /// into geometry, colour and α ([`SwapScores`]).
    pub teacher: Option<PathBuf>,
    /// What an asset renders with (its knobs: step, hit rule, early stop); an i-NGP
    /// checkpoint renders with its own settings.
    pub settings: nephele_renderer::RenderSettings,
}

/// Mean PSNR of an asset's own march with parts swapped for its teacher's
/// ([`variants::render_swaps`]): how much each part of the asset costs.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SwapScores {
    pub teacher: String,
    /// The asset's hits, the teacher's colours and α.
    pub teacher_colour_and_alpha_psnr: f64,
    /// The asset's hits and α, the teacher's colours.
    pub teacher_colour_psnr: f64,
    /// The asset's hits and colours, the teacher's α.
    pub teacher_alpha_psnr: f64,
    /// The same, each teacher sample's colour going to its nearest query.
    pub teacher_nearest_psnr: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct ViewScore {
    pub index: usize,
    pub image: String,
    pub psnr: f64,
    pub ssim: f64,
    /// The side-by-side PNG, if written.
    pub comparison: Option<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    pub checkpoint: String,
    pub model: &'static str,
    /// Training step of a checkpoint.
    pub step: Option<u64>,
    pub dataset: String,
    pub split: String,
    pub width: u32,
    pub height: u32,
    pub background: [f32; 3],
    pub ssim_definition: &'static str,
    pub views: Vec<ViewScore>,
    pub mean_psnr: f64,
    pub mean_ssim: f64,
    /// With `--teacher`: the asset's loss split by part.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub swaps: Option<SwapScores>,
    pub seconds: f64,
}

/// What `eval` renders with.
enum Model {
    Ngp(Box<Trainer>),
    Nolf(Box<Asset>),
}

pub fn eval(opts: &EvalOptions) -> Result<EvalReport> {
    let path = &opts.checkpoint;
    let (model, step) = if path.extension().is_some_and(|e| e == "nolf") {
        (Model::Nolf(Box::new(Asset::load(path).with_context(|| format!("loading asset {}", path.display()))?)), None)
    } else {
        let (trainer, meta) = Trainer::load_checkpoint(path, None).with_context(|| format!("loading checkpoint {}", path.display()))?;
        (Model::Ngp(Box::new(trainer)), Some(meta.step))
    };
    let load = LoadOptions { split: opts.split, downscale: opts.downscale, holdout_every: opts.holdout_every, ..LoadOptions::default() };
    let data = Dataset::load(&opts.dataset, &load).with_context(|| format!("loading the {} split of {}", opts.split, opts.dataset.display()))?;
    if let Some(dir) = &opts.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating output directory {}", dir.display()))?;
    }
    let teacher = match (&opts.teacher, &model) {
        (None, _) => None,
        (Some(path), Model::Nolf(_)) => Some(Trainer::load_checkpoint(path, None).with_context(|| format!("loading the teacher {}", path.display()))?.0),
        (Some(_), Model::Ngp(_)) => bail!("--teacher splits an asset's loss; {} is an i-NGP checkpoint", opts.checkpoint.display()),
    };
    if matches!(model, Model::Ngp(_)) && opts.settings != nephele_renderer::RenderSettings::default() {
        bail!("render knobs (--step-scale, --hit-tau, --max-hits, --early-stop) set an asset's march; {} is an i-NGP checkpoint", opts.checkpoint.display());
    }
    let mut swaps = opts.teacher.as_ref().filter(|_| teacher.is_some()).map(|p| SwapScores { teacher: p.display().to_string(), ..SwapScores::default() });
    let background = Vec3::ONE;
    let t = Instant::now();
    let bar = ProgressBar::new(data.images.len() as u64);
    bar.set_style(ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} views (ETA {eta})").unwrap_or_else(|_| ProgressStyle::default_bar()));
    bar.set_prefix("eval");
    bar.enable_steady_tick(Duration::from_millis(200));
    let mut views = Vec::with_capacity(data.images.len());
    for (index, image) in data.images.iter().enumerate() {
        let render = match &model {
            Model::Ngp(trainer) => trainer.render_image(image, background),
            Model::Nolf(asset) => distill::render_image_with(asset, image, background, &opts.settings),
        };
        let truth = image.composite_over(background);
        if let (Some(teacher), Model::Nolf(asset), Some(sums)) = (&teacher, &model, &mut swaps) {
            let f = variants::render_swaps(teacher, asset, &image.rays().collect::<Vec<_>>(), background);
            sums.teacher_colour_and_alpha_psnr += psnr(&truth, &f.teacher_colour_and_alpha);
            sums.teacher_colour_psnr += psnr(&truth, &f.teacher_colour);
            sums.teacher_alpha_psnr += psnr(&truth, &f.teacher_alpha);
            sums.teacher_nearest_psnr += psnr(&truth, &f.teacher_nearest);
        }
        let comparison = match &opts.out {
            Some(dir) => {
                let path = dir.join(format!("{}_{index:03}.png", opts.split));
                write_comparison_png(&path, &truth, &render, image.width, image.height).map_err(anyhow::Error::msg)?;
                Some(path.display().to_string())
            }
            None => None,
        };
        views.push(ViewScore {
            index,
            image: image.path.display().to_string(),
            psnr: psnr(&truth, &render),
            ssim: ssim(&truth, &render, image.width as usize, image.height as usize, 3),
            comparison,
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    let n = views.len().max(1) as f64;
    let (w, h) = data.images.first().map(|i| (i.width, i.height)).unwrap_or((0, 0));
    let report = EvalReport {
        checkpoint: opts.checkpoint.display().to_string(),
        model: match model {
            Model::Ngp(_) => "i-NGP checkpoint",
            Model::Nolf(_) => "i-NOLF asset",
        },
        step,
        dataset: opts.dataset.display().to_string(),
        split: opts.split.to_string(),
        width: w,
        height: h,
        background: background.to_array(),
        ssim_definition: "11x11 Gaussian window (sigma 1.5), K1 0.01, K2 0.03, valid windows, mean over RGB channels",
        mean_psnr: views.iter().map(|v| v.psnr).sum::<f64>() / n,
        mean_ssim: views.iter().map(|v| v.ssim).sum::<f64>() / n,
        swaps: swaps.map(|s| SwapScores {
            teacher_colour_and_alpha_psnr: s.teacher_colour_and_alpha_psnr / n,
            teacher_colour_psnr: s.teacher_colour_psnr / n,
            teacher_alpha_psnr: s.teacher_alpha_psnr / n,
            teacher_nearest_psnr: s.teacher_nearest_psnr / n,
            ..s
        }),
        views,
        seconds: t.elapsed().as_secs_f64(),
    };
    if opts.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", format_report(&report));
    }
    Ok(report)
}

/// The text form of an evaluation: one row per view, then the means.
pub fn format_report(r: &EvalReport) -> String {
    let mut s = format!(
        "{} {}{} on the {} split of {} ({}x{}, over white)\n| view | PSNR dB | SSIM | image |\n|---:|---:|---:|---|\n",
        r.model,
        r.checkpoint,
        r.step.map_or(String::new(), |s| format!(" (step {s})")),
        r.split,
        r.dataset,
        r.width,
        r.height
    );
    for v in &r.views {
        let name = Path::new(&v.image).file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
        s += &format!("| {} | {:.2} | {:.4} | {name} |\n", v.index, v.psnr, v.ssim);
    }
    s += &format!("mean PSNR {:.3} dB, mean SSIM {:.4} over {} views ({:.1} s)\n", r.mean_psnr, r.mean_ssim, r.views.len(), r.seconds);
    if let Some(w) = &r.swaps {
        s += &format!(
            "\nThe asset's own hits with parts from its teacher {} (mean PSNR):\n| colour | α | PSNR dB |\n|---|---|---:|\n| asset | asset | {:.3} |\n| teacher | teacher | {:.3} |\n| teacher | asset | {:.3} |\n| asset | teacher | {:.3} |\n| teacher's, each sample to its nearest query | teacher | {:.3} |\n",
            w.teacher, r.mean_psnr, w.teacher_colour_and_alpha_psnr, w.teacher_colour_psnr, w.teacher_alpha_psnr, w.teacher_nearest_psnr
        );
    }
    s
}
