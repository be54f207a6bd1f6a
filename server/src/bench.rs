//! `nephele bench render`: per backend and size, where a frame's time goes (ray march vs
//! network), rays/s and the fraction of rays that hit; plus the asset's memory table.

use std::fmt::Write;

use anyhow::Result;
use glam::DVec3;
use nephele_renderer::{Backend, Intrinsics, RenderSettings, View, ViewRequest};

pub struct RenderBenchRow {
    pub backend: String,
    pub width: u32,
    pub height: u32,
    pub march_ms: f64,
    pub shade_ms: f64,
    pub total_ms: f64,
    pub rays_per_s: f64,
    pub hit_fraction: f64,
}

/// Median of `runs` renders of an orbit view at each size (after one warm-up).
pub fn bench_render(
    backend: &dyn Backend,
    asset: std::sync::Arc<nephele_renderer::Asset>,
    sizes: &[(u32, u32)],
    runs: usize,
    distance: f64,
) -> Result<Vec<RenderBenchRow>> {
    let prepared = backend.prepare(asset)?;
    let settings = RenderSettings::default();
    let mut rows = Vec::new();
    for &(w, h) in sizes {
        let view = View::orbit(DVec3::ZERO, distance, 35.0, 25.0, Intrinsics::from_fov_x(w, h, 0.69));
        let req = [ViewRequest::new(view)];
        prepared.render(&req, &settings)?;
        let mut samples = Vec::new();
        for _ in 0..runs.max(1) {
            samples.push(prepared.render(&req, &settings)?.stats);
        }
        samples.sort_by(|a, b| a.total_ms.total_cmp(&b.total_ms));
        let s = samples[samples.len() / 2];
        rows.push(RenderBenchRow {
            backend: backend.name(),
            width: w,
            height: h,
            march_ms: s.march_ms,
            shade_ms: s.shade_ms,
            total_ms: s.total_ms,
            rays_per_s: s.rays as f64 / (s.total_ms / 1e3),
            hit_fraction: s.hits as f64 / s.rays.max(1) as f64,
        });
    }
    Ok(rows)
}

pub fn format_table(rows: &[RenderBenchRow]) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "| backend | size | ray-march ms | network ms | total ms | Mrays/s | hit fraction |");
    let _ = writeln!(out, "|---|---|---:|---:|---:|---:|---:|");
    for r in rows {
        let _ = writeln!(
            out,
            "| {} | {}×{} | {:.1} | {:.1} | {:.1} | {:.2} | {:.3} |",
            r.backend,
            r.width,
            r.height,
            r.march_ms,
            r.shade_ms,
            r.total_ms,
            r.rays_per_s / 1e6,
            r.hit_fraction
        );
    }
    out
}
