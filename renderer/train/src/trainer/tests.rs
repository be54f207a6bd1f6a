//! Gradient checks of the whole render loss, the sampling rule, determinism, an overfit run
//! on a synthetic scene (also checked for occupancy). Training speed is measured by
//! `nephele train --log-every N` (ms/step, rays/s), not here.

use std::{sync::OnceLock, time::Instant};

use glam::Vec3;
use nephele_renderer::{
    ngp::{DENSITY_WINDOW, FieldTape, field::GEO_FEATURES},
    sh::sh4,
};
use rand::{Rng, SeedableRng, rngs::SmallRng};

use super::*;
use crate::{
    dataset::{Dataset, LoadOptions},
    synth::{self, SynthConfig, SynthScene},
};

/// Random rays from 4 units out through the central part of the box, with random targets.
fn random_rays(count: usize, seed: u64) -> Vec<TrainRay> {
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut unit = || Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
    (0..count)
        .map(|_| {
            let origin = 4.0 * unit().normalize();
            let aim = 0.5 * unit();
            let (target, background) = ((unit() + 1.0) * 0.5, (unit() + 1.0) * 0.5);
            let jitter = (unit().x + 1.0) * 0.5;
            TrainRay { origin, dir: (aim - origin).normalize(), target, background, jitter }
        })
        .collect()
}

#[test]
fn train_render_loss_gradients_match_finite_differences() {
    let mut config = TrainConfig::tiny();
    config.field.grid = HashGridConfig { levels: 6, log2_table_size: 12, base_resolution: 4, finest_resolution: 64 };
    // Narrow MLPs and few samples: fewer ReLU kinks for ±eps to cross (the MLP tests cover
    // full widths).
    config.field.density_hidden = vec![16];
    config.field.colour_hidden = vec![16, 16];
    config.steps_per_diagonal = 64;
    // Early termination makes the loss piecewise; the check wants it smooth.
    config.early_stop_transmittance = 0.0;
    config.rays_per_chunk = 4;
    let mut trainer = Trainer::new(config);
    // Grid features of a partly trained size, so every group matters to the loss.
    let mut rng = SmallRng::seed_from_u64(11);
    trainer.field.grid.params.iter_mut().for_each(|v| *v = rng.random_range(-0.5..0.5));
    // Thinner density (bias of the raw log-density −1) so rays keep some transmittance and
    // the background term matters.
    let raw_bias = trainer.field.density_mlp.params().len() - GEO_FEATURES;
    trainer.field.density_mlp.update(|p| p[raw_bias] -= 1.0);
    let rays = random_rays(8, 12);

    let mut grads = trainer.field.zero_gradients();
    let stats = trainer.gradients(&rays, &mut grads);
    let loss = trainer.loss(&rays);
    assert!((stats.loss - loss).abs() < 1e-6 * loss, "{} vs {loss}", stats.loss);
    assert!(stats.samples > 8 * 20, "{stats:?}");

    // Central differences in f64 over the f32 forward pass. The loss is only good to ~1e-8
    // (f32 colours), so with eps = 1e-3 a finite difference carries ~2e-6 of rounding noise
    // (measured): check the 12 largest gradients of each group (1e-3…1e-2; they agree to
    // < 0.5 %) and 8 more drawn from those above 1e-4, each to within 1 % plus twice that
    // noise. A ReLU kink crossed by ±eps can spoil a check, so 18 of 20 must pass.
    const ROUNDING: f64 = 4e-6;
    let eps = 1e-3f32;
    let agrees = |analytic: f32, up: f64, down: f64| {
        let fd = (up - down) / (2.0 * eps as f64);
        (analytic as f64 - fd).abs() <= 1e-2 * (analytic.abs() as f64).max(fd.abs()) + ROUNDING
    };
    let mut pick = |g: &[f32]| -> Vec<usize> {
        let mut order: Vec<usize> = (0..g.len()).collect();
        order.sort_by(|&i, &j| g[j].abs().total_cmp(&g[i].abs()));
        let large = order.iter().take_while(|&&i| g[i].abs() > 1e-4).count();
        assert!(large >= 40, "only {large} sizeable gradients");
        let mut chosen: Vec<usize> = order[..12].to_vec();
        chosen.extend((0..8).map(|_| order[rng.random_range(12..large)]));
        chosen
    };
    let picks = [pick(&grads.grid), pick(&grads.density_mlp), pick(&grads.colour_mlp)];
    let analytic = [&grads.grid, &grads.density_mlp, &grads.colour_mlp];
    let set = |t: &mut Trainer, group: usize, i: usize, v: f32| match group {
        0 => t.field.grid.params[i] = v,
        1 => t.field.density_mlp.update(|p| p[i] = v),
        _ => t.field.colour_mlp.update(|p| p[i] = v),
    };
    for group in 0..3 {
        let mut agreed = 0;
        for &i in &picks[group] {
            let keep = [&trainer.field.grid.params[..], trainer.field.density_mlp.params(), trainer.field.colour_mlp.params()][group][i];
            set(&mut trainer, group, i, keep + eps);
            let up = trainer.loss(&rays);
            set(&mut trainer, group, i, keep - eps);
            let down = trainer.loss(&rays);
            set(&mut trainer, group, i, keep);
            agreed += agrees(analytic[group][i], up, down) as usize;
        }
        assert!(agreed >= 18, "{}: {agreed} of 20 gradients agree", ["hash grid", "density MLP", "colour MLP"][group]);
    }
}

#[test]
fn train_march_follows_the_renderer_step_rule_and_skips_empty_cells() {
    let mut trainer = Trainer::new(TrainConfig::tiny());
    let delta = trainer.step_size();
    assert!((delta - 3.0 * 3f32.sqrt() / 256.0).abs() < 1e-7);
    let (origin, dir) = (Vec3::new(-4.0, 0.1, 0.2), Vec3::X);
    let mut points = Vec::new();
    trainer.march(origin, dir, 0.5, &mut points);
    // Box entered at x = −1.5: samples at t₀ + (k + ½)δ, all inside, none beyond the exit.
    assert_eq!(points.len(), (3.0 / delta).ceil() as usize - ((3.0 / delta).fract() < 0.5) as usize);
    for (k, p) in points.iter().enumerate() {
        let x = -1.5 + (k as f32 + 0.5) * delta;
        assert!((p.x * 3.0 - 1.5 - x).abs() < 1e-4, "sample {k}: {p}");
    }
    // Empty the grid's left half: samples there disappear.
    let n = trainer.occupancy.cell_count();
    let cells: Vec<usize> = (0..n).collect();
    let density: Vec<f32> = (0..n).map(|c| if trainer.occupancy.cell_coords(c).x < 16 { 0.0 } else { 100.0 }).collect();
    trainer.occupancy.update(&cells, &density, 0.95, 1.0);
    let mut right = Vec::new();
    trainer.march(origin, dir, 0.5, &mut right);
    assert!(right.iter().all(|p| p.x >= 0.5) && (right.len() as i64 - points.len() as i64 / 2).abs() <= 1);
    // A ray that misses the box has no samples.
    let mut none = Vec::new();
    trainer.march(Vec3::new(-4.0, 3.0, 0.0), Vec3::X, 0.5, &mut none);
    assert!(none.is_empty());
}

/// Rendering evaluates σ a window at a time and stops at `T < early_stop`; it must give what
/// evaluating every sample and compositing front to back with the same stop gives, for rays
/// that never stop (thin field: every window), stop within the first window, or stop later.
#[test]
fn train_render_with_density_windows_matches_evaluating_every_sample() {
    let mut trainer = Trainer::new(TrainConfig::tiny());
    let mut rng = SmallRng::seed_from_u64(5);
    trainer.field.grid.params.iter_mut().for_each(|v| *v = rng.random_range(-1.0..1.0));
    let raw_bias = trainer.field.density_mlp.params().len() - GEO_FEATURES;
    let rays = random_rays(96, 6);
    let delta = trainer.step_size();
    for bias in [-6.0f32, 2.0, 3.5] {
        trainer.field.density_mlp.update(|p| p[raw_bias] = bias);
        let mut stops = [0usize; 3];
        let rendered = trainer.render(&rays.iter().map(|r| (r.origin, r.dir)).collect::<Vec<_>>(), Vec3::splat(0.25));
        for (ray, &(rgb, opacity)) in rays.iter().zip(&rendered) {
            let mut points = Vec::new();
            trainer.march(ray.origin, ray.dir, 0.5, &mut points);
            let mut tape = FieldTape::default();
            trainer.field.forward_density(&points, &mut tape);
            let mut used = 0;
            let mut t = 1.0f32;
            while used < points.len() && t >= trainer.config.early_stop_transmittance {
                t *= (-tape.sigma[used] * delta).exp();
                used += 1;
            }
            stops[if used == points.len() { 0 } else if used <= DENSITY_WINDOW { 1 } else { 2 }] += 1;
            let sh = vec![sh4(ray.dir); used];
            trainer.field.forward_colour((0..used as u32).collect(), &sh, &mut tape);
            let (mut c, mut t) = (Vec3::ZERO, 1.0f32);
            for i in 0..used {
                let a = -(-tape.sigma[i] * delta).exp_m1();
                c += t * a * Vec3::from_slice(&tape.rgb[3 * i..3 * i + 3]);
                t *= 1.0 - a;
            }
            c += t * Vec3::splat(0.25);
            assert!((c - rgb).abs().max_element() < 1e-5 && (1.0 - t - opacity).abs() < 1e-5, "bias {bias}: {c} vs {rgb}");
        }
        println!("bias {bias}: rays never stopping / stopping in the first window / later: {stops:?}");
        assert!(stops.iter().sum::<usize>() == rays.len());
        match bias {
            -6.0 => assert!(stops[0] > 80, "{stops:?}"),
            2.0 => assert!(stops[2] > 10, "{stops:?}"),
            _ => assert!(stops[1] > 10, "{stops:?}"),
        }
    }
}

use crate::test_util::TempDir;

/// The training split of a freshly generated synthetic scene (`views` images of `size`²).
fn synthetic_dataset(scene: SynthScene, size: u32, views: usize) -> Dataset {
    let dir = TempDir::new(scene.name());
    let cfg = SynthConfig { width: size, height: size, n_train: views, n_val: 1, n_test: 1, ..SynthConfig::new(scene) };
    synth::generate(&cfg, &dir.0).unwrap();
    Dataset::load(&dir.0, &LoadOptions::default()).unwrap()
}

/// Overfit run shared by the tests that look at a trained field.
struct Trained {
    trainer: Trainer,
    data: Dataset,
    psnr_before: f64,
    psnr_after: f64,
    /// Mean batch loss over the first and the last 50 steps.
    loss_first: f64,
    loss_last: f64,
}

const OVERFIT_STEPS: usize = 300;

fn trained() -> &'static Trained {
    static TRAINED: OnceLock<Trained> = OnceLock::new();
    TRAINED.get_or_init(|| {
        let data = synthetic_dataset(SynthScene::Diffuse, 32, 8);
        let mut trainer = Trainer::new(TrainConfig::tiny());
        let psnr_before = trainer.psnr(&data, Vec3::ONE);
        let start = Instant::now();
        let stats: Vec<StepStats> = (0..OVERFIT_STEPS).map(|_| trainer.train_step(&data)).collect();
        let losses: Vec<f64> = stats.iter().map(|s| s.batch.loss).collect();
        for s in stats.iter().step_by(100) {
            println!(
                "step {}: {:.1} ms, {:.1} samples/ray, {:.1} coloured",
                s.step,
                s.total_ms,
                s.batch.samples as f64 / s.batch.rays as f64,
                s.batch.coloured_samples as f64 / s.batch.rays as f64
            );
        }
        let secs = start.elapsed().as_secs_f64();
        let psnr_after = trainer.psnr(&data, Vec3::ONE);
        let mean = |l: &[f64]| l.iter().sum::<f64>() / l.len() as f64;
        let (loss_first, loss_last) = (mean(&losses[..50]), mean(&losses[losses.len() - 50..]));
        println!(
            "overfit: {OVERFIT_STEPS} steps in {secs:.1} s; loss {loss_first:.5} → {loss_last:.5}; \
             PSNR over white {psnr_before:.2} → {psnr_after:.2} dB; occupied {:.1} %",
            100.0 * trainer.occupancy.occupied_fraction()
        );
        Trained { trainer, data, psnr_before, psnr_after, loss_first, loss_last }
    })
}

#[test]
fn train_overfits_a_synthetic_scene() {
    let t = trained();
    assert!(t.loss_last < 0.25 * t.loss_first, "loss {} → {}", t.loss_first, t.loss_last);
    // Measured: 7.7 dB untrained → 38.0 dB after 300 steps of 1024 rays (tiny preset, seed 0,
    // 32×32 diffuse box, 8 views); the bound leaves a 4 dB margin.
    assert!(t.psnr_after > 34.0, "PSNR {} → {}", t.psnr_before, t.psnr_after);
}

#[test]
fn train_occupancy_finds_the_object() {
    let t = trained();
    let grid = &t.trainer.occupancy;
    // The synthetic box: half extents 0.8 × (1, 0.8, 0.65), turned 25° about +z. Points just
    // inside its faces are occupied...
    let yaw = glam::Quat::from_rotation_z(25f32.to_radians());
    let half = Vec3::new(0.8, 0.64, 0.52);
    for axis in 0..3 {
        for sign in [-1.0, 1.0] {
            let mut p = Vec3::ZERO;
            p[axis] = sign * (half[axis] - 0.03);
            assert!(grid.is_occupied(yaw * p), "face point {p} is empty");
        }
    }
    // ...the corners of the scene box are empty, and most of the box is.
    for c in 0..8 {
        let corner = Vec3::new([-1.4, 1.4][c & 1], [-1.4, 1.4][c >> 1 & 1], [-1.4, 1.4][c >> 2 & 1]);
        assert!(!grid.is_occupied(corner), "corner {corner} is occupied");
    }
    let fraction = grid.occupied_fraction();
    assert!(fraction < 0.3, "{:.1} % occupied", 100.0 * fraction);
    let _ = &t.data;
}

#[test]
fn train_steps_are_deterministic() {
    let data = synthetic_dataset(SynthScene::Mixed, 16, 2);
    let run = || {
        let mut config = TrainConfig::tiny();
        config.rays_per_batch = 128;
        config.seed = 5;
        let mut trainer = Trainer::new(config);
        let losses: Vec<u64> = (0..3).map(|_| trainer.train_step(&data).batch.loss.to_bits()).collect();
        (losses, trainer.field)
    };
    let (a, b) = (run(), run());
    assert_eq!(a.0, b.0);
    assert!(a.1 == b.1, "parameters differ between identical runs");
}

