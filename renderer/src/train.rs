//! CPU training of the i-NGP radiance field (Müller et al., "Instant Neural Graphics
//! Primitives", SIGGRAPH 2022): the geometry teacher and baseline of DESIGN §4 stage 1.
//! Hand-derived gradients throughout, checked against finite differences in the tests.
//!
//! - [`hash_grid`]: multi-resolution hash encoding;
//! - [`mlp`]: batched tiny MLP with forward tape and backward pass;
//! - [`adam`]: the optimiser;
//! - [`field`]: hash grid → density MLP → σ, geometry features; + SH view encoding → colour MLP;
//! - [`occupancy`]: occupancy grid for empty-space skipping;
//! - [`trainer`]: ray batches, volume rendering and its reverse pass, one optimisation step;
//! - [`distill`]: the i-NOLF stages: density cubes, hit points, PSH, diffuse and specular nets,
//!   baking into an asset;
//! - [`variants`]: CPU renderers of the ablation variants the runtime renderer does not serve.

pub mod adam;
pub mod distill;
pub mod field;
pub mod hash_grid;
pub mod mlp;
pub mod occupancy;
pub mod trainer;
pub mod variants;

pub use field::{Field, FieldConfig};
pub use hash_grid::{HashGrid, HashGridConfig};
pub use trainer::{BatchStats, OccupancyConfig, StepStats, TrainConfig, TrainRay, Trainer};
