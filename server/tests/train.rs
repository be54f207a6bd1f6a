//! `nephele train` / `nephele eval` end to end through the binary: synthesise a tiny
//! dataset, train the i-NGP stage with the tiny preset, check that a resumed run ends on
//! the same loss as an uninterrupted one, evaluate the test split (PSNR above a measured
//! floor, side-by-side PNGs written), and bad input is a clear error.

use std::{path::Path, process::Command};

/// Steps of the i-NGP stage in the test (the whole test is ~2·STEPS tiny-preset steps:
/// ≈ 80–160 ms each on 2 cores in release).
const STEPS: u64 = 120;
/// Mean test-split PSNR over white after STEPS steps. Measured (diffuse scene,
/// 32×32, 8 train views, seed 0; deterministic): 20.3 dB; the floor leaves ~3 dB of margin.
const MIN_TEST_PSNR: f64 = 17.0;

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
    ok(&["synth", "--scene", "diffuse", "--size", "32x32", "--train", "8", "--val", "0", "--test", "2", "--out", &data]);

    // One uninterrupted run.
    let steps = STEPS.to_string();
    let full = ok(&["train", &data, "--out", &dir.path("full"), "--preset", "tiny", "--steps", &steps, "--json"]);
    assert_eq!(full["steps"], STEPS);
    assert_eq!(full["stage"], "ngp");
    assert!(dir.0.join("full/ngp.ckpt").exists());

    // Half the steps, then --resume to the end: the same final batch loss, bit for bit (the
    // JSON float round-trips exactly).
    let half = (STEPS / 2).to_string();
    let first = ok(&["train", &data, "--out", &dir.path("split"), "--preset", "tiny", "--steps", &half, "--checkpoint-every", "25", "--json"]);
    assert_eq!(first["steps"], STEPS / 2);
    let resumed = ok(&["train", &data, "--out", &dir.path("split"), "--preset", "tiny", "--steps", &steps, "--resume", "--json"]);
    assert_eq!(resumed["resumed_from_step"], STEPS / 2);
    assert_eq!(resumed["steps"], STEPS);
    assert_eq!(resumed["final_loss"], full["final_loss"], "resumed {resumed}\nuninterrupted {full}");

    // A resume with another preset is refused and says why.
    let o = nephele(&["train", &data, "--out", &dir.path("split"), "--preset", "fast", "--steps", &steps, "--resume"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("different configuration") && !stderr.contains("panicked"), "{stderr}");

    // Evaluation of the test split, with the side-by-side images.
    let eval_dir = dir.path("eval");
    let report = ok(&["eval", &dir.path("full/ngp.ckpt"), &data, "--split", "test", "--out", &eval_dir, "--json"]);
    let mean = report["mean_psnr"].as_f64().unwrap();
    eprintln!("mean test PSNR after {STEPS} steps: {mean:.2} dB, SSIM {}", report["mean_ssim"]);
    assert!(mean > MIN_TEST_PSNR, "mean test PSNR {mean:.2} dB ≤ {MIN_TEST_PSNR}: {report}");
    let ssim = report["mean_ssim"].as_f64().unwrap();
    assert!(ssim > 0.5 && ssim <= 1.0, "{report}");
    let views = report["views"].as_array().unwrap();
    assert_eq!(views.len(), 2);
    for v in views {
        let png = v["comparison"].as_str().unwrap();
        assert_eq!(png_size(Path::new(png)), (3 * 32, 32), "{png}");
    }
    // The resumed checkpoint evaluates identically.
    let again = ok(&["eval", &dir.path("split/ngp.ckpt"), &data, "--json"]);
    assert_eq!(again["mean_psnr"], report["mean_psnr"]);

    // The text report names every view and the means.
    let o = nephele(&["eval", &dir.path("full/ngp.ckpt"), &data]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success() && text.contains("mean PSNR") && text.contains("| 1 |"), "{text}");
}

#[test]
fn train_and_eval_reject_bad_input_clearly() {
    let dir = TempDir::new("bad");
    let missing = dir.path("no-such-dataset");
    let o = nephele(&["train", &missing, "--out", &dir.path("out"), "--preset", "tiny", "--steps", "1"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{stderr}");
    assert!(stderr.contains("no-such-dataset") && !stderr.contains("panicked"), "{stderr}");

    let o = nephele(&["train", &missing, "--out", &dir.path("out"), "--preset", "huge"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("unknown preset"), "{stderr}");

    // A checkpoint that is not one (here: truncated garbage) is an error naming the file.
    let bogus = dir.path("bogus.ckpt");
    std::fs::write(&bogus, b"\x10\0\0\0\0\0\0\0{\"a\":").unwrap();
    let o = nephele(&["eval", &bogus, &missing]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && stderr.contains("bogus.ckpt") && !stderr.contains("panicked"), "{stderr}");
}
