//! The .nolf container: round trip, and every truncation, bit flip, wrong version or hostile
//! size field is a clear error — never a panic or a huge allocation.

mod common;

use nephele_renderer::{
    Asset, AssetError,
    container::ContainerError,
    cubes::CubeStorage,
    procedural::{self, ProceduralConfig, Scene},
};
use rand::{Rng, SeedableRng, rngs::SmallRng};

fn tiny() -> Asset {
    let cfg = ProceduralConfig { density_grid: 8, density_brick: 2, diffuse_grid: 8, diffuse_brick: 2, psh_grid: 16, ..ProceduralConfig::small(Scene::Shiny) };
    procedural::generate(&cfg).unwrap()
}

#[test]
fn round_trip_is_exact() {
    let a = tiny();
    let bytes = a.to_bytes().unwrap();
    let b = Asset::from_bytes(&bytes).unwrap();
    assert_eq!(a, b);
    // And through a file.
    let path = std::env::temp_dir().join(format!("nephele-rt-{}.nolf", std::process::id()));
    a.save(&path).unwrap();
    assert_eq!(Asset::load(&path).unwrap(), a);
    std::fs::remove_file(path).ok();
}

#[test]
fn shipped_fixture_matches_the_generator() {
    let shipped = common::fixture();
    let fresh = procedural::generate(&ProceduralConfig::small(Scene::Trio)).unwrap();
    assert!(*shipped == fresh, "examples/assets/trio-small.nolf is stale: regenerate with `nephele generate --scene trio --small --out examples/assets/trio-small.nolf`");
}

#[test]
fn every_truncation_is_an_error() {
    let bytes = tiny().to_bytes().unwrap();
    for len in 0..bytes.len() {
        let r = std::panic::catch_unwind(|| Asset::from_bytes(&bytes[..len]));
        match r {
            Ok(Err(_)) => {}
            Ok(Ok(_)) => panic!("truncated to {len} bytes but loaded"),
            Err(_) => panic!("truncated to {len} bytes: panic"),
        }
    }
}

#[test]
fn random_bit_flips_are_errors() {
    let bytes = tiny().to_bytes().unwrap();
    let mut rng = SmallRng::seed_from_u64(5);
    // Every byte of the header, and random bytes of the data.
    let header_len = 8 + u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let positions: Vec<usize> = (0..header_len).chain((0..3000).map(|_| rng.random_range(header_len..bytes.len()))).collect();
    for pos in positions {
        let mut b = bytes.clone();
        b[pos] ^= 1 << rng.random_range(0..8);
        match std::panic::catch_unwind(|| Asset::from_bytes(&b)) {
            Ok(Err(_)) => {}
            Ok(Ok(_)) => panic!("flip at byte {pos} loaded silently"),
            Err(_) => panic!("flip at byte {pos}: panic"),
        }
    }
}

/// Rewrites the `nolf` metadata JSON (fixing its checksum) to forge hostile files.
fn forge(bytes: &[u8], edit: impl Fn(&mut serde_json::Value)) -> Vec<u8> {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let meta_str = header["__metadata__"]["nolf"].as_str().unwrap().to_string();
    let mut meta: serde_json::Value = serde_json::from_str(&meta_str).unwrap();
    edit(&mut meta);
    let new_meta = serde_json::to_string(&meta).unwrap();
    use sha2::Digest;
    let sha: String = sha2::Sha256::digest(new_meta.as_bytes()).iter().map(|b| format!("{b:02x}")).collect();
    header["__metadata__"]["nolf"] = new_meta.into();
    header["__metadata__"]["nolf_sha256"] = sha.into();
    let mut h = serde_json::to_vec(&header).unwrap();
    while !h.len().is_multiple_of(8) {
        h.push(b' ');
    }
    let mut out = (h.len() as u64).to_le_bytes().to_vec();
    out.extend(h);
    out.extend_from_slice(&bytes[8 + n..]);
    out
}

#[test]
fn wrong_version_and_hostile_sizes_are_clear_errors() {
    let bytes = tiny().to_bytes().unwrap();
    assert!(Asset::from_bytes(&forge(&bytes, |_| {})).is_ok(), "forging itself must be faithful");
    let err = Asset::from_bytes(&forge(&bytes, |m| m["version"] = 99.into())).unwrap_err();
    assert!(matches!(err, AssetError::Version { version: 99, .. }), "{err}");
    assert!(err.to_string().contains("version 99"));
    for (field, value) in [
        (("density", "grid"), 4_000_000_000u64),
        (("density", "bricks"), 4_000_000_000),
        (("psh", "table_edge"), 100_000),
        (("psh", "features"), 1_000_000),
        (("diffuse", "brick"), 0),
    ] {
        let forged = forge(&bytes, |m| m[field.0][field.1] = value.into());
        let err = Asset::from_bytes(&forged).unwrap_err();
        eprintln!("{}.{} = {value}: {err}", field.0, field.1);
    }
    // A plausible but wrong size is a shape mismatch, not a misread.
    let err = Asset::from_bytes(&forge(&bytes, |m| m["density"]["bricks"] = 3.into())).unwrap_err();
    assert!(matches!(err, AssetError::Container(ContainerError::Shape { name: "density.values", .. })), "{err}");
    let err = Asset::from_bytes(b"definitely not an asset").unwrap_err();
    assert!(matches!(err, AssetError::Container(ContainerError::Parse(_))), "{err}");
    let err = Asset::load(std::path::Path::new("/nonexistent/x.nolf")).unwrap_err();
    assert!(err.to_string().contains("/nonexistent/x.nolf"));
}

/// The march's early stop travels with the asset; assets without one (made before it was an
/// asset setting) load with the old default, and an absurd one is a clear error.
#[test]
fn early_stop_is_saved_defaulted_and_checked() {
    let mut a = tiny();
    a.march.early_stop = 0.03;
    assert_eq!(Asset::from_bytes(&a.to_bytes().unwrap()).unwrap().march.early_stop, 0.03);
    let bytes = tiny().to_bytes().unwrap();
    let legacy = Asset::from_bytes(&forge(&bytes, |m| _ = m["march"].as_object_mut().unwrap().remove("early_stop"))).unwrap();
    assert_eq!(legacy.march.early_stop, nephele_renderer::model::DEFAULT_EARLY_STOP);
    for bad in [serde_json::json!(1.0), serde_json::json!(-0.1)] {
        let err = Asset::from_bytes(&forge(&bytes, |m| m["march"]["early_stop"] = bad.clone())).unwrap_err();
        assert!(err.to_string().contains("early_stop"), "{bad}: {err}");
    }
}

#[test]
fn memory_report_compares_with_dense_grids() {
    let a = common::fixture();
    let m = a.memory();
    assert_eq!(m.parts.len(), 4);
    for p in &m.parts[..3] {
        assert!(p.stored_bytes < p.dense_bytes, "{}: sparse {} ≥ dense {}", p.part, p.stored_bytes, p.dense_bytes);
    }
    let text = m.to_string();
    assert!(text.contains("density cubes") && text.contains("PSH table") && text.contains("total"));
}

/// 8-bit unorm diffuse cubes: one byte per value, exact round trip, a stated rounding error;
/// density must stay f16 (σ is unbounded) and a file that claims otherwise is refused.
#[test]
fn unorm8_diffuse_round_trips_and_density_stays_f16() {
    let half = tiny();
    let mut a = half.clone();
    a.diffuse = a.diffuse.clone().stored_as(CubeStorage::Unorm8);
    let max_err = half.diffuse.values.iter().zip(&a.diffuse.values).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    assert!(max_err <= 0.5 / 255.0 + 1e-3, "unorm8 rounding error {max_err}");
    let bytes = a.to_bytes().unwrap();
    assert_eq!(Asset::from_bytes(&bytes).unwrap(), a);
    assert_eq!(half.memory().stored_bytes() - a.memory().stored_bytes(), a.diffuse.values.len() as u64);
    // Old files (no storage field) are f16; writing f16 adds no field.
    let meta = |b: &[u8]| -> serde_json::Value {
        let n = u64::from_le_bytes(b[..8].try_into().unwrap()) as usize;
        let header: serde_json::Value = serde_json::from_slice(&b[8..8 + n]).unwrap();
        serde_json::from_str(header["__metadata__"]["nolf"].as_str().unwrap()).unwrap()
    };
    assert!(meta(&half.to_bytes().unwrap())["diffuse"].get("storage").is_none());
    assert_eq!(meta(&bytes)["diffuse"]["storage"], "unorm8");
    // Density as unorm8: refused when saving and when a forged file claims it.
    let mut bad = half.clone();
    bad.density = bad.density.clone().stored_as(CubeStorage::Unorm8);
    assert!(bad.to_bytes().unwrap_err().to_string().contains("density cubes must be stored as f16"));
    let err = Asset::from_bytes(&forge(&half.to_bytes().unwrap(), |m| m["density"]["storage"] = "unorm8".into())).unwrap_err();
    assert!(err.to_string().contains("density cubes must be stored as f16"), "{err}");
    // A diffuse tensor whose dtype disagrees with the metadata is a shape error.
    let err = Asset::from_bytes(&forge(&half.to_bytes().unwrap(), |m| m["diffuse"]["storage"] = "unorm8".into())).unwrap_err();
    assert!(matches!(err, AssetError::Container(ContainerError::Shape { name: "diffuse.values", .. })), "{err}");
}

/// Index grids are written as i16 while there are fewer than 32768 bricks (half the bytes) and
/// read back exactly; files written with i32 indices (before this existed) still load.
#[test]
fn small_index_grids_are_i16_and_i32_files_still_load() {
    let a = tiny();
    assert!(a.density.narrow_index() && a.diffuse.narrow_index());
    let bytes = a.to_bytes().unwrap();
    assert_eq!(Asset::from_bytes(&bytes).unwrap(), a);
    // An i32 file: the same tensors widened, the flag dropped from the metadata.
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let mut meta: serde_json::Value = serde_json::from_str(header["__metadata__"]["nolf"].as_str().unwrap()).unwrap();
    assert_eq!(meta["density"]["index_i16"], true);
    let mut tensors = Vec::new();
    let file = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    for (name, view) in file.tensors() {
        let (dtype, data) = if name.ends_with(".index") {
            let wide: Vec<u8> = view.data().chunks_exact(2).flat_map(|c| (i16::from_le_bytes([c[0], c[1]]) as i32).to_le_bytes()).collect();
            (safetensors::Dtype::I32, wide)
        } else {
            (view.dtype(), view.data().to_vec())
        };
        use sha2::Digest;
        let sha: String = sha2::Sha256::digest(&data).iter().map(|b| format!("{b:02x}")).collect();
        meta["checksums"][&name] = sha.into();
        tensors.push((name, dtype, view.shape().to_vec(), data));
    }
    for part in ["density", "diffuse"] {
        meta[part].as_object_mut().unwrap().remove("index_i16");
    }
    let json = serde_json::to_string(&meta).unwrap();
    use sha2::Digest;
    let sha: String = sha2::Sha256::digest(json.as_bytes()).iter().map(|b| format!("{b:02x}")).collect();
    let views: Vec<(String, safetensors::tensor::TensorView<'_>)> =
        tensors.iter().map(|(n, d, s, b)| (n.clone(), safetensors::tensor::TensorView::new(*d, s.clone(), b).unwrap())).collect();
    let info = std::collections::HashMap::from([("nolf".to_string(), json), ("nolf_sha256".to_string(), sha)]);
    let wide = safetensors::serialize(views, Some(info)).unwrap();
    assert!(wide.len() > bytes.len());
    assert_eq!(Asset::from_bytes(&wide).unwrap(), a);
    // The flag with more bricks than i16 can address is refused by name.
    let err = Asset::from_bytes(&forge(&bytes, |m| {
        m["diffuse"]["grid"] = 64.into();
        m["diffuse"]["bricks"] = 40_000.into();
    }))
    .unwrap_err();
    assert!(err.to_string().contains("too many for an i16 index"), "{err}");
}
