//! Renderers for the speed/accuracy variants of NEPHELE's ablation (Table 5) that the runtime
//! renderer does not serve, on the CPU, so `nephele bench tradeoff` can put every variant
//! side by side on one backend:
//!
//! - **base**: the hit point and `α_c` from the teacher's density network instead of cubes
//!   (same step and rule as [`model::march`]: samples `t0 + (k + ½)δ` in the fitted box,
//!   skipping cells the teacher's occupancy grid marks empty, max-weight hit, stop at
//!   `T < early_stop`), shaded by a student ([`render_base`]);
//! - hits from the baked density cubes, shaded by a student with diffuse from its net or
//!   from baked diffuse cubes ([`render_cubes`]); the student's `E_s` may be a hash grid
//!   (the ablation rows) or the PSH;
//! - the i-NGP baseline itself is [`Trainer::render`]; the full asset is the CPU backend;
//! - **oracles** ([`render_oracles`]): the teacher's own march collapsed by a student's rule
//!   (one hit, or the multi-hit rule with each segment's colour at its peak or averaged), the
//!   ceiling of each structure.
//!
//! Each returns interleaved RGB over a background and where the time went.

use std::time::Instant;

use glam::Vec3;
use nephele_renderer::{
    cubes::{Aabb, TextureCubes},
    model::{self, HitRule, MarchHit, RenderSettings, Segments, Tracker, clip_ray},
    ngp::{FieldTape, NgpRay},
};
use rayon::prelude::*;

use crate::{
    distill::{MoreHits, Student, StudentRay, teacher_colour_near, teacher_samples},
    trainer::Trainer,
};

/// A rendered ray batch: interleaved RGB, and milliseconds spent finding hits and in total.
#[derive(Debug, Clone, Default)]
pub struct VariantFrame {
    pub rgb: Vec<f32>,
    pub march_ms: f64,
    pub total_ms: f64,
    pub hits: usize,
}

/// Samples evaluated per ray and round in [`march_network`].
const WINDOW: usize = 32;

/// Marches rays through the teacher's density network (see the module note).
pub fn march_network(teacher: &Trainer, bounds: &Aabb, step: f32, rays: &[(Vec3, Vec3)]) -> Vec<MarchHit> {
    let early_stop = RenderSettings::default().stop_below();
    rays.par_chunks(64)
        .flat_map_iter(|chunk| {
            struct State {
                t0: f32,
                t1: f32,
                k: i32,
                transmittance: f32,
                hit: MarchHit,
                done: bool,
            }
            let mut states: Vec<State> = chunk
                .iter()
                .map(|&(o, d)| {
                    let (t0, t1, done) = clip_ray(bounds, o, d).map_or((0.0, 0.0, true), |(a, b)| (a, b, false));
                    State { t0, t1, k: 0, transmittance: 1.0, hit: MarchHit::default(), done }
                })
                .collect();
            let mut tape = FieldTape::default();
            let mut points01 = Vec::new();
            let mut owners: Vec<(usize, f32)> = Vec::new();
            while states.iter().any(|s| !s.done) {
                points01.clear();
                owners.clear();
                for (i, (s, &(o, d))) in states.iter_mut().zip(chunk).enumerate() {
                    let mut taken = 0;
                    while !s.done && taken < WINDOW {
                        let t = s.t0 + (s.k as f32 + 0.5) * step;
                        if t >= s.t1 {
                            s.done = true;
                            break;
                        }
                        s.k += 1;
                        let p = o + t * d;
                        if teacher.occupancy.is_occupied(p) {
                            points01.push(teacher.to_unit(p).clamp(Vec3::ZERO, Vec3::ONE));
                            owners.push((i, t));
                            taken += 1;
                        }
                    }
                    // A ray that ran out of samples this round is finished after them.
                }
                if points01.is_empty() {
                    break;
                }
                teacher.field.forward_density(&points01, &mut tape);
                let mut stopped = vec![false; states.len()];
                for (&(i, t), &sigma) in owners.iter().zip(&tape.sigma) {
                    if stopped[i] {
                        continue;
                    }
                    let s = &mut states[i];
                    let alpha = 1.0 - (-sigma * step).exp();
                    let w = s.transmittance * alpha;
                    if w > s.hit.w_max {
                        s.hit.w_max = w;
                        s.hit.t_hit = t;
                    }
                    s.transmittance *= 1.0 - alpha;
                    s.hit.samples += 1;
                    if s.transmittance < early_stop {
                        stopped[i] = true;
                        s.done = true;
                    }
                }
            }
            states
                .into_iter()
                .map(|s| MarchHit { alpha_c: 1.0 - s.transmittance, ..s.hit })
                .collect::<Vec<_>>()
        })
        .collect()
}

/// Shades marched rays with the student, diffuse from its net or from `diffuse` cubes;
/// misses get the background.
fn shade_student(student: &Student, diffuse: Option<&TextureCubes>, rays: &[(Vec3, Vec3)], marched: &[MarchHit], alpha_min: f32, background: Vec3) -> (Vec<f32>, usize) {
    let hit_rays: Vec<StudentRay> = rays
        .iter()
        .zip(marched)
        .filter(|(_, m)| m.alpha_c >= alpha_min)
        .map(|(&(o, d), m)| StudentRay { p_hit: o + m.t_hit * d, more: MoreHits::default(), dir: d, alpha_c: m.alpha_c, rgb: Vec3::ZERO, alpha: 0.0, background, query_targets: [[0.0; 4]; model::MAX_HITS] })
        .collect();
    let hits = hit_rays.len();
    let shaded = match diffuse {
        None => student.forward(&hit_rays, 256),
        Some(cubes) => student.forward_with_diffuse(&hit_rays, cubes, 256),
    };
    let mut shaded = shaded.into_iter();
    let rgb = marched
        .iter()
        .flat_map(|m| if m.alpha_c >= alpha_min { shaded.next().map_or(background, |o| o.pixel) } else { background }.to_array())
        .collect();
    (rgb, hits)
}

/// "base": hits from the density network, shaded by the student.
pub fn render_base(teacher: &Trainer, student: &Student, step: f32, alpha_min: f32, rays: &[(Vec3, Vec3)], background: Vec3) -> VariantFrame {
    let start = Instant::now();
    let marched = march_network(teacher, &student.bounds, step, rays);
    let march_ms = start.elapsed().as_secs_f64() * 1e3;
    let (rgb, hits) = shade_student(student, None, rays, &marched, alpha_min, background);
    VariantFrame { rgb, march_ms, total_ms: start.elapsed().as_secs_f64() * 1e3, hits }
}

/// Hits from the density cubes, shaded by the student with diffuse from its net, or from
/// `diffuse` cubes when given.
#[allow(clippy::too_many_arguments)]
pub fn render_cubes(
    student: &Student,
    density: &TextureCubes,
    diffuse: Option<&TextureCubes>,
    step: f32,
    alpha_min: f32,
    early_stop: f32,
    rays: &[(Vec3, Vec3)],
    background: Vec3,
) -> VariantFrame {
    let start = Instant::now();
    let settings = RenderSettings { early_stop: Some(early_stop), ..Default::default() };
    let marched: Vec<MarchHit> = rays.par_iter().map(|&(o, d)| model::march(density, o, d, step, &settings)).collect();
    let march_ms = start.elapsed().as_secs_f64() * 1e3;
    let (rgb, hits) = shade_student(student, diffuse, rays, &marched, alpha_min, background);
    VariantFrame { rgb, march_ms, total_ms: start.elapsed().as_secs_f64() * 1e3, hits }
}

/// The i-NGP baseline, timed.
pub fn render_ngp(teacher: &Trainer, rays: &[(Vec3, Vec3)], background: Vec3) -> VariantFrame {
    let start = Instant::now();
    let out = teacher.render(rays, background);
    let hits = out.iter().filter(|(_, a)| *a > 0.02).count();
    let rgb = out.into_iter().flat_map(|(c, _)| c.to_array()).collect();
    VariantFrame { rgb, march_ms: f64::NAN, total_ms: start.elapsed().as_secs_f64() * 1e3, hits }
}

/// A student's rule applied to the teacher's own march: an oracle, the ceiling of a structure
/// (what a student of that structure would render if it matched the teacher perfectly).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum OracleRule {
    /// The colour of the max-weight sample: the ideal one-hit student.
    OneHit,
    /// The multi-hit rule ([`model::Segments`]) on the teacher's samples: each queried
    /// segment's colour at its peak sample, or (`averaged`) its samples' colours averaged by
    /// weight (what a student trained on pixels can learn at a hit); blended by segment weight.
    MultiHit { rule: HitRule, averaged: bool },
}

/// One oracle's render: RGB over the background, rays hit (α ≥ `alpha_min`), queries made.
#[derive(Debug, Clone, Default)]
pub struct OracleFrame {
    pub rgb: Vec<f32>,
    pub hits: usize,
    pub queries: usize,
}

/// Renders `rays` with the teacher's weights, colours and α (`1 − T_end`) collapsed by each
/// rule, in one march: segments are split `gap_t` (scene units) apart, as the student's rule
/// does with its own step.
pub fn render_oracles(teacher: &Trainer, rays: &[(Vec3, Vec3)], background: Vec3, gap_t: f32, alpha_min: f32, rules: &[OracleRule]) -> Vec<OracleFrame> {
    let per_chunk: Vec<Vec<OracleFrame>> = rays
        .par_chunks(teacher.model().rays_per_chunk.max(1))
        .map(|chunk| {
            let ngp_rays: Vec<NgpRay> = chunk.iter().map(|&(origin, dir)| NgpRay { origin, dir, background, jitter: 0.5 }).collect();
            let mut frames = vec![OracleFrame::default(); rules.len()];
            for (samples, transmittance) in teacher_samples(teacher, &ngp_rays) {
                let alpha_c = 1.0 - transmittance;
                let hit = alpha_c >= alpha_min && !samples.is_empty();
                for (rule, frame) in rules.iter().zip(&mut frames) {
                    let (colour, queries) = if hit { oracle_colour(rule, &samples, alpha_c, gap_t) } else { (Vec3::ZERO, 0) };
                    let pixel = alpha_c * colour + (1.0 - alpha_c) * background;
                    frame.rgb.extend_from_slice(&pixel.to_array());
                    frame.hits += hit as usize;
                    frame.queries += queries;
                }
            }
            frames
        })
        .collect();
    let mut frames = vec![OracleFrame::default(); rules.len()];
    for chunk in per_chunk {
        for (all, part) in frames.iter_mut().zip(chunk) {
            all.rgb.extend(part.rgb);
            all.hits += part.hits;
            all.queries += part.queries;
        }
    }
    frames
}

/// The colour one rule gives a ray's samples `(t, weight, colour)`, and its queries.
fn oracle_colour(rule: &OracleRule, samples: &[(f32, f32, Vec3)], alpha_c: f32, gap_t: f32) -> (Vec3, usize) {
    let heaviest = samples.iter().fold((0.0f32, Vec3::ZERO), |best, &(_, w, c)| if w > best.0 { (w, c) } else { best });
    match *rule {
        OracleRule::OneHit => (heaviest.1, 1),
        OracleRule::MultiHit { rule, averaged } => {
            let mut segments = Segments::new(gap_t);
            let mut w_max = 0.0f32;
            for &(t, w, _) in samples {
                let new_max = w > w_max;
                w_max = w_max.max(w);
                segments.sample(t, w, new_max);
            }
            let (chosen, n) = segments.select(alpha_c, &rule);
            if n == 0 {
                return (heaviest.1, 1);
            }
            let total: f32 = chosen[..n].iter().map(|s| s.weight).sum();
            let colour = chosen[..n]
                .iter()
                .map(|seg| {
                    let inside = samples.iter().filter(|s| s.0 >= seg.first_t && s.0 <= seg.last_t);
                    let c = if averaged {
                        inside.fold(Vec3::ZERO, |acc, &(_, w, c)| acc + w * c) / seg.weight.max(f32::MIN_POSITIVE)
                    } else {
                        samples.iter().find(|s| s.0 == seg.peak_t).map_or(heaviest.1, |s| s.2)
                    };
                    seg.weight / total * c
                })
                .sum();
            (colour, n)
        }
    }
}

/// Where an asset loses against its teacher, pixel by pixel: the asset's own march (its
/// queries, blend weights `β` and coarse opacity) with colour or α swapped for the teacher's.
/// A query's teacher colour is the teacher's colour averaged by weight over its samples
/// within the rule's segment gap of the query (as [`crate::distill::teacher_query_targets`]);
/// the teacher's α is `1 − T_end` of its own march.
#[derive(Debug, Clone, Default)]
pub struct SwapFrames {
    /// The asset's hits, the teacher's colours and α: the ceiling of the asset's geometry.
    pub teacher_colour_and_alpha: Vec<f32>,
    /// The asset's hits and α, the teacher's colours: what the colour stage can still gain.
    pub teacher_colour: Vec<f32>,
    /// The asset's hits and colours, the teacher's α: what the α head can still gain.
    pub teacher_alpha: Vec<f32>,
    /// Like `teacher_colour_and_alpha`, but each teacher sample goes to its nearest query
    /// (instead of those within the gap), which takes their weight-averaged colour; blended
    /// by the asset's `β`, with the teacher's α.
    pub teacher_nearest: Vec<f32>,
}

/// Renders `rays` four ways (see [`SwapFrames`]); rays the asset misses get the background
/// in every frame, rays it hits where the teacher has no weight near a query take the
/// teacher's colour at its heaviest sample for that query.
pub fn render_swaps(teacher: &Trainer, asset: &nephele_renderer::Asset, rays: &[(Vec3, Vec3)], background: Vec3) -> SwapFrames {
    let net = asset.mlp.kernel();
    let settings = RenderSettings::default().for_asset(&asset.march);
    let window = asset.march.hits.gap_steps * asset.march.step;
    let parts: Vec<[Vec<f32>; 4]> = rays
        .par_chunks(teacher.model().rays_per_chunk.max(1))
        .map(|chunk| {
            let ngp_rays: Vec<NgpRay> = chunk.iter().map(|&(origin, dir)| NgpRay { origin, dir, background, jitter: 0.5 }).collect();
            let mut out: [Vec<f32>; 4] = Default::default();
            for (&(o, d), (samples, transmittance)) in chunk.iter().zip(teacher_samples(teacher, &ngp_rays)) {
                let m = model::march_multi(&asset.density, o, d, asset.march.step, &settings, &asset.march.hits);
                let pixels = if m.march.alpha_c < asset.march.alpha_min {
                    [background; 4]
                } else {
                    let heaviest = samples.iter().fold((0.0f32, Vec3::ZERO), |best, &(_, w, c)| if w > best.0 { (w, c) } else { best });
                    let (mut c_teacher, mut c_asset, mut alpha_asset) = (Vec3::ZERO, Vec3::ZERO, 0.0);
                    for i in 0..m.count as usize {
                        let p = o + m.t[i] * d;
                        c_teacher += m.beta[i] * teacher_colour_near(&samples, d.dot(p - o), window).map_or(heaviest.1, |(c, _)| c);
                        // Over black the asset's pixel is α·c.
                        let (premultiplied, a) = model::shade(asset, &net, p, d, m.march.alpha_c, Vec3::ZERO);
                        c_asset += m.beta[i] * if a > 1e-6 { premultiplied / a } else { Vec3::ZERO };
                        alpha_asset += m.beta[i] * a;
                    }
                    let alpha_teacher = 1.0 - transmittance;
                    let mut nearest = [(Vec3::ZERO, 0.0f32); model::MAX_HITS];
                    for &(t, w, c) in &samples {
                        let q = (0..m.count as usize).min_by(|&a, &b| (m.t[a] - t).abs().total_cmp(&(m.t[b] - t).abs())).unwrap_or(0);
                        nearest[q] = (nearest[q].0 + w * c, nearest[q].1 + w);
                    }
                    let c_nearest: Vec3 = (0..m.count as usize).map(|i| m.beta[i] * if nearest[i].1 > 1e-6 { nearest[i].0 / nearest[i].1 } else { heaviest.1 }).sum();
                    let over = |c: Vec3, a: f32| a * c + (1.0 - a) * background;
                    [over(c_teacher, alpha_teacher), over(c_teacher, alpha_asset), over(c_asset, alpha_teacher), over(c_nearest, alpha_teacher)]
                };
                for (frame, p) in out.iter_mut().zip(pixels) {
                    frame.extend_from_slice(&p.to_array());
                }
            }
            out
        })
        .collect();
    let mut frames = SwapFrames::default();
    for [a, b, c, d] in parts {
        frames.teacher_colour_and_alpha.extend(a);
        frames.teacher_colour.extend(b);
        frames.teacher_alpha.extend(c);
        frames.teacher_nearest.extend(d);
    }
    frames
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::TrainConfig;

    /// A teacher of constant density σ = 2 (zero encoding, raw log-density bias ln 2) whose
    /// colour depends on the view direction only.
    fn constant_teacher() -> Trainer {
        let mut teacher = Trainer::new(TrainConfig::tiny());
        teacher.field.grid.params.fill(0.0);
        let raw_bias = teacher.field.density_mlp.params().len() - nephele_renderer::ngp::field::GEO_FEATURES;
        teacher.field.density_mlp.update(|p| p[raw_bias] = 2f32.ln());
        teacher
    }

    /// With a teacher whose colour depends on the view direction only (zero encoding,
    /// constant σ = 2), every oracle gives each ray the teacher's own pixel: all its samples
    /// have one colour, and α is the teacher's.
    #[test]
    fn oracles_of_a_one_colour_ray_are_the_teachers_pixel() {
        let teacher = constant_teacher();
        let rays: Vec<(Vec3, Vec3)> = (0..16)
            .map(|i| {
                let a = i as f32 * 0.41;
                let o = Vec3::new(3.0 * a.cos(), 0.7 * a.sin(), 3.0 * a.sin());
                (o, (Vec3::new(0.2 * a.sin(), 0.1, 0.0) - o).normalize())
            })
            .collect();
        let bg = Vec3::new(0.2, 0.5, 0.9);
        let rule = HitRule { tau: 0.1, max_hits: 3, gap_steps: 3.0 };
        let rules = [OracleRule::OneHit, OracleRule::MultiHit { rule, averaged: false }, OracleRule::MultiHit { rule, averaged: true }];
        let want: Vec<f32> = teacher.render(&rays, bg).into_iter().flat_map(|(c, _)| c.to_array()).collect();
        for frame in render_oracles(&teacher, &rays, bg, 0.05, 0.02, &rules) {
            assert_eq!(frame.hits, rays.len());
            for (a, b) in frame.rgb.iter().zip(&want) {
                assert!((a - b).abs() < 1e-4, "{a} vs {b}");
            }
        }
    }

    /// With the same direction-coloured, constant-σ teacher and an asset whose density cubes
    /// are baked from it (its colours and α from an unrelated procedural asset), the swaps
    /// that take the teacher's colour and α give the teacher's own pixel wherever the asset
    /// hits: every sample near every query has the ray's colour. Rays the asset misses get
    /// the background in every frame.
    #[test]
    fn swaps_with_the_teachers_colour_and_alpha_give_the_teachers_pixel() {
        let teacher = constant_teacher();
        let cfg = crate::distill::DistillConfig { density_grid: 8, density_brick: 4, ..crate::distill::DistillConfig::tiny(1) };
        let bounds = Aabb::cube(1.0);
        let procedural = nephele_renderer::procedural::generate(&nephele_renderer::procedural::ProceduralConfig::small(nephele_renderer::procedural::Scene::Trio)).unwrap();
        let mut asset = procedural.clone();
        asset.density = crate::distill::bake_density(&teacher, bounds, &cfg);
        asset.march.step = cfg.step(&bounds);
        asset.march.hits = HitRule { tau: 0.1, max_hits: 3, gap_steps: 3.0 };
        let rays: Vec<(Vec3, Vec3)> = (0..24)
            .map(|i| {
                let a = i as f32 * 0.29;
                let o = Vec3::new(3.0 * a.cos(), 0.8 * (a * 1.7).sin(), 3.0 * a.sin());
                (o, (Vec3::new(0.3 * a.sin(), 0.2, -0.1) - o).normalize())
            })
            .chain([(Vec3::new(0.0, 3.0, 5.0), Vec3::NEG_Z)])
            .collect();
        let bg = Vec3::new(0.2, 0.5, 0.9);
        let teacher_pixels = teacher.render(&rays, bg);
        let frames = render_swaps(&teacher, &asset, &rays, bg);
        let settings = RenderSettings::default().for_asset(&asset.march);
        let mut hit = 0;
        for (i, &(o, d)) in rays.iter().enumerate() {
            let m = model::march_multi(&asset.density, o, d, asset.march.step, &settings, &asset.march.hits);
            let want = if m.march.alpha_c >= asset.march.alpha_min {
                hit += 1;
                teacher_pixels[i].0
            } else {
                bg
            };
            for frame in [&frames.teacher_colour_and_alpha, &frames.teacher_nearest] {
                let got = Vec3::from_slice(&frame[3 * i..3 * i + 3]);
                assert!((got - want).abs().max_element() < 1e-4, "ray {i}: {got} vs {want}");
            }
            if m.march.alpha_c < asset.march.alpha_min {
                for frame in [&frames.teacher_colour, &frames.teacher_alpha] {
                    assert_eq!(Vec3::from_slice(&frame[3 * i..3 * i + 3]), bg);
                }
            }
        }
        assert!(hit > 12 && hit < rays.len(), "{hit} of {} rays hit", rays.len());
    }

    /// A network of constant density σ = 2 (zero encoding, raw log-density bias ln 2): the
    /// network march and the march of cubes baked from it see the same σ (exact in f16), so
    /// they find the same hits and coarse opacities; and α_c is 1 − exp(−σ·path) up to the
    /// early stop.
    #[test]
    fn network_march_agrees_with_cubes_baked_from_it() {
        let teacher = constant_teacher();
        let bounds = Aabb::cube(1.0);
        let cfg = crate::distill::DistillConfig { density_grid: 8, density_brick: 4, ..crate::distill::DistillConfig::tiny(1) };
        let density = crate::distill::bake_density(&teacher, bounds, &cfg);
        assert_eq!(density.brick_count(), 512);
        let step = cfg.step(&bounds);
        let settings = RenderSettings::default();
        let rays: Vec<(Vec3, Vec3)> = (0..64)
            .map(|i| {
                let a = i as f32 * 0.37;
                let o = Vec3::new(3.0 * a.cos(), 0.5 * (a * 1.3).sin(), 3.0 * a.sin());
                (o, (Vec3::new(0.1 * a.sin(), 0.0, 0.1) - o).normalize())
            })
            .chain([(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z), (Vec3::new(0.0, 3.0, 5.0), Vec3::NEG_Z), (Vec3::ZERO, Vec3::X)])
            .collect();
        let net = march_network(&teacher, &bounds, step, &rays);
        for (&(o, d), n) in rays.iter().zip(&net) {
            let c = model::march(&density, o, d, step, &settings);
            assert!((c.alpha_c - n.alpha_c).abs() < 1e-4 && c.t_hit == n.t_hit, "{o} {d}: cubes {c:?} network {n:?}");
            if let Some((t0, t1)) = clip_ray(&bounds, o, d) {
                // n samples of constant σ: α_c = 1 − exp(−σδ)ⁿ, with n the samples in [t0, t1)
                // unless the early stop came first.
                let want = 1.0 - (-2.0 * step).exp().powi(n.samples as i32);
                assert!((n.alpha_c - want).abs() < 1e-4, "{} vs {want}", n.alpha_c);
                let all = ((t1 - t0) / step + 0.5).floor() as u32;
                assert!(n.samples == all || n.samples + 1 == all || n.samples == all + 1 || n.alpha_c > 1.0 - settings.stop_below(), "{} of {all} samples", n.samples);
            } else {
                assert_eq!(n.alpha_c, 0.0);
            }
        }
    }
}
