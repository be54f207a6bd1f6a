//! The fast CPU renderer against the reference and against itself: every march and network
//! kernel gives the frames the tests say, to the bit where they say so.

use super::*;
use super::detect::wide_lanes;
use rand::{Rng, SeedableRng, rngs::SmallRng};

fn ulps(a: f32, b: f32) -> u32 {
    (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs() as u32
}

#[test]
fn exp_neg_is_within_two_ulp_of_libm() {
    let mut worst = 0;
    for i in 0..200_000 {
        let x = 87.0 * i as f32 / 200_000.0;
        let (a, b) = (exp_neg(x), (-x).exp());
        worst = worst.max(ulps(a, b));
    }
    assert!(worst <= 2, "worst {worst} ulp");
    // Negative arguments too, for the shading's sigmoid: 1 / (1 + e^(−x)) within 4 ulp of
    // libm's (2 from the exp, and the rounding of the sum and quotient).
    let mut worst = 0;
    for i in 0..200_000 {
        let x = -87.0 * i as f32 / 200_000.0;
        worst = worst.max(ulps(exp_neg(x), (-x).exp()));
    }
    assert!(worst <= 2, "worst {worst} ulp for x < 0");
    let worst = (-4000..=4000).map(|i| i as f32 / 100.0).map(|x| ulps(sigmoid(x), crate::mlp::sigmoid(x))).max().unwrap();
    assert!(worst <= 4, "sigmoid: worst {worst} ulp");
    assert_eq!(exp_neg(0.0), 1.0);
    assert_eq!(exp_neg(1e30), 0.0);
    assert_eq!(exp_neg(f32::INFINITY), 0.0);
    assert!(exp_neg(f32::NAN).is_nan());
}

#[test]
fn vector_and_scalar_paths_are_bit_identical() {
    if crate::mlp::simd::level() == crate::mlp::simd::Level::Portable {
        eprintln!("no AVX2 on this CPU: only the portable path exists");
        return;
    }
    let stored = crate::procedural::generate(&crate::procedural::ProceduralConfig::small(crate::procedural::Scene::Trio)).unwrap();
    // As stored (f16: the paired reads) and with densities no f16 holds, as cubes built
    // in memory may have (the f32 reads).
    let mut in_memory = stored.clone();
    in_memory.density.values.iter_mut().for_each(|v| *v *= 1.0 + 1e-5);
    for (asset, f16) in [(stored, true), (in_memory, false)] {
        let asset = Arc::new(asset);
        let prepared = FastPrepared { net: asset.mlp.kernel(), live: LiveCells::new(&asset.density), hash: PshBricks::new(&asset.psh), diffuse: None, asset: asset.clone(), march: March::Avx2 };
        // Both kernels' paths are exercised.
        assert_eq!(prepared.live.values_f16.is_some(), f16);
        same_sigmas(&prepared);
    }
}

#[test]
fn psh_bricks_encode_as_the_hash_does() {
    let asset = crate::procedural::generate(&crate::procedural::ProceduralConfig::small(crate::procedural::Scene::Trio)).unwrap();
    let h = &asset.psh;
    let bricks = PshBricks::new(h);
    let nf = h.features as usize;
    let mut rng = SmallRng::seed_from_u64(5);
    let (mut a, mut b) = (vec![0.0; nf], vec![0.0; nf]);
    let mut nonzero = 0;
    for i in 0..20_000 {
        // Anywhere in (and a little outside) the box, and on vertex planes.
        let mut p = h.bounds.min + (h.bounds.size() * 1.1) * Vec3::new(rng.random(), rng.random(), rng.random()) - 0.05 * h.bounds.size();
        if i % 4 == 0 {
            let cell = h.bounds.size() / h.grid as f32;
            p.x = h.bounds.min.x + cell.x * rng.random_range(0..=h.grid) as f32;
        }
        h.encode(p, &mut a);
        bricks.encode(&bricks.corners(h, p), &mut b);
        assert_eq!(a, b, "at {p}");
        nonzero += usize::from(a.iter().any(|v| *v != 0.0));
    }
    assert!(nonzero > 1000, "{nonzero} points with features");
}

#[test]
fn vector_tile_inputs_match_the_scalar_path() {
    if crate::mlp::simd::level() == crate::mlp::simd::Level::Portable {
        eprintln!("no AVX2 on this CPU: only the portable path exists");
        return;
    }
    // The shipped lego asset: 8 PSH features and 8-bit diffuse cubes, as the vector path needs.
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/assets/lego.nolf");
    let asset = Arc::new(Asset::load(&path).unwrap());
    let prepared = FastPrepared {
        net: asset.mlp.kernel(),
        live: LiveCells::new(&asset.density),
        hash: PshBricks::new(&asset.psh),
        diffuse: DiffuseBytes::new(&asset.diffuse),
        asset: asset.clone(),
        march: March::Avx2,
    };
    assert!(prepared.diffuse.is_some() && asset.psh.features.is_multiple_of(8));
    let nf = asset.psh.features as usize;
    let cell = asset.density.bounds.size() / asset.density.grid as f32;
    let mut rng = SmallRng::seed_from_u64(9);
    let (mut with_features, mut with_diffuse) = (0, 0);
    for round in 0..400 {
        // Points in live density cells (where hits are), a few anywhere in or near the box.
        let tile: Vec<Query> = (0..TILE)
            .map(|lane| {
                let p_hit = if (round + lane) % 8 == 0 {
                    asset.density.bounds.min + asset.density.bounds.size() * (Vec3::new(rng.random(), rng.random(), rng.random()) * 1.2 - 0.1)
                } else {
                    let c = prepared.live.cells[rng.random_range(0..prepared.live.cells.len())];
                    asset.density.bounds.min + (c.as_vec3() + Vec3::new(rng.random(), rng.random(), rng.random())) * cell
                };
                Query { p_hit, d: Vec3::Z, alpha_c: 1.0, beta: 1.0, pixel: 0 }
            })
            .collect();
        let mut p = [[0.0f32; TILE]; 3];
        for (lane, q) in tile.iter().enumerate() {
            (p[0][lane], p[1][lane], p[2][lane]) = (q.p_hit.x, q.p_hit.y, q.p_hit.z);
        }
        let (mut xs, mut ds) = ([[0.0; TILE]; MAX_INPUT], [[0.0; TILE]; 4]);
        let (mut xv, mut dv) = ([[0.0; TILE]; MAX_INPUT], [[0.0; TILE]; 4]);
        prepared.tile_inputs_scalar(&tile, &mut xs, &mut ds);
        // Gathered, and read lane by lane: the same values.
        let (mut xl, mut dl) = ([[0.0; TILE]; MAX_INPUT], [[0.0; TILE]; 4]);
        // SAFETY: the CPU has x86-64-v3 (checked above).
        #[allow(unsafe_code)]
        unsafe {
            avx2::tile_inputs(&prepared.hash, &asset.psh, prepared.diffuse.as_ref().unwrap(), &asset.diffuse, &p, &mut xv, &mut dv, false);
            avx2::tile_inputs(&prepared.hash, &asset.psh, prepared.diffuse.as_ref().unwrap(), &asset.diffuse, &p, &mut xl, &mut dl, true);
        };
        assert!(xv.iter().flatten().zip(xl.iter().flatten()).chain(dv.iter().flatten().zip(dl.iter().flatten())).all(|(a, b)| a.to_bits() == b.to_bits()), "round {round}");
        for lane in 0..TILE {
            let at = tile[lane].p_hit;
            for f in 0..nf {
                assert_eq!(xs[f][lane].to_bits(), xv[f][lane].to_bits(), "feature {f} at {at}");
            }
            for c in 0..4 {
                assert!((ds[c][lane] - dv[c][lane]).abs() <= 1e-6, "diffuse {c} at {at}: {} vs {}", ds[c][lane], dv[c][lane]);
            }
            with_features += usize::from((0..nf).any(|f| xs[f][lane] != 0.0));
            with_diffuse += usize::from((0..4).any(|c| ds[c][lane] != 0.0));
        }
    }
    assert!(with_features > 3000 && with_diffuse > 3000, "{with_features} points with features, {with_diffuse} with diffuse colour");
}

#[test]
fn wavefront_and_per_ray_marches_render_the_same_frames() {
    if crate::mlp::simd::level() == crate::mlp::simd::Level::Portable {
        eprintln!("no AVX2 on this CPU: only the per-ray march exists");
        return;
    }
    if !wide_lanes() {
        eprintln!("no AVX-512 on this CPU: the AVX-512 march is not compared");
    }
    use crate::{Intrinsics, View, ViewRequest};
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/assets/lego.nolf");
    let lego = Asset::load(&path).unwrap();
    let procedural = |scene| crate::procedural::generate(&crate::procedural::ProceduralConfig::small(scene)).unwrap();
    let (trio, translucent) = (procedural(crate::procedural::Scene::Trio), procedural(crate::procedural::Scene::Translucent));
    let orbit = |w, h, azimuth, elevation, distance| ViewRequest::new(View::orbit(glam::DVec3::ZERO, distance, azimuth, elevation, Intrinsics::from_fov_x(w, h, 0.69)));
    // Outside the box, grazing, and inside it (whole rays, no footprints).
    let inside = ViewRequest::new(View::look_at(glam::DVec3::new(-0.2, 0.0, 0.3), glam::DVec3::new(0.65, 0.35, 0.0), glam::DVec3::Z, Intrinsics::from_fov_x(48, 40, 1.2)));
    let views = [orbit(160, 120, 35.0, 25.0, 4.0), orbit(97, 61, 200.0, -10.0, 3.0), orbit(64, 64, 90.0, 0.0, 6.0), inside];
    for asset in [lego, trio, translucent] {
        let asset = Arc::new(asset);
        let prepare = |march| FastPrepared {
            net: asset.mlp.kernel(),
            live: LiveCells::new(&asset.density),
            hash: PshBricks::new(&asset.psh),
            diffuse: DiffuseBytes::new(&asset.diffuse),
            asset: asset.clone(),
            march,
        };
        let (wave, ray) = (prepare(March::Avx2), prepare(March::Ray));
        // The AVX-512 march where the CPU has it.
        let wide = wide_lanes().then(|| prepare(March::Avx512));
        // Footprints of merged blocks bound the rays more loosely, and without footprints
        // every ray is marched whole: the extra samples lie in dead cells and change
        // nothing. (These small views take the coarser blocks, `COARSE_BLOCKS_BELOW_PX`,
        // where there are any; `merged` keeps its own.)
        let merged = FastPrepared { live: LiveCells { coarse: None, ..LiveCells::new(&asset.density).with_blocks_at_most(asset.density.brick_count() / 20) }, ..prepare(March::Avx2) };
        assert!(merged.live.block >= 2, "{} blocks of {}", merged.live.blocks.len(), merged.live.block);
        let whole = FastPrepared { live: LiveCells { footprints: false, ..LiveCells::new(&asset.density) }, ..prepare(March::Avx2) };
        // Cell numbers by integer multiplies (the path of grids above 256³), both marches.
        let integer = |march| FastPrepared { live: LiveCells { cell_numbers_in_f32: false, ..LiveCells::new(&asset.density) }, ..prepare(march) };
        let integer = [Some(integer(March::Avx2)), wide_lanes().then(|| integer(March::Avx512))];
        for settings in [
            RenderSettings { hit_tau: Some(1.0), ..Default::default() },
            RenderSettings::default(),
            RenderSettings { hit_tau: Some(0.02), max_hits: Some(3), ..Default::default() },
            RenderSettings { hit_tau: Some(1.0), step_scale: 0.5, stop_ratio: 0.5, ..Default::default() },
        ] {
            let a = wave.render(&views, &settings).unwrap();
            let b = ray.render(&views, &settings).unwrap();
            let c = merged.render(&views, &settings).unwrap();
            assert_eq!((a.stats.hits, a.stats.queries), (c.stats.hits, c.stats.queries), "{settings:?}: merged footprints");
            let e = whole.render(&views, &settings).unwrap();
            assert_eq!((a.stats.hits, a.stats.samples, a.stats.queries), (e.stats.hits, e.stats.samples, e.stats.queries), "{settings:?}: no footprints");
            let d = wide.as_ref().map(|w| w.render(&views, &settings).unwrap());
            if let Some(d) = &d {
                assert_eq!((a.stats.hits, a.stats.samples, a.stats.queries), (d.stats.hits, d.stats.samples, d.stats.queries), "{settings:?}: AVX-512 march");
            }
            let integer: Vec<_> = integer.iter().flatten().map(|p| p.render(&views, &settings).unwrap()).collect();
            for i in &integer {
                assert_eq!((a.stats.hits, a.stats.samples, a.stats.queries), (i.stats.hits, i.stats.samples, i.stats.queries), "{settings:?}: integer cell numbers");
            }
            let integer_frames = integer.iter().flat_map(|i| a.frames.iter().zip(&i.frames));
            let wide_frames = d.iter().flat_map(|d| a.frames.iter().zip(&d.frames)).chain(integer_frames);
            for (fa, fb) in a.frames.iter().zip(&b.frames).chain(a.frames.iter().zip(&c.frames)).chain(a.frames.iter().zip(&e.frames)).chain(wide_frames) {
                assert!(fa.rgba == fb.rgba, "{settings:?}: the colours differ");
                assert!(fa.depth.iter().zip(&fb.depth).all(|(x, y)| x.to_bits() == y.to_bits()), "{settings:?}: the depths differ");
            }
            assert_eq!((a.stats.hits, a.stats.samples, a.stats.queries), (b.stats.hits, b.stats.samples, b.stats.queries), "{settings:?}");
            assert!(a.stats.hits > 1000, "{settings:?}: the views should hit ({} hits)", a.stats.hits);
        }
    }
}

#[test]
#[allow(unsafe_code)]
fn vector_shading_matches_the_scalar_path() {
    if crate::mlp::simd::level() == crate::mlp::simd::Level::Portable {
        eprintln!("no AVX2 on this CPU: only the portable path exists");
        return;
    }
    let mut rng = SmallRng::seed_from_u64(11);
    let features = 8;
    for round in 0..300 {
        // Full and partial tiles; several queries per pixel; outputs from saturated to 0.
        let n = if round % 3 == 0 { 1 + round % TILE } else { TILE };
        let tile: Vec<Query> = (0..n)
            .map(|_| {
                let d = Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)).normalize_or(Vec3::X);
                Query { p_hit: Vec3::ZERO, d, alpha_c: rng.random(), beta: rng.random(), pixel: rng.random_range(0..6) }
            })
            .collect();
        let scale = [0.1f32, 3.0, 40.0, 120.0][round % 4];
        let o: [[f32; TILE]; 4] = std::array::from_fn(|_| std::array::from_fn(|_| rng.random_range(-scale..scale)));
        let diffuse: [[f32; TILE]; 4] = std::array::from_fn(|_| std::array::from_fn(|_| rng.random_range(-0.2..1.2)));
        let bg = Vec3::new(rng.random(), rng.random(), 1.0);
        let (mut xs, mut xv) = ([[0.0f32; TILE]; MAX_INPUT], [[0.0f32; TILE]; MAX_INPUT]);
        view_inputs(&tile, features, &mut xs);
        // SAFETY: the CPU has x86-64-v3 (the level above).
        unsafe { avx2::view_inputs(&tile, features, &mut xv) };
        for (row, (a, b)) in xs.iter().zip(&xv).enumerate() {
            assert_eq!(a[..n].iter().map(|v| v.to_bits()).collect::<Vec<_>>(), b[..n].iter().map(|v| v.to_bits()).collect::<Vec<_>>(), "round {round}: input row {row}");
        }
        let (mut cs, mut cv) = (vec![Vec3::splat(0.25); 6], vec![Vec3::splat(0.25); 6]);
        let (mut als, mut alv) = (vec![0.5f32; 6], vec![0.5f32; 6]);
        composite(&tile, &o, &diffuse, bg, &mut cs, &mut als);
        // SAFETY: as above.
        unsafe { avx2::composite(&tile, &o, &diffuse, bg, &mut cv, &mut alv) };
        let bits = |c: &[Vec3], a: &[f32]| c.iter().flat_map(|v| v.to_array()).chain(a.iter().copied()).map(f32::to_bits).collect::<Vec<_>>();
        assert_eq!(bits(&cs, &als), bits(&cv, &alv), "round {round}: composited pixels");
    }
}

/// The vector RGBA pack gives `to_unorm8`'s bytes: NaN, ±0, ±∞, out of range, and
/// values whose × 255 lies within a few ulps of every k + ½ (the rounding's ties), and it
/// leaves a band's last pixels (not a multiple of 8) to the caller.
#[test]
#[cfg(target_arch = "x86_64")]
fn vector_rgba_pack_matches_to_unorm8() {
    if crate::mlp::simd::level() == crate::mlp::simd::Level::Portable {
        eprintln!("no AVX2 on this CPU: the vector pack does not run");
        return;
    }
    let mut values = vec![f32::NAN, 0.0, -0.0, f32::INFINITY, f32::NEG_INFINITY, -1.0, 2.0, 1.0, 0.5, 1e-30];
    for k in 0..256 {
        let tie = (k as f32 + 0.5) / 255.0;
        let mut v = tie;
        for _ in 0..3 {
            v = f32::from_bits(v.to_bits() - 1);
        }
        for _ in 0..7 {
            values.push(v);
            v = f32::from_bits(v.to_bits() + 1);
        }
    }
    let mut rng = SmallRng::seed_from_u64(8);
    values.extend((0..1000).map(|_| rng.random_range(-0.1..1.1f32)));
    let n = values.len() / 4;
    let color: Vec<Vec3> = (0..n).map(|i| Vec3::new(values[4 * i], values[4 * i + 1], values[4 * i + 2])).collect();
    let alpha: Vec<f32> = (0..n).map(|i| values[4 * i + 3]).collect();
    let mut rgba = vec![0u8; 4 * n];
    #[allow(unsafe_code)]
    // SAFETY: the CPU has x86-64-v3 (checked above).
    let packed = unsafe { avx2::pack_rgba(&color, &alpha, &mut rgba) };
    assert_eq!(packed, n / 8 * 8);
    assert!(n % 8 != 0, "the test leaves a tail");
    for i in 0..packed {
        let want = [to_unorm8(color[i].x), to_unorm8(color[i].y), to_unorm8(color[i].z), to_unorm8(alpha[i])];
        assert_eq!(rgba[4 * i..4 * i + 4], want, "pixel {i}: {:?} {}", color[i], alpha[i]);
    }
    assert!(rgba[4 * packed..].iter().all(|&b| b == 0), "the tail is the caller's");
}

/// The AVX-512 band bounds (masked min/max per row of a rectangle) equal the scalar
/// ones to the bit: rows of 1 to 40 pixels (under, at and past 16 lanes), rectangles
/// cut by the band's rows and the view's edge, and ties of +0 and −0.
#[test]
fn masked_band_bounds_match_the_scalar_ones() {
    if crate::mlp::simd::level() != crate::mlp::simd::Level::Avx512 {
        eprintln!("no AVX-512 on this CPU: the masked band bounds do not run");
    }
    #[cfg(target_arch = "x86_64")]
    if crate::mlp::simd::level() == crate::mlp::simd::Level::Avx512 {
        let (width, height) = (100u32, 37u32);
        let mut rng = SmallRng::seed_from_u64(14);
        let t = |rng: &mut SmallRng| if rng.random_bool(0.5) { [0.0, -0.0, 1.5, -2.25][rng.random_range(0..4)] } else { rng.random_range(-3.0..3.0f32) };
        let rects: Vec<CellRect> = (0..400)
            .map(|_| {
                let (x0, y0) = (rng.random_range(0..width), rng.random_range(0..height));
                let (x1, y1) = ((x0 + rng.random_range(0..40)).min(width - 1), (y0 + rng.random_range(0..9)).min(height - 1));
                let (a, b) = (t(&mut rng), t(&mut rng));
                CellRect { x0, x1, y0, y1, t_lo: a.min(b), t_hi: a.max(b) }
            })
            .collect();
        let bin_rows = 16;
        let mut bins = vec![Vec::new(); height.div_ceil(bin_rows) as usize];
        for (i, r) in rects.iter().enumerate() {
            for bin in &mut bins[(r.y0 / bin_rows) as usize..=(r.y1 / bin_rows) as usize] {
                bin.push(i as u32);
            }
        }
        let fp = Footprints { rects, bin_rows, bins };
        for y0 in (0..height).step_by(BAND_ROWS as usize) {
            let n = (BAND_ROWS.min(height - y0) * width) as usize;
            let scalar = fp.band_bounds_with(width, y0, n, Footprints::span_bounds);
            #[allow(unsafe_code)]
            // SAFETY: the CPU has AVX-512 (checked above).
            let masked = unsafe { avx512::band_bounds(&fp, width, y0, n) };
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&masked.t_lo), bits(&scalar.t_lo), "t_lo, band at row {y0}");
            assert_eq!(bits(&masked.t_hi), bits(&scalar.t_hi), "t_hi, band at row {y0}");
            assert!(scalar.t_lo.iter().any(|t| t.is_finite()), "the band at row {y0} has bounds");
        }
    }
}

#[test]
fn dead_boxes_hold_no_live_cell() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/assets/lego.nolf");
    let density = Asset::load(&path).unwrap().density;
    let live = LiveCells::new(&density);
    let g = density.grid as usize;
    let mut per_radius = [0usize; MAX_SKIP_RADIUS as usize + 1];
    // The box of cells c + s∘[0, r]³ (cut at the grid's faces) for octant `oct` has no
    // live cell.
    let dead_box = |c: [usize; 3], oct: usize, r: usize| {
        let span = |a: usize| if oct >> a & 1 == 1 { c[a]..=(c[a] + r).min(g - 1) } else { c[a].saturating_sub(r)..=c[a] };
        span(2).all(|z| span(1).all(|y| span(0).all(|x| live.index[x + g * (y + g * z)] < 0)))
    };
    // Every 7th cell (of 128³), every octant: its radius is right, and the largest that is.
    for i in (0..g.pow(3)).step_by(7) {
        let entry = live.index[i];
        if entry >= 0 {
            continue;
        }
        let c = [i % g, (i / g) % g, i / (g * g)];
        for oct in 0..8 {
            let radius = ((-1 - entry) >> (3 * oct) & 7) as usize;
            per_radius[radius] += 1;
            assert!(dead_box(c, oct, radius), "cell {c:?}, octant {oct}: its box of radius {radius} holds a live cell");
            assert!(radius == MAX_SKIP_RADIUS as usize || !dead_box(c, oct, radius + 1), "cell {c:?}, octant {oct}: radius {radius} is not the largest");
        }
    }
    assert!(per_radius.iter().all(|&n| n > 0), "every radius should occur in lego: {per_radius:?}");
}

fn same_sigmas(prepared: &FastPrepared) {
    let asset = &prepared.asset;
    let mut rng = SmallRng::seed_from_u64(3);
    let step = asset.march.step;
    let mut live_lanes = 0;
    for _ in 0..2000 {
        let o = Vec3::new(rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0));
        let d = (-o + Vec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5))).normalize();
        let Some((t0, t1)) = clip_ray(&asset.density.bounds, o, d) else { continue };
        let k0 = rng.random_range(0..((t1 - t0) / step).max(1.0) as i32);
        let (s, e, m) = prepared.sigmas::<false>(k0, BATCH, o, d, t0, step);
        let (sv, ev, mv) = prepared.sigmas::<true>(k0, BATCH, o, d, t0, step);
        assert_eq!(s.map(f32::to_bits), sv.map(f32::to_bits));
        assert_eq!(e.map(f32::to_bits), ev.map(f32::to_bits));
        assert_eq!(m, mv);
        live_lanes += s.iter().filter(|v| **v != 0.0).count();
    }
    assert!(live_lanes > 1000, "the rays should cross the objects ({live_lanes} live samples)");
}

/// The closed segments kept in vectors file runs as the per-ray tracker does: the scalar
/// [`avx2::Closed::push`] and, on AVX-512, `avx512::close16` on 16 lanes at once, with weights
/// that tie (the first of equals gives way) and primaries that come and go.
#[cfg(target_arch = "x86_64")]
#[test]
fn closed_segments_in_vectors_match_the_tracker() {
    use avx2::{Closed, LANES, Runs};
    let wide = crate::mlp::simd::level() == crate::mlp::simd::Level::Avx512;
    if !wide {
        eprintln!("no AVX-512 on this CPU: the 16-lane filing does not run");
    }
    let rule = HitRule { tau: 0.1, max_hits: 3, gap_steps: 3.0 };
    let mut rng = SmallRng::seed_from_u64(9);
    let mut trackers: Vec<Segments> = (0..LANES).map(|_| Segments::new(0.3)).collect();
    let (mut scalar, mut vector) = (Closed::default(), Closed::default());
    let mut runs = Runs::default();
    let (mut filed, mut finished) = (0, 0);
    for round in 0..4000 {
        let at = 16 * (round % (LANES / 16));
        let closing = rng.random::<u16>() & rng.random::<u16>();
        for lane in at..at + 16 {
            let weight = [0.05, 0.1, 0.2, 0.4][rng.random_range(0..4)];
            let t = rng.random_range(0.0..4.0f32);
            (runs.weight[lane], runs.peak_w[lane], runs.peak_t[lane], runs.first_t[lane], runs.last_t[lane]) = (weight, weight / 2.0, t, t - 0.1, t + 0.1);
            runs.primary[lane] = if rng.random_bool(0.3) { -1 } else { 0 };
        }
        for bit in 0..16 {
            let lane = at + bit;
            if closing >> bit & 1 != 0 {
                trackers[lane].close_run(runs.segment(lane), runs.primary[lane] != 0);
                scalar.push(lane, runs.segment(lane), runs.primary[lane] != 0);
                filed += 1;
            }
        }
        if wide {
            #[allow(unsafe_code)]
            // SAFETY: the CPU has AVX-512 (checked above); lanes `at..at + 16` of `LANES`.
            unsafe { avx512::close16(&mut runs, &mut vector, at, closing) };
            for bit in 0..16 {
                assert!(closing >> bit & 1 == 0 || runs.primary[at + bit] == 0, "a filed run's primary flag is cleared");
            }
        }
        // Now and then a lane's ray ends: all three give the same queries.
        let lane = rng.random_range(0..LANES);
        if rng.random_bool(0.2) {
            let m = MarchHit { t_hit: 1.0, alpha_c: rng.random_range(0.2..1.0), w_max: 0.4, samples: 9 };
            let want = trackers[lane].finish(None, m, &rule);
            let mut got = Segments::new(0.3);
            scalar.take(lane, &mut got);
            assert_eq!(got.finish(None, m, &rule), want, "scalar, round {round}, lane {lane}");
            if wide {
                let mut got = Segments::new(0.3);
                vector.take(lane, &mut got);
                assert_eq!(got.finish(None, m, &rule), want, "16 lanes, round {round}, lane {lane}");
            }
            finished += 1;
        }
    }
    assert!(filed > 10_000 && finished > 500, "{filed} runs filed, {finished} rays finished");
}
