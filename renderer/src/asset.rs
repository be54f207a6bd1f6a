//! The `.nolf` asset: one [`crate::container`] file (safetensors, readable from numpy/torch)
//! whose `__metadata__` holds versioned, self-describing JSON (`nolf`) and its SHA-256
//! (`nolf_sha256`); the JSON in turn holds a SHA-256 per tensor. Loading validates the
//! container, the checksums, every shape against the metadata (before any allocation sized by
//! it), every index and range, the perfect hash (collision-free) and finite weights. Any
//! failure is an [`AssetError`].

use std::{collections::BTreeMap, fmt, path::Path};

use safetensors::Dtype;
use serde::{Deserialize, Serialize};

use crate::{
    container::{self, ContainerError, Reader, Tensor, Verify},
    cubes::{Aabb, CubeStorage, TextureCubes},
    mlp::{HIDDEN, SpecularMlp},
    psh::SpatialHash,
    sh::SH_COEFFS,
};

pub const FORMAT_NAME: &str = "nephele-nolf";
pub const FORMAT_VERSION: u32 = 1;
/// The `__metadata__` key of the JSON.
const META_KEY: &str = "nolf";
/// Files above this size are refused before reading.
pub const MAX_FILE_BYTES: u64 = 2 << 30;
const MAX_GRID: u32 = 512;
const MAX_BRICK: u32 = 32;
const MAX_FINE: u32 = 4096;
const MAX_FEATURES: u32 = 32;
const MAX_TABLE_EDGE: u32 = 1024;

#[derive(Debug, thiserror::Error)]
pub enum AssetError {
    #[error("cannot read {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("asset is {0} bytes; the limit is {MAX_FILE_BYTES}")]
    TooLarge(u64),
    /// The container, the metadata checksum, or a tensor's dtype, shape or checksum.
    #[error("not a valid .nolf file: {0}")]
    Container(#[from] ContainerError),
    #[error("asset format {found:?} version {version} is not supported (this build reads {FORMAT_NAME:?} version {FORMAT_VERSION})")]
    Version { found: String, version: u32 },
    #[error("asset content is invalid: {0}")]
    Invalid(String),
}

fn invalid(s: impl Into<String>) -> AssetError {
    AssetError::Invalid(s.into())
}

/// Grid sizes of a set of texture cubes.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CubesMeta {
    pub grid: u32,
    pub brick: u32,
    pub bricks: u32,
    /// Value storage (`f16` when absent; density is always `f16`).
    #[serde(default, skip_serializing_if = "CubeStorage::is_f16")]
    pub storage: CubeStorage,
    /// The index grid is i16 (written when there are fewer than 32768 bricks); i32 when absent.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub index_i16: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PshMeta {
    pub grid: u32,
    pub table_edge: u32,
    pub offset_edge: u32,
    pub features: u32,
}

impl CubesMeta {
    fn of(c: &TextureCubes) -> Self {
        Self { grid: c.grid, brick: c.brick, bricks: c.brick_count() as u32, storage: c.storage, index_i16: c.narrow_index() }
    }
}

/// Default ray-marching settings the asset was made for.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MarchMeta {
    /// Fixed step δ in object units.
    pub step: f32,
    /// Rays with coarse opacity below this are misses.
    pub alpha_min: f32,
    /// Which parts of a ray's weight get a network query (absent in older assets: one hit).
    #[serde(default)]
    pub hits: crate::rule::HitRule,
    /// The march stops once transmittance falls below this: the threshold the asset was
    /// trained with, so its coarse opacities are the ones its network learnt (absent in older
    /// assets: [`crate::rule::DEFAULT_EARLY_STOP`]).
    #[serde(default = "default_early_stop")]
    pub early_stop: f32,
}

fn default_early_stop() -> f32 {
    crate::rule::DEFAULT_EARLY_STOP
}

/// The `nolf` JSON in the safetensors header (followed there by the tensor checksums).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AssetMeta {
    pub format: String,
    pub version: u32,
    pub name: String,
    pub bounds: Aabb,
    pub march: MarchMeta,
    pub density: CubesMeta,
    pub diffuse: CubesMeta,
    pub psh: PshMeta,
    pub mlp_input: u32,
    /// Where the asset came from: generator or dataset, settings, time, metrics.
    pub provenance: serde_json::Value,
}

/// A loaded, validated i-NOLF asset.
#[derive(Debug, Clone, PartialEq)]
pub struct Asset {
    pub name: String,
    pub bounds: Aabb,
    pub march: MarchMeta,
    /// σ per object unit, 1 channel.
    pub density: TextureCubes,
    /// Diffuse RGB and specular tint, 4 channels.
    pub diffuse: TextureCubes,
    pub psh: SpatialHash,
    pub mlp: SpecularMlp,
    pub provenance: serde_json::Value,
}

fn f16_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| half::f16::from_f32(*x).to_le_bytes()).collect()
}
fn value_bytes(c: &TextureCubes) -> Vec<u8> {
    match c.storage {
        CubeStorage::F16 => f16_bytes(&c.values),
        CubeStorage::Unorm8 => c.values.iter().map(|&v| CubeStorage::unorm8(v)).collect(),
    }
}
fn index_bytes(c: &TextureCubes) -> Vec<u8> {
    if c.narrow_index() { c.index.iter().flat_map(|&i| (i as i16).to_le_bytes()).collect() } else { le_bytes(&c.index) }
}
fn index_dtype(m: &CubesMeta) -> Dtype {
    if m.index_i16 { Dtype::I16 } else { Dtype::I32 }
}
fn value_dtype(s: CubeStorage) -> Dtype {
    match s {
        CubeStorage::F16 => Dtype::F16,
        CubeStorage::Unorm8 => Dtype::U8,
    }
}
fn le_bytes<T: bytemuck::Pod>(v: &[T]) -> Vec<u8> {
    bytemuck::cast_slice(v).to_vec()
}

/// Tensor names, dtypes and shapes implied by the metadata, computed with checked arithmetic
/// so a hostile size field is an error instead of an allocation.
/// A tensor's name, dtype and shape.
type TensorSpec = (&'static str, Dtype, Vec<usize>);

fn expected_tensors(m: &AssetMeta) -> Result<Vec<TensorSpec>, AssetError> {
    let cube = |c: &CubesMeta, what: &str| -> Result<(usize, usize), AssetError> {
        if c.grid == 0 || c.grid > MAX_GRID || c.brick == 0 || c.brick > MAX_BRICK || c.grid * c.brick > MAX_FINE {
            return Err(invalid(format!("{what} grid {}×{} is outside the supported range", c.grid, c.brick)));
        }
        if c.bricks as u64 > (c.grid as u64).pow(3) {
            return Err(invalid(format!("{what} has {} bricks for a {}³ grid", c.bricks, c.grid)));
        }
        if c.index_i16 && c.bricks > i16::MAX as u32 {
            return Err(invalid(format!("{what} has {} bricks, too many for an i16 index", c.bricks)));
        }
        Ok((c.grid as usize, c.brick as usize + 1))
    };
    let (bd, ed) = cube(&m.density, "density")?;
    if !m.density.storage.is_f16() {
        return Err(invalid("density cubes must be stored as f16"));
    }
    let (bc, ec) = cube(&m.diffuse, "diffuse")?;
    let p = &m.psh;
    if p.grid == 0 || p.grid > crate::psh::MAX_COORD || p.table_edge == 0 || p.table_edge > MAX_TABLE_EDGE {
        return Err(invalid(format!("PSH grid {} / table {} outside the supported range", p.grid, p.table_edge)));
    }
    if p.offset_edge == 0 || p.offset_edge > MAX_TABLE_EDGE || p.features == 0 || p.features > MAX_FEATURES {
        return Err(invalid(format!("PSH offsets {} / features {} outside the supported range", p.offset_edge, p.features)));
    }
    let input = p.features as usize + SH_COEFFS + 1;
    if m.mlp_input as usize != input {
        return Err(invalid(format!("MLP input {} does not match {} features + 17", m.mlp_input, p.features)));
    }
    let (m3, r3) = ((p.table_edge as usize).pow(3), (p.offset_edge as usize).pow(3));
    Ok(vec![
        ("density.index", index_dtype(&m.density), vec![bd, bd, bd]),
        ("density.values", value_dtype(m.density.storage), vec![m.density.bricks as usize, ed, ed, ed]),
        ("diffuse.index", index_dtype(&m.diffuse), vec![bc, bc, bc]),
        ("diffuse.values", value_dtype(m.diffuse.storage), vec![m.diffuse.bricks as usize, ec, ec, ec, 4]),
        ("psh.keys", Dtype::U32, vec![m3]),
        ("psh.offsets", Dtype::U32, vec![r3]),
        ("psh.values", Dtype::F16, vec![m3, p.features as usize]),
        ("mlp.w0", Dtype::F32, vec![HIDDEN, input]),
        ("mlp.b0", Dtype::F32, vec![HIDDEN]),
        ("mlp.w1", Dtype::F32, vec![HIDDEN, HIDDEN]),
        ("mlp.b1", Dtype::F32, vec![HIDDEN]),
        ("mlp.w2", Dtype::F32, vec![4, HIDDEN]),
        ("mlp.b2", Dtype::F32, vec![4]),
    ])
}

impl Asset {
    fn meta(&self) -> AssetMeta {
        AssetMeta {
            format: FORMAT_NAME.into(),
            version: FORMAT_VERSION,
            name: self.name.clone(),
            bounds: self.bounds,
            march: self.march,
            density: CubesMeta::of(&self.density),
            diffuse: CubesMeta::of(&self.diffuse),
            psh: PshMeta {
                grid: self.psh.grid,
                table_edge: self.psh.table_edge,
                offset_edge: self.psh.offset_edge,
                features: self.psh.features,
            },
            mlp_input: self.mlp.input as u32,
            provenance: self.provenance.clone(),
        }
    }

    /// Serialises to `.nolf` bytes. Fails only if the asset itself is invalid.
    pub fn to_bytes(&self) -> Result<Vec<u8>, AssetError> {
        self.validate()?;
        let meta = self.meta();
        let data: Vec<(&'static str, Vec<u8>)> = vec![
            ("density.index", index_bytes(&self.density)),
            ("density.values", value_bytes(&self.density)),
            ("diffuse.index", index_bytes(&self.diffuse)),
            ("diffuse.values", value_bytes(&self.diffuse)),
            ("psh.keys", le_bytes(&self.psh.keys)),
            ("psh.offsets", le_bytes(&self.psh.offsets)),
            ("psh.values", f16_bytes(&self.psh.values)),
            ("mlp.w0", le_bytes(&self.mlp.w0)),
            ("mlp.b0", le_bytes(&self.mlp.b0)),
            ("mlp.w1", le_bytes(&self.mlp.w1)),
            ("mlp.b1", le_bytes(&self.mlp.b1)),
            ("mlp.w2", le_bytes(&self.mlp.w2)),
            ("mlp.b2", le_bytes(&self.mlp.b2)),
        ];
        let tensors: Vec<Tensor<'_>> =
            expected_tensors(&meta)?.into_iter().zip(&data).map(|((name, dtype, shape), (_, bytes))| Tensor { name, dtype, shape, data: bytes }).collect();
        Ok(container::write(META_KEY, &meta, &tensors)?)
    }

    pub fn save(&self, path: &Path) -> Result<(), AssetError> {
        let bytes = self.to_bytes()?;
        std::fs::write(path, bytes).map_err(|source| AssetError::Io { path: path.display().to_string(), source })
    }

    pub fn load(path: &Path) -> Result<Self, AssetError> {
        let io = |source| AssetError::Io { path: path.display().to_string(), source };
        let len = std::fs::metadata(path).map_err(io)?.len();
        if len > MAX_FILE_BYTES {
            return Err(AssetError::TooLarge(len));
        }
        Self::from_bytes(&std::fs::read(path).map_err(io)?)
    }

    /// Parses and fully validates `.nolf` bytes.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, AssetError> {
        let file = Reader::new(bytes, META_KEY, Verify::Always)?;
        let meta: AssetMeta = file.meta()?;
        if meta.format != FORMAT_NAME || meta.version != FORMAT_VERSION {
            return Err(AssetError::Version { found: meta.format, version: meta.version });
        }
        let mut tensors = BTreeMap::new();
        for (name, dtype, shape) in expected_tensors(&meta)? {
            tensors.insert(name, file.tensor(name, dtype, &shape)?);
        }
        let f32s = |n: &str| bytemuck::pod_collect_to_vec::<u8, f32>(tensors[n]);
        let i32s = |n: &str| bytemuck::pod_collect_to_vec::<u8, i32>(tensors[n]);
        let u32s = |n: &str| bytemuck::pod_collect_to_vec::<u8, u32>(tensors[n]);
        let f16s = |n: &str| -> Vec<f32> {
            tensors[n].chunks_exact(2).map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32()).collect()
        };
        let cubes = |m: &CubesMeta, channels, prefix: &str| {
            let values = format!("{prefix}.values");
            TextureCubes {
                bounds: meta.bounds,
                grid: m.grid,
                brick: m.brick,
                channels,
                index: if m.index_i16 {
                    bytemuck::pod_collect_to_vec::<u8, i16>(tensors[format!("{prefix}.index").as_str()]).into_iter().map(i32::from).collect()
                } else {
                    i32s(&format!("{prefix}.index"))
                },
                values: match m.storage {
                    CubeStorage::F16 => f16s(&values),
                    CubeStorage::Unorm8 => tensors[values.as_str()].iter().map(|&b| b as f32 / 255.0).collect(),
                },
                storage: m.storage,
            }
        };
        let asset = Asset {
            name: meta.name.clone(),
            bounds: meta.bounds,
            march: meta.march,
            density: cubes(&meta.density, 1, "density"),
            diffuse: cubes(&meta.diffuse, 4, "diffuse"),
            psh: SpatialHash {
                bounds: meta.bounds,
                grid: meta.psh.grid,
                table_edge: meta.psh.table_edge,
                offset_edge: meta.psh.offset_edge,
                features: meta.psh.features,
                keys: u32s("psh.keys"),
                offsets: u32s("psh.offsets"),
                values: f16s("psh.values"),
            },
            mlp: SpecularMlp {
                input: meta.mlp_input as usize,
                w0: f32s("mlp.w0"),
                b0: f32s("mlp.b0"),
                w1: f32s("mlp.w1"),
                b1: f32s("mlp.b1"),
                w2: f32s("mlp.w2"),
                b2: f32s("mlp.b2"),
            },
            provenance: meta.provenance,
        };
        asset.validate()?;
        Ok(asset)
    }

    /// Checks every index, range and size; run on load and before save.
    pub fn validate(&self) -> Result<(), AssetError> {
        if !self.bounds.is_valid() {
            return Err(invalid(format!("bounds {:?} are not a finite non-empty box", self.bounds)));
        }
        let m = &self.march;
        if !(m.step.is_finite() && m.step > 0.0 && m.step >= self.bounds.size().max_element() / 1e5) {
            return Err(invalid(format!("march step {} is not a sane positive length", m.step)));
        }
        if !(0.0..1.0).contains(&m.alpha_min) {
            return Err(invalid(format!("alpha_min {} outside [0, 1)", m.alpha_min)));
        }
        if !(0.0..1.0).contains(&m.early_stop) {
            return Err(invalid(format!("early_stop {} outside [0, 1)", m.early_stop)));
        }
        m.hits.validate().map_err(invalid)?;
        for (cubes, what, channels) in [(&self.density, "density", 1), (&self.diffuse, "diffuse", 4)] {
            let b = cubes.grid as usize;
            if cubes.channels != channels || cubes.index.len() != b * b * b || cubes.bounds != self.bounds {
                return Err(invalid(format!("{what} cubes have the wrong layout")));
            }
            let per_brick = cubes.brick_corners() * channels as usize;
            if cubes.values.len() % per_brick != 0 {
                return Err(invalid(format!("{what} values are not whole bricks")));
            }
            let n = (cubes.values.len() / per_brick) as i32;
            let mut seen = vec![false; n as usize];
            for &i in &cubes.index {
                if i < -1 || i >= n {
                    return Err(invalid(format!("{what} index {i} outside -1..{n}")));
                }
                if i >= 0 {
                    if seen[i as usize] {
                        return Err(invalid(format!("{what} brick {i} referenced twice")));
                    }
                    seen[i as usize] = true;
                }
            }
            if cubes.values.iter().any(|v| !v.is_finite()) {
                return Err(invalid(format!("{what} has non-finite values")));
            }
        }
        if self.density.values.iter().any(|&v| v < 0.0) {
            return Err(invalid("negative density"));
        }
        if self.diffuse.storage == CubeStorage::Unorm8 && self.diffuse.values.iter().any(|&v| CubeStorage::Unorm8.round(v) != v) {
            return Err(invalid("diffuse values are not 8-bit unorm values"));
        }
        if self.psh.bounds != self.bounds {
            return Err(invalid("PSH bounds differ from the asset bounds"));
        }
        self.psh.verify().map_err(|e| invalid(e.to_string()))?;
        if self.mlp.input != self.psh.features as usize + SH_COEFFS + 1 {
            return Err(invalid("MLP input width does not match the encodings"));
        }
        self.mlp.check().map_err(|e| invalid(format!("specular MLP: {e}")))?;
        Ok(())
    }

    /// Memory by part, next to what dense grids of the same resolution would need.
    pub fn memory(&self) -> MemoryReport {
        let d = &self.density;
        let c = &self.diffuse;
        let p = &self.psh;
        let mlp = self.mlp.parameter_count() as u64 * 4;
        MemoryReport {
            parts: vec![
                MemoryPart {
                    part: "density cubes",
                    detail: format!("{}³ index × {}³ bricks, {} of {} cells", d.grid, d.brick, d.brick_count(), d.grid.pow(3)),
                    stored_bytes: d.stored_bytes(),
                    dense_bytes: d.dense_bytes(),
                },
                MemoryPart {
                    part: "diffuse cubes",
                    detail: format!("{}³ index × {}³ bricks, {} of {} cells, {:?}", c.grid, c.brick, c.brick_count(), c.grid.pow(3), c.storage),
                    stored_bytes: c.stored_bytes(),
                    dense_bytes: c.dense_bytes(),
                },
                MemoryPart {
                    part: "PSH table",
                    detail: format!("N={} F={}, {} vertices in {}³ slots", p.grid, p.features, p.len(), p.table_edge),
                    stored_bytes: p.stored_bytes(),
                    dense_bytes: p.dense_bytes(),
                },
                MemoryPart {
                    part: "networks",
                    detail: format!("specular MLP {}→{HIDDEN}→{HIDDEN}→4", self.mlp.input),
                    stored_bytes: mlp,
                    dense_bytes: mlp,
                },
            ],
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct MemoryPart {
    pub part: &'static str,
    pub detail: String,
    pub stored_bytes: u64,
    pub dense_bytes: u64,
}

#[derive(Debug, Clone, PartialEq)]
pub struct MemoryReport {
    pub parts: Vec<MemoryPart>,
}

impl MemoryReport {
    pub fn stored_bytes(&self) -> u64 {
        self.parts.iter().map(|p| p.stored_bytes).sum()
    }
    pub fn dense_bytes(&self) -> u64 {
        self.parts.iter().map(|p| p.dense_bytes).sum()
    }
}

fn mib(b: u64) -> f64 {
    b as f64 / (1024.0 * 1024.0)
}

impl fmt::Display for MemoryReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "{:<14} {:>11} {:>11} {:>7}  detail", "part", "stored MiB", "dense MiB", "ratio")?;
        let (mut s, mut d) = (0, 0);
        for p in &self.parts {
            writeln!(
                f,
                "{:<14} {:>11.3} {:>11.3} {:>6.1}%  {}",
                p.part,
                mib(p.stored_bytes),
                mib(p.dense_bytes),
                100.0 * p.stored_bytes as f64 / p.dense_bytes.max(1) as f64,
                p.detail
            )?;
            s += p.stored_bytes;
            d += p.dense_bytes;
        }
        writeln!(f, "{:<14} {:>11.3} {:>11.3} {:>6.1}%", "total", mib(s), mib(d), 100.0 * s as f64 / d.max(1) as f64)
    }
}
