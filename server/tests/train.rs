//! `nephele train` / `nephele eval` end to end through the binary: synthesise a small
//! dataset (diffuse, glossy and translucent objects), run the whole pipeline with the tiny
//! preset to a `.nolf` asset, check that a run stopped after the i-NGP stage and resumed ends
//! on the same loss and the same asset as an uninterrupted one, that a finished stage is
//! skipped on resume, evaluate the asset and the checkpoint on the test split (PSNR above a
//! measured floor, side-by-side PNGs written), and that bad input is a clear error.

use std::{path::Path, process::Command};

/// Steps of the i-NGP and i-NOLF stages in the test (tiny preset: ≈ 30–80 ms and ≈ 12 ms
/// per step on 2 cores in release).
const STEPS: u64 = 240;
const NOLF_STEPS: u64 = 200;
/// Mean test-split PSNR over white of the i-NGP teacher and of the asset. Measured (mixed
/// scene, 40×40, 16 train views, seed 0; deterministic): 25.8 and 23.3 dB; the floors leave
/// ~4–5 dB of margin for other CPUs' rounding.
const MIN_TEST_PSNR_NGP: f64 = 20.0;
const MIN_TEST_PSNR_NOLF: f64 = 19.0;

fn nephele(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_nephele")).args(args).output().expect("runs")
}

fn ok(args: &[&str]) -> serde_json::Value {
    let o = nephele(args);
    let (stdout, stderr) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success(), "nephele {args:?} failed:\n{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    if args.contains(&"--json") { serde_json::from_str(&stdout).unwrap_or_else(|e| panic!("{e}: {stdout}")) } else { serde_json::Value::Null }
}

struct TempDir(std::path::PathBuf);

impl TempDir {
    fn new(tag: &str) -> Self {
        let path = std::env::temp_dir().join(format!("nephele-train-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&path);
        std::fs::create_dir_all(&path).unwrap();
        Self(path)
    }
    fn path(&self, name: &str) -> String {
        self.0.join(name).display().to_string()
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn png_size(path: &Path) -> (u32, u32) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert_eq!(&bytes[1..4], b"PNG");
    let be = |i: usize| u32::from_be_bytes(bytes[i..i + 4].try_into().unwrap());
    (be(16), be(20))
}

#[test]
fn train_resume_and_eval_end_to_end() {
    let dir = TempDir::new("e2e");
    let data = dir.path("data");
    ok(&["synth", "--scene", "mixed", "--size", "40x40", "--train", "16", "--val", "0", "--test", "3", "--out", &data]);
    let (steps, nolf_steps) = (STEPS.to_string(), NOLF_STEPS.to_string());
    let common = ["--preset", "tiny", "--nolf-steps", &nolf_steps, "--json"];
    let run = |out: &str, extra: &[&str]| ok(&[&["train", &data, "--out", &dir.path(out)], &common[..], extra].concat());

    // One uninterrupted run to the asset, scored on the held-out test views.
    let full = run("full.nolf", &["--steps", &steps]);
    assert_eq!(full["ngp"]["steps"], STEPS);
    assert_eq!(full["nolf"]["steps"], NOLF_STEPS);
    assert!(dir.0.join("full.train/ngp.ckpt").exists() && dir.0.join("full.train/student.ckpt").exists());
    let held = &full["held_out"];
    let (ngp_psnr, nolf_psnr) = (held["ngp_psnr"].as_f64().unwrap(), held["nolf_psnr"].as_f64().unwrap());
    eprintln!("held out: i-NGP {ngp_psnr:.2} dB, i-NOLF {nolf_psnr:.2} dB; {}", full["nolf"]);
    assert!(ngp_psnr > MIN_TEST_PSNR_NGP && nolf_psnr > MIN_TEST_PSNR_NOLF, "{held}");
    // Only what the scene needs is stored.
    assert!(full["nolf"]["asset_bytes"].as_u64().unwrap() < full["nolf"]["dense_equivalent_bytes"].as_u64().unwrap(), "{}", full["nolf"]);

    // Stop halfway through the i-NGP stage; then --resume to the end: the same final batch loss, bit
    // for bit (the JSON float round-trips exactly), and the same asset.
    let half = (STEPS / 2).to_string();
    let first = run("split.nolf", &["--steps", &steps, "--stop-at-step", &half, "--checkpoint-every", "25"]);
    assert_eq!(first["ngp"]["steps"], STEPS / 2);
    assert!(first["nolf"].is_null() && !dir.0.join("split.nolf").exists());
    let resumed = run("split.nolf", &["--steps", &steps, "--resume"]);
    assert_eq!(resumed["ngp"]["resumed_from_step"], STEPS / 2);
    assert_eq!(resumed["ngp"]["final_loss"], full["ngp"]["final_loss"], "resumed {resumed}\nuninterrupted {full}");
    assert_eq!(resumed["held_out"], full["held_out"]);
    // Resuming a finished run skips both stages and rebuilds the same asset.
    let again = run("split.nolf", &["--steps", &steps, "--resume"]);
    assert_eq!(again["nolf"]["resumed"], true);
    assert!(again["ngp"]["final_loss"].is_null());
    assert_eq!(again["held_out"], full["held_out"]);

    // A resume with another preset is refused and says why.
    let o = nephele(&["train", &data, "--out", &dir.path("split.nolf"), "--preset", "fast", "--steps", &steps, "--resume"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("different configuration") && !stderr.contains("panicked"), "{stderr}");

    // Evaluation of the asset on the test split, with the side-by-side images; it agrees with
    // the score the training run stored.
    let eval_dir = dir.path("eval");
    let report = ok(&["eval", &dir.path("full.nolf"), &data, "--split", "test", "--out", &eval_dir, "--json"]);
    assert_eq!(report["model"], "i-NOLF asset");
    let mean = report["mean_psnr"].as_f64().unwrap();
    assert!((mean - nolf_psnr).abs() < 1e-9, "{mean} vs {nolf_psnr}");
    let ssim = report["mean_ssim"].as_f64().unwrap();
    assert!(ssim > 0.5 && ssim <= 1.0, "{report}");
    let views = report["views"].as_array().unwrap();
    assert_eq!(views.len(), 3);
    for v in views {
        let png = v["comparison"].as_str().unwrap();
        assert_eq!(png_size(Path::new(png)), (3 * 40, 40), "{png}");
    }
    // The i-NGP checkpoint evaluates to the teacher's stored score.
    let teacher = ok(&["eval", &dir.path("full.train/ngp.ckpt"), &data, "--json"]);
    assert_eq!(teacher["model"], "i-NGP checkpoint");
    assert!((teacher["mean_psnr"].as_f64().unwrap() - ngp_psnr).abs() < 1e-9);
    // Render knobs change the asset's score (a ray stopped at T < 0.5 keeps half its opacity
    // budget unspent), and are refused for an i-NGP checkpoint, whose march they do not set.
    let knob = ok(&["eval", &dir.path("full.nolf"), &data, "--split", "test", "--early-stop", "0.5", "--json"]);
    let knob_psnr = knob["mean_psnr"].as_f64().unwrap();
    assert!(knob_psnr.is_finite() && (knob_psnr - mean).abs() > 1e-6, "{knob_psnr} vs {mean}");
    let o = nephele(&["eval", &dir.path("full.train/ngp.ckpt"), &data, "--early-stop", "0.01"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("i-NGP checkpoint") && !stderr.contains("panicked"), "{stderr}");

    // The asset serves: `nephele info` reads it and reports its memory.
    let o = nephele(&["info", &dir.path("full.nolf")]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success() && text.contains("nephele train") && text.contains("PSH table"), "{text}");

    // The text report names every view and the means.
    let o = nephele(&["eval", &dir.path("full.nolf"), &data]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success() && text.contains("mean PSNR") && text.contains("| 2 |"), "{text}");
}

#[test]
fn train_and_eval_reject_bad_input_clearly() {
    let dir = TempDir::new("bad");
    let missing = dir.path("no-such-dataset");
    let o = nephele(&["train", &missing, "--out", &dir.path("out.nolf"), "--preset", "tiny", "--steps", "1"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{stderr}");
    assert!(stderr.contains("no-such-dataset") && !stderr.contains("panicked"), "{stderr}");

    let o = nephele(&["train", &missing, "--out", &dir.path("out.nolf"), "--preset", "huge"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("'huge'") && stderr.contains("tiny, fast, default, quality"), "the accepted values are named: {stderr}");

    // The asset must be a .nolf (unless stopping after the i-NGP stage).
    let o = nephele(&["train", &missing, "--out", &dir.path("asset.txt"), "--preset", "tiny"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains(".nolf"), "{stderr}");

    // A truncated asset is an error naming the file.
    let truncated = dir.path("cut.nolf");
    std::fs::write(&truncated, &std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/../examples/assets/trio-small.nolf")).unwrap()[..5000]).unwrap();
    let o = nephele(&["eval", &truncated, &missing]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("cut.nolf") && !stderr.contains("panicked"), "{stderr}");

    // A checkpoint that is not one (here: truncated garbage) is an error naming the file.
    let bogus = dir.path("bogus.ckpt");
    std::fs::write(&bogus, b"\x10\0\0\0\0\0\0\0{\"a\":").unwrap();
    let o = nephele(&["eval", &bogus, &missing]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("bogus.ckpt") && !stderr.contains("panicked"), "{stderr}");
}

/// `nephele bench tradeoff` runs end to end on a small dataset and prints every variant of
/// the table in order (the ablation, the PSH sizes, one-hit and multi-hit rows of `nephele
/// train`'s settings with their queries per hit ray, the oracle ceilings) and every distance
/// of the sweep, with both plots. Numbers here say nothing about quality (a few steps on
/// 32×32 views); the figures come from the lego run in `examples/assets/README.md`.
#[test]
fn bench_tradeoff_prints_the_table_and_plots_the_sweep() {
    let dir = TempDir::new("tradeoff");
    let data = dir.path("data");
    ok(&["synth", "--scene", "mixed", "--size", "32x32", "--train", "8", "--val", "0", "--test", "2", "--out", &data]);
    ok(&["train", &data, "--out", &dir.path("a"), "--until", "ngp", "--preset", "tiny", "--steps", "150"]);
    let out = dir.path("bench");
    let o = nephele(&[
        "bench", "tradeoff", &data, "--teacher", &dir.path("a/ngp.ckpt"), "--downscale", "1", "--nolf-steps", "20", "--psh", "64,256",
        "--size", "48x48", "--views", "1", "--distances", "3", "--taus", "1,0.02", "--out", &out, "--json",
    ]);
    // With --json the table goes to stderr and the report to stdout.
    let (json_out, stdout) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success() && !stdout.contains("panicked"), "{stdout}");
    // Every row of the paper's ablation, in its order, the PSH sizes, the τ rows, the oracles.
    let rows = [
        "| i-NGP |",
        "| i-NOLF base (density network; hash-grid E_s, no diffuse net) |",
        "| + density cubes |",
        "| + diffuse MLP |",
        "| + diffuse cubes |",
        "| + PSH 256 (an asset) |",
        "| + diffuse net trained on its bake lattice, PSH 256 (the asset) |",
        "| PSH 64 (the asset at another N) |",
        "| `nephele train` default (PSH 128), one hit (τ = 1) |",
        "| `nephele train` default (PSH 128), τ = 0.02, up to 3 hits |",
        "| oracle: the teacher's colour at its max-weight sample (ideal one-hit student) |",
        "| oracle: multi-hit τ = 0.02, colour at each segment's peak |",
        "| oracle: multi-hit τ = 0.02, each segment's colour averaged by weight |",
    ];
    let mut at = 0;
    for row in rows {
        let found = stdout[at..].find(row).unwrap_or_else(|| panic!("missing {row:?} (in order) in\n{stdout}"));
        at += found + row.len();
    }
    assert!(stdout.contains("queries per hit ray") && stdout.contains("Fig. 13"), "{stdout}");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.0.join("bench/tradeoff.json")).unwrap()).unwrap();
    assert_eq!(serde_json::from_str::<serde_json::Value>(&json_out).unwrap(), report, "--json prints what tradeoff.json holds");
    let json_rows = report["rows"].as_array().unwrap();
    assert_eq!(json_rows.len(), rows.len());
    assert_eq!(report["sweep"].as_array().unwrap().len(), 3);
    for row in json_rows {
        let name = row["variant"].as_str().unwrap();
        assert!(row["psnr"].as_f64().unwrap() > 10.0, "{row}");
        // Oracles are not timed (they cost a teacher march); everything else is.
        assert!(name.starts_with("oracle") || row["total_ms"].as_f64().unwrap() > 0.0, "{row}");
        let queries = row["queries_per_hit"].as_f64();
        match name {
            "i-NGP" => assert!(queries.is_none(), "{row}"),
            _ if name.contains("τ = 0.02") => assert!(queries.is_some_and(|q| (1.0..=3.0).contains(&q)), "{row}"),
            _ => assert_eq!(queries, Some(1.0), "{row}"),
        }
    }
    // Coverage grows as the camera comes closer.
    let cov: Vec<f64> = report["sweep"].as_array().unwrap().iter().map(|p| p["coverage"].as_f64().unwrap()).collect();
    assert!(cov[2] > cov[0], "{cov:?}");
    assert_eq!(png_size(&dir.0.join("bench/tradeoff_distance.png")), (720, 460));
    assert_eq!(png_size(&dir.0.join("bench/tradeoff_psnr_ms.png")), (720, 460));
    for svg in ["bench/tradeoff_distance.svg", "bench/tradeoff_psnr_ms.svg"] {
        let text = std::fs::read_to_string(dir.0.join(svg)).unwrap_or_else(|e| panic!("{svg}: {e}"));
        assert!(text.starts_with("<svg") && text.contains("i-NOLF"), "{svg}");
    }
    // `--replot` redraws both charts from the saved report (NaN figures read back from JSON
    // nulls) and prints the same report.
    for chart in ["bench/tradeoff_distance.png", "bench/tradeoff_psnr_ms.png"] {
        std::fs::remove_file(dir.0.join(chart)).unwrap();
    }
    let o = nephele(&["bench", "tradeoff", "--replot", &dir.path("bench/tradeoff.json"), "--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(serde_json::from_slice::<serde_json::Value>(&o.stdout).unwrap(), report, "--replot prints the saved report");
    assert_eq!(png_size(&dir.0.join("bench/tradeoff_distance.png")), (720, 460));
    assert_eq!(png_size(&dir.0.join("bench/tradeoff_psnr_ms.png")), (720, 460));

    // `bench quilt` with the same teacher, at a 2×2 quilt of tiny tiles on both backends,
    // and the stereo stream: every figure finite, the table on stderr.
    let o = nephele(&[
        "bench", "quilt", "--asset", "builtin:trio-small", "--teacher", &dir.path("a/ngp.ckpt"), "--quilt", "2x2", "--tile", "16x24", "--backends", "cpu,gpu",
        "--runs", "1", "--stereo-size", "64x32", "--stereo-poses", "30", "--json",
    ]);
    let (json_out, table) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success() && !table.contains("panicked"), "{table}");
    assert!(table.contains("| backend | i-NOLF one task ms |"), "{table}");
    let quilt: serde_json::Value = serde_json::from_str(&json_out).unwrap_or_else(|e| panic!("{e}: {json_out}"));
    assert_eq!(quilt["views"], 4);
    let quilt_rows = quilt["rows"].as_array().unwrap();
    assert_eq!(quilt_rows.len(), 2, "{quilt:#}");
    for row in quilt_rows {
        for key in ["nolf_batched_ms", "nolf_separate_ms", "ngp_ms", "speedup_vs_ngp", "speedup_batched"] {
            assert!(row[key].as_f64().is_some_and(|v| v > 0.0), "{key} in {row}");
        }
    }
    for key in ["mono_fps", "stereo_fps", "latency_ratio", "stereo_latency_ms.p50"] {
        let v = key.split('.').fold(&quilt["stereo"], |v, k| &v[k]);
        assert!(v.as_f64().is_some_and(|v| v > 0.0), "stereo {key} in {quilt:#}");
    }
}

/// An instant-ngp `transforms.json` with `aabb_scale` trains in the grown box.
#[test]
fn train_maps_aabb_scale_to_the_scene_box() {
    let dir = TempDir::new("aabb");
    let data = dir.path("data");
    ok(&["synth", "--scene", "diffuse", "--size", "16x16", "--train", "3", "--val", "0", "--test", "0", "--out", &data]);
    let file = dir.0.join("data/transforms_train.json");
    let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    json["aabb_scale"] = 2.into();
    std::fs::write(dir.0.join("data/transforms.json"), json.to_string()).unwrap();
    for split in ["train", "val", "test"] {
        let _ = std::fs::remove_file(dir.0.join(format!("data/transforms_{split}.json")));
    }
    let summary = ok(&["train", &data, "--out", &dir.path("w"), "--until", "ngp", "--preset", "tiny", "--steps", "2", "--json"]);
    assert_eq!(summary["ngp"]["bounds"], serde_json::json!([[-3.0, -3.0, -3.0], [3.0, 3.0, 3.0]]), "{summary}");
    json["aabb_scale"] = 1000.into();
    std::fs::write(dir.0.join("data/transforms.json"), json.to_string()).unwrap();
    let o = nephele(&["train", &data, "--out", &dir.path("w2"), "--until", "ngp", "--preset", "tiny", "--steps", "2"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("aabb_scale 1000"), "{stderr}");
}

