//! The scene catalogue of a master: each asset loaded once, prepared on the chosen backend
//! and shared by every render worker of the process, with what the scheduler needs to know
//! of it ([`SceneInfo`]: bounds and the coarse proxy for cost estimates).

use std::{collections::BTreeMap, sync::Arc};

use anyhow::{Context, Result, bail};
use nephele_renderer::{Backend, PreparedAsset, RenderSettings};

use crate::{
    assets::load_asset,
    master::core::{SceneInfo, estimate::Proxy},
};

/// One servable scene.
pub struct SceneEntry {
    pub prepared: Box<dyn PreparedAsset>,
    pub info: SceneInfo,
}

/// Every scene of this master, plus how to render them.
pub struct Catalog {
    pub scenes: BTreeMap<String, Arc<SceneEntry>>,
    pub default_scene: String,
    pub settings: RenderSettings,
    pub backend_name: String,
}

impl Catalog {
    /// `specs` are `name=asset` or a bare asset (`builtin:trio` → named `trio`,
    /// `path/lego.nolf` → `lego`). The first is the default.
    pub fn load(specs: &[String], backend: &dyn Backend, settings: RenderSettings) -> Result<Self> {
        if specs.is_empty() {
            bail!("no scenes to serve");
        }
        let mut scenes = BTreeMap::new();
        let mut default_scene = None;
        for spec in specs {
            let (name, asset_spec) = match spec.split_once('=') {
                Some((n, a)) => (n.to_owned(), a),
                None => (scene_name_of(spec), spec.as_str()),
            };
            if !nephele_signaling::protocol::is_valid_name(&name) {
                bail!("scene name {name:?} must be 1..=64 characters from [A-Za-z0-9_-] (write name=asset)");
            }
            let asset = load_asset(asset_spec)?;
            let b = asset.bounds;
            let info = SceneInfo {
                name: name.clone(),
                center: (b.min + b.max) * 0.5,
                radius: (b.max - b.min).length() * 0.5,
                proxy: Proxy::from_density(&asset.density),
            };
            let prepared = backend.prepare(asset).with_context(|| format!("preparing scene {name}"))?;
            default_scene.get_or_insert_with(|| name.clone());
            if scenes.insert(name.clone(), Arc::new(SceneEntry { prepared, info })).is_some() {
                bail!("scene {name:?} is given twice");
            }
        }
        Ok(Self { scenes, default_scene: default_scene.expect("at least one scene"), settings, backend_name: backend.name() })
    }

    pub fn names(&self) -> Vec<String> {
        self.scenes.keys().cloned().collect()
    }

    pub fn infos(&self) -> Vec<SceneInfo> {
        self.scenes.values().map(|s| s.info.clone()).collect()
    }
}

fn scene_name_of(spec: &str) -> String {
    let base = spec.strip_prefix("builtin:").unwrap_or(spec);
    let base = std::path::Path::new(base).file_stem().and_then(|s| s.to_str()).unwrap_or(base);
    base.to_owned()
}
