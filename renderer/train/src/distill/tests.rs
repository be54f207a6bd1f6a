//! Gradient check of the student loss, and the whole pipeline on a synthetic scene: teacher →
//! geometry → student → baked asset, scored on held-out views against the teacher.

use std::sync::OnceLock;

use glam::Vec3;
use rand::{Rng, SeedableRng, rngs::SmallRng};

use super::*;
use crate::{
    TrainConfig,
    dataset::{Dataset, LoadOptions, Split},
    synth::{self, SynthConfig, SynthScene},
    test_util::TempDir,
    trainer::eval::psnr,
};

fn unit(rng: &mut SmallRng) -> Vec3 {
    Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0))
}

/// A student over [-1, 1]³ with a PSH on the vertices of a random cloud of points (or the
/// ablation nets `cfg` asks for).
fn small_student(rng: &mut SmallRng, variant: impl Fn(&mut DistillConfig)) -> (Student, Vec<StudentRay>) {
    let bounds = Aabb::cube(1.0);
    let mut cfg = DistillConfig::tiny(10);
    cfg.diffuse_encoding = HashGridConfig { levels: 4, log2_table_size: 10, base_resolution: 4, finest_resolution: 32 };
    cfg.psh_grid = 16;
    variant(&mut cfg);
    let points: Vec<Vec3> = (0..24).map(|_| 0.9 * unit(rng)).collect();
    let vertices = marked_cells(&bounds, cfg.psh_grid, 1, points.iter().copied(), 0);
    let psh = SpatialHash::build(bounds, cfg.psh_grid, cfg.psh_features, &vertices, |_, o| o.fill(0.0), 3).unwrap();
    let mut student = Student::new(bounds, psh, &cfg, rng);
    // Sizeable features everywhere, so every group matters to the loss.
    if let Some(net) = &mut student.diffuse {
        net.grid.params.iter_mut().for_each(|v| *v = rng.random_range(-0.5..0.5));
    }
    student.encoding.params_mut().iter_mut().for_each(|v| *v = rng.random_range(-0.5..0.5));
    let rays = points
        .iter()
        .enumerate()
        .map(|(i, &p)| StudentRay {
            p_hit: p + 0.02 * unit(rng),
            more: more_hits(i % 3 + 1, p, rng),
            dir: unit(rng).normalize(),
            alpha_c: rng.random_range(0.1..1.0),
            rgb: (unit(rng) + 1.0) * 0.5,
            alpha: rng.random_range(0.0..1.0),
            background: (unit(rng) + 1.0) * 0.5,
            // Colour targets on some queries (the per-query loss), none on others.
            query_targets: std::array::from_fn(|_| {
                let c = (unit(rng) + 1.0) * 0.5;
                [c.x, c.y, c.z, if rng.random_bool(0.5) { rng.random_range(0.2..1.0) } else { 0.0 }]
            }),
        })
        .collect();
    (student, rays)
}

/// `count` queries (the multi-hit rule): the primary and more near `p`, random weights.
fn more_hits(count: usize, p: Vec3, rng: &mut SmallRng) -> MoreHits {
    let mut more = MoreHits { count: count as u8, ..MoreHits::default() };
    for q in &mut more.p[..count - 1] {
        *q = p + 0.1 * unit(rng);
    }
    let raw: Vec<f32> = (0..count).map(|_| rng.random_range(0.1..1.0)).collect();
    let total: f32 = raw.iter().sum();
    for (b, r) in more.beta.iter_mut().zip(&raw) {
        *b = r / total;
    }
    more
}

fn loss(student: &Student, rays: &[StudentRay]) -> f64 {
    student.forward(rays, 4).iter().map(|o| (o.rgb_error + o.alpha_error + o.target_error) as f64).sum::<f64>() / (4 * rays.len()) as f64
}

/// Checks 20 gradients of each parameter group the student has (the largest 12 and 8 at
/// random) against central differences.
fn check_gradients(mut student: Student, rays: &[StudentRay], rng: &mut SmallRng) {
    let mut grads = student.zero_gradients();
    let outputs = student.gradients(rays, 4, &mut grads);
    assert_eq!(outputs.len(), rays.len());
    // Small enough that few ReLU or clamp kinks lie within ±eps of the ~50 queries (1e-3 put
    // 2–4 of 20 across one once rays had up to three queries), large enough for f32 losses.
    let eps = 3e-4f32;
    let groups: [&[f32]; 4] = [&grads.diffuse_grid, &grads.diffuse_mlp, &grads.encoding, &grads.specular_mlp];
    let names = ["diffuse grid", "diffuse MLP", "E_s features", "specular MLP"];
    for (group, g) in groups.iter().enumerate() {
        if g.is_empty() {
            assert!(group < 2 && student.diffuse.is_none(), "{} has no gradients", names[group]);
            continue;
        }
        let mut order: Vec<usize> = (0..g.len()).collect();
        order.sort_by(|&i, &j| g[j].abs().total_cmp(&g[i].abs()));
        let large = order.iter().take_while(|&&i| g[i].abs() > 1e-5).count();
        assert!(large >= 20, "{}: only {large} sizeable gradients", names[group]);
        let mut picks: Vec<usize> = order[..12].to_vec();
        picks.extend((0..8).map(|_| order[rng.random_range(12..large)]));
        let mut agreed = 0;
        for &i in &picks {
            let get = |s: &Student| match group {
                0 => s.diffuse.as_ref().unwrap().grid.params[i],
                1 => s.diffuse.as_ref().unwrap().mlp.params()[i],
                2 => s.encoding.params()[i],
                _ => s.specular_mlp.params()[i],
            };
            let set = |s: &mut Student, v: f32| match group {
                0 => s.diffuse.as_mut().unwrap().grid.params[i] = v,
                1 => s.diffuse.as_mut().unwrap().mlp.update(|p| p[i] = v),
                2 => s.encoding.params_mut()[i] = v,
                _ => s.specular_mlp.update(|p| p[i] = v),
            };
            let keep = get(&student);
            set(&mut student, keep + eps);
            let up = loss(&student, rays);
            set(&mut student, keep - eps);
            let down = loss(&student, rays);
            set(&mut student, keep);
            let fd = (up - down) / (2.0 * eps as f64);
            let a = g[i] as f64;
            agreed += ((a - fd).abs() <= 1e-2 * a.abs().max(fd.abs()) + 2e-6) as usize;
        }
        assert!(agreed >= 18, "{}: {agreed} of 20 gradients agree", names[group]);
    }
}

#[test]
fn distill_student_gradients_match_finite_differences() {
    let mut rng = SmallRng::seed_from_u64(7);
    // The asset's student (PSH, diffuse net read through its bake lattice) and the two
    // ablation students of Table 5: hash-grid E_s with and without a diffuse net.
    let (student, rays) = small_student(&mut rng, |_| {});
    assert!(matches!(student.encoding, SpecularEncoding::Psh(_)) && student.diffuse_lattice.is_some());
    check_gradients(student, &rays, &mut rng);
    // Fine levels, so each entry feeds few rays and few ReLU or clamp kinks lie within ±eps.
    let grid = HashGridConfig { levels: 2, log2_table_size: 12, base_resolution: 16, finest_resolution: 32 };
    let (student, rays) = small_student(&mut rng, |c| {
        c.specular_hash_grid = Some(grid);
        c.train_on_bake_lattice = false;
    });
    assert!(matches!(student.encoding, SpecularEncoding::HashGrid(_)) && student.diffuse_lattice.is_none());
    check_gradients(student, &rays, &mut rng);
    let (student, rays) = small_student(&mut rng, |c| {
        c.specular_hash_grid = Some(grid);
        c.diffuse_net = false;
    });
    assert!(student.diffuse.is_none() && student.diffuse_lattice.is_none());
    check_gradients(student, &rays, &mut rng);
}

/// A teacher of constant density σ = 2 whose colour depends on the view direction only
/// (zero encoding): every sample of a ray has the ray's colour, so each query's target is
/// that colour; its weight is the teacher's weight within the window, less for the deeper
/// query, and 0 for a query where the teacher has no samples.
#[test]
fn teacher_query_targets_average_the_teachers_colour_near_each_query() {
    let mut teacher = crate::Trainer::new(TrainConfig::tiny());
    teacher.field.grid.params.fill(0.0);
    let raw_bias = teacher.field.density_mlp.params().len() - nephele_renderer::ngp::field::GEO_FEATURES;
    teacher.field.density_mlp.update(|p| p[raw_bias] = 2f32.ln());
    let dir = TempDir::new("query-targets");
    synth::generate(&SynthConfig { width: 16, height: 16, n_train: 1, n_val: 1, n_test: 1, ..SynthConfig::new(SynthScene::Mixed) }, &dir.0).unwrap();
    let data = Dataset::load(&dir.0, &LoadOptions::default()).unwrap();
    let bounds = teacher.model().bounds;
    let mut hits = Hits { rays: Vec::new(), tile_start: vec![0], tiles_x: 1, tiles_y: 1, total_rays: 0, missed_opaque: 0 };
    let mut expected = Vec::new();
    for (x, y) in [(8, 8), (4, 9), (11, 6)] {
        let (o, d) = data.images[0].ray(x, y);
        let (t0, t1) = model::clip_ray(&bounds, o, d).expect("the camera looks at the teacher's box");
        let at = |f: f32| o + (t0 + f * (t1 - t0)) * d;
        let more = MoreHits { p: [at(0.6), o + (t1 + 1.0) * d], beta: [0.5, 0.3, 0.2], count: 3 };
        hits.rays.push(HitRay { image: 0, x_px: x as u16, y_px: y as u16, p_hit: at(0.3), alpha_c: 1.0, more });
        let (premultiplied, alpha) = teacher.render(&[(o, d)], Vec3::ZERO)[0];
        expected.push(premultiplied / alpha);
    }
    let targets = teacher_query_targets(&teacher, &data, &hits, 0.05);
    for (t, want) in targets.iter().zip(&expected) {
        for q in &t[..2] {
            assert!((Vec3::new(q[0], q[1], q[2]) - *want).abs().max_element() < 1e-4, "{q:?} vs {want}");
        }
        assert!(t[0][3] > t[1][3] && t[1][3] > 0.0 && t[0][3] <= 1.0, "weights {t:?}");
        assert_eq!(t[2], [0.0; 4], "a query outside the teacher's box has no target");
    }
}

/// Diffuse colour read from cubes replaces the net (at every query); without a diffuse net
/// the colour is the specular net's alone.
#[test]
fn distill_student_takes_diffuse_from_cubes_and_runs_without_a_diffuse_net() {
    let mut rng = SmallRng::seed_from_u64(8);
    let (student, rays) = small_student(&mut rng, |c| c.train_on_bake_lattice = false);
    let constant = |v: [f32; 4]| TextureCubes::bake(Aabb::cube(1.0), 4, 2, 4, |_| true, move |_, out| out.copy_from_slice(&v));
    for (o, r) in student.forward_with_diffuse(&rays, &constant([1.0, 1.0, 1.0, 0.0]), 4).iter().zip(&rays) {
        // c = 1 at every query whatever the specular net says: pixel = α + (1 − α)·bg.
        let want = Vec3::splat(o.alpha) + (1.0 - o.alpha) * r.background;
        assert!((o.pixel - want).abs().max_element() < 1e-5, "{o:?} vs {want}");
    }
    let (bare, rays) = small_student(&mut rng, |c| c.diffuse_net = false);
    let points: Vec<Vec3> = rays.iter().map(|r| r.p_hit).collect();
    assert!(bare.diffuse(&points).chunks_exact(4).all(|c| c == [0.0, 0.0, 0.0, 1.0]));
    for (a, b) in bare.forward(&rays, 4).iter().zip(&bare.forward_with_diffuse(&rays, &constant([0.0, 0.0, 0.0, 1.0]), 4)) {
        assert!((a.pixel - b.pixel).abs().max_element() < 1e-6 && (a.alpha - b.alpha).abs() < 1e-6, "{a:?} vs {b:?}");
    }
}

/// A ray's queries blend by their weights: a ray with two queries at the same point gives
/// exactly the one-query result, whatever the split of the weight.
#[test]
fn distill_queries_blend_by_weight() {
    let mut rng = SmallRng::seed_from_u64(9);
    let (student, rays) = small_student(&mut rng, |_| {});
    let one: Vec<StudentRay> = rays.iter().map(|r| StudentRay { more: MoreHits::default(), ..*r }).collect();
    let twice: Vec<StudentRay> = one.iter().map(|r| StudentRay { more: MoreHits { p: [r.p_hit; 2], beta: [0.3, 0.7, 0.0], count: 2 }, ..*r }).collect();
    for (a, b) in student.forward(&one, 4).iter().zip(&student.forward(&twice, 4)) {
        assert!((a.pixel - b.pixel).abs().max_element() < 1e-5 && (a.alpha - b.alpha).abs() < 1e-5, "{a:?} vs {b:?}");
    }
}

#[test]
fn distill_marks_cells_and_dilates() {
    let bounds = Aabb::cube(1.0);
    // One point in cell (2, 2, 2) of a 4³ grid: its 8 vertices, or 4³ after dilation by 1.
    let p = Vec3::splat(0.1);
    assert_eq!(marked_cells(&bounds, 4, 1, [p].into_iter(), 0).len(), 8);
    assert_eq!(marked_cells(&bounds, 4, 1, [p].into_iter(), 1).len(), 64);
    assert_eq!(marked_cells(&bounds, 4, 0, [p].into_iter(), 0), vec![UVec3::splat(2)]);
    assert_eq!(marked_cells(&bounds, 4, 0, [p].into_iter(), 1).len(), 27);
    // Points outside the box clamp to the border cells; corners stay in range.
    let far = marked_cells(&bounds, 4, 1, [Vec3::splat(9.0)].into_iter(), 2);
    assert!(far.iter().all(|v| v.max_element() <= 4));
}

/// The PSH's dilation is kept only where a density brick could put a hit: with one brick,
/// every stored vertex is a corner of a PSH cell overlapping it, the hit's own corners are
/// always kept, and without dilation the set is the hit cells' corners alone.
#[test]
fn distill_psh_dilation_stays_where_rays_can_hit() {
    let bounds = Aabb::cube(1.0);
    // Density: a 4³ index grid with one brick, cell (2, 2, 2) = [0, 0.5)³.
    let density = TextureCubes::bake(bounds, 4, 2, 1, |c| c == UVec3::splat(2), |_, out| out[0] = 1.0);
    let hit = |p: Vec3| HitRay { image: 0, x_px: 0, y_px: 0, p_hit: p, alpha_c: 1.0, more: MoreHits::default() };
    let hits = |points: &[Vec3]| Hits { rays: points.iter().map(|&p| hit(p)).collect(), tile_start: vec![0, points.len()], tiles_x: 1, tiles_y: 1, total_rays: points.len(), missed_opaque: 0 };
    // PSH 8³ (cells of 0.25): a hit in PSH cell (4, 4, 4), the brick covers PSH cells 4..6.
    let one = hits(&[Vec3::splat(0.1)]);
    assert_eq!(psh_vertex_set(&bounds, 8, &density, &one, 0).len(), 8);
    let dilated = psh_vertex_set(&bounds, 8, &density, &one, 1);
    let unpruned = marked_cells(&bounds, 8, 1, [Vec3::splat(0.1)].into_iter(), 1);
    assert_eq!(unpruned.len(), 64);
    // Vertices 3..=6 per axis, less those below the brick (coordinate 3): 3³.
    assert_eq!(dilated.len(), 27, "{dilated:?}");
    assert!(dilated.iter().all(|v| v.min_element() >= 4 && v.max_element() <= 6));
    assert!(marked_cells(&bounds, 8, 1, [Vec3::splat(0.1)].into_iter(), 0).iter().all(|v| dilated.contains(v)));
    // A PSH coarser than the index grid: cells overlapping the brick still count.
    assert_eq!(psh_vertex_set(&bounds, 2, &density, &one, 1).len(), 8);
}

/// The student state goes through its container file and back; a file written before it had
/// checksums still loads, and a corrupted one does not.
#[test]
fn distill_student_state_round_trips_and_old_files_load() {
    let bounds = Aabb::cube(1.0);
    let cfg = DistillConfig { psh_grid: 16, ..DistillConfig::tiny(10) };
    let density = TextureCubes::bake(bounds, 4, 2, 1, |c| c == UVec3::splat(2), |_, out| out[0] = 1.0);
    let p = Vec3::splat(0.1);
    let ray = HitRay { image: 0, x_px: 0, y_px: 0, p_hit: p, alpha_c: 1.0, more: MoreHits::default() };
    let hits = Hits { rays: vec![ray], tile_start: vec![0, 1], tiles_x: 1, tiles_y: 1, total_rays: 1, missed_opaque: 0 };
    let psh_vertices = marked_cells(&bounds, cfg.psh_grid, 1, [p].into_iter(), 1);
    let geometry = Geometry { bounds, step: 0.05, density, hits, psh_vertices };
    let params = |s: &Student| -> Vec<f32> {
        let net = s.diffuse.as_ref().unwrap();
        [&net.grid.params[..], net.mlp.params(), s.encoding.params(), s.specular_mlp.params()].concat()
    };
    let mut trained = Distiller::new(geometry.clone(), cfg.clone()).unwrap();
    trained.student.specular_mlp.update(|w| w.iter_mut().for_each(|v| *v += 0.5));
    trained.step = 7;
    let bytes = trained.student_bytes(3).unwrap();
    let mut loaded = Distiller::new(geometry.clone(), cfg.clone()).unwrap();
    assert_ne!(params(&loaded.student), params(&trained.student));
    loaded.load_student(&bytes, 3).unwrap();
    assert_eq!((params(&loaded.student), loaded.step), (params(&trained.student), 7));
    assert!(loaded.load_student(&bytes, 4).unwrap_err().contains("step 3"));

    // The same nets as written before the container: metadata without checksums.
    let file = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let mut meta: serde_json::Value = serde_json::from_str(&header.metadata().as_ref().unwrap()["nolf_student"]).unwrap();
    meta.as_object_mut().unwrap().remove("checksums");
    let info = std::collections::HashMap::from([("nolf_student".to_string(), meta.to_string())]);
    let old = safetensors::serialize(file.tensors(), Some(info)).unwrap();
    let mut from_old = Distiller::new(geometry.clone(), cfg.clone()).unwrap();
    from_old.load_student(&old, 3).unwrap();
    assert_eq!(params(&from_old.student), params(&trained.student));

    let mut corrupt = bytes.clone();
    let n = corrupt.len();
    corrupt[n - 5] ^= 0x10;
    let err = Distiller::new(geometry, cfg).unwrap().load_student(&corrupt, 3).unwrap_err();
    assert!(err.contains("checksum"), "{err}");
}

const STUDENT_STEPS: u64 = 800;

struct Pipeline {
    teacher_psnr: f64,
    asset: Asset,
    asset_psnr: f64,
    /// The student before baking (diffuse from its net on the bake lattice).
    mlp_psnr: f64,
    geometry_counts: (usize, usize, usize),
    first_psnr: f64,
    last_psnr: f64,
}

/// Teacher and student on a small glossy + diffuse + translucent scene; scored on its test views.
fn pipeline() -> &'static Pipeline {
    static RUN: OnceLock<Pipeline> = OnceLock::new();
    RUN.get_or_init(|| {
        let dir = TempDir::new("distill");
        let synth_cfg = SynthConfig { width: 48, height: 48, n_train: 24, n_val: 1, n_test: 3, ..SynthConfig::new(SynthScene::Mixed) };
        synth::generate(&synth_cfg, &dir.0).unwrap();
        let train = Dataset::load(&dir.0, &LoadOptions::default()).unwrap();
        let test = Dataset::load(&dir.0, &LoadOptions::split(Split::Test)).unwrap();
        let mut teacher = crate::Trainer::new(TrainConfig::tiny());
        for _ in 0..400 {
            teacher.train_step(&train);
        }
        let score = |render: &dyn Fn(&crate::dataset::DatasetImage) -> Vec<f32>| {
            test.images.iter().map(|im| psnr(&im.composite_over(Vec3::ONE), &render(im))).sum::<f64>() / test.images.len() as f64
        };
        let teacher_psnr = score(&|im| teacher.render_image(im, Vec3::ONE));
        let cfg = DistillConfig::tiny(STUDENT_STEPS);
        let geometry = geometry(&teacher, &train, &cfg).unwrap();
        let geometry_counts = (geometry.density.brick_count(), geometry.hits.rays.len(), geometry.psh_vertices.len());
        let (density, step) = (geometry.density.clone(), geometry.step);
        let mut distiller = Distiller::new(geometry, cfg).unwrap();
        let stats: Vec<DistillStats> = (0..STUDENT_STEPS).map(|_| distiller.train_step(&train)).collect();
        let mean = |s: &[DistillStats]| s.iter().map(|s| s.psnr()).sum::<f64>() / s.len() as f64;
        let asset = distiller.bake(density, step, "synthetic-mixed", serde_json::json!({ "test": true })).unwrap();
        let asset_psnr = score(&|im| render_image(&asset, im, Vec3::ONE));
        let mlp_psnr = score(&|im| {
            let rays: Vec<(Vec3, Vec3)> = im.rays().collect();
            crate::variants::render_cubes(&distiller.student, &asset.density, None, step, asset.march.alpha_min, asset.march.early_stop, &rays, Vec3::ONE).rgb
        });
        let train_psnr = train.images.iter().map(|im| psnr(&im.composite_over(Vec3::ONE), &render_image(&asset, im, Vec3::ONE))).sum::<f64>() / train.images.len() as f64;
        println!(
            "teacher {teacher_psnr:.2} dB, asset {asset_psnr:.2} dB (diffuse MLP {mlp_psnr:.2} dB; train views {train_psnr:.2} dB), batch {:.2} → {:.2} dB, counts {geometry_counts:?}",
            mean(&stats[..30]),
            mean(&stats[stats.len() - 30..])
        );
        Pipeline { teacher_psnr, asset_psnr, mlp_psnr, geometry_counts, first_psnr: mean(&stats[..30]), last_psnr: mean(&stats[stats.len() - 30..]), asset }
    })
}

/// The early stop a student is trained with: saved in checkpoints (older ones without it
/// read as the renderer's default), checked, never later than the default for the marches
/// that choose the asset's bricks, and written into the asset it bakes.
#[test]
fn early_stop_is_a_checked_training_setting() {
    let cfg = DistillConfig { early_stop: 0.1, ..DistillConfig::tiny(10) };
    assert!(cfg.validate().is_ok());
    assert_eq!(cfg.geometry_early_stop(), nephele_renderer::model::DEFAULT_EARLY_STOP);
    let mut json = serde_json::to_value(&cfg).unwrap();
    assert_eq!(serde_json::from_value::<DistillConfig>(json.clone()).unwrap().early_stop, 0.1);
    json.as_object_mut().unwrap().remove("early_stop");
    assert_eq!(serde_json::from_value::<DistillConfig>(json).unwrap().early_stop, nephele_renderer::model::DEFAULT_EARLY_STOP);
    for bad in [1.0, -0.01, f32::NAN] {
        assert!(DistillConfig { early_stop: bad, ..cfg.clone() }.validate().is_err(), "{bad}");
    }
    assert_eq!(pipeline().asset.march.early_stop, DistillConfig::tiny(STUDENT_STEPS).early_stop);
}

#[test]
fn distill_pipeline_makes_a_valid_asset_close_to_its_teacher() {
    let p = pipeline();
    assert!(p.last_psnr > p.first_psnr + 5.0, "batch PSNR {:.2} → {:.2}", p.first_psnr, p.last_psnr);
    // Only what the scene needs: bricks in a minority of cells, PSH far below a dense grid.
    let (bricks, hits, vertices) = p.geometry_counts;
    assert!(hits > 1000 && bricks > 0, "{:?}", p.geometry_counts);
    assert!(bricks < 16 * 16 * 16 / 3, "{bricks} density bricks");
    assert!(vertices < 33usize.pow(3) / 2, "{vertices} PSH vertices");
    // The file round-trips and loads with every check.
    let bytes = p.asset.to_bytes().unwrap();
    assert_eq!(Asset::from_bytes(&bytes).unwrap(), p.asset);
    // Held-out views (measured: teacher 28.07 dB, asset 25.73 dB, unbaked student 25.73 dB;
    // deterministic): baking changes nothing the student learned (it trained on the bake
    // lattice; only f16 rounding is left), and the asset is close to its teacher.
    assert!((p.asset_psnr - p.mlp_psnr).abs() < 0.05, "asset {:.3} dB, unbaked {:.3} dB", p.asset_psnr, p.mlp_psnr);
    assert!(p.teacher_psnr > 20.0, "teacher {:.2} dB", p.teacher_psnr);
    assert!(p.asset_psnr > p.teacher_psnr - 3.0 && p.asset_psnr > 20.0, "asset {:.2} dB vs teacher {:.2} dB", p.asset_psnr, p.teacher_psnr);
}

