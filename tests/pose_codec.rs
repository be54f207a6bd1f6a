//! The pages' pose messages (`web/pose.js`, run by Node) are the master's
//! (`nephele_wire`): `NPO1` and `NPO2`, with and without an anchor and a prediction, decode
//! in Rust to what the page encoded, and pass the master's checks.

use std::process::Command;

use glam::{DMat4, DVec3, Mat4};
use nephele_renderer::{Intrinsics, View};
use nephele_wire::{FrameLayout, MultiViewPose, PoseMessage, check_pose};

/// Runs `body` (JavaScript with `pose` bound to web/pose.js and `input` to the JSON
/// argument) and returns the bytes it prints as a JSON array of arrays.
fn page_encodes(body: &str, input: &serde_json::Value) -> Vec<Vec<u8>> {
    let js = nephele_e2e::repo().join("web/pose.js");
    let script = format!(
        "const pose = await import({url});\nconst input = JSON.parse(process.argv[1]);\nconst out = (() => {{ {body} }})();\nconsole.log(JSON.stringify(out.map((b) => Array.from(b))));",
        url = serde_json::to_string(&format!("file://{}", js.display())).unwrap()
    );
    let o = Command::new("node").args(["--input-type=module", "-e", &script, &input.to_string()]).output().expect("node runs (tests/run installs Node.js)");
    assert!(o.status.success(), "node failed: {}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&o.stdout)))
}

fn camera(azimuth_deg: f64) -> Mat4 {
    View::orbit(DVec3::ZERO, 4.0, azimuth_deg, 20.0, Intrinsics::from_fov_x(64, 48, 0.8)).world_from_camera.as_mat4()
}

#[test]
fn single_camera_messages_agree() {
    let (predicted, present) = (camera(35.0), camera(30.0));
    let anchor = Mat4::from_scale(glam::Vec3::splat(0.5));
    let input = serde_json::json!({
        "predicted": predicted.to_cols_array(), "present": present.to_cols_array(), "anchor": anchor.to_cols_array(),
    });
    let body = "const k = { fx: 50, fy: 50, cx: 32, cy: 24 };
        const base = { seq: 7, tClientMs: 1234.5, worldFromCamera: input.predicted, intrinsics: k, width: 64, height: 48 };
        const predicted = { horizonMs: 80, presentWorldFromCamera: input.present };
        return [pose.encodePose(base), pose.encodePose({ ...base, worldFromAnchor: input.anchor }),
                pose.encodePose({ ...base, predicted }), pose.encodePose({ ...base, worldFromAnchor: input.anchor, predicted })];";
    let messages = page_encodes(body, &input);
    assert_eq!(messages.iter().map(Vec::len).collect::<Vec<_>>(), [104, 168, 176, 240]);
    for (i, bytes) in messages.iter().enumerate() {
        let m = PoseMessage::decode(bytes).unwrap_or_else(|e| panic!("message {i}: {e}"));
        assert_eq!((m.seq, m.t_client_ms, m.world_from_camera), (7, 1234.5, predicted));
        assert_eq!(m.world_from_anchor, (i % 2 == 1).then_some(anchor));
        match m.predicted {
            Some(p) => assert_eq!((i >= 2, p.horizon_ms, p.present_world_from_camera), (true, 80.0, present)),
            None => assert!(i < 2),
        }
        let checked = check_pose(bytes, &FrameLayout::Views { width: 64, height: 48 }).unwrap_or_else(|e| panic!("message {i}: {e}"));
        assert_eq!(checked.predicted_ms, if i >= 2 { 80.0 } else { 0.0 });
    }
}

#[test]
fn multi_view_messages_agree() {
    let eye = |dx: f64| (camera(35.0).as_dmat4() * DMat4::from_translation(DVec3::new(dx, 0.0, 0.0))).as_mat4();
    let present = |dx: f64| (camera(32.0).as_dmat4() * DMat4::from_translation(DVec3::new(dx, 0.0, 0.0))).as_mat4();
    let input = serde_json::json!({
        "eyes": [eye(-0.03).to_cols_array(), eye(0.03).to_cols_array()],
        "present": [present(-0.03).to_cols_array(), present(0.03).to_cols_array()],
    });
    let body = "const clip = pose.projectionFromIntrinsics({ fx: 50, fy: 50, cx: 32, cy: 24 }, 64, 48, 0.05);
        const views = input.eyes.map((m, i) => ({ worldFromCamera: m, clipFromCamera: clip, viewport: [64 * i, 0, 64, 48] }));
        const base = { seq: 9, tClientMs: 5, width: 128, height: 48, views };
        return [pose.encodePoseViews(base), pose.encodePoseViews({ ...base, predicted: { horizonMs: 60, presentViews: input.present } })];";
    let messages = page_encodes(body, &input);
    let layout = FrameLayout::Views { width: 128, height: 48 };
    let plain = MultiViewPose::decode(&messages[0]).unwrap();
    assert!(plain.predicted.is_none());
    let with = MultiViewPose::decode(&messages[1]).unwrap();
    assert_eq!(with.predicted, Some((60.0, vec![present(-0.03), present(0.03)])));
    assert_eq!(with.views.iter().map(|v| v.world_from_camera).collect::<Vec<_>>(), [eye(-0.03), eye(0.03)]);
    assert_eq!(check_pose(&messages[0], &layout).unwrap().predicted_ms, 0.0);
    assert_eq!(check_pose(&messages[1], &layout).unwrap().predicted_ms, 60.0);
}
