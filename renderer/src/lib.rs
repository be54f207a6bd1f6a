//! Nephele renderer: the i-NOLF model of NEPHELE (Luo et al., arXiv 2303.04086) — asset
//! format, camera and ray maths, a plain CPU reference and a wgpu compute backend that agree
//! on DESIGN §3, procedural assets, and training data: posed-image datasets (NeRF-synthetic,
//! instant-ngp), exactly ray-traced synthetic ones, and CPU training of the i-NGP teacher
//! field (`train`). No tokio, no network.

pub mod asset;
pub mod camera;
pub mod compose;
pub mod cubes;
pub mod dataset;
pub mod gpu;
pub mod mlp;
pub mod model;
pub mod procedural;
pub mod psh;
pub mod render;
pub mod scene;
pub mod sh;
pub mod synth;
pub mod train;
pub mod views;

#[cfg(test)]
mod test_util;

pub use asset::{Asset, AssetError};
pub use camera::{Instance, Intrinsics, PoseError, View};
pub use model::RenderSettings;
pub use render::{Backend, CancelFlag, CpuBackend, Frame, PreparedAsset, RenderError, RenderOutput, RenderStats, ViewRequest};
