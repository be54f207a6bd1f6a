//! Where the master composes the objects of a multi-object scene by depth: the CPU
//! reference (`nephele_renderer::compose`, the default: a few ms at 640×480) or the same
//! rule as a wgpu kernel (`--compose gpu`, for a master with a real GPU).

use std::sync::Arc;

use glam::Vec3;
use nephele_renderer::{
    Frame,
    compose::compose,
    gpu::{GpuContext, compose::GpuCompositor},
};

/// Which compositor a master uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ComposeChoice {
    Cpu,
    Gpu,
}

pub enum Compositor {
    Cpu,
    Gpu(GpuCompositor),
}

impl Compositor {
    pub fn new(choice: ComposeChoice) -> anyhow::Result<Self> {
        Ok(match choice {
            ComposeChoice::Cpu => Self::Cpu,
            ComposeChoice::Gpu => Self::Gpu(GpuCompositor::new(GpuContext::new()?)),
        })
    }

    /// Composes premultiplied layers over `background`.
    pub fn compose(&self, parts: &[Arc<Frame>], background: Vec3) -> Result<Frame, String> {
        let layers: Vec<&Frame> = parts.iter().map(|p| p.as_ref()).collect();
        match self {
            Self::Cpu => compose(&layers, background).map_err(|e| e.to_string()),
            Self::Gpu(g) => g.compose(&layers, background).map_err(|e| e.to_string()),
        }
    }
}
