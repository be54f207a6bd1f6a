//! Numerical stability at the extremes of docs/architecture.md §7, on every backend (the CPU reference, the
//! fast CPU renderer, wgpu): cameras inside the box,
//! on its face and 10⁶ units away; axis-parallel rays with exactly zero components; σ = 0 and
//! σ saturating f16; 1×1 and 8K viewports; NaN/Inf/non-rigid poses and absurd sizes → errors;
//! a cancelled render stops with `Cancelled` on both backends.

mod common;

use std::sync::Arc;

use glam::{DMat4, DVec3, DVec4};
use nephele_renderer::{
    Asset, Backend, CancelFlag, CpuBackend, FastCpuBackend, Intrinsics, PoseError, RenderError, RenderOutput, RenderSettings, View, ViewRequest,
    procedural::{self, ProceduralConfig, Scene},
};

/// Renders on every backend, checks they agree and that nothing is NaN. The fast CPU
/// renderer follows the reference to within a level (tests/fast_cpu.rs); wgpu within 4.
fn both(asset: &Arc<Asset>, views: &[ViewRequest]) -> Option<RenderOutput> {
    let settings = RenderSettings::default();
    let cpu = CpuBackend.prepare(asset.clone()).unwrap().render(views, &settings).unwrap();
    for f in &cpu.frames {
        assert!(f.depth.iter().all(|d| !d.is_nan() && *d > 0.0), "depth must be positive or +inf");
    }
    let fast = FastCpuBackend.prepare(asset.clone()).unwrap().render(views, &settings).unwrap();
    for (c, f) in cpu.frames.iter().zip(&fast.frames) {
        let d = common::diff(c, f, 2, 1e-3 * asset.march.step);
        assert!(d.frac_over <= 0.001 && d.hit_mismatch <= 0.001 && d.depth_off <= 0.001, "fast CPU vs reference: {d:?}");
    }
    let gpu = common::gpu()?;
    let out = gpu.prepare(asset.clone()).unwrap().render(views, &settings).unwrap();
    for (c, g) in cpu.frames.iter().zip(&out.frames) {
        let d = common::diff(c, g, 4, 2.0 * asset.march.step * 1.001);
        assert!(d.mean_abs <= 0.5 && d.frac_over <= 0.01 && d.hit_mismatch <= 0.005, "{d:?}");
    }
    Some(cpu)
}

fn k(w: u32, h: u32) -> Intrinsics {
    Intrinsics::from_fov_x(w, h, 1.2)
}

#[test]
fn camera_inside_the_box_and_inside_an_object() {
    let a = common::fixture();
    // Inside the box, between the objects, looking at the sphere (centre (0.65, 0.35, 0)).
    let inside = View::look_at(DVec3::new(-0.2, 0.0, 0.3), DVec3::new(0.65, 0.35, 0.0), DVec3::Z, k(48, 40));
    // Inside the sphere: sees its back side from within.
    let in_sphere = View::look_at(DVec3::new(0.65, 0.35, 0.0), DVec3::new(0.0, 0.0, 0.0), DVec3::Z, k(33, 21));
    let out = both(&a, &[ViewRequest::new(inside), ViewRequest::new(in_sphere)]).unwrap();
    assert!(out.frames[0].coverage() > 0.2, "the sphere fills much of the view");
    let near = out.frames[0].depth.iter().copied().filter(|d| d.is_finite()).fold(f32::MAX, f32::min);
    assert!(near > 0.2 && near < 1.0, "nearest hit {near}");
}

#[test]
fn camera_touching_the_box_face() {
    let a = common::fixture();
    let on_face = View::look_at(DVec3::new(1.5, 0.35, 0.0), DVec3::new(0.0, 0.35, 0.0), DVec3::Z, k(31, 31));
    let out = both(&a, &[ViewRequest::new(on_face)]).unwrap();
    assert!(out.frames[0].coverage() > 0.3);
}

#[test]
fn a_million_units_away_looks_like_a_thousand() {
    let a = common::fixture();
    // Telephoto so the 3-unit box fills the frame; at 10³ and 10⁶ the projection is
    // orthographic to within 10⁻³, so the two images must agree.
    let frame_at = |dist: f64| {
        let mut intr = k(64, 64);
        intr.fx = (dist * 64.0 / 3.2) as f32;
        intr.fy = intr.fx;
        ViewRequest::new(View::orbit(DVec3::ZERO, dist, 30.0, 20.0, intr))
    };
    let out = both(&a, &[frame_at(1e3), frame_at(1e6)]).unwrap();
    let d = common::diff(&out.frames[0], &out.frames[1], 6, 1e9);
    assert!(out.frames[1].coverage() > 0.1, "object visible at 10⁶");
    assert!(d.hit_mismatch < 0.01 && d.frac_over < 0.02, "10³ vs 10⁶: {d:?}");
    let depth = out.frames[1].depth.iter().copied().find(|d| d.is_finite()).unwrap();
    assert!((depth as f64 - 1e6).abs() < 3.0, "depth {depth}");
}

#[test]
fn axis_parallel_rays_with_zero_components() {
    let a = common::fixture();
    // Odd sizes put a pixel centre exactly on the optical axis: direction (−1, 0, 0) etc.
    let axes = [DVec3::X, DVec3::Y, DVec3::Z, -DVec3::X, -DVec3::Y, -DVec3::Z];
    let views: Vec<ViewRequest> = axes
        .iter()
        .map(|&ax| {
            let up = if ax.z.abs() > 0.5 { DVec3::Y } else { DVec3::Z };
            // Along a grid plane through cell boundaries (y = 0.375 is a boundary of the 32³ grid).
            ViewRequest::new(View::look_at(ax * 4.0 + DVec3::new(0.0, 0.375, 0.0) * (1.0 - ax.y.abs()), DVec3::new(0.0, 0.375, 0.0) * (1.0 - ax.y.abs()), up, k(41, 41)))
        })
        .collect();
    let out = both(&a, &views).unwrap();
    for f in &out.frames {
        assert!(f.coverage() > 0.05);
    }
}

#[test]
fn sigma_zero_and_sigma_huge() {
    let cfg = |s| ProceduralConfig { sigma_scale: s, ..ProceduralConfig::small(Scene::Shiny) };
    let view = [ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 0.0, 10.0, k(40, 40)))];
    let empty = Arc::new(procedural::generate(&cfg(0.0)).unwrap());
    let out = both(&empty, &view).unwrap();
    assert_eq!(out.frames[0].coverage(), 0.0, "σ = 0 is empty");
    assert!(out.frames[0].rgba.chunks(4).all(|p| p == [255, 255, 255, 0]));
    let dense = Arc::new(procedural::generate(&cfg(1e9)).unwrap());
    assert!(dense.density.values.contains(&65504.0), "σ saturates f16");
    let out = both(&dense, &view).unwrap();
    let normal = both(&Arc::new(procedural::generate(&cfg(1.0)).unwrap()), &view).unwrap();
    assert!((out.frames[0].coverage() - normal.frames[0].coverage()).abs() < 0.05);
}

#[test]
fn one_pixel_and_8k_viewports() {
    let a = common::fixture();
    let one = ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 35.0, 25.0, k(1, 1)));
    // 8K UHD spans several GPU chunks; from 60 units the trio covers a small patch.
    let eight_k = ViewRequest::new(View::orbit(DVec3::ZERO, 60.0, 35.0, 25.0, Intrinsics::from_fov_x(7680, 4320, 0.5)));
    let out = both(&a, &[one, eight_k]).unwrap();
    assert_eq!(out.frames[0].rgba.len(), 4);
    assert_eq!(out.frames[1].depth.len(), 7680 * 4320);
    assert!(out.frames[1].coverage() > 1e-3 && out.frames[1].coverage() < 0.1);
}

#[test]
fn bad_poses_and_sizes_are_clear_errors() {
    let a = common::fixture();
    let good = View::orbit(DVec3::ZERO, 4.0, 0.0, 0.0, k(8, 8));
    let mut cases: Vec<(View, &str)> = Vec::new();
    let mut v = good;
    v.world_from_camera.w_axis.x = f64::NAN;
    cases.push((v, "non-finite"));
    let mut v = good;
    v.world_from_camera.y_axis.z = f64::INFINITY;
    cases.push((v, "non-finite"));
    let mut v = good;
    v.world_from_camera = DMat4::from_cols(DVec4::X * 3.0, DVec4::Y, DVec4::Z, DVec4::W);
    cases.push((v, "not rigid"));
    let mut v = good;
    v.intrinsics.width = 1 << 20;
    cases.push((v, "outside"));
    let mut v = good;
    v.intrinsics.fy = 0.0;
    cases.push((v, "intrinsics"));
    let mut backends: Vec<&dyn Backend> = vec![&CpuBackend, &FastCpuBackend];
    if let Some(g) = common::gpu() {
        backends.push(g);
    }
    for b in backends {
        let p = b.prepare(a.clone()).unwrap();
        for (view, words) in &cases {
            let err = p.render(&[ViewRequest::new(good), ViewRequest::new(*view)], &RenderSettings::default()).unwrap_err();
            assert!(matches!(err, RenderError::BadView { index: 1, .. }), "{err}");
            assert!(err.to_string().contains(words), "{err:?} should mention {words:?}");
        }
        let err = p.render(&[], &RenderSettings::default()).unwrap_err();
        assert!(matches!(err, RenderError::NoViews));
        let err = p.render(&[ViewRequest::new(good)], &RenderSettings { step_scale: f32::NAN, ..Default::default() }).unwrap_err();
        assert!(matches!(err, RenderError::BadSettings(_)));
    }
    assert!(matches!(good.validate(), Ok(())));
    let _ = PoseError::NonFinite;
}

#[test]
fn a_cancelled_render_stops_with_cancelled() {
    let a = common::fixture();
    // 8K UHD from close by: seconds of work on the CPU, several chunks on the GPU.
    let big = [ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 35.0, 25.0, Intrinsics::from_fov_x(7680, 4320, 1.2)))];
    let settings = RenderSettings::default();
    let mut backends: Vec<&dyn Backend> = vec![&CpuBackend, &FastCpuBackend];
    if let Some(g) = common::gpu() {
        backends.push(g);
    }
    for b in backends {
        let p = b.prepare(a.clone()).unwrap();
        // Cancelled before it starts: nothing is rendered.
        let before = CancelFlag::default();
        before.cancel();
        assert!(matches!(p.render_cancellable(&big, &settings, &before), Err(RenderError::Cancelled)), "{}", b.name());
        // Cancelled while it runs: it stops at the next safe point instead of finishing.
        let during = CancelFlag::default();
        let stopper = {
            let flag = during.clone();
            std::thread::spawn(move || {
                std::thread::sleep(std::time::Duration::from_millis(30));
                flag.cancel();
            })
        };
        let out = p.render_cancellable(&big, &settings, &during);
        stopper.join().unwrap();
        assert!(matches!(out, Err(RenderError::Cancelled)), "{}: a render cancelled after 30 ms finished anyway", b.name());
        // A flag nobody sets changes nothing.
        let small = [ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 35.0, 25.0, k(32, 24)))];
        assert_eq!(p.render_cancellable(&small, &settings, &CancelFlag::default()).unwrap().frames, p.render(&small, &settings).unwrap().frames);
    }
}
