//! `nephele synth` (analytic datasets), `nephele dataset-info` and `nephele eval`.

use std::path::PathBuf;

use anyhow::Result;

use nephele_farm::assets::parse_size;

#[derive(clap::Args)]
pub struct SynthArgs {
    /// diffuse, glossy, translucent or mixed.
    #[arg(long, default_value = "mixed")]
    scene: String,
    #[arg(long, default_value = "200x200")]
    size: String,
    #[arg(long, default_value_t = 100)]
    train: usize,
    #[arg(long, default_value_t = 20)]
    val: usize,
    #[arg(long, default_value_t = 20)]
    test: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long)]
    out: PathBuf,
}

#[derive(clap::Args)]
pub struct DatasetInfoArgs {
    dataset: PathBuf,
    /// instant-ngp: move every n-th frame to the test split.
    #[arg(long)]
    holdout_every: Option<usize>,
    /// Also decode every image of every split (finds broken files).
    #[arg(long)]
    load: bool,
}

#[derive(clap::Args)]
pub struct EvalArgs {
    checkpoint: PathBuf,
    dataset: PathBuf,
    /// test, val or train.
    #[arg(long, default_value = "test")]
    split: String,
    #[arg(long, default_value_t = 1)]
    downscale: u32,
    /// Views held out of training with `train --holdout-every N` (the test split).
    #[arg(long)]
    holdout_every: Option<usize>,
    /// Directory for the side-by-side PNGs.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
    /// For an asset: the i-NGP checkpoint it was distilled from. Also scores the asset's own
    /// hits with the teacher's colours and/or α, to show whether its geometry, its colour or
    /// its α loses the most.
    #[arg(long)]
    teacher: Option<PathBuf>,
    /// An asset's render knobs (the held-out score of a speed-for-accuracy setting).
    #[command(flatten)]
    knobs: nephele_farm::assets::RenderKnobs,
}

pub fn synth(args: SynthArgs) -> Result<()> {
    use nephele_train::synth::{SynthConfig, SynthScene, generate};
    let scene: SynthScene = args.scene.parse().map_err(|e| anyhow::anyhow!("{e}"))?;
    let (width, height) = parse_size(&args.size)?;
    let (train, val, test) = (args.train, args.val, args.test);
    let cfg = SynthConfig { scene, width, height, n_train: train, n_val: val, n_test: test, seed: args.seed };
    let t = std::time::Instant::now();
    generate(&cfg, &args.out)?;
    println!("wrote {} ({scene}, {width}x{height}, {train}/{val}/{test} views) in {:.1} s", args.out.display(), t.elapsed().as_secs_f64());
    Ok(())
}

pub fn dataset_info(args: DatasetInfoArgs) -> Result<()> {
    use nephele_train::dataset::{Dataset, LoadOptions, inspect};
    let info = inspect(&args.dataset, args.holdout_every)?;
    println!("{} ({:?}), aabb_scale {:?}", info.name, info.format, info.aabb_scale);
    for s in &info.splits {
        println!("  {:5} {:4} frames, first image {:?} ({})", s.split.to_string(), s.frames, s.first_image_size, s.transforms_file.display());
        if args.load {
            let t = std::time::Instant::now();
            let d = Dataset::load(&args.dataset, &LoadOptions { holdout_every: args.holdout_every, ..LoadOptions::split(s.split) })?;
            println!("        decoded {} images in {:.2} s", d.images.len(), t.elapsed().as_secs_f64());
        }
    }
    Ok(())
}

pub fn eval(args: EvalArgs) -> Result<()> {
    use super::train::{EvalOptions, eval};
    let split = args.split.parse().map_err(anyhow::Error::msg)?;
    let settings = args.knobs.settings()?;
    let EvalArgs { checkpoint, dataset, downscale, holdout_every, out, json, teacher, .. } = args;
    eval(&EvalOptions { checkpoint, dataset, split, downscale, holdout_every, out, json, teacher, settings }).map(|_| ())
}
