//! Every `nephele bench …` subcommand through the binary at a tiny size, so that no later
//! change (a new limit, a renamed flag, a report field) breaks one unseen. Each run asks for
//! `--json`: the JSON report on stdout must parse and hold its keys as numbers (serde_json
//! writes a NaN or infinite figure as `null`, so a number here is a finite figure), and the
//! table a person reads goes to stderr, whose header is checked too. `quilt` and `tradeoff`
//! need an i-NGP teacher: they run in `tests/train.rs`, after one is trained.
//!
//! Nothing here says how fast anything is: the figures come from the benches run at full
//! size (docs/benchmarks.md).

use std::process::Command;

use serde_json::Value;

/// Runs `nephele bench ARGS --json`; returns the report and the table.
fn bench(args: &[&str]) -> (Value, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_nephele")).arg("bench").args(args).arg("--json").output().expect("runs");
    let (stdout, stderr) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr).into_owned());
    assert!(o.status.success(), "nephele bench {args:?} failed:\n{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    let report = serde_json::from_str(&stdout).unwrap_or_else(|e| panic!("bench {args:?}: stdout is not JSON ({e}):\n{stdout}"));
    (report, stderr)
}

/// The value at a dotted path (`rows.0.total_ms`).
fn at<'a>(v: &'a Value, path: &str) -> &'a Value {
    path.split('.').fold(v, |v, key| match key.parse::<usize>() {
        Ok(i) => &v[i],
        Err(_) => &v[key],
    })
}

/// Every path is a finite number (asserts and returns them).
fn numbers(v: &Value, paths: &[&str]) -> Vec<f64> {
    paths.iter().map(|p| at(v, p).as_f64().unwrap_or_else(|| panic!("{p} is not a finite number in\n{v:#}"))).collect()
}

/// For every element of the array at `array`, each of `keys` is a finite number.
fn rows(v: &Value, array: &str, keys: &[&str]) -> usize {
    let items = at(v, array).as_array().unwrap_or_else(|| panic!("{array} is not an array in\n{v:#}"));
    assert!(!items.is_empty(), "{array} is empty in\n{v:#}");
    for item in items {
        numbers(item, keys);
    }
    items.len()
}

#[test]
fn bench_render() {
    let (r, table) = bench(&["render", "--asset", "builtin:trio-small", "--sizes", "32x24,17x9", "--backends", "cpu,gpu", "--runs", "1", "--batch", "2"]);
    assert_eq!(rows(&r, "rows", &["width", "height", "march_ms", "shade_ms", "total_ms", "rays_per_s", "hit_fraction", "samples_per_ray"]), 4, "two backends × two sizes");
    assert_eq!(rows(&r, "batches", &["together_ms", "alone_ms"]), 4);
    let [stored, dense] = numbers(&r, &["asset_stored_bytes", "asset_dense_bytes"])[..] else { unreachable!() };
    assert!(stored > 0.0 && dense >= stored, "{r:#}");
    if cfg!(target_arch = "x86_64") {
        assert!(numbers(&r, &["peak_fma_gflops"])[0] > 0.0);
    }
    assert!(table.contains("| backend | size | ray-march ms |") && table.contains("batching speed-up") && table.contains("memory:"), "{table}");
}

#[test]
fn bench_encode() {
    let (r, table) = bench(&["encode", "--sizes", "64x48", "--frames", "6", "--asset", "builtin:trio-small", "--bits-per-pixel", "0.1,0.3", "--threads", "1"]);
    assert_eq!(rows(&r, "rows", &["convert_ms_p50", "convert_ms_p99", "encode_ms_p50", "encode_ms_p99", "bytes_per_frame", "idr_bytes", "psnr_db", "bitrate_bps"]), 4, "pattern and asset × two rates");
    for row in r["rows"].as_array().unwrap() {
        assert!(row["psnr_db"].as_f64().unwrap() > 20.0, "{row}");
    }
    assert!(table.contains("| content | size | frames | bits/pixel |"), "{table}");
}

#[test]
fn bench_stream() {
    let (r, table) = bench(&["stream", "--asset", "builtin:trio-small", "--sizes", "64x48", "--backend", "cpu", "--render-scales", "1,auto", "--poses", "60"]);
    assert_eq!(
        rows(&r, "rows", &["fps", "kbps", "frames", "idr_frames", "bad_frames", "render_ms.p50", "encode_ms.p50", "pose_to_info_ms.p50", "pose_to_decoded_ms.p50", "pose_to_decoded_ms.p99", "psnr_mean_db", "psnr_min_db"]),
        2
    );
    for row in r["rows"].as_array().unwrap() {
        assert!(row["frames"].as_u64().unwrap() > 0 && row["bad_frames"] == 0, "{row}");
    }
    assert_eq!(r["poses"], 60);
    assert!(table.contains("| size | scale | queue | render |") && table.contains("PSNR mean / min dB"), "{table}");
}

/// What the eye sees, at 0 and 50 ms: every mode scored, depth with every frame (none missing,
/// bytes counted), warped frames show the display pose (age 0), and a still camera loses
/// nothing to reprojection (≤ 0.2 dB: the bound; the warp to the same camera is exact).
#[test]
fn bench_glass() {
    let (r, table) = bench(&["glass", "--asset", "builtin:trio-small", "--size", "64x48", "--backend", "cpu", "--rtts", "0,50"]);
    assert_eq!(rows(&r, "rows", &["psnr_mean_db", "psnr_p5_db", "pose_age_mean_ms", "rotation_error_mean_deg", "video_bytes_per_frame", "depth_bytes_per_frame", "render_ms_mean", "learnt_latency_ms"]), 8);
    for row in r["rows"].as_array().unwrap() {
        assert!(row["display_frames"].as_u64().unwrap() > 100, "{row}");
        assert_eq!(row["missing_depth"], 0, "{row}");
        assert!(row["depth_bytes_per_frame"].as_f64().unwrap() > 0.0, "{row}");
        if ["reproject", "both"].contains(&row["mode"].as_str().unwrap()) {
            assert_eq!(row["pose_age_mean_ms"], 0.0, "{row}");
        }
    }
    let [stale, warped] = numbers(&r, &["still_stale_db", "still_reproject_db"])[..] else { unreachable!() };
    assert!(warped >= stale - 0.2, "still camera: {stale} dB as decoded, {warped} dB warped");
    for (mode, rtt) in [("both", "50"), ("stale", "0"), ("reproject", "0"), ("predict", "50")] {
        assert!(r["psnr_db"][mode][rtt].as_f64().is_some(), "psnr_db.{mode}.{rtt} in {}", r["psnr_db"]);
    }
    assert!(table.contains("| RTT ms | mode | PSNR mean dB |") && table.contains("Still camera, 0 ms"), "{table}");
}

/// Two users, batching on and off, one address: the bench's own server raises signaling's
/// per-address limits (`users::hub_for`), so its clients are not refused as a flood.
#[test]
fn bench_users() {
    let (r, table) = bench(&["users", "--asset", "builtin:trio-small", "--size", "64x48", "--users", "1,2", "--backends", "cpu", "--poses", "50", "--fps", "20"]);
    numbers(&r, &["backends.cpu.speedup", "backends.cpu.pixel_speedup", "backends.cpu.batched.user_frames_per_s", "backends.cpu.per_user.user_megapixels_per_s"]);
    for mode in ["batched", "per_user"] {
        assert_eq!(rows(&r, &format!("backends.cpu.{mode}.runs"), &["users", "users_held", "fps_min", "fps_mean", "user_megapixels_per_s", "latency_p50_ms", "latency_p99_ms", "mean_batch_views"]), 2);
    }
    let wrong: u64 = ["batched", "per_user"].iter().flat_map(|m| r["backends"]["cpu"][m]["runs"].as_array().unwrap()).map(|run| run["frames_wrong_pose"].as_u64().unwrap()).sum();
    assert_eq!(wrong, 0);
    numbers(&r, &["shared_view.users", "shared_view.reused_frames", "overload.offered", "overload.admitted"]);
    assert!(table.contains("| backend | mode | users | held |") && table.contains("batching raises user-frames/s"), "{table}");
}

/// One object on one in-process worker, one and two NATS workers, a composed scene, and one
/// worker killed: every figure finite, both NATS workers served, none lost a session.
#[test]
fn bench_farm() {
    let (r, table) = bench(&["farm", "--asset", "builtin:trio-small", "--scene", "builtin:duo", "--size", "64x48", "--poses", "40", "--kills", "1"]);
    rows(&r, "runs", &["fps", "frames", "latency_p50_ms", "frame_ms", "render_max_ms", "hop_ms"]);
    assert_eq!(numbers(&r, &["failover_gaps_ms.0", "failover_gap_ms", "sessions_lost"])[2], 0.0, "{r:#}");
    assert!(table.contains("| scene | farm | fps |"), "{table}");
}

#[test]
fn bench_abuse() {
    let (r, table) = bench(&["abuse", "--connections", "40", "--addresses", "4", "--seconds", "2", "--size", "64x48"]);
    let [before, during, after, peak] = numbers(&r, &["fps_before", "fps_during", "fps_after", "rss_peak_mb"])[..] else { unreachable!() };
    assert!(before > 0.0 && during > 0.0 && after > 0.0 && peak > 0.0, "{r:#}");
    assert!(r["viewer_errors"].as_array().is_some_and(Vec::is_empty), "{r:#}");
    assert!(table.contains("| phase | viewer fps | server RSS MB |"), "{table}");
}
