//! The renderer interface shared by both backends: a batch of views (cameras of any sizes,
//! each with the asset's instance transform and a background colour) in, one RGBA8 + depth
//! frame per view out, with the time spent marching and shading.

use std::{
    path::Path,
    sync::{
        Arc,
        atomic::{AtomicBool, Ordering},
    },
    time::Instant,
};

use glam::Vec3;
use rayon::prelude::*;

use crate::{
    asset::Asset,
    camera::{Instance, PoseError, RayFrame, View},
    model::{self, RenderSettings},
};

/// One camera of a batch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewRequest {
    pub view: View,
    /// Where the asset sits in the scene.
    pub instance: Instance,
    /// Linear RGB in [0, 1] behind the object (AR uses pure green).
    pub background: Vec3,
}

impl ViewRequest {
    pub fn new(view: View) -> Self {
        Self { view, instance: Instance::default(), background: Vec3::ONE }
    }
    pub fn with_background(mut self, bg: Vec3) -> Self {
        self.background = bg;
        self
    }
}

/// A rendered view: RGBA8 (alpha = object opacity) and depth in scene units (∞ for misses).
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<u8>,
    pub depth: Vec<f32>,
}

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("view {index}: {source}")]
    BadView { index: usize, source: PoseError },
    #[error("{0}")]
    BadSettings(String),
    #[error("no views to render")]
    NoViews,
    #[error("GPU error: {0}")]
    Gpu(String),
    #[error("cannot write {path}: {message}")]
    Output { path: String, message: String },
    #[error("cancelled")]
    Cancelled,
}

/// Asks a running render to stop at its next safe point: between rays on the CPU, between
/// dispatch chunks on the GPU. Clones share one flag.
#[derive(Debug, Clone, Default)]
pub struct CancelFlag(Arc<AtomicBool>);

impl CancelFlag {
    pub fn cancel(&self) {
        self.0.store(true, Ordering::Relaxed);
    }
    pub fn is_cancelled(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
    /// `Err(Cancelled)` once cancelled.
    pub fn check(&self) -> Result<(), RenderError> {
        if self.is_cancelled() { Err(RenderError::Cancelled) } else { Ok(()) }
    }
}

/// Where the time of one batch went.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RenderStats {
    pub march_ms: f64,
    pub shade_ms: f64,
    /// Of `shade_ms`, the network's matrix products (the fast CPU renderer; 0 where not
    /// timed).
    pub mlp_ms: f64,
    pub total_ms: f64,
    pub rays: u64,
    pub hits: u64,
    /// Density samples taken (CPU backends only; 0 where not counted): every sample in an
    /// occupied cell for the reference, those with σ > 0 for the fast renderer.
    pub samples: u64,
    /// Network queries (≥ `hits`; more with multi-hit; 0 where not counted).
    pub queries: u64,
}

#[derive(Debug, Clone, PartialEq)]
pub struct RenderOutput {
    pub frames: Vec<Frame>,
    pub stats: RenderStats,
}

/// An asset made ready for one backend (uploaded, for the GPU).
pub trait PreparedAsset: Send + Sync {
    fn asset(&self) -> &Arc<Asset>;
    /// Renders every view in one pass; stops with [`RenderError::Cancelled`] at the next safe
    /// point once `cancel` is set.
    fn render_cancellable(&self, views: &[ViewRequest], settings: &RenderSettings, cancel: &CancelFlag) -> Result<RenderOutput, RenderError>;
    fn render(&self, views: &[ViewRequest], settings: &RenderSettings) -> Result<RenderOutput, RenderError> {
        self.render_cancellable(views, settings, &CancelFlag::default())
    }
}

pub trait Backend: Send + Sync {
    /// Human-readable name, e.g. "cpu" or the adapter's.
    fn name(&self) -> String;
    fn prepare(&self, asset: Arc<Asset>) -> Result<Box<dyn PreparedAsset>, RenderError>;
}

/// Validation shared by both backends: nothing reaches a kernel unchecked.
pub fn check_request(views: &[ViewRequest], settings: &RenderSettings) -> Result<(), RenderError> {
    settings.validate().map_err(RenderError::BadSettings)?;
    if views.is_empty() {
        return Err(RenderError::NoViews);
    }
    for (index, v) in views.iter().enumerate() {
        v.view.validate().and_then(|_| v.instance.validate()).map_err(|source| RenderError::BadView { index, source })?;
        if !v.background.is_finite() {
            return Err(RenderError::BadSettings(format!("view {index}: background is not finite")));
        }
    }
    Ok(())
}

pub fn to_unorm8(x: f32) -> u8 {
    (x.clamp(0.0, 1.0) * 255.0).round() as u8
}

impl Frame {
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 4] {
        let i = 4 * (y * self.width + x) as usize;
        self.rgba[i..i + 4].try_into().unwrap()
    }

    /// Fraction of pixels hit (alpha > 0).
    pub fn coverage(&self) -> f64 {
        self.depth.iter().filter(|d| d.is_finite()).count() as f64 / self.depth.len().max(1) as f64
    }

    fn write_png(path: &Path, width: u32, height: u32, color: png::ColorType, data: &[u8]) -> Result<(), RenderError> {
        let err = |e: &dyn std::fmt::Display| RenderError::Output { path: path.display().to_string(), message: e.to_string() };
        let file = std::fs::File::create(path).map_err(|e| err(&e))?;
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), width, height);
        enc.set_color(color);
        enc.set_depth(png::BitDepth::Eight);
        enc.write_header().and_then(|mut w| w.write_image_data(data)).map_err(|e| err(&e))
    }

    /// Colour as RGB PNG (the background is already composited).
    pub fn save_png(&self, path: &Path) -> Result<(), RenderError> {
        let rgb: Vec<u8> = self.rgba.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
        Self::write_png(path, self.width, self.height, png::ColorType::Rgb, &rgb)
    }

    pub fn save_alpha_png(&self, path: &Path) -> Result<(), RenderError> {
        let a: Vec<u8> = self.rgba.chunks_exact(4).map(|p| p[3]).collect();
        Self::write_png(path, self.width, self.height, png::ColorType::Grayscale, &a)
    }

    /// Depth as grey (near = white, far = dark, miss = black), normalised to the hit range.
    pub fn save_depth_png(&self, path: &Path) -> Result<(), RenderError> {
        let hits = self.depth.iter().copied().filter(|d| d.is_finite());
        let (lo, hi) = hits.fold((f32::MAX, f32::MIN), |(a, b), d| (a.min(d), b.max(d)));
        let span = (hi - lo).max(1e-6);
        let g: Vec<u8> = self
            .depth
            .iter()
            .map(|&d| if d.is_finite() { to_unorm8(1.0 - 0.8 * (d - lo) / span) } else { 0 })
            .collect();
        Self::write_png(path, self.width, self.height, png::ColorType::Grayscale, &g)
    }
}

/// The plain CPU reference renderer: one parallel pass (rayon) over every ray of every view
/// of a batch, then one over the hits.
#[derive(Debug, Default, Clone, Copy)]
pub struct CpuBackend;

/// The asset plus its network in the CPU's SIMD layout.
struct CpuPrepared(Arc<Asset>, crate::mlp::MlpKernel);

impl Backend for CpuBackend {
    fn name(&self) -> String {
        "cpu-ref".into()
    }
    fn prepare(&self, asset: Arc<Asset>) -> Result<Box<dyn PreparedAsset>, RenderError> {
        let net = asset.mlp.kernel();
        Ok(Box::new(CpuPrepared(asset, net)))
    }
}

impl PreparedAsset for CpuPrepared {
    fn asset(&self) -> &Arc<Asset> {
        &self.0
    }

    fn render_cancellable(&self, views: &[ViewRequest], settings: &RenderSettings, cancel: &CancelFlag) -> Result<RenderOutput, RenderError> {
        check_request(views, settings)?;
        let asset = &*self.0;
        let settings = &settings.for_asset(&asset.march);
        let step = asset.march.step * settings.step_scale;
        let alpha_min = settings.alpha_min.unwrap_or(asset.march.alpha_min);
        let start = Instant::now();
        let frames_setup: Vec<RayFrame> =
            views.iter().map(|v| RayFrame::new(&v.view, &v.instance, asset.bounds.center(), asset.bounds.radius())).collect();
        // Every ray of every view in one list: (view, pixel) by prefix sums over the views'
        // pixel counts, so one parallel pass covers the whole batch.
        let mut starts = Vec::with_capacity(views.len() + 1);
        starts.push(0u64);
        for f in &frames_setup {
            starts.push(starts[starts.len() - 1] + f.intrinsics.pixel_count());
        }
        let total = *starts.last().expect("one entry per view plus one");
        let locate = |i: u64| -> (usize, u32) {
            let v = starts.partition_point(|&s| s <= i) - 1;
            (v, (i - starts[v]) as u32)
        };
        let ray = |i: u64| {
            let (v, p) = locate(i);
            let f = &frames_setup[v];
            let w = f.intrinsics.width;
            (v, f.ray(p % w, p / w))
        };
        // Pass 1: march every ray of every view (a cancelled render stops within one ray per
        // thread: the collect short-circuits on the first `None`).
        let rule = settings.hit_rule(&asset.march.hits);
        let marched: Vec<model::MultiHit> = (0..total)
            .into_par_iter()
            .map(|i| {
                if cancel.is_cancelled() {
                    return None;
                }
                let (_, (o, d)) = ray(i);
                Some(model::march_multi(&asset.density, o, d, step, settings, &rule))
            })
            .collect::<Option<_>>()
            .ok_or(RenderError::Cancelled)?;
        cancel.check()?;
        let march_done = Instant::now();
        // Pass 2: shade the hits; misses get the background and infinite depth.
        let shaded: Vec<([u8; 4], f32)> = marched
            .par_iter()
            .enumerate()
            .map(|(i, m)| {
                let (v, (o, d)) = ray(i as u64);
                let (req, f) = (&views[v], &frames_setup[v]);
                if m.march.alpha_c < alpha_min {
                    let bg = req.background;
                    return Some(([to_unorm8(bg.x), to_unorm8(bg.y), to_unorm8(bg.z), 0], f32::INFINITY));
                }
                if cancel.is_cancelled() {
                    return None;
                }
                let (rgb, a) = if m.count == 1 {
                    model::shade(asset, &self.1, o + m.t[0] * d, d, m.march.alpha_c, req.background)
                } else {
                    model::shade_multi(asset, &self.1, m, o, d, req.background)
                };
                Some(([to_unorm8(rgb.x), to_unorm8(rgb.y), to_unorm8(rgb.z), to_unorm8(a)], (f.t_shift + m.march.t_hit) * f.scale))
            })
            .collect::<Option<_>>()
            .ok_or(RenderError::Cancelled)?;
        let mut stats = RenderStats {
            rays: total,
            hits: shaded.iter().filter(|s| s.1.is_finite()).count() as u64,
            samples: marched.iter().map(|m| m.march.samples as u64).sum::<u64>(),
            queries: marched.iter().zip(&shaded).filter(|(_, s)| s.1.is_finite()).map(|(m, _)| m.count as u64).sum::<u64>(),
            ..Default::default()
        };
        let frames = frames_setup
            .iter()
            .zip(starts.windows(2))
            .map(|(f, range)| {
                let px = &shaded[range[0] as usize..range[1] as usize];
                Frame { width: f.intrinsics.width, height: f.intrinsics.height, rgba: px.iter().flat_map(|s| s.0).collect(), depth: px.iter().map(|s| s.1).collect() }
            })
            .collect();
        let end = Instant::now();
        stats.march_ms = (march_done - start).as_secs_f64() * 1e3;
        stats.shade_ms = (end - march_done).as_secs_f64() * 1e3;
        stats.total_ms = (end - start).as_secs_f64() * 1e3;
        Ok(RenderOutput { frames, stats })
    }
}

pub fn psnr_rgb(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len(), "images differ in size");
    let (mut se, mut n) = (0.0f64, 0usize);
    for (pa, pb) in a.chunks_exact(4).zip(b.chunks_exact(4)) {
        for c in 0..3 {
            let d = f64::from(pa[c]) - f64::from(pb[c]);
            se += d * d;
        }
        n += 3;
    }
    let mse = se / n.max(1) as f64;
    if mse == 0.0 { f64::INFINITY } else { 10.0 * (255.0f64 * 255.0 / mse).log10() }
}
