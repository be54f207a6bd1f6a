//! Golden image: the fixture from a fixed camera, on both backends, against a stored PNG.
//! Threshold: mean |Δ| ≤ 1 level and ≤ 1% of pixels off by more than 8 levels.
//! Regenerate with `UPDATE_SNAPSHOTS=1 cargo test --release -p nephele-renderer --test golden`
//! (then look at the picture before committing it).

mod common;

use glam::DVec3;
use nephele_renderer::{Backend, CpuBackend, Frame, Intrinsics, RenderSettings, View, ViewRequest};

fn golden_path() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/trio_96x72.png")
}

fn read_png(path: &std::path::Path) -> (u32, u32, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).expect("golden image exists")));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

fn render(backend: &dyn Backend) -> Frame {
    let view = View::orbit(DVec3::ZERO, 4.2, 35.0, 25.0, Intrinsics::from_fov_x(96, 72, 0.75));
    let p = backend.prepare(common::fixture()).unwrap();
    p.render(&[ViewRequest::new(view)], &RenderSettings::default()).unwrap().frames.remove(0)
}

fn compare(frame: &Frame, label: &str) {
    let (w, h, rgb) = read_png(&golden_path());
    assert_eq!((w, h), (frame.width, frame.height));
    let mine: Vec<u8> = frame.rgba.chunks(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
    let diffs: Vec<u8> = mine.iter().zip(&rgb).map(|(a, b)| a.abs_diff(*b)).collect();
    let mean = diffs.iter().map(|&d| d as f64).sum::<f64>() / diffs.len() as f64;
    let over = diffs.chunks(3).filter(|p| p.iter().any(|&d| d > 8)).count() as f64 / (w * h) as f64;
    assert!(mean <= 1.0 && over <= 0.01, "{label}: mean |Δ| {mean:.3}, {:.2}% pixels > 8 levels", over * 100.0);
}

#[test]
fn fixture_matches_golden_image() {
    let cpu = render(&CpuBackend);
    if std::env::var_os("UPDATE_SNAPSHOTS").is_some() {
        cpu.save_png(&golden_path()).unwrap();
    }
    assert!(cpu.coverage() > 0.1);
    compare(&cpu, "cpu");
    if let Some(gpu) = common::gpu() {
        compare(&render(gpu), "gpu");
    }
}
