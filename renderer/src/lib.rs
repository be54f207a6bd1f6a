//! Nephele renderer: the i-NOLF model of NEPHELE (Luo et al., arXiv 2303.04086) — asset
//! format, camera and ray maths, a plain CPU reference and a wgpu compute backend that agree
//! on docs/architecture.md §3, procedural assets, and the forward i-NGP model (`ngp`) that the baseline
//! renders with. Training lives in the `nephele-train` crate. No tokio, no network.

pub mod asset;
pub mod camera;
pub mod compose;
pub mod container;
pub mod cubes;
pub mod fast;
pub mod gpu;
pub mod mlp;
pub mod model;
pub mod ngp;
pub mod procedural;
pub mod psh;
pub mod render;
pub mod rule;
pub mod scene;
pub mod sh;
pub mod views;

pub use asset::{Asset, AssetError};
pub use fast::FastCpuBackend;
pub use camera::{Instance, Intrinsics, PoseError, View};
pub use model::RenderSettings;
pub use render::{Backend, CancelFlag, CpuBackend, Frame, PreparedAsset, RenderError, RenderOutput, RenderStats, ViewRequest};
