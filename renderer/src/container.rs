//! The file container shared by the `.nolf` asset, the i-NGP trainer checkpoint and the
//! distillation student state: one safetensors file (readable from numpy and torch) whose
//! `__metadata__` holds the format's JSON under a key of its own (`nolf`, `ngp_checkpoint`,
//! `nolf_student`) and that JSON's SHA-256 under `<key>_sha256`. The JSON ends with a
//! `checksums` member: the hex SHA-256 of every tensor's bytes.
//!
//! [`write()`] adds the checksums; [`Reader`] checks the container, the metadata checksum and,
//! for each tensor asked for, its dtype, shape and checksum. Every failure is a
//! [`ContainerError`], which each format wraps in its own error type; no input panics.

use std::collections::{BTreeMap, HashMap};

use safetensors::{Dtype, SafeTensors, tensor::TensorView};
use serde::{Deserialize, Serialize, de::DeserializeOwned};
use sha2::{Digest, Sha256};

#[derive(Debug, thiserror::Error)]
pub enum ContainerError {
    #[error("truncated or not safetensors: {0}")]
    Parse(String),
    /// The metadata JSON is missing, fails its checksum or does not parse.
    #[error("metadata is corrupt: {0}")]
    Metadata(String),
    #[error("tensor {0:?} is missing")]
    Missing(&'static str),
    #[error("tensor {name:?} has dtype {found:?} and shape {shape:?}; expected {want_dtype:?} {want_shape:?}")]
    Shape { name: &'static str, found: Dtype, shape: Vec<usize>, want_dtype: Dtype, want_shape: Vec<usize> },
    #[error("tensor {0:?} fails its checksum (file corrupted)")]
    Checksum(&'static str),
    /// Writing: a tensor's bytes do not fit its dtype and shape, or the metadata does not
    /// serialise to a JSON object.
    #[error("{0}")]
    Invalid(String),
}

/// Which checksums [`Reader::new`] insists on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verify {
    /// The metadata checksum and every tensor's checksum must be there and match.
    Always,
    /// Checked where the file has them: for formats written without checksums before this
    /// container existed (student checkpoints).
    WhenPresent,
}

/// One tensor to write: little-endian bytes of the given dtype and shape.
#[derive(Debug, Clone)]
pub struct Tensor<'a> {
    pub name: &'static str,
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub data: &'a [u8],
}

/// Hex SHA-256 of some bytes.
pub fn sha_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// The metadata as written: the format's own members, then the checksums.
#[derive(Serialize)]
struct Written<'a, M: Serialize> {
    #[serde(flatten)]
    meta: &'a M,
    checksums: BTreeMap<&'static str, String>,
}

/// Serialises `tensors` with `meta` (which must serialise to a JSON object without a
/// `checksums` member) stored under `key`, adding the tensors' checksums to it.
pub fn write(key: &str, meta: &impl Serialize, tensors: &[Tensor<'_>]) -> Result<Vec<u8>, ContainerError> {
    let checksums = tensors.iter().map(|t| (t.name, sha_hex(t.data))).collect();
    let json = serde_json::to_string(&Written { meta, checksums }).map_err(|e| ContainerError::Invalid(e.to_string()))?;
    let views = tensors
        .iter()
        .map(|t| {
            let view = TensorView::new(t.dtype, t.shape.clone(), t.data).map_err(|e| ContainerError::Invalid(format!("{}: {e}", t.name)))?;
            Ok((t.name, view))
        })
        .collect::<Result<Vec<_>, ContainerError>>()?;
    let info = HashMap::from([(format!("{key}_sha256"), sha_hex(json.as_bytes())), (key.to_string(), json)]);
    safetensors::serialize(views, Some(info)).map_err(|e| ContainerError::Parse(e.to_string()))
}

/// The checksums member of the metadata (the format's own members are read by [`Reader::meta`]).
#[derive(Deserialize)]
struct Checksums {
    #[serde(default)]
    checksums: Option<BTreeMap<String, String>>,
}

/// A parsed container whose metadata checksum has been checked.
pub struct Reader<'a> {
    file: SafeTensors<'a>,
    json: String,
    /// `None` only for files read with [`Verify::WhenPresent`] that have no checksums.
    checksums: Option<BTreeMap<String, String>>,
}

impl<'a> Reader<'a> {
    /// Parses the container and the metadata stored under `key`.
    pub fn new(bytes: &'a [u8], key: &str, verify: Verify) -> Result<Self, ContainerError> {
        let file = SafeTensors::deserialize(bytes).map_err(|e| ContainerError::Parse(e.to_string()))?;
        let (_, header) = SafeTensors::read_metadata(bytes).map_err(|e| ContainerError::Parse(e.to_string()))?;
        let info = header.metadata().as_ref().ok_or_else(|| ContainerError::Metadata("no __metadata__".into()))?;
        let json = info.get(key).ok_or_else(|| ContainerError::Metadata(format!("no {key} entry")))?.clone();
        let sha = info.get(&format!("{key}_sha256"));
        let unchecked = sha.is_none() && verify == Verify::WhenPresent;
        if !unchecked && sha.map(String::as_str) != Some(sha_hex(json.as_bytes()).as_str()) {
            return Err(ContainerError::Metadata("checksum mismatch".into()));
        }
        let Checksums { checksums } = serde_json::from_str(&json).map_err(|e| ContainerError::Metadata(e.to_string()))?;
        if checksums.is_none() && verify == Verify::Always {
            return Err(ContainerError::Metadata("no tensor checksums".into()));
        }
        Ok(Self { file, json, checksums })
    }

    /// The metadata JSON as the format's own type (the `checksums` member is ignored).
    pub fn meta<M: DeserializeOwned>(&self) -> Result<M, ContainerError> {
        serde_json::from_str(&self.json).map_err(|e| ContainerError::Metadata(e.to_string()))
    }

    /// The bytes of tensor `name`, once its dtype, shape and checksum are right.
    pub fn tensor(&self, name: &'static str, dtype: Dtype, shape: &[usize]) -> Result<&'a [u8], ContainerError> {
        let view = self.file.tensor(name).map_err(|_| ContainerError::Missing(name))?;
        if view.dtype() != dtype || view.shape() != shape {
            return Err(ContainerError::Shape { name, found: view.dtype(), shape: view.shape().to_vec(), want_dtype: dtype, want_shape: shape.to_vec() });
        }
        if let Some(sums) = &self.checksums
            && sums.get(name).map(String::as_str) != Some(sha_hex(view.data()).as_str())
        {
            return Err(ContainerError::Checksum(name));
        }
        Ok(view.data())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Vec<u8> {
        let (a, b) = ([1u8, 2, 3, 4, 5, 6, 7, 8], [9u8; 6]);
        let tensors = [
            Tensor { name: "a", dtype: Dtype::F32, shape: vec![2], data: &a },
            Tensor { name: "b", dtype: Dtype::U8, shape: vec![2, 3], data: &b },
        ];
        write("thing", &serde_json::json!({ "format": "test", "version": 1 }), &tensors).unwrap()
    }

    #[test]
    fn container_round_trips_and_checks_every_tensor() {
        let bytes = sample();
        let file = Reader::new(&bytes, "thing", Verify::Always).unwrap();
        let meta: serde_json::Value = file.meta().unwrap();
        assert_eq!((meta["format"].as_str(), meta["checksums"]["b"].as_str()), (Some("test"), Some(sha_hex(&[9; 6]).as_str())));
        assert_eq!(file.tensor("a", Dtype::F32, &[2]).unwrap(), [1, 2, 3, 4, 5, 6, 7, 8]);
        assert!(matches!(file.tensor("b", Dtype::U8, &[3, 2]), Err(ContainerError::Shape { name: "b", .. })));
        assert!(matches!(file.tensor("c", Dtype::U8, &[1]), Err(ContainerError::Missing("c"))));
        assert!(matches!(Reader::new(&bytes, "other", Verify::Always), Err(ContainerError::Metadata(_))));

        // The last data byte belongs to "b" (tensors are laid out by dtype, then name).
        let mut corrupt = bytes.clone();
        *corrupt.last_mut().unwrap() ^= 1;
        let file = Reader::new(&corrupt, "thing", Verify::Always).unwrap();
        assert!(file.tensor("a", Dtype::F32, &[2]).is_ok());
        assert!(matches!(file.tensor("b", Dtype::U8, &[2, 3]), Err(ContainerError::Checksum("b"))));
        for cut in 0..bytes.len() {
            assert!(Reader::new(&bytes[..cut], "thing", Verify::Always).is_err(), "cut at {cut}");
        }
    }

    #[test]
    fn container_reads_files_without_checksums_only_when_told() {
        let data = [0u8; 4];
        let view = TensorView::new(Dtype::F32, vec![1], &data).unwrap();
        let info = HashMap::from([("thing".to_string(), r#"{"format":"old"}"#.to_string())]);
        let old = safetensors::serialize([("a", view)], Some(info)).unwrap();
        assert!(matches!(Reader::new(&old, "thing", Verify::Always), Err(ContainerError::Metadata(_))));
        let file = Reader::new(&old, "thing", Verify::WhenPresent).unwrap();
        assert_eq!(file.tensor("a", Dtype::F32, &[1]).unwrap(), data);
        // A file that has checksums is held to them either way.
        let mut corrupt = sample();
        *corrupt.last_mut().unwrap() ^= 1;
        let file = Reader::new(&corrupt, "thing", Verify::WhenPresent).unwrap();
        assert!(matches!(file.tensor("b", Dtype::U8, &[2, 3]), Err(ContainerError::Checksum("b"))));
    }
}
