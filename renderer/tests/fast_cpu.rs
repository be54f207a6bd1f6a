//! The fast CPU renderer against the CPU reference (docs/architecture.md §3): on the shipped lego asset and
//! procedural ones, one-hit and multi-hit, several step scales, a batch of views of mixed
//! sizes, and views where the footprint prepass cannot help (camera inside the box). Its σ is
//! the reference's to the bit and its network differs only by fused multiply-add rounding, so
//! the tolerance is one 8-bit level on ≤ 0.1% of pixels, and with one hit per ray no pixel off
//! by more than 3. With multi-hit a sample exactly on a cell face (read from the other cell's
//! brick: the same value up to rounding) can tip a segment across τ, which changes that
//! pixel's blend: such pixels stay within the 0.1%. That is with the f32 network; the 8-bit
//! hidden layer (the default where the CPU has AVX-512 VNNI) is held to its own tolerance.

mod common;

use std::sync::Arc;

use glam::DVec3;
use nephele_renderer::{
    Asset, Backend, CpuBackend, FastCpuBackend, Intrinsics, RenderSettings, View, ViewRequest,
    fast::{March, Network},
    procedural::{self, ProceduralConfig, Scene},
};

fn lego() -> Arc<Asset> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/assets/lego.nolf");
    Arc::new(Asset::load(&path).expect("the shipped lego asset loads"))
}

/// Renders `views` on both CPU backends and checks the fast one against the reference.
fn agree(what: &str, asset: &Arc<Asset>, views: &[ViewRequest], settings: &RenderSettings) {
    let one_hit = settings.hit_rule(&asset.march.hits).one_hit();
    let reference = CpuBackend.prepare(asset.clone()).unwrap().render(views, settings).unwrap();
    let fast = FastCpuBackend.prepare_with(asset.clone(), March::detect(), Network::F32).unwrap().render(views, settings).unwrap();
    assert_eq!(fast.frames.len(), views.len());
    for (i, (r, f)) in reference.frames.iter().zip(&fast.frames).enumerate() {
        let d = common::diff(r, f, 1, 1e-3 * asset.march.step * settings.step_scale);
        assert!((d.max_abs <= 3 || !one_hit) && d.frac_over <= 0.001 && d.hit_mismatch <= 0.001 && d.depth_off <= 0.001, "{what}, view {i}: {d:?}");
    }
    // The same rays hit and get the same queries, up to the pixels above.
    let close = |a: u64, b: u64| a.abs_diff(b) as f64 <= 1.0 + 1e-3 * b as f64;
    assert!(close(fast.stats.hits, reference.stats.hits) && close(fast.stats.queries, reference.stats.queries), "{what}: {:?} vs {:?}", fast.stats, reference.stats);
    // The matrix products are timed as part of the network stage, and only where there are queries.
    let s = fast.stats;
    assert!(if s.queries > 0 { s.mlp_ms > 0.0 && s.mlp_ms <= s.shade_ms } else { s.mlp_ms == 0.0 }, "{what}: {s:?}");
}

fn orbit(w: u32, h: u32, azimuth: f64, elevation: f64, distance: f64) -> ViewRequest {
    ViewRequest::new(View::orbit(DVec3::ZERO, distance, azimuth, elevation, Intrinsics::from_fov_x(w, h, 0.69)))
}

#[test]
fn lego_matches_the_reference_one_hit_and_multi_hit() {
    let asset = lego();
    let views = [orbit(160, 120, 35.0, 25.0, 4.0), orbit(97, 61, 200.0, -10.0, 3.0), orbit(64, 64, 90.0, 80.0, 6.0)];
    let one_hit = RenderSettings { hit_tau: Some(1.0), ..Default::default() };
    agree("one hit", &asset, &views, &one_hit);
    agree("the asset's multi-hit rule", &asset, &views, &RenderSettings::default());
    agree("multi-hit τ 0.05", &asset, &views, &RenderSettings { hit_tau: Some(0.05), max_hits: Some(3), ..Default::default() });
    agree("half step", &asset, &views[..1], &RenderSettings { step_scale: 0.5, ..one_hit });
    agree("double step, stop ratio", &asset, &views[..1], &RenderSettings { step_scale: 2.0, stop_ratio: 0.5, ..one_hit });
    agree("early stop 0.05", &asset, &views, &RenderSettings { early_stop: Some(0.05), ..Default::default() });
}

/// An asset's own early stop (the threshold it was trained with) is what both CPU backends
/// march with unless the settings name one: the same frames to the bit as naming it, and
/// not those of another threshold.
#[test]
fn the_assets_early_stop_is_the_default() {
    let asset = lego();
    let mut stopping = (*asset).clone();
    stopping.march.early_stop = 0.05;
    let stopping = Arc::new(stopping);
    let views = [orbit(96, 72, 35.0, 25.0, 4.0)];
    let named = RenderSettings { early_stop: Some(0.05), ..Default::default() };
    let fast = |a: &Arc<Asset>| FastCpuBackend.prepare(a.clone()).unwrap();
    let reference = |a: &Arc<Asset>| CpuBackend.prepare(a.clone()).unwrap();
    for (what, b) in [("fast", fast as fn(&Arc<Asset>) -> Box<dyn nephele_renderer::PreparedAsset>), ("reference", reference)] {
        let own = b(&stopping).render(&views, &RenderSettings::default()).unwrap();
        let asked = b(&asset).render(&views, &named).unwrap();
        let usual = b(&asset).render(&views, &RenderSettings::default()).unwrap();
        assert!(own.frames[0] == asked.frames[0], "{what}: the asset's early stop is not the default");
        assert!(own.frames[0].rgba != usual.frames[0].rgba, "{what}: an early stop of 0.05 changed nothing");
        assert!(own.stats.samples < usual.stats.samples, "{what}: {:?} vs {:?}", own.stats, usual.stats);
    }
}

/// The 8-bit hidden layer ([`Network::Int8`]) rounds each query's hidden values to 1/255 of
/// their largest and each weight row to 1/127 of its largest (1/64 with AVX2): on lego and
/// the shiny scene, one-hit and multi-hit, ≤ 1% of pixels are more than 1 level off the
/// reference, none more than 4 with one hit per ray (multi-hit as in [`agree`]), and the
/// same rays hit (measured with VNNI: ≤ 3 levels, ≤ 0.4%; with AVX2 on Zen 3: ≤ 3 levels,
/// ≤ 0.14%).
#[test]
fn int8_network_stays_within_its_tolerance() {
    if !Network::Int8.available() {
        eprintln!("this CPU has neither AVX-512 VNNI nor AVX2: the int8 network is never used here");
        return;
    }
    let shiny = Arc::new(procedural::generate(&ProceduralConfig::small(Scene::Shiny)).unwrap());
    for (what, asset) in [("lego", lego()), ("shiny", shiny)] {
        let views = [orbit(160, 120, 35.0, 25.0, 4.0), orbit(97, 61, 200.0, -10.0, 3.0), orbit(50, 70, 300.0, 5.0, 2.5)];
        for settings in [RenderSettings { hit_tau: Some(1.0), ..Default::default() }, RenderSettings::default()] {
            let one_hit = settings.hit_rule(&asset.march.hits).one_hit();
            let reference = CpuBackend.prepare(asset.clone()).unwrap().render(&views, &settings).unwrap();
            let int8 = FastCpuBackend.prepare_with(asset.clone(), March::detect(), Network::Int8).unwrap().render(&views, &settings).unwrap();
            for (i, (r, f)) in reference.frames.iter().zip(&int8.frames).enumerate() {
                let d = common::diff(r, f, 1, 1e-3 * asset.march.step);
                assert!((d.max_abs <= 4 || !one_hit) && d.frac_over <= 0.01 && d.hit_mismatch <= 0.001 && d.depth_off <= 0.001, "{what}, view {i}, one hit {one_hit}: {d:?}");
            }
        }
    }
}

#[test]
fn procedural_scenes_match_the_reference() {
    for scene in [Scene::Shiny, Scene::Translucent, Scene::Trio] {
        let asset = Arc::new(procedural::generate(&ProceduralConfig::small(scene)).unwrap());
        let views = [orbit(120, 90, 35.0, 25.0, 4.0), orbit(50, 70, 300.0, 5.0, 2.5)];
        agree(&format!("{scene:?}"), &asset, &views, &RenderSettings::default());
        agree(&format!("{scene:?} multi-hit"), &asset, &views, &RenderSettings { hit_tau: Some(0.02), max_hits: Some(3), ..Default::default() });
    }
}

#[test]
fn cameras_inside_the_box_march_whole_rays() {
    // The footprint prepass gives up when a live cell reaches behind the camera; the march
    // then covers the whole box span and must still agree.
    let asset = common::fixture();
    let inside = ViewRequest::new(View::look_at(DVec3::new(-0.2, 0.0, 0.3), DVec3::new(0.65, 0.35, 0.0), DVec3::Z, Intrinsics::from_fov_x(48, 40, 1.2)));
    let grazing = ViewRequest::new(View::look_at(DVec3::new(1.5, 0.35, 0.0), DVec3::new(0.0, 0.35, 0.0), DVec3::Z, Intrinsics::from_fov_x(31, 31, 1.2)));
    agree("inside and on the face", &asset, &[inside, grazing], &RenderSettings::default());
}
