//! Nephele training: images → i-NOLF asset, on the CPU (docs/architecture.md §4). Training data, the i-NGP
//! teacher (Müller et al., "Instant Neural Graphics Primitives", SIGGRAPH 2022; stage 1) and
//! the distillation into an asset (stages 2–4). The forward i-NGP model (hash grid, MLPs,
//! field, occupancy grid, volume rendering) is the renderer's [`nephele_renderer::ngp`]; this
//! crate adds the backward passes, hand-derived and checked against finite differences in the
//! tests.
//!
//! - [`dataset`]: posed-image datasets (NeRF-synthetic, instant-ngp);
//! - [`synth`]: exactly ray-traced synthetic scenes with ground truth, written as datasets;
//! - [`hash_grid`], [`mlp`], [`field`]: backward passes of the renderer's i-NGP parts;
//! - [`adam`]: the optimiser;
//! - [`trainer`]: ray batches, the loss and its reverse pass, one optimisation step;
//!   checkpoints and evaluation;
//! - [`distill`]: the i-NOLF stages: density cubes, hit points, PSH, diffuse and specular nets,
//!   baking into an asset;
//! - [`variants`]: CPU renderers of the ablation variants the runtime renderer does not serve.

pub mod adam;
pub mod dataset;
pub mod distill;
pub mod field;
pub mod hash_grid;
pub mod mlp;
pub mod synth;
pub mod trainer;
pub mod variants;

#[cfg(test)]
mod test_util;

pub use nephele_renderer::ngp::{Field, FieldConfig, HashGrid, HashGridConfig};
pub use trainer::{BatchStats, OccupancyConfig, StepStats, TrainConfig, TrainRay, Trainer};
