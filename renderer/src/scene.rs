//! Scene files: several assets placed in one world and composed by depth (NEPHELE §5.1,
//! §6.1). JSON:
//!
//! ```json
//! { "background": [1, 1, 1],
//!   "objects": [
//!     { "asset": "builtin:lego",
//!       "world_from_object": { "rotation": [0, 0, 0, 1], "translation": [-0.8, 0, 0], "scale": 0.7 } },
//!     { "asset": "trio.nolf" } ] }
//! ```
//!
//! `asset` is a `.nolf` path (relative to the scene file) or `builtin:<name>`;
//! `world_from_object` places the object: `rotation` a unit quaternion `[x, y, z, w]`
//! (default identity), `translation` in scene units (default 0), `scale` a uniform factor
//! (default 1). `background` is the linear RGB behind everything in viewer mode (default
//! white). At most [`MAX_SCENE_OBJECTS`] objects: each is a layer of the composition.

use std::path::{Path, PathBuf};

use glam::{DQuat, DVec3, Vec3};
use serde::{Deserialize, Serialize};

use crate::{camera::Instance, compose::MAX_LAYERS};

/// Most objects in one scene (each is one layer of the depth composition).
pub const MAX_SCENE_OBJECTS: usize = MAX_LAYERS;
/// Longest scene file read, bytes.
pub const MAX_SCENE_FILE_BYTES: u64 = 1 << 20;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Placement {
    #[serde(default = "identity_rotation")]
    pub rotation: [f64; 4],
    #[serde(default)]
    pub translation: [f64; 3],
    #[serde(default = "unit_scale")]
    pub scale: f64,
}

fn identity_rotation() -> [f64; 4] {
    [0.0, 0.0, 0.0, 1.0]
}

fn unit_scale() -> f64 {
    1.0
}

impl Default for Placement {
    fn default() -> Self {
        Self { rotation: identity_rotation(), translation: [0.0; 3], scale: 1.0 }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneObject {
    pub asset: String,
    #[serde(default)]
    pub world_from_object: Placement,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    #[serde(default)]
    pub background: Option<[f32; 3]>,
    pub objects: Vec<SceneObject>,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SceneError {
    #[error("cannot read scene file {path}: {message}")]
    Read { path: String, message: String },
    #[error("scene file is {0} bytes; the limit is {MAX_SCENE_FILE_BYTES}")]
    TooLarge(u64),
    #[error("scene file is not valid: {0}")]
    Json(String),
    #[error("a scene needs at least one object")]
    NoObjects,
    #[error("the scene has {0} objects; at most {MAX_SCENE_OBJECTS} are composed into one frame")]
    TooManyObjects(usize),
    #[error("object {index} ({asset}): {reason}")]
    Placement { index: usize, asset: String, reason: String },
    #[error("background must be three finite values in [0, 1]")]
    Background,
}

impl Placement {
    /// The placement as an instance transform, validated.
    pub fn instance(&self) -> Result<Instance, String> {
        let q = DQuat::from_array(self.rotation);
        if !q.is_finite() || !DVec3::from_array(self.translation).is_finite() || !self.scale.is_finite() {
            return Err("world_from_object has a non-finite value (NaN or infinity)".into());
        }
        let len = q.length();
        if (len - 1.0).abs() > 1e-3 {
            return Err(format!("rotation must be a unit quaternion [x, y, z, w]; its length is {len:.4}"));
        }
        if !(1e-6..=1e6).contains(&self.scale) {
            return Err(format!("scale {} is outside 1e-6..=1e6", self.scale));
        }
        if DVec3::from_array(self.translation).length() > crate::camera::MAX_CAMERA_DISTANCE {
            return Err("translation is too far from the origin".into());
        }
        Ok(Instance { rotation: q.normalize(), translation: DVec3::from_array(self.translation), scale: self.scale })
    }
}

impl SceneFile {
    /// Parses and validates scene JSON.
    pub fn parse(text: &str) -> Result<Self, SceneError> {
        let scene: Self = serde_json::from_str(text).map_err(|e| SceneError::Json(e.to_string()))?;
        scene.validate()?;
        Ok(scene)
    }

    /// Reads and validates a scene file.
    pub fn load(path: &Path) -> Result<Self, SceneError> {
        let err = |message: String| SceneError::Read { path: path.display().to_string(), message };
        let len = std::fs::metadata(path).map_err(|e| err(e.to_string()))?.len();
        if len > MAX_SCENE_FILE_BYTES {
            return Err(SceneError::TooLarge(len));
        }
        Self::parse(&std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?)
    }

    pub fn validate(&self) -> Result<(), SceneError> {
        if self.objects.is_empty() {
            return Err(SceneError::NoObjects);
        }
        if self.objects.len() > MAX_SCENE_OBJECTS {
            return Err(SceneError::TooManyObjects(self.objects.len()));
        }
        for (index, o) in self.objects.iter().enumerate() {
            o.world_from_object.instance().map_err(|reason| SceneError::Placement { index, asset: o.asset.clone(), reason })?;
        }
        if let Some(bg) = self.background
            && !bg.iter().all(|c| c.is_finite() && (0.0..=1.0).contains(c))
        {
            return Err(SceneError::Background);
        }
        Ok(())
    }

    /// Viewer-mode background (white unless the file says otherwise).
    pub fn background(&self) -> Vec3 {
        self.background.map_or(Vec3::ONE, Vec3::from_array)
    }

    /// Each object's asset spec, with paths made relative to the scene file's folder.
    pub fn asset_specs(&self, scene_path: &Path) -> Vec<String> {
        let dir = scene_path.parent().unwrap_or(Path::new("."));
        self.objects
            .iter()
            .map(|o| {
                if o.asset.starts_with("builtin:") || Path::new(&o.asset).is_absolute() {
                    o.asset.clone()
                } else {
                    PathBuf::from(dir).join(&o.asset).display().to_string()
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scene_file_reads_and_places_its_objects() {
        let s = SceneFile::parse(
            r#"{"background":[0,0,0],"objects":[
                {"asset":"builtin:lego","world_from_object":{"rotation":[0,0,0.7071068,0.7071068],"translation":[1,2,3],"scale":0.5}},
                {"asset":"trio.nolf"}]}"#,
        )
        .unwrap();
        assert_eq!(s.background(), Vec3::ZERO);
        let i = s.objects[0].world_from_object.instance().unwrap();
        assert!((i.rotation.mul_vec3(DVec3::X) - DVec3::Y).length() < 1e-6);
        assert_eq!((i.translation, i.scale), (DVec3::new(1.0, 2.0, 3.0), 0.5));
        assert_eq!(s.objects[1].world_from_object.instance().unwrap(), Instance::default());
        assert_eq!(s.asset_specs(Path::new("/scenes/duo.json")), vec!["builtin:lego".to_string(), "/scenes/trio.nolf".to_string()]);
    }

    #[test]
    fn bad_scene_files_say_what_is_wrong() {
        let cases = [
            ("{", "not valid"),
            (r#"{"objects":[]}"#, "at least one object"),
            (r#"{"objects":[{"asset":"a","world_from_object":{"scale":"big"}}]}"#, "not valid"),
            (r#"{"objects":[{"asset":"a","extra":1}]}"#, "unknown field"),
            (r#"{"objects":[{"asset":"a","world_from_object":{"rotation":[0,0,0,2]}}]}"#, "unit quaternion"),
            (r#"{"objects":[{"asset":"a","world_from_object":{"scale":0}}]}"#, "scale 0 is outside"),
            (r#"{"objects":[{"asset":"a","world_from_object":{"scale":-1}}]}"#, "scale -1 is outside"),
            (r#"{"objects":[{"asset":"a","world_from_object":{"translation":[1e300,0,0]}}]}"#, "too far"),
            (r#"{"background":[2,0,0],"objects":[{"asset":"a"}]}"#, "background"),
        ];
        for (text, words) in cases {
            let e = SceneFile::parse(text).unwrap_err().to_string();
            assert!(e.contains(words), "{text}: {e}");
        }
        // JSON has no NaN literal, but a placement built in code can carry one.
        let nan = Placement { scale: f64::NAN, ..Placement::default() };
        assert!(nan.instance().unwrap_err().contains("non-finite"));
        let many = format!(r#"{{"objects":[{}]}}"#, vec![r#"{"asset":"a"}"#; 100].join(","));
        assert_eq!(SceneFile::parse(&many).unwrap_err(), SceneError::TooManyObjects(100));
    }
}
