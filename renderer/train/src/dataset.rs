//! Posed images for training and evaluation, read from the two common layouts:
//!
//! - **NeRF-synthetic** (Mildenhall et al., ECCV 2020): a folder holding
//!   `transforms_{train,val,test}.json`, each `{camera_angle_x, frames: [{file_path,
//!   transform_matrix}]}`; `file_path` is relative to the folder and has no extension
//!   (`./train/r_0` → `train/r_0.png`).
//! - **instant-ngp** (Müller et al., SIGGRAPH 2022): one `transforms.json` with the same frames
//!   and pinhole intrinsics (`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`, or `camera_angle_x`/`_y`)
//!   at the top level and/or per frame; `file_path` may carry its extension; optional
//!   `aabb_scale`. Every frame is training data unless [`LoadOptions::holdout_every`] moves
//!   every n-th frame (index 0, n, 2n, …) to the test split.
//!
//! `transform_matrix` is a row-major camera-to-world 4×4 with the OpenGL camera (looks down
//! −z, y up) — the convention of [`View`]. Poses are kept exactly as written (instant-ngp's
//! own `scale`/`offset` are not applied; lens distortion is ignored with a warning).
//!
//! Pixel values are the PNG's, used as-is like NeRF does: no sRGB decoding, straight (not
//! premultiplied) alpha, 0..1. 16-bit images are scaled by 1/65535; RGB and grey images get
//! alpha 1. Only PNG is read. Images are decoded in parallel (rayon).
//!
//! Bad input never panics: each problem is a [`DatasetError`] naming the file and the field.

use std::{
    fmt,
    fs::File,
    io::BufReader,
    path::{Path, PathBuf},
    str::FromStr,
    time::Instant,
};

use glam::{DMat4, Vec3};
use nephele_renderer::camera::{Intrinsics, MAX_EDGE_PX, PoseError, View};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

/// Which part of a dataset.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    pub const ALL: [Split; 3] = [Split::Train, Split::Val, Split::Test];

    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        }
    }
}

impl fmt::Display for Split {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Split {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Split::ALL.into_iter().find(|v| v.name() == s).ok_or_else(|| format!("unknown split {s:?} (train, val, test)"))
    }
}

/// Which file layout a dataset was read from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Format {
    /// `transforms_{train,val,test}.json` in a folder.
    NerfSynthetic,
    /// One `transforms.json`.
    InstantNgp,
}

/// What to load and how.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LoadOptions {
    pub split: Split,
    /// Integer shrink factor: 1, 2, 4 or 8 (box filter on premultiplied colour).
    pub downscale: u32,
    /// Keep only the first `n` frames of the split, in file order.
    pub max_images: Option<usize>,
    /// instant-ngp only: frames 0, n, 2n, … form the test split, the rest the train split.
    pub holdout_every: Option<usize>,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self { split: Split::Train, downscale: 1, max_images: None, holdout_every: None }
    }
}

impl LoadOptions {
    pub fn split(split: Split) -> Self {
        Self { split, ..Self::default() }
    }
}

/// One posed image.
#[derive(Clone, PartialEq)]
pub struct DatasetImage {
    /// Pose and intrinsics at this (possibly downscaled) size.
    pub view: View,
    pub width: u32,
    pub height: u32,
    /// Straight RGBA, row-major from the top row, values from the file scaled to 0..1.
    pub rgba: Vec<f32>,
    /// The PNG it came from.
    pub path: PathBuf,
}

/// The images of one split.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// Folder name, e.g. "lego".
    pub name: String,
    pub format: Format,
    pub split: Split,
    /// The JSON file the frames came from.
    pub transforms_file: PathBuf,
    /// instant-ngp `aabb_scale`, if given.
    pub aabb_scale: Option<f64>,
    pub images: Vec<DatasetImage>,
}

/// Why a dataset could not be loaded. Every variant names the file, and the field where one
/// is at fault (`frames[3].transform_matrix[0][2]`).
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("dataset path {path} does not exist")]
    MissingFolder { path: PathBuf },
    #[error("{dir}: no {looked_for}")]
    MissingTransforms { dir: PathBuf, looked_for: String },
    #[error("cannot read {file}: {source}")]
    Io { file: PathBuf, source: std::io::Error },
    #[error("{file}: bad JSON at line {line}, column {column}: {message}")]
    BadJson { file: PathBuf, line: usize, column: usize, message: String },
    #[error("{file}: missing field `{field}`")]
    MissingField { file: PathBuf, field: String },
    #[error("{file}: field `{field}` {problem}")]
    BadField { file: PathBuf, field: String, problem: String },
    #[error("{file}: `{field}` is not a usable camera pose: {source}")]
    BadPose { file: PathBuf, field: String, source: PoseError },
    #[error("image {image} not found (`{field}` of {file})")]
    MissingImage { image: PathBuf, file: PathBuf, field: String },
    #[error("{image}: unreadable PNG: {message}")]
    BadPng { image: PathBuf, message: String },
    #[error("{image} is {width}x{height} but {expected_from} says {expected_width}x{expected_height}")]
    SizeMismatch { image: PathBuf, width: u32, height: u32, expected_width: u32, expected_height: u32, expected_from: String },
    #[error("{file}: no frames in the {split} split{hint}")]
    NoFrames { file: PathBuf, split: Split, hint: &'static str },
    #[error("bad load option: {0}")]
    BadOption(String),
}

type Result<T, E = DatasetError> = std::result::Result<T, E>;

impl Dataset {
    /// Loads one split from a dataset folder (either layout) or from a JSON file, which is read
    /// as a single instant-ngp `transforms.json`.
    pub fn load(path: &Path, options: &LoadOptions) -> Result<Dataset> {
        let start = Instant::now();
        let LoadOptions { split, downscale, max_images, holdout_every } = *options;
        if ![1, 2, 4, 8].contains(&downscale) {
            return Err(DatasetError::BadOption(format!("downscale must be 1, 2, 4 or 8, not {downscale}")));
        }
        if max_images == Some(0) {
            return Err(DatasetError::BadOption("max_images must be at least 1".into()));
        }
        check_holdout(holdout_every)?;
        // With a holdout, both halves come from the train file (NeRF-synthetic) or the single
        // transforms.json (instant-ngp).
        let (format, file) = locate(path, if holdout_every.is_some() { Split::Train } else { split })?;
        let transforms = read_transforms(&file, format)?;
        let mut frames = select_split(transforms.frames, format, split, holdout_every);
        if frames.is_empty() {
            let hint = match format {
                Format::InstantNgp if split != Split::Train => {
                    " (an instant-ngp transforms.json is all train unless holdout_every moves frames to test)"
                }
                _ => "",
            };
            return Err(DatasetError::NoFrames { file, split, hint });
        }
        if let Some(n) = max_images {
            frames.truncate(n);
        }

        let decoded: Vec<Result<(DatasetImage, (u32, u32))>> = frames.par_iter().map(|frame| load_image(&file, frame, downscale)).collect();
        let mut images = Vec::with_capacity(decoded.len());
        let mut first_size: Option<((u32, u32), &Path)> = None;
        for (result, frame) in decoded.into_iter().zip(&frames) {
            let (image, size) = result?;
            match first_size {
                None => first_size = Some((size, &frame.image_path)),
                Some((first, first_path)) if first != size => {
                    return Err(DatasetError::SizeMismatch {
                        image: image.path,
                        width: size.0,
                        height: size.1,
                        expected_width: first.0,
                        expected_height: first.1,
                        expected_from: format!("{} (first image of the {split} split)", first_path.display()),
                    });
                }
                Some(_) => {}
            }
            images.push(image);
        }
        let dataset = Dataset { name: dataset_name(path), format, split, transforms_file: file, aabb_scale: transforms.aabb_scale, images };
        tracing::debug!(
            name = %dataset.name, %split, images = dataset.images.len(),
            secs = start.elapsed().as_secs_f64(), "dataset loaded"
        );
        Ok(dataset)
    }

    /// World-space rays of image `index`; see [`DatasetImage::rays`]. Panics if `index` is out
    /// of range.
    pub fn rays(&self, index: usize) -> impl Iterator<Item = (Vec3, Vec3)> + '_ {
        self.images[index].rays()
    }
}

/// Without the pixels.
impl fmt::Debug for DatasetImage {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("DatasetImage")
            .field("path", &self.path)
            .field("width", &self.width)
            .field("height", &self.height)
            .field("view", &self.view)
            .finish_non_exhaustive()
    }
}

impl DatasetImage {
    /// Straight RGBA of pixel (`x_px`, `y_px`). Panics outside the image.
    pub fn pixel(&self, x_px: u32, y_px: u32) -> [f32; 4] {
        let i = 4 * (y_px as usize * self.width as usize + x_px as usize);
        [self.rgba[i], self.rgba[i + 1], self.rgba[i + 2], self.rgba[i + 3]]
    }

    /// World-space ray through the centre of pixel (`x_px`, `y_px`): (origin, unit direction).
    pub fn ray(&self, x_px: u32, y_px: u32) -> (Vec3, Vec3) {
        let (origin, dir) = self.view.ray_in_world(x_px as f64 + 0.5, y_px as f64 + 0.5);
        (origin.as_vec3(), dir.as_vec3())
    }

    /// World-space rays (origin, unit direction) through every pixel centre, in the order of
    /// [`Self::rgba`] (row-major from the top row).
    pub fn rays(&self) -> impl Iterator<Item = (Vec3, Vec3)> + '_ {
        (0..self.height).flat_map(move |y| (0..self.width).map(move |x| self.ray(x, y)))
    }

    /// RGB over a background colour (`c·α + bg·(1 − α)`): ground truth as published
    /// NeRF-synthetic figures use it (over white).
    pub fn composite_over(&self, background: Vec3) -> Vec<f32> {
        let bg = background.to_array();
        self.rgba.chunks_exact(4).flat_map(|p| std::array::from_fn::<f32, 3, _>(|c| p[c] * p[3] + bg[c] * (1.0 - p[3]))).collect()
    }
}

/// What [`inspect`] finds without decoding images.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetInfo {
    pub name: String,
    pub format: Format,
    pub aabb_scale: Option<f64>,
    pub splits: Vec<SplitInfo>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct SplitInfo {
    pub split: Split,
    pub transforms_file: PathBuf,
    pub frames: usize,
    /// Size of the split's first image, from its PNG header.
    pub first_image_size: Option<(u32, u32)>,
}

/// Lists the splits of a dataset with their frame counts; reads only the JSON and one PNG
/// header per split. `holdout_every` as in [`LoadOptions`].
pub fn inspect(path: &Path, holdout_every: Option<usize>) -> Result<DatasetInfo> {
    check_holdout(holdout_every)?;
    let mut found = None;
    let mut splits = Vec::new();
    for split in Split::ALL {
        let (format, file) = match locate(path, if holdout_every.is_some() { Split::Train } else { split }) {
            Ok(located) => located,
            // A NeRF-synthetic folder may lack some of its splits.
            Err(DatasetError::MissingTransforms { .. }) if split != Split::Train || has_split_files(path) => continue,
            Err(e) => return Err(e),
        };
        let transforms = read_transforms(&file, format)?;
        let frames = select_split(transforms.frames, format, split, holdout_every);
        if (format == Format::InstantNgp || holdout_every.is_some()) && split != Split::Train && frames.is_empty() {
            continue;
        }
        let first_image_size = frames.first().and_then(|f| png_size(&f.image_path));
        found = Some((format, transforms.aabb_scale));
        splits.push(SplitInfo { split, transforms_file: file, frames: frames.len(), first_image_size });
    }
    let (format, aabb_scale) = found.ok_or_else(|| DatasetError::MissingTransforms {
        dir: path.to_path_buf(),
        looked_for: "transforms_{train,val,test}.json".into(),
    })?;
    Ok(DatasetInfo { name: dataset_name(path), format, aabb_scale, splits })
}

/// Intrinsics of a NeRF-synthetic camera: square pixels, principal point at the centre, focal
/// length from the horizontal field of view (radians). Computed in f64 like the loader does.
pub fn intrinsics_from_angle_x(width: u32, height: u32, camera_angle_x: f64) -> Intrinsics {
    Lens { angle_x: Some(camera_angle_x), ..Lens::default() }.intrinsics(width, height)
}

/// Finds the JSON file for `split` and which layout it is.
fn locate(path: &Path, split: Split) -> Result<(Format, PathBuf)> {
    if !path.exists() {
        return Err(DatasetError::MissingFolder { path: path.to_path_buf() });
    }
    if path.is_file() {
        return Ok((Format::InstantNgp, path.to_path_buf()));
    }
    let split_file = |s: Split| path.join(format!("transforms_{s}.json"));
    if has_split_files(path) {
        let file = split_file(split);
        return if file.is_file() {
            Ok((Format::NerfSynthetic, file))
        } else {
            Err(DatasetError::MissingTransforms { dir: path.to_path_buf(), looked_for: format!("transforms_{split}.json") })
        };
    }
    let single = path.join("transforms.json");
    if single.is_file() {
        return Ok((Format::InstantNgp, single));
    }
    Err(DatasetError::MissingTransforms {
        dir: path.to_path_buf(),
        looked_for: "transforms_train.json (NeRF-synthetic) or transforms.json (instant-ngp)".into(),
    })
}

fn check_holdout(holdout_every: Option<usize>) -> Result<()> {
    match holdout_every {
        Some(n) if n < 2 => Err(DatasetError::BadOption(format!("holdout_every must be at least 2, not {n}"))),
        _ => Ok(()),
    }
}

fn has_split_files(dir: &Path) -> bool {
    Split::ALL.iter().any(|s| dir.join(format!("transforms_{s}.json")).is_file())
}

/// The frames of `split`: all of a NeRF-synthetic split file; when holding out every n-th
/// (either layout, frames of the train file for NeRF-synthetic), frames 0, n, 2n, … are test,
/// the rest train, and val is empty; without a holdout an instant-ngp file is all train.
fn select_split(frames: Vec<FrameSpec>, format: Format, split: Split, holdout_every: Option<usize>) -> Vec<FrameSpec> {
    if format == Format::NerfSynthetic && holdout_every.is_none() {
        return frames;
    }
    let held_out = |i: usize| holdout_every.is_some_and(|n| i.is_multiple_of(n));
    let keep = |i: usize| match split {
        Split::Train => !held_out(i),
        Split::Test => held_out(i),
        Split::Val => false,
    };
    frames.into_iter().enumerate().filter(|(i, _)| keep(*i)).map(|(_, f)| f).collect()
}

fn dataset_name(path: &Path) -> String {
    let dir = if path.is_file() { path.parent().unwrap_or(path) } else { path };
    let dir = dir.canonicalize().unwrap_or_else(|_| dir.to_path_buf());
    dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "dataset".into())
}

/// Pinhole parameters as written; per-frame values override the top level.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Lens {
    fl_x: Option<f64>,
    fl_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    angle_x: Option<f64>,
    angle_y: Option<f64>,
    width: Option<u32>,
    height: Option<u32>,
}

impl Lens {
    /// Reads the lens fields of `obj`; `prefix` is its path in the file (`frames[2].`).
    fn read(obj: &Map<String, Value>, file: &Path, prefix: &str) -> Result<Lens> {
        let field = |key: &str| format!("{prefix}{key}");
        let num = |key: &str| optional_number(obj, key, file, &field(key));
        let positive = |key: &str| -> Result<Option<f64>> {
            match num(key)? {
                Some(v) if v <= 0.0 => Err(bad_field(file, &field(key), format!("must be positive, found {v}"))),
                v => Ok(v),
            }
        };
        let angle = |key: &str| -> Result<Option<f64>> {
            match num(key)? {
                Some(v) if !(v > 0.0 && v < std::f64::consts::PI) => {
                    Err(bad_field(file, &field(key), format!("must be an angle in (0, π) radians, found {v}")))
                }
                v => Ok(v),
            }
        };
        let size = |key: &str| -> Result<Option<u32>> {
            match num(key)? {
                Some(v) if v.fract() != 0.0 || v < 1.0 || v > MAX_EDGE_PX as f64 => {
                    Err(bad_field(file, &field(key), format!("must be a whole number of pixels in 1..={MAX_EDGE_PX}, found {v}")))
                }
                v => Ok(v.map(|v| v as u32)),
            }
        };
        Ok(Lens {
            fl_x: positive("fl_x")?,
            fl_y: positive("fl_y")?,
            cx: num("cx")?,
            cy: num("cy")?,
            angle_x: angle("camera_angle_x")?,
            angle_y: angle("camera_angle_y")?,
            width: size("w")?,
            height: size("h")?,
        })
    }

    fn or(self, fallback: Lens) -> Lens {
        Lens {
            fl_x: self.fl_x.or(fallback.fl_x),
            fl_y: self.fl_y.or(fallback.fl_y),
            cx: self.cx.or(fallback.cx),
            cy: self.cy.or(fallback.cy),
            angle_x: self.angle_x.or(fallback.angle_x),
            angle_y: self.angle_y.or(fallback.angle_y),
            width: self.width.or(fallback.width),
            height: self.height.or(fallback.height),
        }
    }

    fn has_focal(&self) -> bool {
        self.fl_x.is_some() || self.angle_x.is_some()
    }

    /// Intrinsics for an image of this size; call only when [`Self::has_focal`].
    fn intrinsics(&self, width: u32, height: u32) -> Intrinsics {
        let (w, h) = (width as f64, height as f64);
        let focal = |fl: Option<f64>, angle: Option<f64>, size: f64| fl.or(angle.map(|a| 0.5 * size / (0.5 * a).tan()));
        let fx = focal(self.fl_x, self.angle_x, w).unwrap_or(f64::NAN);
        let fy = focal(self.fl_y, self.angle_y, h).unwrap_or(fx);
        Intrinsics {
            fx: fx as f32,
            fy: fy as f32,
            cx: self.cx.unwrap_or(0.5 * w) as f32,
            cy: self.cy.unwrap_or(0.5 * h) as f32,
            width,
            height,
        }
    }
}

/// One frame as read from JSON, before its image is decoded.
#[derive(Debug, Clone)]
struct FrameSpec {
    /// Path of the frame in the file, e.g. `frames[3]`.
    field: String,
    image_path: PathBuf,
    world_from_camera: DMat4,
    lens: Lens,
}

struct Transforms {
    frames: Vec<FrameSpec>,
    aabb_scale: Option<f64>,
}

/// Parses and checks a transforms file: fields, types, poses. Images are not touched.
fn read_transforms(file: &Path, format: Format) -> Result<Transforms> {
    let text = std::fs::read_to_string(file).map_err(|source| DatasetError::Io { file: file.to_path_buf(), source })?;
    let root: Value = serde_json::from_str(&text).map_err(|e| json_error(file, &text, &e))?;
    let root = root.as_object().ok_or_else(|| bad_field(file, "(top level)", "must be a JSON object".into()))?;
    let top_lens = Lens::read(root, file, "")?;
    let aabb_scale = optional_number(root, "aabb_scale", file, "aabb_scale")?;
    let distortion = ["k1", "k2", "k3", "k4", "p1", "p2"];
    if distortion.iter().any(|k| root.get(*k).and_then(Value::as_f64).is_some_and(|v| v != 0.0)) {
        tracing::warn!(file = %file.display(), "lens distortion coefficients are ignored (pinhole model only)");
    }
    let frames = root.get("frames").ok_or_else(|| missing_field(file, "frames"))?;
    let frames = frames.as_array().ok_or_else(|| bad_field(file, "frames", "must be an array".into()))?;
    let base_dir = file.parent().unwrap_or(Path::new("."));
    let mut specs = Vec::with_capacity(frames.len());
    for (i, frame) in frames.iter().enumerate() {
        let field = format!("frames[{i}]");
        let obj = frame.as_object().ok_or_else(|| bad_field(file, &field, "must be an object".into()))?;
        let file_path = obj.get("file_path").ok_or_else(|| missing_field(file, &format!("{field}.file_path")))?;
        let file_path = file_path
            .as_str()
            .filter(|s| !s.is_empty())
            .ok_or_else(|| bad_field(file, &format!("{field}.file_path"), "must be a non-empty string".into()))?;
        let matrix_field = format!("{field}.transform_matrix");
        let world_from_camera = read_matrix(obj.get("transform_matrix"), file, &matrix_field)?;
        // The pose alone, with a placeholder camera: intrinsics are checked once sizes are known.
        let placeholder = Intrinsics::from_fov_x(1, 1, 1.0);
        View { world_from_camera, intrinsics: placeholder }.validate().map_err(|source| DatasetError::BadPose {
            file: file.to_path_buf(),
            field: matrix_field,
            source,
        })?;
        let lens = Lens::read(obj, file, &format!("{field}."))?.or(top_lens);
        if !lens.has_focal() {
            let name = match format {
                Format::NerfSynthetic => "camera_angle_x",
                Format::InstantNgp => "fl_x (or camera_angle_x)",
            };
            return Err(missing_field(file, name));
        }
        specs.push(FrameSpec { image_path: image_path(base_dir, file_path), field, world_from_camera, lens });
    }
    Ok(Transforms { frames: specs, aabb_scale })
}

/// `file_path` as written if it names a file or ends in `.png`; otherwise with `.png`
/// appended (NeRF-synthetic leaves the extension out).
fn image_path(base_dir: &Path, file_path: &str) -> PathBuf {
    let path = base_dir.join(file_path);
    let is_png = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if path.is_file() || is_png {
        return path;
    }
    let mut with_ext = path.into_os_string();
    with_ext.push(".png");
    PathBuf::from(with_ext)
}

/// A row-major 4×4 of finite numbers.
fn read_matrix(value: Option<&Value>, file: &Path, field: &str) -> Result<DMat4> {
    let value = value.ok_or_else(|| missing_field(file, field))?;
    let shape_error = || bad_field(file, field, "must be a 4×4 array of rows".into());
    let rows = value.as_array().filter(|r| r.len() == 4).ok_or_else(shape_error)?;
    let mut m = [[0.0f64; 4]; 4];
    for (r, row) in rows.iter().enumerate() {
        let row = row.as_array().filter(|c| c.len() == 4).ok_or_else(shape_error)?;
        for (c, entry) in row.iter().enumerate() {
            m[r][c] = entry.as_f64().filter(|v| v.is_finite()).ok_or_else(|| {
                bad_field(file, &format!("{field}[{r}][{c}]"), format!("must be a finite number, found {}", short(entry)))
            })?;
        }
    }
    // `m` holds rows; glam builds from columns.
    Ok(DMat4::from_cols_array_2d(&m).transpose())
}

/// Decodes, checks and downscales the image of `frame`; also returns its size in the file.
fn load_image(file: &Path, frame: &FrameSpec, downscale: u32) -> Result<(DatasetImage, (u32, u32))> {
    let image = &frame.image_path;
    if !image.is_file() {
        return Err(DatasetError::MissingImage {
            image: image.clone(),
            file: file.to_path_buf(),
            field: format!("{}.file_path", frame.field),
        });
    }
    let (width, height, rgba) = decode_png(image)?;
    let (expected_width, expected_height) = (frame.lens.width.unwrap_or(width), frame.lens.height.unwrap_or(height));
    if (expected_width, expected_height) != (width, height) {
        return Err(DatasetError::SizeMismatch {
            image: image.clone(),
            width,
            height,
            expected_width,
            expected_height,
            expected_from: format!("`w`/`h` of {} in {}", frame.field, file.display()),
        });
    }
    if width < downscale || height < downscale {
        return Err(DatasetError::BadOption(format!("{}: a {width}x{height} image cannot be downscaled by {downscale}", image.display())));
    }
    let full = frame.lens.intrinsics(width, height);
    let (rgba, small_width, small_height) = downscale_rgba(&rgba, width, height, downscale);
    // Output pixel x covers input pixels [f·x, f·x + f): dividing by f maps image points exactly.
    let f = downscale as f32;
    let intrinsics =
        Intrinsics { fx: full.fx / f, fy: full.fy / f, cx: full.cx / f, cy: full.cy / f, width: small_width, height: small_height };
    let view = View { world_from_camera: frame.world_from_camera, intrinsics };
    view.validate().map_err(|source| DatasetError::BadPose { file: file.to_path_buf(), field: frame.field.clone(), source })?;
    Ok((DatasetImage { view, width: small_width, height: small_height, rgba, path: image.clone() }, (width, height)))
}

/// Decodes any PNG (grey, grey+alpha, RGB, RGBA, palette; 1–16 bits) to straight RGBA f32.
fn decode_png(image: &Path) -> Result<(u32, u32, Vec<f32>)> {
    let bad = |message: String| DatasetError::BadPng { image: image.to_path_buf(), message };
    let reader = File::open(image).map_err(|source| DatasetError::Io { file: image.to_path_buf(), source })?;
    let mut decoder = png::Decoder::new(BufReader::new(reader));
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(|e| {
        let hint = if image.extension().is_some_and(|e| !e.eq_ignore_ascii_case("png")) { " (only PNG images are supported)" } else { "" };
        bad(format!("{e}{hint}"))
    })?;
    let (width, height) = reader.info().size();
    if width > MAX_EDGE_PX || height > MAX_EDGE_PX {
        return Err(bad(format!("{width}x{height} exceeds the {MAX_EDGE_PX}-pixel edge limit")));
    }
    let len = reader.output_buffer_size().ok_or_else(|| bad("image too large for memory".into()))?;
    let mut buf = vec![0u8; len];
    let out = reader.next_frame(&mut buf).map_err(|e| bad(e.to_string()))?;
    let channels = out.color_type.samples();
    let bytes_per_sample = match out.bit_depth {
        png::BitDepth::Eight => 1,
        png::BitDepth::Sixteen => 2,
        depth => return Err(bad(format!("unexpected bit depth {depth:?} after expansion"))),
    };
    let sample = |bytes: &[u8]| -> f32 {
        match bytes {
            [b] => *b as f32 / 255.0,
            [hi, lo, ..] => u16::from_be_bytes([*hi, *lo]) as f32 / 65535.0,
            [] => 0.0,
        }
    };
    let pixel_bytes = channels * bytes_per_sample;
    let mut rgba = Vec::with_capacity(4 * width as usize * height as usize);
    for row in buf.chunks_exact(out.line_size).take(height as usize) {
        for px in row.chunks_exact(pixel_bytes).take(width as usize) {
            let s = |c: usize| sample(&px[c * bytes_per_sample..(c + 1) * bytes_per_sample]);
            let p = match channels {
                1 => [s(0), s(0), s(0), 1.0],
                2 => [s(0), s(0), s(0), s(1)],
                3 => [s(0), s(1), s(2), 1.0],
                _ => [s(0), s(1), s(2), s(3)],
            };
            rgba.extend_from_slice(&p);
        }
    }
    if rgba.len() != 4 * width as usize * height as usize {
        return Err(bad("decoded data is shorter than the image".into()));
    }
    Ok((width, height, rgba))
}

/// Reads only the PNG header.
fn png_size(image: &Path) -> Option<(u32, u32)> {
    let decoder = png::Decoder::new(BufReader::new(File::open(image).ok()?));
    decoder.read_info().ok().map(|r| r.info().size())
}

/// Box filter over `factor`×`factor` blocks, averaging premultiplied colour; straight colour
/// out (0 where the block is fully transparent). A partial last column/row of blocks is dropped.
fn downscale_rgba(rgba: &[f32], width: u32, height: u32, factor: u32) -> (Vec<f32>, u32, u32) {
    if factor == 1 {
        return (rgba.to_vec(), width, height);
    }
    let (small_width, small_height) = (width / factor, height / factor);
    let f = factor as usize;
    let inv_area = 1.0 / (f * f) as f32;
    let mut out = Vec::with_capacity(4 * (small_width * small_height) as usize);
    for y in 0..small_height as usize {
        for x in 0..small_width as usize {
            let mut sum = [0.0f32; 4];
            for dy in 0..f {
                for dx in 0..f {
                    let i = 4 * ((y * f + dy) * width as usize + x * f + dx);
                    let a = rgba[i + 3];
                    for c in 0..3 {
                        sum[c] += rgba[i + c] * a;
                    }
                    sum[3] += a;
                }
            }
            let alpha = sum[3] * inv_area;
            let unpremultiply = if sum[3] > 0.0 { 1.0 / sum[3] } else { 0.0 };
            out.extend_from_slice(&[sum[0] * unpremultiply, sum[1] * unpremultiply, sum[2] * unpremultiply, alpha]);
        }
    }
    (out, small_width, small_height)
}

fn optional_number(obj: &Map<String, Value>, key: &str, file: &Path, field: &str) -> Result<Option<f64>> {
    match obj.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(v) => match v.as_f64().filter(|x| x.is_finite()) {
            Some(x) => Ok(Some(x)),
            None => Err(bad_field(file, field, format!("must be a finite number, found {}", short(v)))),
        },
    }
}

fn missing_field(file: &Path, field: &str) -> DatasetError {
    DatasetError::MissingField { file: file.to_path_buf(), field: field.to_string() }
}

fn bad_field(file: &Path, field: &str, problem: String) -> DatasetError {
    DatasetError::BadField { file: file.to_path_buf(), field: field.to_string(), problem }
}

/// A JSON value for an error message, cut to a readable length.
fn short(v: &Value) -> String {
    let s = v.to_string();
    if s.chars().count() > 40 { format!("{}…", s.chars().take(40).collect::<String>()) } else { s }
}

/// serde's message with its line/column, plus a hint when the culprit is a bare NaN or
/// Infinity (what Python's `json.dump` writes for non-finite floats; JSON has no such values).
fn json_error(file: &Path, text: &str, e: &serde_json::Error) -> DatasetError {
    let (line, column) = (e.line(), e.column());
    let at = text.lines().nth(line.saturating_sub(1)).and_then(|l| l.get(column.saturating_sub(1)..)).unwrap_or("");
    let at = at.trim_start_matches('-');
    let non_finite = ["NaN", "Infinity", "nan", "inf"].iter().any(|t| at.starts_with(t)) || e.to_string().contains("out of range");
    let hint = if non_finite { " (non-finite numbers such as NaN, Infinity or 1e400 are not allowed)" } else { "" };
    DatasetError::BadJson { file: file.to_path_buf(), line, column, message: format!("{e}{hint}") }
}

#[cfg(test)]
mod tests;
