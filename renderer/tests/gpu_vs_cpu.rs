//! The wgpu backend agrees with the CPU reference on lavapipe.
//!
//! Tolerance, and why: the GPU filters the f16 atlases in hardware (weights may be quantised
//! to ~8 bits of sub-texel precision) and fuses multiply-adds differently, so near-tied
//! max-weight samples may pick a neighbouring sample at silhouettes and thin shells. We
//! require: mean |Δ| ≤ 0.5 levels (of 255) over RGBA; ≥ 99% of pixels within 4 levels in every
//! channel; hit/miss disagreement on ≤ 0.5% of pixels; depth within two steps on ≥ 99% of
//! pixels both hit.

mod common;

use glam::{DQuat, DVec3, Vec3};
use nephele_renderer::{
    Backend, CpuBackend, Instance, Intrinsics, RenderSettings, View, ViewRequest,
};
use rand::{Rng, SeedableRng, rngs::SmallRng};

fn check(label: &str, d: &common::FrameDiff) {
    eprintln!("{label}: {d:?}");
    assert!(d.mean_abs <= 0.5, "{label}: mean |Δ| {:.3} levels", d.mean_abs);
    assert!(d.frac_over <= 0.01, "{label}: {:.3}% of pixels off by > 4 levels", 100.0 * d.frac_over);
    assert!(d.hit_mismatch <= 0.005, "{label}: hit/miss differ on {:.3}%", 100.0 * d.hit_mismatch);
    assert!(d.depth_off <= 0.01, "{label}: depth off on {:.3}%", 100.0 * d.depth_off);
}

#[test]
fn whole_frames_in_one_batch_of_several_sizes() {
    let Some(gpu) = common::gpu() else { return };
    let asset = common::fixture();
    let step = asset.march.step;
    let k = |w, h| Intrinsics::from_fov_x(w, h, 0.7);
    let views = [
        ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 35.0, 25.0, k(160, 120))),
        ViewRequest::new(View::orbit(DVec3::ZERO, 3.0, 200.0, -30.0, k(97, 131))).with_background(Vec3::new(0.0, 1.0, 0.0)),
        ViewRequest::new(View::orbit(DVec3::ZERO, 6.0, 90.0, 80.0, k(64, 64))).with_background(Vec3::ZERO),
        ViewRequest {
            view: View::orbit(DVec3::new(5.0, 0.0, 1.0), 5.0, -20.0, 10.0, k(120, 90)),
            instance: Instance { rotation: DQuat::from_rotation_z(0.7), translation: DVec3::new(5.0, 0.0, 1.0), scale: 2.0 },
            background: Vec3::new(0.2, 0.3, 0.4),
        },
    ];
    let settings = RenderSettings::default();
    let cpu = CpuBackend.prepare(asset.clone()).unwrap().render(&views, &settings).unwrap();
    let out = gpu.prepare(asset.clone()).unwrap().render(&views, &settings).unwrap();
    assert_eq!(out.frames.len(), views.len());
    assert_eq!(cpu.stats.rays, out.stats.rays);
    for (i, (c, g)) in cpu.frames.iter().zip(&out.frames).enumerate() {
        let scale = views[i].instance.scale as f32;
        check(&format!("view {i} {}×{}", c.width, c.height), &common::diff(c, g, 4, 2.0 * step * scale));
        assert!(c.coverage() > 0.05, "view {i} should see the object");
    }
    let hit_ratio = out.stats.hits as f64 / cpu.stats.hits as f64;
    assert!((hit_ratio - 1.0).abs() < 0.01, "GPU hits {} vs CPU {}", out.stats.hits, cpu.stats.hits);
}

#[test]
fn random_rays() {
    let Some(gpu) = common::gpu() else { return };
    let asset = common::fixture();
    let mut rng = SmallRng::seed_from_u64(11);
    // Many tiny views from random places and directions (inside the box too), random
    // intrinsics: each pixel is a random ray.
    let views: Vec<ViewRequest> = (0..300)
        .map(|_| {
            let eye = DVec3::new(rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0));
            let target = DVec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
            let (w, h) = (rng.random_range(1..9), rng.random_range(1..9));
            let k = Intrinsics::from_fov_x(w, h, rng.random_range(0.2..1.5));
            ViewRequest::new(View::look_at(eye, target, DVec3::Z, k)).with_background(Vec3::new(rng.random(), rng.random(), rng.random()))
        })
        .collect();
    // Pool all rays into one comparison.
    let pool = |frames: &[nephele_renderer::Frame]| nephele_renderer::Frame {
        width: frames.iter().map(|f| f.width * f.height).sum(),
        height: 1,
        rgba: frames.iter().flat_map(|f| f.rgba.iter().copied()).collect(),
        depth: frames.iter().flat_map(|f| f.depth.iter().copied()).collect(),
    };
    // One hit per ray, and up to three (τ small, so most rays through several parts get
    // more than one query).
    for settings in [RenderSettings::default(), RenderSettings { hit_tau: Some(0.02), max_hits: Some(3), ..Default::default() }] {
        let cpu = CpuBackend.prepare(asset.clone()).unwrap().render(&views, &settings).unwrap();
        let out = gpu.prepare(asset.clone()).unwrap().render(&views, &settings).unwrap();
        let d = common::diff(&pool(&cpu.frames), &pool(&out.frames), 4, 2.0 * asset.march.step);
        assert!(cpu.stats.hits > 500, "too few random rays hit ({})", cpu.stats.hits);
        eprintln!("{} queries for {} hit rays", cpu.stats.queries, cpu.stats.hits);
        if settings.max_hits.is_some() {
            assert!(cpu.stats.queries as f64 > 1.05 * cpu.stats.hits as f64, "the multi-hit rule should add queries: {:?}", cpu.stats);
        }
        check(&format!("random rays, {settings:?}"), &d);
    }
}

#[test]
fn settings_knobs_reach_the_gpu() {
    let Some(gpu) = common::gpu() else { return };
    let asset = common::fixture();
    let view = [ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 10.0, 20.0, Intrinsics::from_fov_x(96, 96, 0.7)))];
    for settings in [
        RenderSettings { step_scale: 2.0, ..Default::default() },
        RenderSettings { stop_ratio: 1.0, ..Default::default() },
        RenderSettings { alpha_min: Some(0.5), ..Default::default() },
        RenderSettings { early_stop: Some(0.05), ..Default::default() },
        RenderSettings { hit_tau: Some(0.02), max_hits: Some(3), ..Default::default() },
        RenderSettings { hit_tau: Some(0.02), max_hits: Some(2), step_scale: 0.5, ..Default::default() },
    ] {
        let c = CpuBackend.prepare(asset.clone()).unwrap().render(&view, &settings).unwrap();
        let g = gpu.prepare(asset.clone()).unwrap().render(&view, &settings).unwrap();
        check(&format!("{settings:?}"), &common::diff(&c.frames[0], &g.frames[0], 4, 2.0 * asset.march.step * settings.step_scale));
    }
    // The asset's own early stop, where the settings name none.
    let mut stopping = (*asset).clone();
    stopping.march.early_stop = 0.05;
    let stopping = std::sync::Arc::new(stopping);
    let c = CpuBackend.prepare(stopping.clone()).unwrap().render(&view, &RenderSettings::default()).unwrap();
    let g = gpu.prepare(stopping.clone()).unwrap().render(&view, &RenderSettings::default()).unwrap();
    check("the asset's early stop", &common::diff(&c.frames[0], &g.frames[0], 4, 2.0 * asset.march.step));
    let named = CpuBackend.prepare(asset.clone()).unwrap().render(&view, &RenderSettings { early_stop: Some(0.05), ..Default::default() }).unwrap();
    assert!(c.frames[0] == named.frames[0], "the reference ignores the asset's early stop");
}

/// Buffers are reused between renders: a small batch after a large one, and a larger one
/// after that, give the same frames as fresh renders.
#[test]
fn reused_buffers_give_the_same_frames() {
    let Some(gpu) = common::gpu() else { return };
    let asset = common::fixture();
    let settings = RenderSettings::default();
    let k = |w, h| Intrinsics::from_fov_x(w, h, 0.7);
    let big = [
        ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 10.0, 20.0, k(120, 90))),
        ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 80.0, 20.0, k(64, 64))),
    ];
    let small = [ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 200.0, 5.0, k(33, 17)))];
    let bigger = [big[0], big[1], small[0], ViewRequest::new(View::orbit(DVec3::ZERO, 3.0, 300.0, 40.0, k(160, 160)))];
    let shared = gpu.prepare(asset.clone()).unwrap();
    for batch in [&big[..], &small[..], &bigger[..], &small[..]] {
        let reused = shared.render(batch, &settings).unwrap();
        let fresh = gpu.prepare(asset.clone()).unwrap().render(batch, &settings).unwrap();
        assert_eq!(reused.frames, fresh.frames);
        assert_eq!(reused.stats.hits, fresh.stats.hits);
    }
}

/// 8-bit unorm diffuse cubes go to an Rgba8Unorm atlas; the GPU still agrees with the CPU
/// reading the same rounded values, and the frames stay within a level of the f16 asset's.
#[test]
fn unorm8_diffuse_atlas_matches_the_cpu() {
    let Some(gpu) = common::gpu() else { return };
    let half = common::fixture();
    let mut asset = (*half).clone();
    asset.diffuse = asset.diffuse.clone().stored_as(nephele_renderer::cubes::CubeStorage::Unorm8);
    let asset = std::sync::Arc::new(asset);
    let view = [ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 35.0, 25.0, Intrinsics::from_fov_x(128, 96, 0.7)))];
    let settings = RenderSettings::default();
    let c = CpuBackend.prepare(asset.clone()).unwrap().render(&view, &settings).unwrap();
    let g = gpu.prepare(asset.clone()).unwrap().render(&view, &settings).unwrap();
    check("unorm8 diffuse", &common::diff(&c.frames[0], &g.frames[0], 4, 2.0 * asset.march.step));
    let f = CpuBackend.prepare(half.clone()).unwrap().render(&view, &settings).unwrap();
    let d = common::diff(&f.frames[0], &c.frames[0], 2, 2.0 * asset.march.step);
    assert!(d.mean_abs <= 0.25 && d.frac_over <= 0.001, "unorm8 vs f16 on the CPU: {d:?}");
}
