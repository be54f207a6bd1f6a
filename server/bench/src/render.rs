//! `nephele bench render`: per backend and frame size, where a frame's time goes (ray march
//! against network), rays per second, the fraction of rays that hit, samples per ray and
//! network queries per hit; against the FMA peak measured in the same run, the frame's FMA
//! floor and how far above it the frame is. Variants of the fast CPU renderer (marches,
//! network kernels) and speed-for-accuracy knobs are timed with their frames alternating, so
//! every variant sees the same machine; `--batch` adds what batching views into one call saves.

use std::fmt::Write;

use anyhow::Result;
use glam::DVec3;
use nephele_farm::assets::{BackendChoice, DEFAULT_ASSET, RenderKnobs, load_asset, make_backend, parse_size};
use nephele_renderer::{Backend, Intrinsics, PreparedAsset, RenderSettings, View, ViewRequest};
use serde::Serialize;

/// Ray-march / network / total ms, rays/s and hit fraction per backend and size.
#[derive(clap::Args, Debug, Clone)]
pub struct RenderArgs {
    #[arg(long, default_value = DEFAULT_ASSET)]
    asset: String,
    /// Comma-separated sizes.
    #[arg(long, default_value = "256x256,800x800,1920x1080")]
    sizes: String,
    /// Backends to compare side by side.
    #[arg(long, value_delimiter = ',', default_value = "cpu,gpu")]
    backends: Vec<BackendChoice>,
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// Camera distance from the object centre.
    #[arg(long, default_value_t = 4.0)]
    distance: f64,
    /// Also render this many views (around the orbit) in one call and one at a time, and
    /// print ms per view of each: what batching a render task saves.
    #[arg(long, default_value_t = 0)]
    batch: usize,
    /// The `cpu` backend with each of these ray marches, frames alternating (all give the
    /// same frames; the PSNR column shows it): avx512, avx2, ray. Default: the widest
    /// this CPU has.
    #[arg(long, value_delimiter = ',')]
    marches: Vec<nephele_renderer::fast::March>,
    /// The `cpu` backend with each of these network kernels, frames alternating (with
    /// --marches: every pair): f32, int8 (the hidden layer in 8 bits: AVX-512 VNNI, or
    /// AVX2 without AVX-512; the PSNR column gives its cost). Default: int8 where the CPU
    /// has it.
    #[arg(long, value_delimiter = ',')]
    networks: Vec<nephele_renderer::fast::Network>,
    #[command(flatten)]
    knobs: RenderKnobs,
    /// Print the report as JSON on stdout (the table goes to stderr).
    #[arg(long)]
    pub json: bool,
}

/// What `bench render` measured.
#[derive(Debug, Clone, Serialize)]
pub struct RenderReport {
    pub asset: String,
    /// The fast CPU renderer's march and network kernels on this CPU.
    pub cpu_march: String,
    pub cpu_network: String,
    /// The FMA rate measured in this run, GFLOP/s on all threads (none where it cannot be).
    pub peak_fma_gflops: Option<f64>,
    pub rows: Vec<RenderBenchRow>,
    pub batches: Vec<BatchRow>,
    /// The asset's memory as stored, and as dense grids would take.
    pub asset_stored_bytes: u64,
    pub asset_dense_bytes: u64,
}

pub fn run(args: RenderArgs) -> Result<()> {
    let RenderArgs { asset, sizes, backends, runs, distance, batch, marches, networks, knobs, json } = args;
    // With knobs set, the default rule is timed beside them (frames alternating), and
    // their frame's PSNR against its frame is printed.
    let settings = knobs.settings()?;
    let rules = if settings == RenderSettings::default() { vec![settings] } else { vec![RenderSettings::default(), settings] };
    let a = load_asset(&asset)?;
    let sizes: Vec<(u32, u32)> = sizes.split(',').map(parse_size).collect::<Result<_>>()?;
    let mut rows = Vec::new();
    let mut batches = Vec::new();
    if !(marches.is_empty() && networks.is_empty()) && !backends.contains(&BackendChoice::Cpu) {
        anyhow::bail!("--marches and --networks compare the `cpu` backend's variants: add cpu to --backends");
    }
    for b in backends {
        let backend = make_backend(b)?;
        eprintln!("benchmarking {} ...", backend.name());
        let variants = if b == BackendChoice::Cpu && !(marches.is_empty() && networks.is_empty()) {
            use nephele_renderer::fast::{March, Network};
            let fast = nephele_renderer::FastCpuBackend;
            let ms = if marches.is_empty() { vec![March::detect()] } else { marches.clone() };
            let ns = if networks.is_empty() { vec![Network::detect()] } else { networks.clone() };
            let pairs: Vec<(March, Network)> = ms.iter().flat_map(|&m| ns.iter().map(move |&n| (m, n))).collect();
            pairs.iter().map(|&(m, n)| Ok((format!("cpu, {} march, {} network", m.name(), n.name()), fast.prepare_with(a.clone(), m, n)?))).collect::<Result<Vec<_>>>()?
        } else {
            vec![(backend.name(), backend.prepare(a.clone())?)]
        };
        rows.extend(bench_render(&variants, &sizes, runs, distance, &rules)?);
        if batch > 1 {
            batches.extend(bench_batch(backend.as_ref(), a.clone(), &sizes, runs, distance, batch, &settings)?);
        }
    }
    let peak = nephele_renderer::mlp::peak_fma_gflops();
    let (cpu_march, cpu_network) = (nephele_renderer::fast::March::detect().describe().to_string(), nephele_renderer::fast::Network::detect().describe().to_string());
    let mut table = format!("asset: {asset}\n");
    // The march the plain `cpu` rows used.
    if rows.iter().any(|r| r.backend == "cpu") {
        let _ = writeln!(table, "fast CPU march: {cpu_march}; network: {cpu_network}");
    }
    match &peak {
        Some((p, threads, level)) => {
            let _ = write!(table, "peak FMA rate measured now: {p:.0} GFLOP/s on {threads} threads ({level})\n\n{}", format_table_with_peak(&rows, Some(*p)));
        }
        None => {
            let _ = write!(table, "\n{}", format_table(&rows));
        }
    }
    if !batches.is_empty() {
        let _ = writeln!(table, "\n{batch} views around the orbit, median of {runs} runs:\n");
        let _ = writeln!(table, "| backend | size | one call ms per view | one view per call ms per view | batching speed-up |");
        let _ = writeln!(table, "|---|---|---:|---:|---:|");
        for BatchRow { backend, size: (w, h), together_ms, alone_ms } in &batches {
            let _ = writeln!(table, "| {backend} | {w}×{h} | {together_ms:.1} | {alone_ms:.1} | {:.2}x |", alone_ms / together_ms);
        }
    }
    let memory = a.memory();
    let _ = writeln!(table, "\nmemory:\n{memory}");
    let report = RenderReport {
        asset,
        cpu_march,
        cpu_network,
        peak_fma_gflops: peak.map(|(p, _, _)| p),
        rows,
        batches,
        asset_stored_bytes: memory.stored_bytes(),
        asset_dense_bytes: memory.dense_bytes(),
    };
    crate::emit(json, &table, &report)
}

#[derive(Debug, Clone, Serialize)]
pub struct RenderBenchRow {
    pub backend: String,
    /// The render knobs, in words ([`describe_rule`]).
    pub rule: String,
    pub width: u32,
    pub height: u32,
    pub march_ms: f64,
    pub shade_ms: f64,
    /// Of `shade_ms`, the matrix products (0 where the backend does not time them).
    pub mlp_ms: f64,
    pub total_ms: f64,
    pub rays_per_s: f64,
    pub hit_fraction: f64,
    /// Network queries of the frame and multiply-adds per query.
    pub queries: u64,
    pub macs_per_query: u64,
    /// Density samples per ray (CPU backends; 0 where not counted).
    pub samples_per_ray: f64,
    /// PSNR of the frame against the same view under the default rule, when the knobs differ.
    pub psnr_vs_first: Option<f64>,
}

/// Median of `runs` renders of an orbit view at each size (after one warm-up), for each
/// prepared variant (named, e.g. a backend or one of its marches) under each of `rules`, their
/// frames alternating so that every variant and rule sees the same machine. Rows after the
/// first carry their PSNR against its frame (the trade of a speed-for-accuracy knob).
pub fn bench_render(variants: &[(String, Box<dyn PreparedAsset>)], sizes: &[(u32, u32)], runs: usize, distance: f64, rules: &[RenderSettings]) -> Result<Vec<RenderBenchRow>> {
    let combos: Vec<(&String, &dyn PreparedAsset, &RenderSettings)> = variants.iter().flat_map(|(name, p)| rules.iter().map(move |r| (name, p.as_ref(), r))).collect();
    let mut rows = Vec::new();
    for &(w, h) in sizes {
        let view = View::orbit(DVec3::ZERO, distance, 35.0, 25.0, Intrinsics::from_fov_x(w, h, 0.69));
        let req = [ViewRequest::new(view)];
        let frames: Vec<Vec<u8>> = combos.iter().map(|(_, p, s)| Ok(p.render(&req, s)?.frames.remove(0).rgba)).collect::<Result<_>>()?;
        let mut samples = vec![Vec::new(); combos.len()];
        for _ in 0..runs.max(1) {
            for ((_, prepared, rule), out) in combos.iter().zip(&mut samples) {
                out.push(prepared.render(&req, rule)?.stats);
            }
        }
        for (i, ((name, prepared, rule), mut samples)) in combos.iter().zip(samples).enumerate() {
            samples.sort_by(|a, b| a.total_ms.total_cmp(&b.total_ms));
            let s = samples[samples.len() / 2];
            rows.push(RenderBenchRow {
                backend: name.to_string(),
                rule: describe_rule(rule),
                width: w,
                height: h,
                march_ms: s.march_ms,
                shade_ms: s.shade_ms,
                mlp_ms: s.mlp_ms,
                total_ms: s.total_ms,
                rays_per_s: s.rays as f64 / (s.total_ms / 1e3),
                hit_fraction: s.hits as f64 / s.rays.max(1) as f64,
                queries: s.queries,
                macs_per_query: prepared.asset().mlp.macs(),
                samples_per_ray: s.samples as f64 / s.rays.max(1) as f64,
                psnr_vs_first: (i > 0).then(|| nephele_renderer::render::psnr_rgb(&frames[i], &frames[0])),
            });
        }
    }
    Ok(rows)
}

/// The knobs of `s` that differ from the default rule, in words ("default" for none).
fn describe_rule(s: &RenderSettings) -> String {
    let d = RenderSettings::default();
    let mut parts = Vec::new();
    if s.step_scale != d.step_scale {
        parts.push(format!("step ×{}", s.step_scale));
    }
    if let Some(t) = s.hit_tau {
        parts.push(format!("τ = {t}"));
    }
    if let Some(m) = s.max_hits {
        parts.push(format!("≤ {m} hits"));
    }
    if let Some(e) = s.early_stop {
        parts.push(format!("early stop {e}"));
    }
    if parts.is_empty() { "default".into() } else { parts.join(", ") }
}

/// One row of `bench render --batch`: ms per view in one call and one view per call.
#[derive(Debug, Clone, Serialize)]
pub struct BatchRow {
    pub backend: String,
    pub size: (u32, u32),
    pub together_ms: f64,
    pub alone_ms: f64,
}

/// ms per view rendering `n` orbit views in one call, and one per call (medians of `runs`).
pub fn bench_batch(
    backend: &dyn Backend,
    asset: std::sync::Arc<nephele_renderer::Asset>,
    sizes: &[(u32, u32)],
    runs: usize,
    distance: f64,
    n: usize,
    settings: &RenderSettings,
) -> Result<Vec<BatchRow>> {
    let prepared = backend.prepare(asset)?;
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let mut out = Vec::new();
    for &(w, h) in sizes {
        let views: Vec<ViewRequest> = (0..n)
            .map(|i| ViewRequest::new(View::orbit(DVec3::ZERO, distance, 35.0 + 360.0 * i as f64 / n as f64, 25.0, Intrinsics::from_fov_x(w, h, 0.69))))
            .collect();
        prepared.render(&views, settings)?;
        let (mut together, mut alone) = (Vec::new(), Vec::new());
        for _ in 0..runs.max(1) {
            let t = std::time::Instant::now();
            prepared.render(&views, settings)?;
            together.push(t.elapsed().as_secs_f64() * 1e3 / n as f64);
            let t = std::time::Instant::now();
            for v in &views {
                prepared.render(std::slice::from_ref(v), settings)?;
            }
            alone.push(t.elapsed().as_secs_f64() * 1e3 / n as f64);
        }
        out.push(BatchRow { backend: backend.name(), size: (w, h), together_ms: median(together), alone_ms: median(alone) });
    }
    Ok(out)
}

pub fn format_table(rows: &[RenderBenchRow]) -> String {
    format_table_with_peak(rows, None)
}

/// The render table; with the machine's peak FMA rate (GFLOP/s, all threads) also the
/// network's rate over its stage, the FMA floor of the frame (its network FLOPs at peak), how
/// far the frame is above that floor, and the matrix products' own time and rate (their
/// inputs' gathers, view encoding and compositing are the rest of the network stage).
pub fn format_table_with_peak(rows: &[RenderBenchRow], peak_gflops: Option<f64>) -> String {
    let mut out = String::new();
    // The rule and PSNR columns only when some row has knobs set.
    let rules = rows.iter().any(|r| r.rule != "default");
    // The PSNR column also when several marches (or backends' variants) are compared.
    let psnr = rules || rows.iter().any(|r| r.psnr_vs_first.is_some());
    let _ = write!(out, "| backend |{} size | ray-march ms | network ms | total ms | Mrays/s | hit fraction | samples/ray | queries/hit |", if rules { " rule |" } else { "" });
    let _ = write!(out, "{}", if peak_gflops.is_some() { " network GFLOP/s | % of peak | FMA floor ms | total / floor | MLP ms | MLP % of peak |" } else { "" });
    let _ = writeln!(out, "{}", if rules { " PSNR vs default rule dB |" } else if psnr { " PSNR vs first variant dB |" } else { "" });
    let _ = writeln!(out, "|---|{}---|---:|---:|---:|---:|---:|---:|---:|{}{}", if rules { "---|" } else { "" }, if peak_gflops.is_some() { "---:|---:|---:|---:|---:|---:|" } else { "" }, if psnr { "---:|" } else { "" });
    for r in rows {
        let hits = (r.hit_fraction * (r.width as f64 * r.height as f64)).max(1.0);
        // Backends that count no samples or queries (the GPU's) get dashes, not zeros.
        let counted = r.samples_per_ray > 0.0 || r.queries > 0;
        let _ = write!(
            out,
            "| {} |{} {}×{} | {:.1} | {:.1} | {:.1} | {:.2} | {:.3} | {} | {} |",
            r.backend,
            if rules { format!(" {} |", r.rule) } else { String::new() },
            r.width,
            r.height,
            r.march_ms,
            r.shade_ms,
            r.total_ms,
            r.rays_per_s / 1e6,
            r.hit_fraction,
            if counted { format!("{:.1}", r.samples_per_ray) } else { "–".into() },
            if counted { format!("{:.2}", r.queries as f64 / hits) } else { "–".into() }
        );
        if let Some(peak) = peak_gflops {
            let gflop = 2.0 * (r.queries * r.macs_per_query) as f64 / 1e9;
            if gflop > 0.0 {
                let rate = gflop / (r.shade_ms / 1e3).max(1e-9);
                let floor_ms = gflop / peak * 1e3;
                let _ = write!(out, " {rate:.1} | {:.1}% | {floor_ms:.2} | {:.1}× |", 100.0 * rate / peak, r.total_ms / floor_ms);
                if r.mlp_ms > 0.0 {
                    let _ = write!(out, " {:.1} | {:.1}% |", r.mlp_ms, 100.0 * floor_ms / r.mlp_ms);
                } else {
                    let _ = write!(out, " – | – |");
                }
            } else {
                let _ = write!(out, " – | – | – | – | – | – |");
            }
        }
        if psnr {
            let _ = write!(out, " {} |", r.psnr_vs_first.map_or("–".into(), |p| if p.is_infinite() { "∞ (same frame)".into() } else { format!("{p:.1}") }));
        }
        let _ = writeln!(out);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(backend: &str, queries: u64, samples_per_ray: f64) -> RenderBenchRow {
        RenderBenchRow {
            backend: backend.into(),
            rule: "default".into(),
            width: 64,
            height: 48,
            march_ms: 2.0,
            shade_ms: 1.0,
            mlp_ms: 0.6,
            total_ms: 3.0,
            rays_per_s: 1e6,
            hit_fraction: 0.5,
            queries,
            macs_per_query: 6000,
            samples_per_ray,
            psnr_vs_first: None,
        }
    }

    #[test]
    fn uncounted_columns_are_dashes_not_zeros() {
        let untimed = RenderBenchRow { mlp_ms: 0.0, ..row("cpu-ref", 2000, 4.0) };
        let table = format_table_with_peak(&[row("cpu", 2000, 4.0), row("wgpu", 0, 0.0), untimed], Some(100.0));
        let line = |backend: &str| table.lines().find(|l| l.starts_with(&format!("| {backend} |"))).unwrap();
        // 2000 queries × 6000 MACs × 2 = 0.024 GFLOP: 0.24 ms at 100 GFLOP/s, 3 ms is 12.5×,
        // and products timed at 0.6 ms run at 40% of the peak.
        assert!(line("cpu").ends_with("| 4.0 | 1.30 | 24.0 | 24.0% | 0.24 | 12.5× | 0.6 | 40.0% |"), "{}", line("cpu"));
        assert!(line("wgpu").ends_with("| – | – | – | – | – | – |"), "{}", line("wgpu"));
        assert!(line("cpu-ref").ends_with("| 12.5× | – | – |"), "{}", line("cpu-ref"));
    }
}
