//! Depth composition: the wgpu kernel agrees with the CPU reference on lavapipe, on random
//! layers (ties, misses, full and partial alpha, odd sizes) and on real renders of two
//! overlapping objects. Tolerance: every channel within 1 level of 255 (the GPU unpacks
//! colours to f32 and may fuse multiply-adds; the CPU rounds the same values), depths equal.

mod common;

use glam::{DQuat, DVec3, Vec3};
use nephele_renderer::{
    Backend, CpuBackend, Frame, Instance, Intrinsics, RenderSettings, View, ViewRequest,
    compose::{MAX_LAYERS, compose},
    gpu::compose::GpuCompositor,
};
use rand::{Rng, SeedableRng, rngs::SmallRng};

fn random_layer(rng: &mut SmallRng, w: u32, h: u32) -> Frame {
    let n = (w * h) as usize;
    let mut rgba = Vec::with_capacity(4 * n);
    let mut depth = Vec::with_capacity(n);
    for _ in 0..n {
        let a: u8 = match rng.random_range(0..4) {
            0 => 0,
            1 => 255,
            _ => rng.random(),
        };
        // Premultiplied: no channel above alpha.
        let c = |rng: &mut SmallRng| if a == 0 { 0 } else { rng.random_range(0..=a) };
        rgba.extend_from_slice(&[c(rng), c(rng), c(rng), a]);
        depth.push(if a == 0 { f32::INFINITY } else { [1.0, 2.0, 2.5][rng.random_range(0..3)] + rng.random_range(0.0..0.001f32) * f32::from(rng.random_range(0..2u8)) });
    }
    Frame { width: w, height: h, rgba, depth }
}

fn assert_close(cpu: &Frame, gpu: &Frame, label: &str) {
    assert_eq!((cpu.width, cpu.height), (gpu.width, gpu.height));
    let worst = cpu.rgba.iter().zip(&gpu.rgba).map(|(a, b)| a.abs_diff(*b)).max().unwrap_or(0);
    assert!(worst <= 1, "{label}: a channel differs by {worst} levels");
    assert!(cpu.depth.iter().zip(&gpu.depth).all(|(a, b)| a == b), "{label}: depths differ");
}

#[test]
fn gpu_compose_matches_the_cpu_on_random_layers() {
    let Some(gpu) = common::gpu() else { return };
    let compositor = GpuCompositor::new(gpu.ctx.clone());
    let mut rng = SmallRng::seed_from_u64(5);
    for (w, h, n) in [(1, 1, 1), (17, 9, 2), (64, 48, 3), (33, 65, MAX_LAYERS)] {
        let layers: Vec<Frame> = (0..n).map(|_| random_layer(&mut rng, w, h)).collect();
        let refs: Vec<&Frame> = layers.iter().collect();
        for bg in [Vec3::ONE, Vec3::new(0.0, 1.0, 0.0), Vec3::new(0.2, 0.4, 0.6)] {
            let cpu = compose(&refs, bg).unwrap();
            let out = compositor.compose(&refs, bg).unwrap();
            assert_close(&cpu, &out, &format!("{w}x{h}, {n} layers, bg {bg}"));
        }
    }
    // Bad input is an error on the GPU path too.
    let a = random_layer(&mut rng, 4, 4);
    let b = random_layer(&mut rng, 4, 5);
    assert!(compositor.compose(&[&a, &b], Vec3::ONE).is_err());
    assert!(compositor.compose(&[], Vec3::ONE).is_err());
}

#[test]
fn two_overlapping_objects_compose_the_same_on_both() {
    let Some(gpu) = common::gpu() else { return };
    let asset = common::fixture();
    let k = Intrinsics::from_fov_x(96, 72, 0.7);
    let view = View::orbit(DVec3::ZERO, 4.0, 10.0, 15.0, k);
    let near = Instance { rotation: DQuat::from_rotation_z(0.5), translation: DVec3::new(0.4, 0.0, 0.0), scale: 0.6 };
    let far = Instance { rotation: DQuat::IDENTITY, translation: DVec3::new(-0.4, 0.0, 0.0), scale: 0.8 };
    let prepared = CpuBackend.prepare(asset).unwrap();
    let layer = |instance: Instance| {
        let req = ViewRequest { view, instance, background: Vec3::ZERO };
        prepared.render(&[req], &RenderSettings::default()).unwrap().frames.remove(0)
    };
    let (a, b) = (layer(near), layer(far));
    let cpu = compose(&[&a, &b], Vec3::ONE).unwrap();
    let out = GpuCompositor::new(gpu.ctx.clone()).compose(&[&a, &b], Vec3::ONE).unwrap();
    assert_close(&cpu, &out, "trio pair");
    // Both objects are in the picture and occlude each other somewhere: some pixels take
    // their depth from each layer.
    let from = |l: &Frame| cpu.depth.iter().zip(&l.depth).filter(|(c, d)| c.is_finite() && c == d).count();
    assert!(from(&a) > 50 && from(&b) > 50, "{} {}", from(&a), from(&b));
    let both = a.depth.iter().zip(&b.depth).filter(|(x, y)| x.is_finite() && y.is_finite()).count();
    assert!(both > 20, "the objects should overlap on screen ({both} pixels)");
}
