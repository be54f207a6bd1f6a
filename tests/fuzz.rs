//! Bounded fuzzing, run by CI: whatever bytes arrive — a pose message, a signaling text
//! frame, an asset file — the parser answers with an error or a value, never a panic.
//! Random inputs and mutations of valid ones (proptest), `NEPHELE_FUZZ_CASES` per property
//! (default 2,000; the asset property runs a tenth of that, each case parses 3 MB). A longer
//! run for humans: `NEPHELE_FUZZ_CASES=1000000 cargo test --release -p nephele-e2e --test fuzz`.

use std::time::Instant;

use glam::DVec3;
use nephele_wire::{FrameLayout, MultiViewPose, PoseMessage, PoseView, Viewport, check_pose};
use nephele_renderer::{
    Asset, Intrinsics, View,
    views::{QuiltLayout, projection_from_intrinsics},
};
use nephele_signaling::{ConnId, Hub, HubConfig};
use proptest::{collection::vec, prelude::*};

fn cases(divisor: u32) -> ProptestConfig {
    let n = std::env::var("NEPHELE_FUZZ_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(2000u32);
    ProptestConfig { cases: (n / divisor).max(1), failure_persistence: None, ..ProptestConfig::default() }
}

const LAYOUTS: [FrameLayout; 2] = [
    FrameLayout::Views { width: 128, height: 48 },
    FrameLayout::Quilt { width: 320, height: 432, layout: QuiltLayout { cols: 5, rows: 9, cone_rad: 0.7 }, focal_target: DVec3::ZERO, min_focal: 0.1 },
];

/// Valid messages to mutate: NPO1 at both layouts' sizes (and with a prediction), NPO2 with two
/// eyes and an anchor (and with a prediction).
fn seeds() -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    for (w, h) in [(128, 48), (64, 48)] {
        let v = View::orbit(DVec3::ZERO, 4.0, 30.0, 20.0, Intrinsics::from_fov_x(w, h, 0.8));
        let m = PoseMessage { seq: 5, t_client_ms: 1.0, world_from_camera: v.world_from_camera.as_mat4(), intrinsics: v.intrinsics, world_from_anchor: None, predicted: None };
        out.push(m.encode());
        let predicted = nephele_wire::Predicted { horizon_ms: 70.0, present_world_from_camera: v.world_from_camera.as_mat4() };
        out.push(PoseMessage { predicted: Some(predicted), ..m }.encode());
    }
    let k = Intrinsics::from_fov_x(64, 48, 0.8);
    let v = View::orbit(DVec3::ZERO, 4.0, 30.0, 20.0, k);
    let eye = |x| PoseView { world_from_camera: v.world_from_camera.as_mat4(), clip_from_camera: projection_from_intrinsics(&k, 0.1, 10.0), viewport: Viewport { x, y: 0, width: 64, height: 48 } };
    let stereo = MultiViewPose { seq: 6, t_client_ms: 2.0, frame_width: 128, frame_height: 48, views: vec![eye(0), eye(64)], world_from_anchor: Some(glam::Mat4::IDENTITY), predicted: None };
    out.push(stereo.encode());
    let present = vec![v.world_from_camera.as_mat4(); 2];
    out.push(MultiViewPose { predicted: Some((70.0, present)), ..stereo }.encode());
    out
}

proptest! {
    #![proptest_config(cases(1))]

    #[test]
    fn any_bytes_are_a_pose_or_an_error(bytes in vec(any::<u8>(), 0..1400)) {
        for layout in &LAYOUTS {
            let _ = check_pose(&bytes, layout);
        }
    }

    #[test]
    fn mutated_poses_are_a_pose_or_an_error(seed in 0usize..3, edits in vec((any::<u16>(), any::<u8>()), 1..8), cut in any::<u16>()) {
        let mut bytes = seeds()[seed].clone();
        for (at, value) in edits {
            let i = at as usize % bytes.len();
            bytes[i] = value;
        }
        if cut % 4 == 0 {
            bytes.truncate(cut as usize % (bytes.len() + 1));
        }
        for layout in &LAYOUTS {
            if let Ok(p) = check_pose(&bytes, layout) {
                // Whatever passes is a usable camera set.
                prop_assert!(!p.views.is_empty());
                for v in &p.views {
                    prop_assert!(v.view.validate().is_ok(), "{:?}: {:?}", v.view.validate(), v.view);
                }
            }
        }
    }

    #[test]
    fn any_signaling_text_is_handled(texts in vec(vec(any::<char>(), 0..200), 1..6), mutate in vec((any::<u16>(), any::<char>()), 0..4)) {
        let mut hub = Hub::new(HubConfig::default());
        let now = Instant::now();
        hub.connect(ConnId(1), now);
        hub.connect(ConnId(2), now);
        let _ = hub.handle_text(ConnId(2), r#"{"type":"register","name":"m","capacity":4,"scenes":["lego"]}"#, now);
        let valid = [
            r#"{"type":"join","scene":"lego","mode":"quilt","width":600,"height":1440,"fps":25,"quilt":{"cols":5,"rows":9,"cone_deg":40}}"#,
            r#"{"type":"offer","sdp":"v=0"}"#,
            r#"{"type":"ice","candidate":{"candidate":"x"}}"#,
            r#"{"type":"answer","session":"s1","sdp":"v=0"}"#,
            r#"{"type":"heartbeat","sessions":1,"free_rays_per_s":1e9,"saturated":false}"#,
        ];
        for (i, chars) in texts.iter().enumerate() {
            let mut text: Vec<char> = valid[i % valid.len()].chars().collect();
            for (at, c) in &mutate {
                let j = *at as usize % text.len();
                text[j] = *c;
            }
            let text: String = text.into_iter().collect();
            let random: String = chars.iter().collect();
            for (conn, t) in [(1, &text), (2, &text), (1, &random), (2, &random)] {
                let _ = hub.handle_text(ConnId(conn), t, now);
            }
        }
        let _ = hub.disconnect(ConnId(2), now);
        let _ = hub.disconnect(ConnId(1), now);
    }
}

proptest! {
    #![proptest_config(cases(10))]

    #[test]
    fn mutated_assets_load_or_fail_in_words(edits in vec((any::<u32>(), any::<u8>()), 1..6), cut in any::<u32>()) {
        static FIXTURE: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
        let original = FIXTURE.get_or_init(|| std::fs::read(nephele_e2e::repo().join("examples/assets/trio-small.nolf")).expect("the fixture asset"));
        let mut bytes = original.clone();
        // Edits near the start hit the header and metadata, the rest anywhere.
        for (k, (at, value)) in edits.iter().enumerate() {
            let span = if k % 2 == 0 { 4096.min(bytes.len()) } else { bytes.len() };
            bytes[*at as usize % span] = *value;
        }
        if cut % 3 == 0 {
            bytes.truncate(cut as usize % (bytes.len() + 1));
        }
        if let Err(e) = Asset::from_bytes(&bytes) {
            prop_assert!(!e.to_string().is_empty());
        }
    }
}
