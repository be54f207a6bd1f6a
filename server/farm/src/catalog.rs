//! The scene catalogue of a process (master or render worker): each asset loaded once and
//! prepared on the chosen backend, and the scenes that place them — one asset, or a scene
//! file of several (`nephele_renderer::scene`) composed by depth. What the scheduler needs
//! to know of a scene is its [`SceneInfo`] (bounds, and a coarse proxy of each object for
//! cost estimates); the pixels stay here, with the workers.

use std::{collections::BTreeMap, path::Path, sync::Arc};

use anyhow::{Context, Result, bail};
use glam::{DVec3, Vec3};
use nephele_renderer::{
    Backend, Frame, Instance, PreparedAsset, RenderSettings, View, ViewRequest,
    compose::compose,
    scene::SceneFile,
};

use nephele_core::{ObjectInfo, SceneInfo, estimate::Proxy};

use crate::assets::{BUILTIN_SCENE_FILES, load_asset};

/// One asset, ready to render.
pub struct AssetEntry {
    pub name: String,
    /// Where it came from (`builtin:lego`, a path).
    pub spec: String,
    pub prepared: Box<dyn PreparedAsset>,
    pub proxy: Proxy,
}

/// Every scene and asset of this process, plus how to render them.
pub struct Catalog {
    pub assets: BTreeMap<String, Arc<AssetEntry>>,
    pub scenes: BTreeMap<String, SceneInfo>,
    pub default_scene: String,
    pub settings: RenderSettings,
    pub backend_name: String,
}

/// The name an asset is known by to masters and workers: `builtin:lego` → `lego`,
/// `path/duck.nolf` → `duck`.
pub fn asset_name_of(spec: &str) -> String {
    let base = spec.strip_prefix("builtin:").unwrap_or(spec);
    let base = Path::new(base).file_stem().and_then(|s| s.to_str()).unwrap_or(base);
    base.to_owned()
}

impl Catalog {
    /// `specs` are `name=asset`, `name=scene.json`, or a bare asset or scene file
    /// (`builtin:trio` → scene `trio`, `path/duo.json` → `duo`, `builtin:duo` the shipped
    /// scene file). The first is the default.
    pub fn load(specs: &[String], backend: &dyn Backend, settings: RenderSettings) -> Result<Self> {
        if specs.is_empty() {
            bail!("no scenes to serve");
        }
        let mut catalog = Self { assets: BTreeMap::new(), scenes: BTreeMap::new(), default_scene: String::new(), settings, backend_name: backend.name() };
        for spec in specs {
            let (name, source) = match spec.split_once('=') {
                Some((n, a)) => (n.to_owned(), a),
                None => (asset_name_of(spec), spec.as_str()),
            };
            if !nephele_protocol::is_valid_name(&name) {
                bail!("scene name {name:?} must be 1..=64 characters from [A-Za-z0-9_-] (write name=asset)");
            }
            let builtin_scene = source.strip_prefix("builtin:").and_then(|b| BUILTIN_SCENE_FILES.iter().find(|(n, _)| *n == b));
            let scene = if source.ends_with(".json") || builtin_scene.is_some() {
                let file = match builtin_scene {
                    Some((_, text)) => SceneFile::parse(text).with_context(|| format!("built-in scene {name}"))?,
                    None => SceneFile::load(Path::new(source)).with_context(|| format!("scene {name}"))?,
                };
                let mut objects = Vec::new();
                for (asset_spec, object) in file.asset_specs(Path::new(source)).iter().zip(&file.objects) {
                    let asset = catalog.add_asset(asset_spec, backend).with_context(|| format!("scene {name} ({source})"))?;
                    let instance = object.world_from_object.instance().map_err(anyhow::Error::msg)?;
                    objects.push(ObjectInfo { asset: asset.name.clone(), instance, proxy: asset.proxy.clone() });
                }
                scene_info(&name, file.background(), objects, &catalog)
            } else {
                let asset = catalog.add_asset(source, backend).with_context(|| format!("scene {name}"))?;
                let objects = vec![ObjectInfo { asset: asset.name.clone(), instance: Instance::default(), proxy: asset.proxy.clone() }];
                scene_info(&name, Vec3::ONE, objects, &catalog)
            };
            if catalog.default_scene.is_empty() {
                catalog.default_scene = name.clone();
            }
            if catalog.scenes.insert(name.clone(), scene).is_some() {
                bail!("scene {name:?} is given twice");
            }
        }
        Ok(catalog)
    }

    /// Loads and prepares an asset once; the same spec twice is the same asset, two specs
    /// with one name are an error.
    fn add_asset(&mut self, spec: &str, backend: &dyn Backend) -> Result<Arc<AssetEntry>> {
        let name = asset_name_of(spec);
        if let Some(existing) = self.assets.get(&name) {
            if existing.spec != spec {
                bail!("two assets are both named {name:?} ({} and {spec}); rename one file", existing.spec);
            }
            return Ok(Arc::clone(existing));
        }
        if !nephele_protocol::is_valid_name(&name) {
            bail!("asset {spec:?} would be named {name:?}: names are 1..=64 characters from [A-Za-z0-9_-]; rename the file");
        }
        let asset = load_asset(spec)?;
        let proxy = Proxy::from_density(&asset.density);
        let prepared = backend.prepare(asset).with_context(|| format!("preparing asset {name}"))?;
        let entry = Arc::new(AssetEntry { name: name.clone(), spec: spec.to_owned(), prepared, proxy });
        self.assets.insert(name, Arc::clone(&entry));
        Ok(entry)
    }

    pub fn names(&self) -> Vec<String> {
        self.scenes.keys().cloned().collect()
    }

    pub fn asset_names(&self) -> Vec<String> {
        self.assets.keys().cloned().collect()
    }

    pub fn infos(&self) -> Vec<SceneInfo> {
        self.scenes.values().cloned().collect()
    }

    /// The prepared asset of a one-object scene.
    pub fn single_asset(&self, scene: &str) -> Option<&dyn PreparedAsset> {
        let s = self.scenes.get(scene)?;
        if s.objects.len() != 1 {
            return None;
        }
        self.assets.get(&s.objects[0].asset).map(|a| a.prepared.as_ref())
    }

    /// A direct render of `scene` from `view` (the reference streamed frames are compared
    /// with): each object placed by `anchor ∘ its placement`; several objects rendered over
    /// black and composed by depth over `background`.
    pub fn render_scene(&self, scene: &str, view: View, anchor: Instance, background: Vec3) -> Result<Frame> {
        let s = self.scenes.get(scene).with_context(|| format!("no scene {scene:?}"))?;
        let layer_background = if s.composed() { Vec3::ZERO } else { background };
        let mut layers = Vec::new();
        for o in &s.objects {
            let asset = self.assets.get(&o.asset).with_context(|| format!("no asset {:?}", o.asset))?;
            let req = ViewRequest { view, instance: anchor.then_inside(&o.instance), background: layer_background };
            layers.push(asset.prepared.render(&[req], &self.settings)?.frames.remove(0));
        }
        if layers.len() == 1 {
            return Ok(layers.remove(0));
        }
        Ok(compose(&layers.iter().collect::<Vec<_>>(), background)?)
    }
}

/// Bounds of the placed objects, as one sphere.
fn scene_info(name: &str, background: Vec3, objects: Vec<ObjectInfo>, catalog: &Catalog) -> SceneInfo {
    let spheres: Vec<(DVec3, f64)> = objects
        .iter()
        .map(|o| {
            let b = catalog.assets[&o.asset].prepared.asset().bounds;
            let (c, r) = (((b.min + b.max) * 0.5).as_dvec3(), f64::from((b.max - b.min).length() * 0.5));
            (o.instance.world_from_object().transform_point3(c), r * o.instance.scale)
        })
        .collect();
    let lo = spheres.iter().fold(DVec3::splat(f64::MAX), |a, (c, r)| a.min(*c - *r));
    let hi = spheres.iter().fold(DVec3::splat(f64::MIN), |a, (c, r)| a.max(*c + *r));
    let center = 0.5 * (lo + hi);
    let radius = spheres.iter().map(|(c, r)| (*c - center).length() + r).fold(0.0, f64::max);
    SceneInfo { name: name.into(), center: center.as_vec3(), radius: radius as f32, background, objects }
}
