//! The i-NGP radiance field (Müller et al., "Instant Neural Graphics Primitives", SIGGRAPH
//! 2022), NEPHELE's baseline, as the renderer evaluates it: forward passes only. Training (the
//! backward passes, Adam, the trainer loop) is in the `nephele-train` crate, whose `Trainer`
//! owns a [`Field`] and an [`OccupancyGrid`] and lends them out as an [`NgpModel`].
//!
//! - [`hash_grid`]: multi-resolution hash encoding;
//! - [`mlp`]: batched tiny MLP that keeps its activations (for the trainer's backward pass);
//! - [`field`]: hash grid → density MLP → σ, geometry features; + SH view encoding → colour MLP;
//! - [`occupancy`]: occupancy grid for empty-space skipping;
//! - [`NgpModel`]: the fixed-step march and front-to-back compositing, the CPU reference of
//!   the wgpu baseline ([`crate::gpu::ngp`]).

pub mod field;
pub mod hash_grid;
pub mod mlp;
mod model;
pub mod occupancy;

pub use field::{Field, FieldConfig, FieldTape};
pub use hash_grid::{HashGrid, HashGridConfig};
pub use model::{DENSITY_WINDOW, NgpChunk, NgpModel, NgpRay};
pub use occupancy::OccupancyGrid;
