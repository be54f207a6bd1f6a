//! `nephele train` and `nephele eval`: the i-NGP stage of training on a posed-image dataset,
//! with checkpoints and resume, and evaluation of a checkpoint on a dataset split (PSNR,
//! SSIM, side-by-side images). The i-NOLF distillation stages come later.

use std::{
    path::{Path, PathBuf},
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail};
use glam::Vec3;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

use nephele_renderer::{
    dataset::{Dataset, LoadOptions, Split},
    train::{
        TrainConfig, Trainer,
        trainer::eval::{psnr, ssim, write_comparison_png},
    },
};

/// File name of the i-NGP checkpoint inside the output directory.
pub const NGP_CHECKPOINT: &str = "ngp.ckpt";

#[derive(Debug, Clone)]
pub struct TrainOptions {
    pub dataset: PathBuf,
    pub out: PathBuf,
    /// tiny, fast or default.
    pub preset: String,
    /// Total steps of the i-NGP stage (None: the preset's default).
    pub steps: Option<u64>,
    pub downscale: u32,
    pub resume: bool,
    /// Write the checkpoint every this many steps (and at the end).
    pub checkpoint_every: u64,
    pub seed: u64,
    /// Print a JSON summary on stdout instead of text.
    pub json: bool,
    /// When the progress bar is not shown (stderr not a terminal), log a line to stderr
    /// every this many steps (0: never).
    pub log_every: u64,
}

/// Default step counts per preset.
pub fn default_steps(preset: &str) -> u64 {
    match preset {
        "tiny" => 500,
        "fast" => 5_000,
        _ => 20_000,
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct TrainSummary {
    pub stage: &'static str,
    pub preset: String,
    pub dataset: String,
    pub train_images: usize,
    pub resumed_from_step: Option<u64>,
    pub steps: u64,
    /// Batch loss (MSE) and PSNR of the last step taken in this run (None if none was).
    pub final_loss: Option<f64>,
    pub final_batch_psnr: Option<f64>,
    pub seconds: f64,
    pub ms_per_step: f64,
    pub checkpoint: String,
}

fn progress_bar(total: u64, start: u64) -> ProgressBar {
    let bar = ProgressBar::new(total);
    bar.set_style(
        ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {msg} (ETA {eta})")
            .map(|s| s.progress_chars("=> "))
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_prefix("ngp");
    bar.set_position(start);
    bar.reset_eta();
    bar
}

pub fn train(opts: &TrainOptions) -> Result<TrainSummary> {
    let Some(mut config) = TrainConfig::preset(&opts.preset) else {
        bail!("unknown preset {:?} (use one of: {})", opts.preset, TrainConfig::PRESETS.join(", "));
    };
    config.seed = opts.seed;
    let steps = opts.steps.unwrap_or_else(|| default_steps(&opts.preset));
    if opts.checkpoint_every == 0 {
        bail!("--checkpoint-every must be at least 1");
    }
    let load = LoadOptions { split: Split::Train, downscale: opts.downscale, ..LoadOptions::default() };
    let t = Instant::now();
    let data = Dataset::load(&opts.dataset, &load).with_context(|| format!("loading the train split of {}", opts.dataset.display()))?;
    let (w, h) = data.images.first().map(|i| (i.width, i.height)).unwrap_or((0, 0));
    eprintln!("dataset {}: {} train images of {w}x{h} (downscale {}) in {:.1} s", data.name, data.images.len(), opts.downscale, t.elapsed().as_secs_f64());
    std::fs::create_dir_all(&opts.out).with_context(|| format!("creating output directory {}", opts.out.display()))?;
    let ckpt = opts.out.join(NGP_CHECKPOINT);

    let mut trainer = if opts.resume {
        if !ckpt.exists() {
            bail!("--resume: no checkpoint at {}", ckpt.display());
        }
        let (trainer, _) = Trainer::load_checkpoint(&ckpt, Some(&config)).with_context(|| format!("resuming from {}", ckpt.display()))?;
        eprintln!("resuming from {} at step {}", ckpt.display(), trainer.step);
        trainer
    } else {
        Trainer::new(config)
    };
    let resumed_from_step = opts.resume.then_some(trainer.step);
    let provenance = serde_json::json!({
        "dataset": opts.dataset.display().to_string(),
        "dataset_name": data.name,
        "downscale": opts.downscale,
        "preset": opts.preset,
    });
    eprintln!(
        "stage ngp: preset {}, {} parameters, {} rays per batch, steps {}..{steps}",
        opts.preset,
        trainer.field.parameter_count(),
        trainer.config.rays_per_batch,
        trainer.step
    );

    let start_step = trainer.step;
    let bar = progress_bar(steps, start_step.min(steps));
    let t = Instant::now();
    let mut last = None;
    let mut window = (Instant::now(), 0usize);
    // (start of the log interval, step then, rays since)
    let mut log = (Instant::now(), start_step, 0usize);
    while trainer.step < steps {
        let s = trainer.train_step(&data);
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
        if trainer.step % opts.checkpoint_every == 0 || trainer.step == steps {
            trainer.save_checkpoint(&ckpt, provenance.clone())?;
        }
    }
    bar.finish_and_clear();
    if trainer.step == start_step {
        // Nothing to do, but make sure the checkpoint exists.
        trainer.save_checkpoint(&ckpt, provenance)?;
    }
    let seconds = t.elapsed().as_secs_f64();
    let taken = trainer.step - start_step;
    let summary = TrainSummary {
        stage: "ngp",
        preset: opts.preset.clone(),
        dataset: opts.dataset.display().to_string(),
        train_images: data.images.len(),
        resumed_from_step,
        steps: trainer.step,
        final_loss: last.map(|s| s.batch.loss),
        final_batch_psnr: last.map(|s| s.batch.psnr()),
        seconds,
        ms_per_step: if taken > 0 { seconds * 1e3 / taken as f64 } else { 0.0 },
        checkpoint: ckpt.display().to_string(),
    };
    eprintln!("the i-NOLF stages (distillation into a .nolf asset) are not implemented yet; stopping after the i-NGP stage");
    if opts.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        match (summary.final_loss, summary.final_batch_psnr) {
            (Some(loss), Some(p)) => println!(
                "ngp: {taken} steps to step {} in {seconds:.1} s ({:.1} ms/step); final loss {loss} (batch PSNR {p:.2} dB); wrote {}",
                summary.steps, summary.ms_per_step, summary.checkpoint
            ),
            _ => println!("ngp: already at step {} (asked for {steps}); checkpoint {}", summary.steps, summary.checkpoint),
        }
    }
    Ok(summary)
}

#[derive(Debug, Clone)]
pub struct EvalOptions {
    pub checkpoint: PathBuf,
    pub dataset: PathBuf,
    pub split: Split,
    pub downscale: u32,
    pub out: Option<PathBuf>,
    pub json: bool,
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
    pub step: u64,
    pub dataset: String,
    pub split: String,
    pub width: u32,
    pub height: u32,
    pub background: [f32; 3],
    pub ssim_definition: &'static str,
    pub views: Vec<ViewScore>,
    pub mean_psnr: f64,
    pub mean_ssim: f64,
    pub seconds: f64,
}

pub fn eval(opts: &EvalOptions) -> Result<EvalReport> {
    let (trainer, meta) = Trainer::load_checkpoint(&opts.checkpoint, None).with_context(|| format!("loading checkpoint {}", opts.checkpoint.display()))?;
    let load = LoadOptions { split: opts.split, downscale: opts.downscale, ..LoadOptions::default() };
    let data = Dataset::load(&opts.dataset, &load).with_context(|| format!("loading the {} split of {}", opts.split, opts.dataset.display()))?;
    if let Some(dir) = &opts.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating output directory {}", dir.display()))?;
    }
    let background = Vec3::ONE;
    let t = Instant::now();
    let bar = ProgressBar::new(data.images.len() as u64);
    bar.set_style(ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} views (ETA {eta})").unwrap_or_else(|_| ProgressStyle::default_bar()));
    bar.set_prefix("eval");
    bar.enable_steady_tick(Duration::from_millis(200));
    let mut views = Vec::with_capacity(data.images.len());
    for (index, image) in data.images.iter().enumerate() {
        let render = trainer.render_image(image, background);
        let truth = image.composite_over(background);
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
        step: meta.step,
        dataset: opts.dataset.display().to_string(),
        split: opts.split.to_string(),
        width: w,
        height: h,
        background: background.to_array(),
        ssim_definition: "11x11 Gaussian window (sigma 1.5), K1 0.01, K2 0.03, valid windows, mean over RGB channels",
        mean_psnr: views.iter().map(|v| v.psnr).sum::<f64>() / n,
        mean_ssim: views.iter().map(|v| v.ssim).sum::<f64>() / n,
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
        "checkpoint {} (step {}) on the {} split of {} ({}x{}, over white)\n| view | PSNR dB | SSIM | image |\n|---:|---:|---:|---|\n",
        r.checkpoint, r.step, r.split, r.dataset, r.width, r.height
    );
    for v in &r.views {
        let name = Path::new(&v.image).file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
        s += &format!("| {} | {:.2} | {:.4} | {name} |\n", v.index, v.psnr, v.ssim);
    }
    s += &format!("mean PSNR {:.3} dB, mean SSIM {:.4} over {} views ({:.1} s)\n", r.mean_psnr, r.mean_ssim, r.views.len(), r.seconds);
    s
}
