//! `nephele bench encode`: RGB→I420 and H.264 encode times on a moving test pattern and on
//! real content (an asset orbiting, rendered on the CPU before the timing starts), per size,
//! bits per pixel and encoder thread count, with the bytes per frame and the decoded PSNR.

use std::fmt::Write;

use anyhow::Result;
use glam::DVec3;
use nephele_farm::assets::{DEFAULT_ASSET, load_asset, parse_size};
use nephele_master::encoder::{BenchResult, DEFAULT_BITS_PER_PIXEL, bench_encode, check_bits_per_pixel, check_encoder_threads, default_encoder_threads, pattern_frames};
use nephele_renderer::{Backend as _, Intrinsics, RenderSettings, View, ViewRequest};
use serde::Serialize;

/// RGB→I420 and H.264 encode times on a moving test pattern and on real content.
#[derive(clap::Args, Debug, Clone)]
pub struct EncodeArgs {
    #[arg(long, default_value = "640x480,1280x720")]
    sizes: String,
    #[arg(long, default_value_t = 200)]
    frames: u32,
    /// The real content; `none` for the pattern only.
    #[arg(long, default_value = DEFAULT_ASSET)]
    asset: String,
    /// Bits per pixel per frame to compare (the server's `--bits-per-pixel`): encode time
    /// and quality against bandwidth.
    #[arg(long, value_delimiter = ',', default_values_t = [DEFAULT_BITS_PER_PIXEL])]
    bits_per_pixel: Vec<f64>,
    /// OpenH264 threads to compare, 1..=4 (default: one more than the cores, at most 4).
    #[arg(long, value_delimiter = ',')]
    threads: Vec<u16>,
    /// Print the report as JSON on stdout (the table goes to stderr).
    #[arg(long)]
    pub json: bool,
}

/// One content × size × bit rate × thread count: the encoder's own measurement.
#[derive(Debug, Clone, Serialize)]
pub struct EncodeRow {
    pub content: String,
    pub bits_per_pixel: f64,
    pub threads: u16,
    #[serde(flatten)]
    pub result: BenchResult,
}

#[derive(Debug, Clone, Serialize)]
pub struct EncodeReport {
    pub rows: Vec<EncodeRow>,
}

pub fn run(args: EncodeArgs) -> Result<()> {
    let EncodeArgs { sizes, frames, asset, bits_per_pixel, threads, json } = args;
    for &bpp in &bits_per_pixel {
        check_bits_per_pixel(bpp).map_err(anyhow::Error::msg)?;
    }
    let threads = if threads.is_empty() { vec![default_encoder_threads()] } else { threads };
    for &t in &threads {
        check_encoder_threads(t).map_err(|e| anyhow::anyhow!("--threads: {e}"))?;
    }
    let prepared = if asset == "none" { None } else { Some(nephele_renderer::FastCpuBackend.prepare(load_asset(&asset)?)?) };
    let mut rows = Vec::new();
    for size in sizes.split(',') {
        let (w, h) = parse_size(size)?;
        let mut contents = vec![("test pattern".to_string(), pattern_frames(w, h, frames))];
        if let Some(p) = &prepared {
            eprintln!("rendering {frames} frames of {asset} at {w}x{h} ...");
            // An orbit at 40°/s seen at 50 fps, as a user turning the object.
            let rendered = (0..frames.max(1))
                .map(|i| {
                    let view = View::orbit(DVec3::ZERO, 4.0, 35.0 + 0.8 * f64::from(i), 25.0, Intrinsics::from_fov_x(w, h, 0.69));
                    p.render(&[ViewRequest::new(view)], &RenderSettings::default()).map(|o| o.frames.into_iter().next().expect("one view").rgba)
                })
                .collect::<Result<Vec<_>, _>>()?;
            contents.push((asset.clone(), rendered));
        }
        for (name, content) in contents {
            for &bpp in &bits_per_pixel {
                for &t in &threads {
                    rows.push(EncodeRow { content: name.clone(), bits_per_pixel: bpp, threads: t, result: bench_encode(w, h, &content, bpp, t)? });
                }
            }
        }
    }
    let report = EncodeReport { rows };
    crate::emit(json, &format_table(&report), &report)
}

pub fn format_table(report: &EncodeReport) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "| content | size | frames | bits/pixel | threads | kbit/s target | RGB→I420 p50 / p99 ms | encode p50 / p99 ms | bytes/frame | IDR bytes | PSNR dB |");
    let _ = writeln!(out, "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in &report.rows {
        let e = &r.result;
        let _ = writeln!(
            out,
            "| {} | {}x{} | {} | {} | {} | {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.0} | {} | {:.2} |",
            r.content, e.width, e.height, e.frames, r.bits_per_pixel, r.threads, e.bitrate_bps / 1000, e.convert_ms_p50, e.convert_ms_p99, e.encode_ms_p50, e.encode_ms_p99, e.bytes_per_frame, e.idr_bytes, e.psnr_db
        );
    }
    out
}
