//! The depth compositor on wgpu: `compose.wgsl`, one thread per pixel, the same rule as the
//! CPU reference [`crate::compose`] (tested against it). Layers go up as two storage
//! buffers (packed RGBA8 and f32 depth, layer-major), the result comes back as RGBA8 +
//! depth.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use wgpu::util::DeviceExt;

use super::{GpuContext, dispatch_2d, gpu_err};
use crate::{
    compose::{ComposeError, check_layers},
    render::{Frame, RenderError},
};

pub const COMPOSE_WGSL: &str = include_str!("compose.wgsl");

/// Keep in sync with `ComposeParams` in compose.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct ComposeParams {
    pub pixels: u32,
    pub layers: u32,
    pub _pad: [u32; 2],
    pub background: [f32; 4],
}
const _: () = assert!(std::mem::size_of::<ComposeParams>() == 32);

#[derive(Debug, thiserror::Error)]
pub enum GpuComposeError {
    #[error(transparent)]
    Layers(#[from] ComposeError),
    #[error(transparent)]
    Gpu(#[from] RenderError),
}

/// The compose pipeline on one device.
pub struct GpuCompositor {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
}

impl GpuCompositor {
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        let module = ctx.device.create_shader_module(wgpu::ShaderModuleDescriptor { label: Some("compose"), source: wgpu::ShaderSource::Wgsl(COMPOSE_WGSL.into()) });
        let pipeline = ctx.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("compose_main"),
            layout: None,
            module: &module,
            entry_point: Some("compose_main"),
            compilation_options: Default::default(),
            cache: None,
        });
        Self { ctx, pipeline }
    }

    /// Composes premultiplied layers over `background`, like [`crate::compose::compose`].
    pub fn compose(&self, layers: &[&Frame], background: Vec3) -> Result<Frame, GpuComposeError> {
        let (width, height) = check_layers(layers, background)?;
        let pixels = width * height;
        let dev = &self.ctx.device;
        let mut colors: Vec<u32> = Vec::with_capacity(pixels as usize * layers.len());
        let mut depths: Vec<f32> = Vec::with_capacity(pixels as usize * layers.len());
        for l in layers {
            colors.extend(l.rgba.chunks_exact(4).map(|p| u32::from_le_bytes([p[0], p[1], p[2], p[3]])));
            depths.extend_from_slice(&l.depth);
        }
        let params = ComposeParams { pixels, layers: layers.len() as u32, _pad: [0; 2], background: background.extend(0.0).to_array() };
        use wgpu::BufferUsages as U;
        let init = |label: &str, contents: &[u8], usage: U| dev.create_buffer_init(&wgpu::util::BufferInitDescriptor { label: Some(label), contents, usage });
        let params_buf = init("compose params", bytemuck::bytes_of(&params), U::UNIFORM);
        let colors_buf = init("compose colors", bytemuck::cast_slice(&colors), U::STORAGE);
        let depths_buf = init("compose depths", bytemuck::cast_slice(&depths), U::STORAGE);
        let out_bytes = u64::from(pixels) * 8;
        let out = dev.create_buffer(&wgpu::BufferDescriptor { label: Some("compose out"), size: out_bytes, usage: U::STORAGE | U::COPY_SRC, mapped_at_creation: false });
        let readback = dev.create_buffer(&wgpu::BufferDescriptor { label: Some("compose readback"), size: out_bytes, usage: U::MAP_READ | U::COPY_DST, mapped_at_creation: false });
        let bind = dev.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("compose"),
            layout: &self.pipeline.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: params_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: colors_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: depths_buf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: out.as_entire_binding() },
            ],
        });
        let mut enc = dev.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind, &[]);
            let (x, y) = dispatch_2d(pixels.div_ceil(64));
            pass.dispatch_workgroups(x, y, 1);
        }
        enc.copy_buffer_to_buffer(&out, 0, &readback, 0, out_bytes);
        self.ctx.queue.submit([enc.finish()]);
        let slice = readback.slice(..);
        slice.map_async(wgpu::MapMode::Read, |_| {});
        dev.poll(wgpu::PollType::wait_indefinitely()).map_err(gpu_err)?;
        let packed: Vec<[u32; 2]> = slice.get_mapped_range().map(|data| bytemuck::cast_slice(&data).to_vec()).map_err(gpu_err)?;
        readback.unmap();
        Ok(Frame {
            width,
            height,
            rgba: packed.iter().flat_map(|p| p[0].to_le_bytes()).collect(),
            depth: packed.iter().map(|p| f32::from_bits(p[1])).map(|d| if d < 0.0 { f32::INFINITY } else { d }).collect(),
        })
    }
}
