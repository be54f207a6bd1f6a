//! Where assets and backends come from: a `.nolf` path, the embedded demo asset
//! (`builtin:lego`, trained by `nephele train` from the NeRF-synthetic lego views and compiled
//! into the binary), or a built-in procedural scene (`builtin:trio`, `builtin:shiny`, ...);
//! and the backend choice with a loud CPU fallback.

use std::{path::Path, sync::Arc};

use anyhow::{Context, Result, bail};
use nephele_renderer::{
    Asset, Backend, CpuBackend, FastCpuBackend,
    gpu::GpuBackend,
    procedural::{self, ProceduralConfig, Scene},
};

/// The scene rendered when none is named.
pub const DEFAULT_ASSET: &str = "builtin:lego";

/// The scenes `nephele serve` offers by default (the first is the default scene).
pub const DEFAULT_SCENES: [&str; 3] = ["lego=builtin:lego", "trio=builtin:trio", "duo=builtin:duo"];

/// The built-in scene files (`builtin:<name>` as a scene): `duo` places lego and trio so
/// that their depth order flips as the camera orbits.
pub const BUILTIN_SCENE_FILES: &[(&str, &str)] = &[("duo", include_str!("../../../examples/scenes/duo.json"))];

/// The demo asset (see `examples/assets/README.md` for how it was made).
pub const LEGO_NOLF: &[u8] = include_bytes!("../../../examples/assets/lego.nolf");

/// Loads `spec`: `builtin:lego`, `builtin:<procedural scene>[-small]` or a path to a `.nolf`
/// file.
pub fn load_asset(spec: &str) -> Result<Arc<Asset>> {
    if spec == "builtin:lego" {
        return Ok(Arc::new(Asset::from_bytes(LEGO_NOLF).context("the embedded lego asset")?));
    }
    if let Some(name) = spec.strip_prefix("builtin:") {
        let (name, small) = match name.strip_suffix("-small") {
            Some(n) => (n, true),
            None => (name, false),
        };
        let scene: Scene = name.parse().map_err(anyhow::Error::msg)?;
        let cfg = if small { ProceduralConfig::small(scene) } else { ProceduralConfig::default_quality(scene) };
        let asset = procedural::generate(&cfg).context("building the procedural asset")?;
        return Ok(Arc::new(asset));
    }
    let asset = Asset::load(Path::new(spec)).with_context(|| format!("loading asset {spec}"))?;
    Ok(Arc::new(asset))
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BackendChoice {
    /// A hardware GPU if there is one; else the fast CPU renderer, which outruns software
    /// Vulkan (lavapipe) on the same cores — see `nephele bench render`.
    Auto,
    Gpu,
    /// The fast CPU renderer (empty-space skipping, batched SIMD network).
    Cpu,
    /// The plain CPU reference renderer that the others are tested against.
    CpuRef,
}

pub fn make_backend(choice: BackendChoice) -> Result<Box<dyn Backend>> {
    match choice {
        BackendChoice::Cpu => Ok(Box::new(FastCpuBackend)),
        BackendChoice::CpuRef => Ok(Box::new(CpuBackend)),
        BackendChoice::Gpu => Ok(Box::new(GpuBackend::new()?)),
        BackendChoice::Auto => match GpuBackend::new() {
            Ok(gpu) if gpu.ctx.info.device_type != nephele_renderer::gpu::DeviceType::Cpu => Ok(Box::new(gpu)),
            Ok(gpu) => {
                tracing::info!("the only GPU adapter is software ({}); rendering on the CPU, which is faster here (force with --backend gpu)", gpu.ctx.describe());
                Ok(Box::new(FastCpuBackend))
            }
            Err(e) => {
                tracing::warn!("{e}; rendering on the CPU");
                Ok(Box::new(FastCpuBackend))
            }
        },
    }
}

/// A render worker's `--backend gpu`: a hardware GPU, or an error in words. On a software
/// adapter (lavapipe, a CPU device) a worker would take heavy tasks at a small fraction of
/// the speed its farm is sized for; that is almost always a missing driver or device plugin.
pub fn hardware_gpu_backend() -> Result<Box<dyn Backend>> {
    let gpu = GpuBackend::new()?;
    if gpu.ctx.info.device_type == nephele_renderer::gpu::DeviceType::Cpu {
        bail!(
            "--backend gpu found only a software adapter, {}: this machine or container sees no GPU (check the GPU driver, and in a container the NVIDIA container toolkit or the Kubernetes device plugin); run with --allow-software-gpu to render on it anyway, or --backend cpu",
            gpu.ctx.describe()
        );
    }
    Ok(Box::new(gpu))
}

/// Parses "W" "x" "H".
pub fn parse_size(s: &str) -> Result<(u32, u32)> {
    let (w, h) = s.split_once(['x', 'X']).with_context(|| format!("size {s:?} should look like 800x600"))?;
    let (w, h) = (w.trim().parse::<u32>()?, h.trim().parse::<u32>()?);
    if w == 0 || h == 0 {
        bail!("size {s:?} has a zero edge");
    }
    Ok((w, h))
}

/// Parses "r,g,b" in 0..=1 or a name (white, black, green).
pub fn parse_color(s: &str) -> Result<glam::Vec3> {
    let named = match s {
        "white" => Some(glam::Vec3::ONE),
        "black" => Some(glam::Vec3::ZERO),
        "green" => Some(glam::Vec3::new(0.0, 1.0, 0.0)),
        _ => None,
    };
    if let Some(c) = named {
        return Ok(c);
    }
    let v: Vec<f32> = s.split(',').map(|x| x.trim().parse::<f32>()).collect::<Result<_, _>>().with_context(|| format!("colour {s:?}"))?;
    match v[..] {
        [r, g, b] if v.iter().all(|c| (0.0..=1.0).contains(c)) => Ok(glam::Vec3::new(r, g, b)),
        _ => bail!("colour {s:?} should be r,g,b in [0, 1] or white/black/green"),
    }
}

/// The renderer's speed-for-accuracy knobs, as flags.
#[derive(clap::Args, Debug, Clone)]
pub struct RenderKnobs {
    /// Step-size multiplier (speed/accuracy knob; keep it equal on every worker).
    #[arg(long, default_value_t = 1.0)]
    pub step_scale: f32,
    /// Multi-hit threshold τ: a further query for each part of a ray's weight holding at
    /// least τ of its opacity (1 = one hit per ray); default: the asset's own.
    #[arg(long)]
    pub hit_tau: Option<f32>,
    /// Most network queries per ray (1..=3); default: the asset's own.
    #[arg(long)]
    pub max_hits: Option<u32>,
    /// Stop a ray's march once its transmittance falls below this (its coarse opacity is
    /// then within this of the whole ray's): larger is faster and less exact (`nephele bench
    /// render` prints the PSNR against the default rule); default: the asset's own, the
    /// threshold it was trained with.
    #[arg(long)]
    pub early_stop: Option<f32>,
}

impl RenderKnobs {
    pub fn settings(&self) -> Result<nephele_renderer::RenderSettings> {
        let s = nephele_renderer::RenderSettings { step_scale: self.step_scale, hit_tau: self.hit_tau, max_hits: self.max_hits, early_stop: self.early_stop, ..Default::default() };
        if s.validate().is_err() {
            bail!(
                "--step-scale must be in [0.05, 20], --hit-tau in [0, 1], --max-hits in 1..={} and --early-stop in [0, 1) (got {}, {:?}, {:?}, {:?})",
                nephele_renderer::model::MAX_HITS,
                self.step_scale,
                self.hit_tau,
                self.max_hits,
                self.early_stop
            );
        }
        Ok(s)
    }
}
