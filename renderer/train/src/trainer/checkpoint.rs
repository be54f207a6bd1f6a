//! Trainer checkpoints: one safetensors file holding everything a [`Trainer`] needs to take
//! the same next step as an uninterrupted run — field parameters, Adam moments and step
//! counts, the occupancy grid (estimates and bits), the step and the [`TrainConfig`] (which
//! holds the seed; batches and occupancy samples are drawn from `(seed, step)`, so there is
//! no further RNG state). Gradients are not stored: Adam leaves them zeroed after each step.
//!
//! The file is the renderer's [`container`], like the `.nolf` asset: `__metadata__` holds
//! versioned JSON (`ngp_checkpoint`) and its SHA-256 (`ngp_checkpoint_sha256`); the JSON holds
//! a SHA-256 per tensor. Loading checks the container, the checksums, the configuration's
//! ranges and every tensor's dtype and shape against the configuration before allocating
//! anything sized by it. Every failure is a [`CheckpointError`]; nothing panics on a bad file.

use std::path::Path;

use nephele_renderer::{
    container::{self, ContainerError, Reader, Tensor, Verify},
    ngp::{OccupancyGrid, field::GEO_FEATURES, hash_grid::FEATURES_PER_LEVEL, mlp::Mlp},
    sh::SH_COEFFS,
};
use safetensors::Dtype;
use serde::{Deserialize, Serialize};

use super::{TrainConfig, Trainer};
use crate::adam::Adam;

pub const CHECKPOINT_FORMAT: &str = "nephele-ngp-checkpoint";
pub const CHECKPOINT_VERSION: u32 = 1;
/// The `__metadata__` key of the JSON.
const META_KEY: &str = "ngp_checkpoint";
/// Files above this size are refused before reading.
pub const MAX_CHECKPOINT_BYTES: u64 = 4 << 30;

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("cannot read checkpoint {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("cannot write checkpoint {path}: {source}")]
    Write { path: String, source: std::io::Error },
    #[error("checkpoint is {0} bytes; the limit is {MAX_CHECKPOINT_BYTES}")]
    TooLarge(u64),
    /// The container, the metadata checksum, or a tensor's dtype, shape or checksum.
    #[error("not a valid checkpoint file: {0}")]
    Container(#[from] ContainerError),
    #[error("checkpoint format {found:?} version {version} is not supported (this build reads {CHECKPOINT_FORMAT:?} version {CHECKPOINT_VERSION})")]
    Version { found: String, version: u32 },
    #[error("checkpoint content is invalid: {0}")]
    Invalid(String),
    #[error("checkpoint was trained with a different configuration ({differs}); use the same preset or start afresh")]
    ConfigMismatch { differs: String },
}

/// The JSON in the safetensors header (followed there by the tensor checksums).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointMeta {
    pub format: String,
    pub version: u32,
    /// Training stage: "ngp".
    pub stage: String,
    /// Optimisation steps taken.
    pub step: u64,
    /// Adam step counts of the grid, density-MLP and colour-MLP groups.
    pub adam_steps: [u32; 3],
    pub config: TrainConfig,
    /// Free-form: dataset, preset, … (not used when loading).
    pub provenance: serde_json::Value,
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn u64_bytes(v: &[u64]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn f32_from(bytes: &[u8]) -> Vec<f32> {
    bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

fn u64_from(bytes: &[u8]) -> Vec<u64> {
    bytes.chunks_exact(8).map(|c| u64::from_le_bytes(std::array::from_fn(|i| c[i]))).collect()
}

/// Widths of the density and colour MLPs a configuration implies.
fn mlp_widths(config: &TrainConfig) -> (Vec<usize>, Vec<usize>) {
    let mut density = vec![config.field.grid.levels as usize * FEATURES_PER_LEVEL];
    density.extend(&config.field.density_hidden);
    density.push(GEO_FEATURES);
    let mut colour = vec![GEO_FEATURES + SH_COEFFS];
    colour.extend(&config.field.colour_hidden);
    colour.push(3);
    (density, colour)
}

/// Tensor names, dtypes and shapes implied by a (validated) configuration.
fn expected_tensors(config: &TrainConfig) -> Vec<(&'static str, Dtype, Vec<usize>)> {
    let layout = config.field.grid.layout();
    let entries = layout.last().map_or(0, |l| l.first_entry + l.entries);
    let (dw, cw) = mlp_widths(config);
    let (grid, density, colour) = (vec![entries, FEATURES_PER_LEVEL], vec![Mlp::count(&dw)], vec![Mlp::count(&cw)]);
    let r = config.occupancy.resolution as usize;
    vec![
        ("field.grid", Dtype::F32, grid.clone()),
        ("field.density_mlp", Dtype::F32, density.clone()),
        ("field.colour_mlp", Dtype::F32, colour.clone()),
        ("adam.grid.m", Dtype::F32, grid.clone()),
        ("adam.grid.v", Dtype::F32, grid),
        ("adam.density_mlp.m", Dtype::F32, density.clone()),
        ("adam.density_mlp.v", Dtype::F32, density),
        ("adam.colour_mlp.m", Dtype::F32, colour.clone()),
        ("adam.colour_mlp.v", Dtype::F32, colour),
        ("occupancy.density", Dtype::F32, vec![r, r, r]),
        ("occupancy.bits", Dtype::U64, vec![(r * r * r).div_ceil(64)]),
    ]
}

/// Top-level fields (and field sub-fields) where two configurations differ, by name.
fn config_differences(a: &TrainConfig, b: &TrainConfig) -> String {
    let (Ok(serde_json::Value::Object(a)), Ok(serde_json::Value::Object(b))) = (serde_json::to_value(a), serde_json::to_value(b)) else {
        return "unknown".into();
    };
    let mut out = Vec::new();
    for (key, va) in &a {
        let vb = b.get(key);
        if Some(va) != vb {
            out.push(format!("{key}: checkpoint {va}, requested {}", vb.map_or("none".into(), |v| v.to_string())));
        }
    }
    out.join("; ")
}

impl Trainer {
    /// Serialises the full training state. `provenance` is stored as-is (e.g. dataset and
    /// preset names).
    pub fn checkpoint_bytes(&self, provenance: serde_json::Value) -> Result<Vec<u8>, CheckpointError> {
        let (gm, gv) = self.adam_grid.moments();
        let (dm, dv) = self.adam_density.moments();
        let (cm, cv) = self.adam_colour.moments();
        let data: Vec<Vec<u8>> = vec![
            f32_bytes(&self.field.grid.params),
            f32_bytes(self.field.density_mlp.params()),
            f32_bytes(self.field.colour_mlp.params()),
            f32_bytes(gm),
            f32_bytes(gv),
            f32_bytes(dm),
            f32_bytes(dv),
            f32_bytes(cm),
            f32_bytes(cv),
            f32_bytes(self.occupancy.densities()),
            u64_bytes(self.occupancy.bits()),
        ];
        let meta = CheckpointMeta {
            format: CHECKPOINT_FORMAT.into(),
            version: CHECKPOINT_VERSION,
            stage: "ngp".into(),
            step: self.step,
            adam_steps: [self.adam_grid.steps(), self.adam_density.steps(), self.adam_colour.steps()],
            config: self.config.clone(),
            provenance,
        };
        let tensors: Vec<Tensor<'_>> =
            expected_tensors(&self.config).into_iter().zip(&data).map(|((name, dtype, shape), bytes)| Tensor { name, dtype, shape, data: bytes }).collect();
        Ok(container::write(META_KEY, &meta, &tensors)?)
    }

    /// Writes a checkpoint atomically (to a temporary file beside `path`, then renamed), so an
    /// interrupted save leaves the previous checkpoint intact.
    pub fn save_checkpoint(&self, path: &Path, provenance: serde_json::Value) -> Result<(), CheckpointError> {
        let bytes = self.checkpoint_bytes(provenance)?;
        let write = |source| CheckpointError::Write { path: path.display().to_string(), source };
        let mut tmp = path.as_os_str().to_owned();
        tmp.push(".partial");
        let tmp = std::path::PathBuf::from(tmp);
        std::fs::write(&tmp, bytes).map_err(write)?;
        std::fs::rename(&tmp, path).map_err(write)
    }

    /// Reads a checkpoint; with `expected`, its configuration must equal that one.
    pub fn load_checkpoint(path: &Path, expected: Option<&TrainConfig>) -> Result<(Self, CheckpointMeta), CheckpointError> {
        let io = |source| CheckpointError::Io { path: path.display().to_string(), source };
        let len = std::fs::metadata(path).map_err(io)?.len();
        if len > MAX_CHECKPOINT_BYTES {
            return Err(CheckpointError::TooLarge(len));
        }
        Self::from_checkpoint_bytes(&std::fs::read(path).map_err(io)?, expected)
    }

    /// Parses and validates checkpoint bytes; see [`Self::load_checkpoint`].
    pub fn from_checkpoint_bytes(bytes: &[u8], expected: Option<&TrainConfig>) -> Result<(Self, CheckpointMeta), CheckpointError> {
        let file = Reader::new(bytes, META_KEY, Verify::Always)?;
        let meta: CheckpointMeta = file.meta()?;
        if meta.format != CHECKPOINT_FORMAT || meta.version != CHECKPOINT_VERSION {
            return Err(CheckpointError::Version { found: meta.format, version: meta.version });
        }
        meta.config.validate().map_err(CheckpointError::Invalid)?;
        if let Some(want) = expected
            && *want != meta.config
        {
            return Err(CheckpointError::ConfigMismatch { differs: config_differences(&meta.config, want) });
        }
        let tensors = expected_tensors(&meta.config)
            .into_iter()
            .map(|(name, dtype, shape)| file.tensor(name, dtype, &shape))
            .collect::<Result<Vec<_>, _>>()?;
        let f = |i: usize| f32_from(tensors[i]);
        let params = [f(0), f(1), f(2)];
        if params.iter().flatten().any(|v| !v.is_finite()) {
            return Err(CheckpointError::Invalid("non-finite field parameters".into()));
        }
        let mut trainer = Trainer::new(meta.config.clone());
        trainer.field.grid.params = params[0].clone();
        trainer.field.density_mlp.update(|p| p.copy_from_slice(&params[1]));
        trainer.field.colour_mlp.update(|p| p.copy_from_slice(&params[2]));
        let adam = meta.config.adam;
        trainer.adam_grid = Adam::from_state(adam, f(3), f(4), meta.adam_steps[0]);
        trainer.adam_density = Adam::from_state(adam, f(5), f(6), meta.adam_steps[1]);
        trainer.adam_colour = Adam::from_state(adam, f(7), f(8), meta.adam_steps[2]);
        trainer.occupancy = OccupancyGrid::from_state(meta.config.bounds, meta.config.occupancy.resolution, f(9), u64_from(tensors[10]))
            .ok_or_else(|| CheckpointError::Invalid("occupancy grid does not fit its resolution".into()))?;
        trainer.step = meta.step;
        Ok((trainer, meta))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{
        dataset::{Dataset, LoadOptions},
        synth::{self, SynthConfig, SynthScene},
        test_util::TempDir,
    };

    fn small_config() -> TrainConfig {
        let mut config = TrainConfig::tiny();
        config.rays_per_batch = 256;
        config.occupancy.warmup_steps = 4;
        config.occupancy.update_every = 4;
        config.occupancy.fraction_per_update = 0.5;
        config
    }

    #[test]
    fn train_checkpoint_resumes_bit_identically_and_rejects_bad_files() {
        let dir = TempDir::new("ckpt");
        let cfg = SynthConfig { width: 16, height: 16, n_train: 2, n_val: 0, n_test: 0, ..SynthConfig::new(SynthScene::Diffuse) };
        synth::generate(&cfg, &dir.0).unwrap();
        let data = Dataset::load(&dir.0, &LoadOptions::default()).unwrap();

        // 10 steps (past the occupancy warm-up, so partial updates are in play), save, load.
        let mut a = Trainer::new(small_config());
        for _ in 0..10 {
            a.train_step(&data);
        }
        let path = dir.0.join("ngp.ckpt");
        a.save_checkpoint(&path, serde_json::json!({"test": true})).unwrap();
        let (mut b, meta) = Trainer::load_checkpoint(&path, Some(&small_config())).unwrap();
        assert_eq!((meta.step, b.step), (10, 10));
        for _ in 0..3 {
            let (sa, sb) = (a.train_step(&data), b.train_step(&data));
            assert_eq!(sa.batch.loss.to_bits(), sb.batch.loss.to_bits(), "step {}", sa.step);
        }
        // (The safetensors header's metadata map is unordered, so compare state, not bytes.)
        assert!(a.field == b.field, "field parameters differ");
        assert!(a.occupancy.bits() == b.occupancy.bits(), "occupancy differs");
        assert!(a.adam_grid == b.adam_grid && a.adam_density == b.adam_density && a.adam_colour == b.adam_colour, "Adam state differs");

        let bytes = std::fs::read(&path).unwrap();
        // Truncated anywhere: an error, never a panic.
        for cut in [0, 7, 100, bytes.len() / 2, bytes.len() - 1] {
            let err = Trainer::from_checkpoint_bytes(&bytes[..cut], None).unwrap_err();
            assert!(matches!(err, CheckpointError::Container(ContainerError::Parse(_))), "cut {cut}: {err}");
        }
        // A flipped byte in the tensor data fails a checksum.
        let mut corrupt = bytes.clone();
        let n = corrupt.len();
        corrupt[n - 9] ^= 0x40;
        let err = Trainer::from_checkpoint_bytes(&corrupt, None).unwrap_err();
        assert!(matches!(err, CheckpointError::Container(ContainerError::Checksum(_))), "{err}");
        // A different configuration is named.
        let err = Trainer::from_checkpoint_bytes(&bytes, Some(&TrainConfig::tiny())).unwrap_err();
        assert!(matches!(&err, CheckpointError::ConfigMismatch { differs } if differs.contains("rays_per_batch")), "{err}");
        // Missing file names the path.
        let err = Trainer::load_checkpoint(&dir.0.join("nope.ckpt"), None).unwrap_err();
        assert!(err.to_string().contains("nope.ckpt"), "{err}");
    }
}
