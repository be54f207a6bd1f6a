//! A batch of views rendered in one call (one parallel pass on the CPU, one dispatch on the
//! GPU) gives exactly the pixels of rendering each view alone, on both backends: render
//! tasks that batch several users' views must not change anyone's picture.

mod common;

use glam::{DQuat, DVec3, Vec3};
use nephele_renderer::{Backend, CpuBackend, Instance, Intrinsics, PreparedAsset, RenderSettings, View, ViewRequest};

fn views() -> Vec<ViewRequest> {
    let k = |w, h| Intrinsics::from_fov_x(w, h, 0.7);
    vec![
        ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 35.0, 25.0, k(96, 72))),
        ViewRequest::new(View::orbit(DVec3::ZERO, 3.0, 200.0, -30.0, k(37, 53))).with_background(Vec3::new(0.0, 1.0, 0.0)),
        ViewRequest::new(View::orbit(DVec3::ZERO, 4.0, 35.0, 25.0, k(96, 72))),
        ViewRequest::new(View::orbit(DVec3::ZERO, 6.0, 90.0, 80.0, k(1, 1))).with_background(Vec3::ZERO),
        ViewRequest {
            view: View::orbit(DVec3::new(5.0, 0.0, 1.0), 5.0, -20.0, 10.0, k(64, 48)),
            instance: Instance { rotation: DQuat::from_rotation_z(0.7), translation: DVec3::new(5.0, 0.0, 1.0), scale: 2.0 },
            background: Vec3::new(0.2, 0.3, 0.4),
        },
    ]
}

fn batched_equals_alone(prepared: &dyn PreparedAsset, label: &str) {
    let views = views();
    let settings = RenderSettings::default();
    let batch = prepared.render(&views, &settings).unwrap();
    assert_eq!(batch.frames.len(), views.len());
    let mut rays = 0;
    for (i, v) in views.iter().enumerate() {
        let alone = prepared.render(std::slice::from_ref(v), &settings).unwrap();
        rays += alone.stats.rays;
        let (a, b) = (&alone.frames[0], &batch.frames[i]);
        assert_eq!((a.width, a.height), (b.width, b.height), "{label} view {i}");
        assert!(a.rgba == b.rgba, "{label} view {i}: colours differ between batched and alone");
        let same_depth = a.depth.iter().zip(&b.depth).all(|(x, y)| x.to_bits() == y.to_bits());
        assert!(same_depth, "{label} view {i}: depths differ");
    }
    assert_eq!(batch.stats.rays, rays);
    // The same view twice in one batch renders identically.
    assert_eq!(batch.frames[0], batch.frames[2]);
}

#[test]
fn cpu_batches_render_the_same_pixels() {
    let p = CpuBackend.prepare(common::fixture()).unwrap();
    batched_equals_alone(p.as_ref(), "cpu");
}

#[test]
fn gpu_batches_render_the_same_pixels() {
    let Some(gpu) = common::gpu() else { return };
    let p = gpu.prepare(common::fixture()).unwrap();
    batched_equals_alone(p.as_ref(), "gpu");
}
