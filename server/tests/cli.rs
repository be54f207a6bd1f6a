//! The `nephele` command line: render, info, generate, synth and bench print and write what
//! they say, and bad input is a clear error with a non-zero exit. (Streaming end to end
//! through separate processes is in the workspace's `tests/` crate.)

use std::process::Command;

fn nephele(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_nephele")).args(args).output().expect("runs")
}

fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("nephele-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

#[test]
fn render_writes_pngs() {
    let out = tmp("r.png");
    let depth = tmp("d.png");
    let o = nephele(&["render", "builtin:trio-small", "--size", "63x47", "--backend", "cpu", "--out", out.to_str().unwrap(), "--depth", depth.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("of rays hit"));
    let png = std::fs::read(&out).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    assert!(depth.exists());
}

/// RGB bytes of a PNG `nephele render` wrote.
fn read_rgb(path: &std::path::Path) -> Vec<u8> {
    let mut reader = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap())).read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    buf
}

/// The fast CPU renderer at every vector level this CPU has (AVX-512/AVX2 as detected,
/// AVX2 capped, portable code) draws what the reference draws, one-hit and multi-hit.
#[test]
fn every_simd_level_renders_what_the_reference_renders() {
    for tau in ["1", "0.1"] {
        let reference = tmp(&format!("ref-{tau}.png"));
        let o = nephele(&["render", "builtin:lego", "--size", "96x72", "--backend", "cpu-ref", "--hit-tau", tau, "--out", reference.to_str().unwrap()]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let want = read_rgb(&reference);
        for level in ["", "avx2", "portable"] {
            let out = tmp(&format!("fast-{tau}-{level}.png"));
            let o = Command::new(env!("CARGO_BIN_EXE_nephele"))
                .args(["render", "builtin:lego", "--size", "96x72", "--backend", "cpu", "--hit-tau", tau, "--out", out.to_str().unwrap()])
                .env("NEPHELE_SIMD", level)
                .output()
                .unwrap();
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
            let got = read_rgb(&out);
            assert_eq!(got.len(), want.len());
            let off = got.chunks(3).zip(want.chunks(3)).filter(|(a, b)| a.iter().zip(*b).any(|(x, y)| x.abs_diff(*y) > 1)).count();
            assert!(off * 1000 <= got.len() / 3, "τ {tau}, NEPHELE_SIMD={level:?}: {off} pixels off by more than one level");
        }
    }
}

#[test]
fn render_from_a_nerf_pose_file() {
    let pose = tmp("pose.json");
    // A NeRF-synthetic style camera 4 units out on +y, looking at the origin.
    std::fs::write(&pose, r#"{"camera_angle_x": 0.69, "transform_matrix": [[-1,0,0,0],[0,0,1,4],[0,1,0,0],[0,0,0,1]]}"#).unwrap();
    let out = tmp("pose.png");
    let o = nephele(&["render", "builtin:shiny-small", "--pose", pose.to_str().unwrap(), "--size", "32x32", "--backend", "cpu", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!String::from_utf8_lossy(&o.stderr).contains("no ray hit"));
}

#[test]
fn generate_info_and_bench_print_tables() {
    let asset = tmp("g.nolf");
    let o = nephele(&["generate", "--scene", "diffuse", "--small", "--out", asset.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = nephele(&["info", asset.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("density cubes") && text.contains("dense MiB"), "{text}");
    let o = nephele(&["bench", "render", "--asset", asset.to_str().unwrap(), "--sizes", "32x32,17x9", "--backends", "cpu", "--runs", "1"]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(text.contains("| cpu | 32×32 |") && text.contains("| cpu | 17×9 |"), "{text}");
    assert!(text.contains("fast CPU march: "), "the march the cpu rows used: {text}");
    // A knob is timed beside the default rule, with its PSNR against the default's frame.
    let o = nephele(&["bench", "render", "--asset", "builtin:trio-small", "--sizes", "64x48", "--backends", "cpu", "--runs", "1", "--early-stop", "0.5"]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(text.contains("PSNR vs default rule") && text.contains("| cpu | default | 64×48 |"), "{text}");
    let knob_row = text.lines().find(|l| l.starts_with("| cpu | early stop 0.5 | 64×48 |")).unwrap_or_else(|| panic!("{text}"));
    let psnr: f64 = knob_row.trim_end_matches(" |").rsplit("| ").next().unwrap().parse().unwrap_or_else(|e| panic!("{knob_row}: {e}"));
    assert!(psnr.is_finite() && psnr > 0.0 && psnr < 60.0, "T < 0.5 stops early enough to change the frame, and the column says so: {knob_row}");
    // The CPU backend's marches side by side: every one renders the first one's frame.
    #[cfg(target_arch = "x86_64")]
    let marches = if std::arch::is_x86_feature_detected!("avx512f") { "avx512,avx2,ray" } else { "avx2,ray" };
    #[cfg(not(target_arch = "x86_64"))]
    let marches = "ray";
    // With the f32 network, every march renders the first one's frame; the 8-bit network
    // (where the CPU has AVX-512 VNNI) is close to it, and the column says how close.
    #[cfg(target_arch = "x86_64")]
    let int8 = std::arch::is_x86_feature_detected!("avx512vnni") && std::arch::is_x86_feature_detected!("avx512f");
    #[cfg(not(target_arch = "x86_64"))]
    let int8 = false;
    let networks = if int8 { "f32,int8" } else { "f32" };
    let o = nephele(&["bench", "render", "--asset", "builtin:trio-small", "--sizes", "64x48", "--backends", "cpu", "--runs", "1", "--marches", marches, "--networks", networks]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(text.contains("PSNR vs first variant dB"), "{text}");
    for (i, march) in marches.split(',').enumerate() {
        let row = text.lines().find(|l| l.starts_with(&format!("| cpu, {march} march, f32 network | 64×48 |"))).unwrap_or_else(|| panic!("no {march} row: {text}"));
        assert_eq!(row.ends_with("| ∞ (same frame) |"), i > 0, "{row}");
        if int8 {
            let row = text.lines().find(|l| l.starts_with(&format!("| cpu, {march} march, int8 network | 64×48 |"))).unwrap_or_else(|| panic!("no {march} int8 row: {text}"));
            let psnr: f64 = row.trim_end_matches(" |").rsplit("| ").next().unwrap().parse().unwrap_or_else(|e| panic!("{row}: {e}"));
            assert!((45.0..200.0).contains(&psnr), "{row}");
        }
    }
}

#[test]
fn bad_input_is_a_clear_error() {
    let missing = tmp("missing.json");
    std::fs::write(&missing, r#"{"objects":[{"asset":"builtin:lego"},{"asset":"nowhere.nolf"}]}"#).unwrap();
    let skewed = tmp("skewed.json");
    std::fs::write(&skewed, r#"{"objects":[{"asset":"builtin:trio-small","world_from_object":{"rotation":[0,0,0.5,0.5]}}]}"#).unwrap();
    let crowded = tmp("crowded.json");
    std::fs::write(&crowded, format!(r#"{{"objects":[{}]}}"#, vec![r#"{"asset":"builtin:trio-small"}"#; 100].join(","))).unwrap();
    let (missing, skewed, crowded) = (missing.display().to_string(), skewed.display().to_string(), crowded.display().to_string());
    for (args, words) in [
        (vec!["render", missing.as_str(), "--backend", "cpu"], "nowhere.nolf"),
        (vec!["render", skewed.as_str(), "--backend", "cpu"], "unit quaternion"),
        (vec!["render", crowded.as_str(), "--backend", "cpu"], "100 objects; at most 16"),
        (vec!["worker", "--scene", "builtin:trio-small"], "needs --nats"),
        (vec!["render", "/nonexistent.nolf"], "nonexistent.nolf"),
        (vec!["render", "builtin:teapot"], "unknown procedural scene"),
        (vec!["render", "builtin:trio-small", "--size", "100000x10", "--backend", "cpu"], "outside"),
        (vec!["render", "builtin:trio-small", "--size", "ax3"], "invalid digit"),
        (vec!["render", "builtin:trio-small", "--background", "purple"], "colour"),
        (vec!["synth", "--scene", "teapot", "--out", "/tmp/never"], "unknown synthetic scene"),
        (vec!["dataset-info", "/nonexistent/lego"], "does not exist"),
        (vec!["serve", "--render-scale", "2"], "render scale"),
        (vec!["serve", "--public-ip", "my.host.example"], "is not an IP address"),
        (vec!["serve", "--listen", "127.0.0.1:0", "--rtc-port", "47999", "--public-ip", "2001:db8::4", "--scene", "builtin:trio-small", "--backend", "cpu"], "IPv4 only"),
        (vec!["health", "https://127.0.0.1:1/readyz"], "only http:// URLs"),
        (vec!["health", "http://127.0.0.1:1/readyz"], "connecting to 127.0.0.1:1"),
        (vec!["render", "builtin:trio-small", "--hit-tau", "2"], "--hit-tau in [0, 1]"),
        (vec!["render", "builtin:trio-small", "--max-hits", "0"], "--max-hits in 1..=3"),
        (vec!["serve", "--hit-tau", "NaN"], "--hit-tau in [0, 1]"),
        (vec!["render", "builtin:trio-small", "--early-stop", "1"], "--early-stop in [0, 1)"),
        (vec!["serve", "--early-stop", "NaN"], "--early-stop in [0, 1)"),
        (vec!["replay", "--trace", "/nonexistent.json"], "nonexistent.json"),
        (vec!["bench", "render", "--backends", "cpu-ref", "--marches", "ray"], "add cpu to --backends"),
        (vec!["bench", "render", "--backends", "cpu", "--marches", "simd"], "the marches are avx512, avx2 and ray"),
        (vec!["bench", "render", "--backends", "cpu", "--networks", "f16"], "the networks are f32 and int8"),
        (vec!["serve", "--pose-latch", "2"], "outside 0..=0.5"),
        (vec!["serve", "--pose-latch", "NaN"], "outside 0..=0.5"),
        (vec!["bench", "stream", "--pose-latch=-0.1"], "outside 0..=0.5"),
        (vec!["bench", "encode", "--asset", "none", "--threads", "2,5"], "--threads: 5 encoder threads: OpenH264 takes 1..=4"),
        // Closed choices name what they accept.
        (vec!["replay", "--mode", "hologram"], "[possible values: viewer, ar]"),
        (vec!["bench", "abuse", "--admission", "lottery"], "[possible values: load, open]"),
        (vec!["bench", "users", "--backends", "tpu"], "[possible values: auto, gpu, cpu, cpu-ref]"),
        (vec!["serve", "--admission", "lottery"], "[possible values: load, open]"),
    ] {
        let o = nephele(&args);
        assert!(!o.status.success(), "{args:?} should fail");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(words), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    }
}

#[test]
fn synth_writes_a_dataset_that_dataset_info_reads() {
    let dir = tmp("synth");
    let o = nephele(&["synth", "--scene", "glossy", "--size", "32x24", "--train", "3", "--val", "1", "--test", "2", "--out", dir.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = nephele(&["dataset-info", dir.to_str().unwrap(), "--load"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for line in ["train    3 frames, first image Some((32, 24))", "val      1 frames", "test     2 frames", "decoded 3 images"] {
        assert!(out.contains(line), "missing {line:?} in:\n{out}");
    }
}

#[test]
fn shipped_traces_are_the_built_in_ones() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/traces");
    for name in nephele_client::replay::BUILTIN_TRACES {
        let shipped = nephele_client::replay::Trace::load(&root.join(format!("{name}.json"))).unwrap();
        assert_eq!(shipped, nephele_client::replay::Trace::builtin(name).unwrap(), "{name}: regenerate with `nephele traces`");
    }
}

/// A headless machine has no `XDG_RUNTIME_DIR`; probing Vulkan adapters must not make the
/// Wayland client library print its complaint: the user sees only what Nephele says.
#[test]
fn first_start_without_a_runtime_dir_prints_only_our_words() {
    let out = std::env::temp_dir().join(format!("nephele-xdg-{}.png", std::process::id()));
    let o = Command::new(env!("CARGO_BIN_EXE_nephele"))
        .args(["render", "builtin:trio-small", "--backend", "gpu", "--size", "8x8", "--out", out.to_str().unwrap()])
        .env_remove("XDG_RUNTIME_DIR")
        .output()
        .expect("runs");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(!stderr.contains("XDG_RUNTIME_DIR") && !String::from_utf8_lossy(&o.stdout).contains("XDG_RUNTIME_DIR"), "{stderr}");
    let _ = std::fs::remove_file(out);
}

/// `--asset` names the asset of `render` and `info` as it does every bench's; the old
/// positional spelling still works, with a deprecation warning naming the new one.
#[test]
fn asset_is_a_flag_and_the_old_positional_still_works() {
    let o = nephele(&["info", "--asset", "builtin:trio-small"]);
    let (out, err) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success() && out.contains("name: ") && !err.contains("deprecated"), "{err}");
    let o = nephele(&["info", "builtin:trio-small"]);
    let (old, err) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success() && old == out, "{err}");
    assert!(err.contains("deprecated") && err.contains("nephele info --asset builtin:trio-small"), "{err}");
}

