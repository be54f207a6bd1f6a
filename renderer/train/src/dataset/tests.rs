//! Round trips through the synthetic generator, the instant-ngp layout, and every kind of
//! broken input (each must give the right error naming its file and field, never a panic).

use std::path::Path;

use glam::{DVec3, Vec3};
use nephele_renderer::camera::{Instance, RayFrame};
use serde_json::{Value, json};

use super::*;
use crate::{
    synth::{self, SynthConfig, SynthScene},
    test_util::TempDir,
};

fn tiny(scene: SynthScene) -> SynthConfig {
    SynthConfig { scene, width: 32, height: 32, n_train: 4, n_val: 2, n_test: 2, seed: 11 }
}

fn synth_dir(tag: &str, cfg: &SynthConfig) -> TempDir {
    let dir = TempDir::new(tag);
    synth::generate(cfg, &dir.0).unwrap();
    dir
}

fn load(path: &Path, split: Split) -> Result<Dataset, DatasetError> {
    Dataset::load(path, &LoadOptions::split(split))
}

fn edit_json(file: &Path, edit: impl FnOnce(&mut Value)) {
    let mut v: Value = serde_json::from_str(&std::fs::read_to_string(file).unwrap()).unwrap();
    edit(&mut v);
    std::fs::write(file, serde_json::to_string_pretty(&v).unwrap()).unwrap();
}

fn write_png(path: &Path, width: u32, height: u32, color: png::ColorType, depth: png::BitDepth, data: &[u8]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let mut enc = png::Encoder::new(std::fs::File::create(path).unwrap(), width, height);
    enc.set_color(color);
    enc.set_depth(depth);
    enc.write_header().unwrap().write_image_data(data).unwrap();
}

/// Generates a tiny dataset, breaks it with `edit`, loads the train split: the error.
fn broken(tag: &str, edit: impl FnOnce(&Path)) -> DatasetError {
    let dir = synth_dir(tag, &tiny(SynthScene::Diffuse));
    edit(&dir.0);
    match load(&dir.0, Split::Train) {
        Ok(_) => panic!("{tag}: broken dataset loaded"),
        Err(e) => e,
    }
}

fn ends_with(path: &Path, tail: &str) -> bool {
    path.ends_with(tail)
}

#[test]
fn synthetic_round_trip_is_exact() {
    for scene in [SynthScene::Diffuse, SynthScene::Translucent, SynthScene::Mixed] {
        let cfg = tiny(scene);
        let dir = synth_dir(&format!("round-trip-{scene}"), &cfg);
        for split in Split::ALL {
            let data = load(&dir.0, split).unwrap();
            let cameras = synth::cameras(&cfg, split);
            assert_eq!((data.format, data.split, data.images.len()), (Format::NerfSynthetic, split, cfg.count(split)));
            assert_eq!(data.name, dir.0.file_name().unwrap().to_string_lossy());
            for (i, (image, camera)) in data.images.iter().zip(&cameras).enumerate() {
                assert!(ends_with(&image.path, &format!("{split}/r_{i}.png")), "{}", image.path.display());
                assert_eq!((image.width, image.height, image.rgba.len()), (32, 32, 32 * 32 * 4));
                // Poses survive JSON exactly; intrinsics follow camera_angle_x.
                assert_eq!(image.view, *camera);
                // Pixels are the exact render, quantised to 8 bits.
                let truth = synth::render_view(scene, camera);
                for (p, (got, want)) in image.rgba.chunks_exact(4).zip(truth.chunks_exact(4)).enumerate() {
                    let (a_got, a_want) = (got[3], want[3]);
                    assert!((a_got - a_want).abs() <= 0.5 / 255.0 + 1e-6, "{scene} {split} {i} pixel {p}: alpha {a_got} vs {a_want}");
                    if a_want == 0.0 {
                        assert_eq!(got, [0.0; 4], "background must be exactly transparent");
                    }
                    if a_want == 1.0 {
                        assert_eq!(a_got, 1.0);
                    }
                    if scene == SynthScene::Translucent && a_want == synth::TORUS_OPACITY {
                        assert_eq!(a_got, 128.0 / 255.0);
                    }
                    if a_got > 0.0 {
                        for c in 0..3 {
                            assert!((got[c] - want[c]).abs() <= 0.5 / 255.0 + 1e-6, "{scene} colour");
                        }
                    }
                }
            }
        }
        // Direct checks that do not lean on render_view: corners are sky, the centre is solid
        // (or half-transparent torus for the translucent scene, whose middle is its hole).
        let train = load(&dir.0, Split::Train).unwrap();
        for image in &train.images {
            for (x, y) in [(0, 0), (31, 0), (0, 31), (31, 31)] {
                assert_eq!(image.pixel(x, y)[3], 0.0);
            }
            let alphas: Vec<f32> = image.rgba.chunks_exact(4).map(|p| p[3]).collect();
            let fractional = alphas.iter().filter(|&&a| a > 0.0 && a < 1.0).count();
            assert!(fractional > 0, "anti-aliased edges have fractional alpha");
            match scene {
                SynthScene::Diffuse => assert_eq!(image.pixel(16, 16)[3], 1.0),
                SynthScene::Translucent => {
                    assert!(alphas.iter().all(|&a| a <= 128.0 / 255.0));
                    assert!(alphas.iter().filter(|&&a| a == 128.0 / 255.0).count() > 30);
                }
                _ => assert!(alphas.contains(&1.0)),
            }
        }
    }
}

#[test]
fn downscale_halves_size_and_keeps_the_field_of_view() {
    let cfg = tiny(SynthScene::Mixed);
    let dir = synth_dir("downscale", &cfg);
    let full = load(&dir.0, Split::Val).unwrap();
    let half = Dataset::load(&dir.0, &LoadOptions { downscale: 2, ..LoadOptions::split(Split::Val) }).unwrap();
    for (big, small) in full.images.iter().zip(&half.images) {
        assert_eq!((small.width, small.height, small.rgba.len()), (16, 16, 16 * 16 * 4));
        let (kb, ks) = (big.view.intrinsics, small.view.intrinsics);
        assert_eq!((ks.width, ks.height), (16, 16));
        assert_eq!(kb.fx / kb.width as f32, ks.fx / ks.width as f32);
        assert_eq!((ks.cx, ks.cy), (8.0, 8.0));
        assert_eq!(small.view.world_from_camera, big.view.world_from_camera);
        // A small pixel's centre is the shared corner of its 2×2 block.
        let (o, d) = small.ray(5, 9);
        let (o_big, d_big) = big.view.ray_in_world(11.0, 19.0);
        assert!((d.as_dvec3() - d_big).length() < 1e-6 && (o.as_dvec3() - o_big).length() < 1e-6);
        // Box filter on premultiplied colour.
        for (x, y) in [(0, 0), (5, 9), (8, 8), (12, 3), (15, 15)] {
            let block =
                [big.pixel(2 * x, 2 * y), big.pixel(2 * x + 1, 2 * y), big.pixel(2 * x, 2 * y + 1), big.pixel(2 * x + 1, 2 * y + 1)];
            let alpha: f32 = block.iter().map(|p| p[3]).sum::<f32>() / 4.0;
            let got = small.pixel(x, y);
            assert!((got[3] - alpha).abs() < 1e-6);
            for c in 0..3 {
                let premultiplied: f32 = block.iter().map(|p| p[c] * p[3]).sum::<f32>() / 4.0;
                assert!((got[c] * got[3] - premultiplied).abs() < 1e-6, "({x}, {y}) channel {c}");
            }
        }
    }
    for factor in [4, 8] {
        let d = Dataset::load(&dir.0, &LoadOptions { downscale: factor, ..LoadOptions::default() }).unwrap();
        assert_eq!(d.images[0].width, 32 / factor);
    }
}

#[test]
fn rays_follow_the_renderer_conventions() {
    let dir = synth_dir("rays", &tiny(SynthScene::Glossy));
    let data = load(&dir.0, Split::Test).unwrap();
    let image = &data.images[1];
    let frame = RayFrame::new(&image.view, &Instance::default(), Vec3::ZERO, 1.5);
    let eye = image.view.world_from_camera.w_axis.truncate().as_vec3();
    for (x, y) in [(0, 0), (31, 0), (7, 20), (31, 31)] {
        let (origin, dir) = image.ray(x, y);
        let (shifted, dir_frame) = frame.ray(x, y);
        assert!((dir - dir_frame).length() < 1e-6, "({x}, {y}): {dir} vs {dir_frame}");
        assert!((origin - eye).length() < 1e-6);
        assert!(((shifted - origin).normalize() - dir).length() < 1e-5);
        assert!((dir.length() - 1.0).abs() < 1e-6);
    }
    // Row 0 is the top: pixel (0, 0) looks up and to the left in the camera's frame.
    let camera_from_world = image.view.world_from_camera.inverse();
    let d = camera_from_world.transform_vector3(image.ray(0, 0).1.as_dvec3());
    assert!(d.x < 0.0 && d.y > 0.0 && d.z < 0.0, "{d}");
    // The centre ray looks at the origin.
    let (o, d) = image.view.ray_in_world(16.0, 16.0);
    assert!((o + d * o.length()).length() < 1e-9);
    // Iteration order is that of `rgba`.
    let rays: Vec<(Vec3, Vec3)> = data.rays(1).collect();
    assert_eq!(rays.len(), 32 * 32);
    assert_eq!(rays[32 + 2], image.ray(2, 1));
}

#[test]
fn composite_over_white_uses_straight_alpha() {
    let dir = synth_dir("composite", &tiny(SynthScene::Translucent));
    let image = &load(&dir.0, Split::Train).unwrap().images[0];
    let rgb = image.composite_over(Vec3::ONE);
    assert_eq!(rgb.len(), 3 * 32 * 32);
    assert_eq!(&rgb[..3], &[1.0, 1.0, 1.0], "sky over white is white");
    for (p, c) in image.rgba.chunks_exact(4).zip(rgb.chunks_exact(3)) {
        for k in 0..3 {
            assert!((c[k] - (p[k] * p[3] + 1.0 - p[3])).abs() < 1e-6);
        }
    }
    let black = image.composite_over(Vec3::ZERO);
    assert!(black.iter().zip(image.rgba.chunks_exact(4).flat_map(|p| [p[0] * p[3], p[1] * p[3], p[2] * p[3]])).all(|(a, b)| a == &b));
}

#[test]
fn max_images_and_inspect() {
    let cfg = tiny(SynthScene::Diffuse);
    let dir = synth_dir("cap", &cfg);
    let capped = Dataset::load(&dir.0, &LoadOptions { max_images: Some(3), ..LoadOptions::default() }).unwrap();
    assert_eq!(capped.images.len(), 3);
    assert_eq!(capped.images[2].view, synth::cameras(&cfg, Split::Train)[2]);
    let info = inspect(&dir.0, None).unwrap();
    assert_eq!(info.format, Format::NerfSynthetic);
    let counts: Vec<_> = info.splits.iter().map(|s| (s.split, s.frames, s.first_image_size)).collect();
    assert_eq!(counts, [(Split::Train, 4, Some((32, 32))), (Split::Val, 2, Some((32, 32))), (Split::Test, 2, Some((32, 32)))]);
    // A folder with only some splits (like the shipped lego subset) still loads them.
    std::fs::remove_file(dir.0.join("transforms_val.json")).unwrap();
    assert_eq!(inspect(&dir.0, None).unwrap().splits.len(), 2);
    let err = load(&dir.0, Split::Val).unwrap_err();
    assert!(matches!(&err, DatasetError::MissingTransforms { looked_for, .. } if looked_for == "transforms_val.json"), "{err}");
}

/// instant-ngp layout written by hand: explicit intrinsics, per-frame overrides, extensions in
/// `file_path`, `aabb_scale`, non-square images, and the holdout split.
#[test]
fn instant_ngp_transforms_load() {
    let dir = TempDir::new("ingp");
    let (width, height) = (24u32, 16u32);
    let mut frames = Vec::new();
    let mut views = Vec::new();
    for i in 0..5 {
        let intrinsics = Intrinsics { fx: 30.0, fy: 32.0, cx: 11.5, cy: 8.25, width, height };
        let view = View::orbit(DVec3::ZERO, 4.0, 72.0 * i as f64, 20.0, intrinsics);
        let rgba = synth::render_view(SynthScene::Glossy, &view);
        let bytes: Vec<u8> = rgba.iter().map(|&v| nephele_renderer::render::to_unorm8(v)).collect();
        let name = format!("images/frame_{i:03}.png");
        write_png(&dir.0.join(&name), width, height, png::ColorType::Rgba, png::BitDepth::Eight, &bytes);
        let rows: Vec<[f64; 4]> = (0..4).map(|r| view.world_from_camera.row(r).to_array()).collect();
        let mut frame = json!({ "file_path": name, "transform_matrix": rows, "sharpness": 100.0 });
        if i == 2 {
            frame["fl_x"] = json!(40.0);
        }
        frames.push(frame);
        views.push(view);
    }
    let transforms = json!({
        "fl_x": 30.0, "fl_y": 32.0, "cx": 11.5, "cy": 8.25, "w": width, "h": height,
        "k1": 0.0, "aabb_scale": 4, "frames": frames,
    });
    let file = dir.0.join("transforms.json");
    std::fs::write(&file, serde_json::to_string_pretty(&transforms).unwrap()).unwrap();

    let all = load(&dir.0, Split::Train).unwrap();
    assert_eq!((all.format, all.images.len(), all.aabb_scale), (Format::InstantNgp, 5, Some(4.0)));
    assert_eq!(all.transforms_file, file);
    for (i, (image, view)) in all.images.iter().zip(&views).enumerate() {
        assert_eq!(image.view.world_from_camera, view.world_from_camera);
        assert_eq!((image.width, image.height), (width, height));
        let k = image.view.intrinsics;
        assert_eq!((k.fx, k.fy, k.cx, k.cy), (if i == 2 { 40.0 } else { 30.0 }, 32.0, 11.5, 8.25));
    }
    // Loading the JSON file itself gives the same.
    assert_eq!(load(&file, Split::Train).unwrap().images, all.images);

    let holdout = |split| Dataset::load(&dir.0, &LoadOptions { holdout_every: Some(2), ..LoadOptions::split(split) });
    let train = holdout(Split::Train).unwrap();
    let test = holdout(Split::Test).unwrap();
    let names = |d: &Dataset| d.images.iter().map(|im| im.path.file_name().unwrap().to_string_lossy().into_owned()).collect::<Vec<_>>();
    assert_eq!(names(&train), ["frame_001.png", "frame_003.png"]);
    assert_eq!(names(&test), ["frame_000.png", "frame_002.png", "frame_004.png"]);
    let info = inspect(&dir.0, Some(2)).unwrap();
    assert_eq!(info.splits.iter().map(|s| (s.split, s.frames)).collect::<Vec<_>>(), [(Split::Train, 2), (Split::Test, 3)]);

    for split in [Split::Val, Split::Test] {
        let err = load(&dir.0, split).unwrap_err();
        assert!(matches!(err, DatasetError::NoFrames { split: s, .. } if s == split), "{err}");
        assert!(err.to_string().contains("holdout_every"));
    }
    let err = Dataset::load(&dir.0, &LoadOptions { holdout_every: Some(1), ..LoadOptions::default() }).unwrap_err();
    assert!(matches!(err, DatasetError::BadOption(_)));

    // Field of view instead of focal lengths; centre defaults to the middle.
    edit_json(&file, |v| {
        let root = v.as_object_mut().unwrap();
        for key in ["fl_x", "fl_y", "cx", "cy", "w", "h"] {
            root.remove(key);
        }
        root.insert("camera_angle_x".into(), json!(0.8));
        root["frames"][2].as_object_mut().unwrap().remove("fl_x");
    });
    let k = load(&dir.0, Split::Train).unwrap().images[0].view.intrinsics;
    let fx = (0.5 * 24.0 / 0.4f64.tan()) as f32;
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (fx, fx, 12.0, 8.0));

    // Sizes in the file must match the images.
    edit_json(&file, |v| v["w"] = json!(25));
    let err = load(&dir.0, Split::Train).unwrap_err();
    match &err {
        DatasetError::SizeMismatch { image, width: 24, expected_width: 25, expected_from, .. } => {
            assert!(ends_with(image, "images/frame_000.png") && expected_from.contains("transforms.json"), "{err}");
        }
        e => panic!("{e}"),
    }
    edit_json(&file, |v| v["w"] = json!(24.5));
    assert!(matches!(load(&dir.0, Split::Train).unwrap_err(), DatasetError::BadField { field, .. } if field == "w"));
    // No focal length at all.
    edit_json(&file, |v| {
        v.as_object_mut().unwrap().remove("w");
        v.as_object_mut().unwrap().remove("camera_angle_x");
    });
    let err = load(&dir.0, Split::Train).unwrap_err();
    assert!(matches!(&err, DatasetError::MissingField { field, .. } if field.contains("fl_x")), "{err}");
}

#[test]
fn png_variants_decode() {
    let dir = TempDir::new("png");
    type Case = (&'static str, png::ColorType, png::BitDepth, Vec<u8>, [f32; 4]);
    let cases: Vec<Case> = vec![
        ("rgb8", png::ColorType::Rgb, png::BitDepth::Eight, vec![255, 0, 51], [1.0, 0.0, 0.2, 1.0]),
        ("rgba8", png::ColorType::Rgba, png::BitDepth::Eight, vec![0, 255, 0, 102], [0.0, 1.0, 0.0, 0.4]),
        ("gray8", png::ColorType::Grayscale, png::BitDepth::Eight, vec![51], [0.2, 0.2, 0.2, 1.0]),
        ("grayalpha8", png::ColorType::GrayscaleAlpha, png::BitDepth::Eight, vec![255, 0], [1.0, 1.0, 1.0, 0.0]),
        (
            "rgba16",
            png::ColorType::Rgba,
            png::BitDepth::Sixteen,
            vec![0xff, 0xff, 0x80, 0x00, 0x00, 0x00, 0x33, 0x33],
            [1.0, 32768.0 / 65535.0, 0.0, 0.2],
        ),
        ("rgb16", png::ColorType::Rgb, png::BitDepth::Sixteen, vec![0, 0, 0xff, 0xff, 0, 0], [0.0, 1.0, 0.0, 1.0]),
    ];
    for (name, color, depth, pixel, want) in cases {
        let path = dir.0.join(format!("{name}.png"));
        let data: Vec<u8> = pixel.iter().copied().cycle().take(pixel.len() * 6).collect();
        write_png(&path, 3, 2, color, depth, &data);
        let (w, h, rgba) = decode_png(&path).unwrap();
        assert_eq!((w, h, rgba.len()), (3, 2, 24), "{name}");
        for p in rgba.chunks_exact(4) {
            for c in 0..4 {
                assert!((p[c] - want[c]).abs() < 1e-6, "{name}: {p:?} vs {want:?}");
            }
        }
    }
    // A palette image with transparency expands to RGBA.
    let path = dir.0.join("palette.png");
    let mut enc = png::Encoder::new(std::fs::File::create(&path).unwrap(), 2, 1);
    enc.set_color(png::ColorType::Indexed);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_palette(vec![255, 0, 0, 0, 0, 255]);
    enc.set_trns(vec![255, 0]);
    enc.write_header().unwrap().write_image_data(&[0, 1]).unwrap();
    let (_, _, rgba) = decode_png(&path).unwrap();
    assert_eq!(rgba, [1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0]);
}

#[test]
fn missing_paths_are_named() {
    let nowhere = std::env::temp_dir().join("nephele-dataset-does-not-exist");
    let err = load(&nowhere, Split::Train).unwrap_err();
    assert!(matches!(&err, DatasetError::MissingFolder { path } if *path == nowhere), "{err}");
    let empty = TempDir::new("empty");
    let err = load(&empty.0, Split::Train).unwrap_err();
    assert!(
        matches!(&err, DatasetError::MissingTransforms { dir, looked_for } if *dir == empty.0 && looked_for.contains("transforms.json"))
    );
    assert!(matches!(inspect(&empty.0, None), Err(DatasetError::MissingTransforms { .. })));

    let err = broken("no-train-split", |d| std::fs::remove_file(d.join("transforms_train.json")).unwrap());
    assert!(matches!(&err, DatasetError::MissingTransforms { looked_for, .. } if looked_for == "transforms_train.json"), "{err}");

    let err = broken("missing-image", |d| std::fs::remove_file(d.join("train/r_1.png")).unwrap());
    match &err {
        DatasetError::MissingImage { image, file, field } => {
            assert!(ends_with(image, "train/r_1.png") && ends_with(file, "transforms_train.json") && field == "frames[1].file_path");
        }
        e => panic!("{e}"),
    }
    assert!(err.to_string().contains("r_1.png"));
}

#[test]
fn bad_json_reports_line_and_column() {
    let err = broken("malformed", |d| {
        let file = d.join("transforms_train.json");
        let text = std::fs::read_to_string(&file).unwrap().replacen("\"frames\": [", "\"frames\": [,", 1);
        std::fs::write(file, text).unwrap();
    });
    match &err {
        DatasetError::BadJson { file, line, column, .. } => {
            assert!(ends_with(file, "transforms_train.json") && *line == 3 && *column > 10, "{err}");
        }
        e => panic!("{e}"),
    }
    // Python's json.dump writes bare NaN; JSON has none. 1e400 overflows f64.
    for (tag, bad) in [("nan", "NaN"), ("inf", "-Infinity"), ("huge", "1e400")] {
        let err = broken(tag, |d| {
            let file = d.join("transforms_train.json");
            let text = std::fs::read_to_string(&file).unwrap();
            let at = text.find("\"transform_matrix\": [").unwrap() + "\"transform_matrix\": [".len();
            let at = text[at..].find(|c: char| c == '-' || c.is_ascii_digit()).unwrap() + at;
            let end = text[at..].find(',').unwrap() + at;
            std::fs::write(file, format!("{}{bad}{}", &text[..at], &text[end..])).unwrap();
        });
        match &err {
            DatasetError::BadJson { line, message, .. } => {
                assert!(*line > 1 && message.contains("non-finite"), "{tag}: {err}");
            }
            e => panic!("{tag}: {e}"),
        }
    }
}

#[test]
fn bad_fields_are_named() {
    let edit = |tag: &str, f: fn(&mut Value)| broken(tag, |d| edit_json(&d.join("transforms_train.json"), f));
    let field_of = |e: &DatasetError| match e {
        DatasetError::MissingField { field, file } | DatasetError::BadField { field, file, .. } => {
            assert!(ends_with(file, "transforms_train.json"));
            assert!(e.to_string().contains("transforms_train.json") && e.to_string().contains(field.as_str()));
            field.clone()
        }
        e => panic!("{e}"),
    };
    let err = edit("no-angle", |v| {
        v.as_object_mut().unwrap().remove("camera_angle_x");
    });
    assert!(matches!(err, DatasetError::MissingField { .. }));
    assert_eq!(field_of(&err), "camera_angle_x");
    let err = edit("neg-angle", |v| v["camera_angle_x"] = json!(-0.5));
    assert!(matches!(err, DatasetError::BadField { .. }));
    assert_eq!(field_of(&err), "camera_angle_x");
    let err = edit("string-nan", |v| v["frames"][1]["transform_matrix"][0][3] = json!("NaN"));
    assert_eq!(field_of(&err), "frames[1].transform_matrix[0][3]");
    assert!(err.to_string().contains("\"NaN\""));
    let err = edit("no-matrix", |v| {
        v["frames"][0].as_object_mut().unwrap().remove("transform_matrix");
    });
    assert_eq!(field_of(&err), "frames[0].transform_matrix");
    let err = edit("3x4", |v| {
        v["frames"][2]["transform_matrix"].as_array_mut().unwrap().pop();
    });
    assert_eq!(field_of(&err), "frames[2].transform_matrix");
    let err = edit("no-path", |v| {
        v["frames"][3].as_object_mut().unwrap().remove("file_path");
    });
    assert_eq!(field_of(&err), "frames[3].file_path");
    let err = edit("no-frames-field", |v| {
        v.as_object_mut().unwrap().remove("frames");
    });
    assert_eq!(field_of(&err), "frames");
    let err = edit("frames-object", |v| v["frames"] = json!({}));
    assert_eq!(field_of(&err), "frames");
    let err = edit("top-array", |v| *v = json!([1, 2]));
    assert!(matches!(err, DatasetError::BadField { .. }));

    let err = edit("zero-frames", |v| v["frames"] = json!([]));
    assert!(matches!(&err, DatasetError::NoFrames { split: Split::Train, file, .. } if ends_with(file, "transforms_train.json")), "{err}");
}

#[test]
fn bad_poses_are_refused() {
    let pose = |tag: &str, f: fn(&mut Value)| -> PoseError {
        match broken(tag, |d| edit_json(&d.join("transforms_train.json"), f)) {
            DatasetError::BadPose { file, field, source } => {
                assert!(ends_with(&file, "transforms_train.json"));
                assert_eq!(field, "frames[1].transform_matrix");
                source
            }
            e => panic!("{tag}: {e}"),
        }
    };
    let scaled = pose("scaled", |v| {
        for r in 0..3 {
            for c in 0..3 {
                let x = v["frames"][1]["transform_matrix"][r][c].as_f64().unwrap();
                v["frames"][1]["transform_matrix"][r][c] = json!(2.0 * x);
            }
        }
    });
    assert!(matches!(scaled, PoseError::NotRigid { .. }));
    let mirrored = pose("mirrored", |v| {
        for r in 0..3 {
            let x = v["frames"][1]["transform_matrix"][r][0].as_f64().unwrap();
            v["frames"][1]["transform_matrix"][r][0] = json!(-x);
        }
    });
    assert!(matches!(mirrored, PoseError::Mirrored { .. }));
    let projective = pose("bottom-row", |v| v["frames"][1]["transform_matrix"][3][0] = json!(0.5));
    assert_eq!(projective, PoseError::NotAffine);
}

#[test]
fn bad_images_are_named() {
    let err = broken("truncated", |d| {
        let path = d.join("train/r_2.png");
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    });
    assert!(matches!(&err, DatasetError::BadPng { image, .. } if ends_with(image, "train/r_2.png")), "{err}");
    let err = broken("not-png", |d| std::fs::write(d.join("train/r_0.png"), "hello").unwrap());
    assert!(matches!(&err, DatasetError::BadPng { image, .. } if ends_with(image, "train/r_0.png")), "{err}");
    let err = broken("wrong-size", |d| {
        write_png(&d.join("train/r_3.png"), 16, 32, png::ColorType::Rgba, png::BitDepth::Eight, &[0; 16 * 32 * 4]);
    });
    match &err {
        DatasetError::SizeMismatch { image, width: 16, height: 32, expected_width: 32, expected_height: 32, expected_from } => {
            assert!(ends_with(image, "train/r_3.png") && expected_from.contains("r_0.png"), "{err}");
        }
        e => panic!("{e}"),
    }
    // RGB and 16-bit images in a NeRF-synthetic folder load (alpha 1, values scaled).
    let dir = synth_dir("rgb16", &tiny(SynthScene::Diffuse));
    let rgb16: Vec<u8> = (0..32 * 32).flat_map(|_| [0xff, 0xff, 0x80, 0x00, 0x00, 0x00]).collect();
    write_png(&dir.0.join("train/r_1.png"), 32, 32, png::ColorType::Rgb, png::BitDepth::Sixteen, &rgb16);
    let image = &load(&dir.0, Split::Train).unwrap().images[1];
    assert_eq!(image.pixel(4, 7), [1.0, 32768.0 / 65535.0, 0.0, 1.0]);
}

#[test]
fn bad_options_are_refused() {
    let dir = synth_dir("options", &tiny(SynthScene::Diffuse));
    for options in [
        LoadOptions { downscale: 3, ..LoadOptions::default() },
        LoadOptions { downscale: 0, ..LoadOptions::default() },
        LoadOptions { max_images: Some(0), ..LoadOptions::default() },
    ] {
        assert!(matches!(Dataset::load(&dir.0, &options), Err(DatasetError::BadOption(_))), "{options:?}");
    }
    assert_eq!("val".parse::<Split>(), Ok(Split::Val));

    // A holdout splits a NeRF-synthetic train file into train and held-out test views.
    let all = Dataset::load(&dir.0, &LoadOptions::default()).unwrap();
    let holdout = |split| Dataset::load(&dir.0, &LoadOptions { holdout_every: Some(3), ..LoadOptions::split(split) }).unwrap();
    let (train, test) = (holdout(Split::Train), holdout(Split::Test));
    assert_eq!(train.images.len() + test.images.len(), all.images.len());
    assert_eq!(test.images[0].path, all.images[0].path);
    assert_eq!(train.images[0].path, all.images[1].path);
    assert!(Dataset::load(&dir.0, &LoadOptions { holdout_every: Some(3), ..LoadOptions::split(Split::Val) }).is_err());
    assert!("validation".parse::<Split>().is_err());
}

/// Corrupted bytes anywhere in the JSON or a PNG give an error or a load, never a panic.
#[test]
fn corrupted_files_never_panic() {
    let dir = synth_dir("fuzz", &tiny(SynthScene::Mixed));
    let json_path = dir.0.join("transforms_val.json");
    let png_path = dir.0.join("val/r_0.png");
    let (json, png_bytes) = (std::fs::read(&json_path).unwrap(), std::fs::read(&png_path).unwrap());
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let garbage = [b'0', b'-', b'e', b'"', b'{', b']', b'N', b',', 0xff, 0x00];
    for round in 0..60 {
        let (path, original) = if round % 2 == 0 { (&json_path, &json) } else { (&png_path, &png_bytes) };
        let mut bytes = original.clone();
        for _ in 0..1 + next() % 3 {
            let at = (next() % bytes.len() as u64) as usize;
            bytes[at] = garbage[(next() % garbage.len() as u64) as usize];
        }
        if next() % 4 == 0 {
            bytes.truncate((next() % bytes.len() as u64) as usize);
        }
        std::fs::write(path, &bytes).unwrap();
        let _ = load(&dir.0, Split::Val);
        let _ = inspect(&dir.0, None);
        std::fs::write(path, original).unwrap();
    }
}
