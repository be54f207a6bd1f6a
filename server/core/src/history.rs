//! The history table of shared rendering (NEPHELE §6.2.1): identical requests are rendered
//! once. A request is identical when it asks for the same asset, over the same
//! background, at the same render size and intrinsics, with the object placed the same way,
//! and a camera pose equal within [`POSE_TOLERANCE`]: every entry of the camera-to-world
//! rotation within 1e-6, and the camera position within 1e-6 scene units per unit of its
//! distance from the origin (at least 1e-6 units). At 1e-6 rad a pixel at 1000 px focal
//! length moves by a thousandth of a pixel, far below one 8-bit level, so a hit is served the
//! stored frame itself. Typical hits: two viewers of the default view, a camera at rest.
//!
//! Entries are kept most-recent-first, at most [`HISTORY_ENTRIES`] of them and at most
//! [`HISTORY_BYTES`] of pixels; the oldest go first.

use std::{collections::VecDeque, sync::Arc};

use glam::{DMat4, Vec3};
use nephele_renderer::{Frame, Instance, Intrinsics};

/// Largest difference of pose entries that still counts as the same camera (see module).
pub const POSE_TOLERANCE: f64 = 1e-6;
/// Most frames remembered.
pub const HISTORY_ENTRIES: usize = 32;
/// Most pixel bytes remembered (RGBA + depth).
pub const HISTORY_BYTES: usize = 64 << 20;

/// What makes two render requests the same.
#[derive(Debug, Clone, PartialEq)]
pub struct RequestKey {
    pub asset: String,
    pub intrinsics: Intrinsics,
    pub background: Vec3,
    pub instance: Instance,
    pub world_from_camera: DMat4,
}

impl RequestKey {
    /// Same request within [`POSE_TOLERANCE`].
    pub fn matches(&self, other: &Self) -> bool {
        if self.asset != other.asset
            || self.intrinsics != other.intrinsics
            || self.background != other.background
            || self.instance != other.instance
        {
            return false;
        }
        let (a, b) = (self.world_from_camera, other.world_from_camera);
        let rotation_close = (0..3).all(|c| (a.col(c) - b.col(c)).abs().max_element() <= POSE_TOLERANCE);
        let (pa, pb) = (a.w_axis.truncate(), b.w_axis.truncate());
        let position_tolerance = POSE_TOLERANCE * pa.length().max(1.0);
        rotation_close && (pa - pb).abs().max_element() <= position_tolerance && a.row(3) == b.row(3)
    }
}

/// Recently rendered frames by request.
#[derive(Debug, Default)]
pub struct History {
    entries: VecDeque<(RequestKey, Arc<Frame>)>,
    bytes: usize,
    pub hits: u64,
    pub misses: u64,
}

fn frame_bytes(f: &Frame) -> usize {
    f.rgba.len() + 4 * f.depth.len()
}

impl History {
    /// The stored frame for `key`, if any (and moves it to the front).
    pub fn lookup(&mut self, key: &RequestKey) -> Option<Arc<Frame>> {
        match self.entries.iter().position(|(k, _)| k.matches(key)) {
            Some(i) => {
                let entry = self.entries.remove(i).expect("found");
                let frame = Arc::clone(&entry.1);
                self.entries.push_front(entry);
                self.hits += 1;
                Some(frame)
            }
            None => {
                self.misses += 1;
                None
            }
        }
    }

    /// Remembers a rendered frame.
    pub fn insert(&mut self, key: RequestKey, frame: Arc<Frame>) {
        if let Some(i) = self.entries.iter().position(|(k, _)| k.matches(&key)) {
            let (_, old) = self.entries.remove(i).expect("found");
            self.bytes -= frame_bytes(&old);
        }
        self.bytes += frame_bytes(&frame);
        self.entries.push_front((key, frame));
        while self.entries.len() > HISTORY_ENTRIES || (self.bytes > HISTORY_BYTES && self.entries.len() > 1) {
            let (_, old) = self.entries.pop_back().expect("non-empty");
            self.bytes -= frame_bytes(&old);
        }
    }

    /// Forgets every frame of `asset`.
    pub fn forget_asset(&mut self, asset: &str) {
        self.entries.retain(|(k, _)| k.asset != asset);
        self.bytes = self.entries.iter().map(|(_, f)| frame_bytes(f)).sum();
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;
    use nephele_renderer::View;

    fn key(azimuth_deg: f64, distance: f64) -> RequestKey {
        let view = View::orbit(DVec3::ZERO, distance, azimuth_deg, 20.0, Intrinsics::from_fov_x(64, 48, 0.8));
        RequestKey {
            asset: "lego".into(),
            intrinsics: view.intrinsics,
            background: Vec3::ONE,
            instance: Instance::default(),
            world_from_camera: view.world_from_camera,
        }
    }

    fn frame(tag: u8, pixels: usize) -> Arc<Frame> {
        Arc::new(Frame { width: pixels as u32, height: 1, rgba: vec![tag; 4 * pixels], depth: vec![1.0; pixels] })
    }

    #[test]
    fn tolerance_is_what_the_module_says() {
        let a = key(30.0, 4.0);
        // 5e-7 rad of azimuth moves rotation entries by ≤ 5e-7 and the position by 2e-6 at
        // distance 4 (tolerance 4e-6): the same request.
        assert!(a.matches(&key(30.0 + 5e-7f64.to_degrees(), 4.0)));
        // 3e-6 rad: rotation entries move by more than 1e-6.
        assert!(!a.matches(&key(30.0 + 3e-6f64.to_degrees(), 4.0)));
        // Far away the position tolerance scales with the distance.
        let far = key(30.0, 1e5);
        let mut moved = far.clone();
        moved.world_from_camera.w_axis.x += 0.05; // 5e-7 of 1e5
        assert!(far.matches(&moved));
        moved.world_from_camera.w_axis.x += 0.1;
        assert!(!far.matches(&moved));
        // Anything else differs → no match.
        let mut other = a.clone();
        other.asset = "trio".into();
        assert!(!a.matches(&other));
        let mut other = a.clone();
        other.background = Vec3::new(0.0, 1.0, 0.0);
        assert!(!a.matches(&other));
        let mut other = a.clone();
        other.intrinsics = other.intrinsics.scaled(0.5);
        assert!(!a.matches(&other));
        let mut other = a.clone();
        other.instance.scale = 2.0;
        assert!(!a.matches(&other));
    }

    #[test]
    fn hits_serve_the_stored_frame_and_old_entries_go() {
        let mut h = History::default();
        assert!(h.lookup(&key(0.0, 4.0)).is_none());
        let f = frame(7, 10);
        h.insert(key(0.0, 4.0), Arc::clone(&f));
        let hit = h.lookup(&key(0.0, 4.0)).unwrap();
        assert!(Arc::ptr_eq(&hit, &f));
        assert_eq!((h.hits, h.misses), (1, 1));
        // Re-inserting the same request replaces, not duplicates.
        h.insert(key(0.0, 4.0), frame(8, 10));
        assert_eq!(h.len(), 1);
        assert_eq!(h.lookup(&key(0.0, 4.0)).unwrap().rgba[0], 8);
        // Bounded by count: the least recently used go first.
        for i in 0..HISTORY_ENTRIES + 5 {
            h.insert(key(i as f64 + 1.0, 4.0), frame(1, 4));
        }
        assert_eq!(h.len(), HISTORY_ENTRIES);
        assert!(h.lookup(&key(1.0, 4.0)).is_none());
        assert!(h.lookup(&key((HISTORY_ENTRIES + 5) as f64, 4.0)).is_some());
        // Bounded by bytes: one huge frame pushes out everything older.
        h.insert(key(500.0, 4.0), frame(2, HISTORY_BYTES / 8 + 1));
        assert_eq!(h.len(), 1);
        h.forget_asset("lego");
        assert!(h.is_empty());
    }
}
