//! Shared test helpers: the software-adapter device, the fixture asset, frame comparison.
#![allow(dead_code)]

use std::sync::{Arc, OnceLock};

use nephele_renderer::{Asset, Backend, Frame, gpu::GpuBackend};

/// The GPU backend on whatever adapter exists (lavapipe in CI). A missing adapter fails the
/// test loudly; set NEPHELE_ALLOW_NO_GPU=1 to turn that into a printed skip (CI never does).
pub fn gpu() -> Option<&'static GpuBackend> {
    static GPU: OnceLock<Result<GpuBackend, String>> = OnceLock::new();
    match GPU.get_or_init(|| GpuBackend::new().map_err(|e| e.to_string())) {
        Ok(g) => Some(g),
        Err(e) if std::env::var_os("NEPHELE_ALLOW_NO_GPU").is_some() => {
            eprintln!("SKIPPED (NEPHELE_ALLOW_NO_GPU): no GPU adapter: {e}");
            None
        }
        Err(e) => panic!("no GPU adapter ({e}); install mesa-vulkan-drivers, or set NEPHELE_ALLOW_NO_GPU=1 to skip loudly"),
    }
}

pub fn fixture_path() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/assets/trio-small.nolf")
}

/// The shipped fixture: the small procedural trio.
pub fn fixture() -> Arc<Asset> {
    static A: OnceLock<Arc<Asset>> = OnceLock::new();
    A.get_or_init(|| Arc::new(Asset::load(&fixture_path()).expect("fixture loads"))).clone()
}

pub fn backend_name(b: &dyn Backend) -> String {
    b.name()
}

/// Per-pixel differences between two frames of the same size.
#[derive(Debug)]
pub struct FrameDiff {
    /// Mean absolute difference over all RGBA channels, in 8-bit levels.
    pub mean_abs: f64,
    pub max_abs: u8,
    /// Fraction of pixels with any channel off by more than `levels`.
    pub frac_over: f64,
    /// Fraction of pixels where one frame hit and the other missed.
    pub hit_mismatch: f64,
    /// Fraction of both-hit pixels whose depths differ by more than `depth_tol`.
    pub depth_off: f64,
    pub pixels: usize,
}

pub fn diff(a: &Frame, b: &Frame, levels: u8, depth_tol: f32) -> FrameDiff {
    assert_eq!((a.width, a.height), (b.width, b.height));
    let n = (a.width * a.height) as usize;
    let (mut sum, mut max, mut over, mut mism, mut doff, mut both) = (0u64, 0u8, 0usize, 0usize, 0usize, 0usize);
    for i in 0..n {
        let mut worst = 0u8;
        for c in 0..4 {
            let d = a.rgba[4 * i + c].abs_diff(b.rgba[4 * i + c]);
            sum += d as u64;
            worst = worst.max(d);
        }
        max = max.max(worst);
        if worst > levels {
            over += 1;
        }
        let (da, db) = (a.depth[i], b.depth[i]);
        if da.is_finite() != db.is_finite() {
            mism += 1;
        } else if da.is_finite() {
            both += 1;
            if (da - db).abs() > depth_tol {
                doff += 1;
            }
        }
    }
    FrameDiff {
        mean_abs: sum as f64 / (4 * n) as f64,
        max_abs: max,
        frac_over: over as f64 / n as f64,
        hit_mismatch: mism as f64 / n as f64,
        depth_off: doff as f64 / both.max(1) as f64,
        pixels: n,
    }
}
