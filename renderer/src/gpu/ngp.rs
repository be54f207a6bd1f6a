//! The instant-NGP baseline renderer on wgpu (Müller et al., "Instant Neural Graphics
//! Primitives", SIGGRAPH 2022), so the baseline's speed can be measured on the same backend as
//! the i-NOLF renderer. An [`NgpModel`]'s hash grid, both tiny MLPs and occupancy bits are
//! uploaded once; `ngp.wgsl` then runs one invocation per ray through the same fixed-step
//! samples as the CPU reference [`NgpModel::render`] (`forward_chunk` in ngp/model.rs),
//! evaluating the whole field at every sample in an occupied cell (four samples at a time,
//! like instant-ngp's batched inference) and compositing front to back with the same early
//! stop. Only instant-ngp's widths are supported: density MLP `[2L, 64, 16]`, colour MLP
//! `[16 + 16, 64, 64, 3]` (every preset uses them). The weights live in an rgba32f texture:
//! why, and what the kernel's shape costs on lavapipe, is noted at the top of ngp.wgsl.

use std::{
    sync::{Arc, Mutex},
    time::Instant,
};

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use wgpu::util::DeviceExt;

use super::{GpuContext, dispatch_2d, gpu_err};
use crate::{
    ngp::{
        Field, NgpModel,
        field::{GEO_FEATURES, MAX_LOG_DENSITY},
        hash_grid::FEATURES_PER_LEVEL,
        mlp::Mlp,
    },
    render::RenderError,
    sh::SH_COEFFS,
};

pub const NGP_WGSL: &str = include_str!("ngp.wgsl");

/// Rays per chunk: bounds the ray and state (32 B each), output and readback (16 B each)
/// buffers.
pub const CHUNK_RAYS: usize = 1 << 16;
/// Samples that go through the networks together (`BATCH` in ngp.wgsl).
const BATCH: u32 = 4;
/// Per ray and dispatch, at most this many batches and sample positions: lavapipe stops all
/// loops of an invocation after 65535 iterations in total (see ngp.wgsl). Keep in sync with
/// `ROUND_*` in ngp.wgsl.
const ROUND_BATCHES: u32 = 32;
const ROUND_POSITIONS: u32 = 2048;
/// Bytes of `RayState` in ngp.wgsl.
const RAY_STATE_BYTES: usize = 32;

/// Dispatches that finish every ray of a march of `max_steps + 1` positions: a round that does
/// not finish a ray takes it at least `BATCH · ROUND_BATCHES` positions further.
fn rounds(max_steps: u32) -> u32 {
    (max_steps + 1).div_ceil(BATCH * ROUND_BATCHES.min(ROUND_POSITIONS / BATCH))
}

/// Levels the kernel's level table holds (`HashGridConfig::validate` allows 32).
pub const MAX_LEVELS: usize = 32;
/// Hidden width of both MLPs.
pub const HIDDEN: usize = 64;
const _: () = assert!(FEATURES_PER_LEVEL == 2 && MAX_LOG_DENSITY == 15.0 && GEO_FEATURES == 16 && SH_COEFFS == 16);

/// vec4s of one packed layer whose rows are `in4` vec4s: output rows padded to a multiple of
/// 4, then `⌈out/4⌉` vec4s of biases.
#[cfg(test)]
const fn layer_vec4s(in4: usize, outputs: usize) -> usize {
    4 * outputs.div_ceil(4) * in4 + outputs.div_ceil(4)
}

/// vec4s of the density network's input for `levels` levels: `2L` features padded to 4, 8 or
/// 16 vec4s, the widths the kernel has a layer for.
pub fn encoding_vec4s(levels: usize) -> usize {
    (FEATURES_PER_LEVEL * levels).div_ceil(4).next_power_of_two().max(4)
}

/// Keep in sync with `Params` in ngp.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct NgpParams {
    pub bounds_min: [f32; 3],
    /// Ray-marching step δ, scene units.
    pub step: f32,
    pub bounds_max: [f32; 3],
    pub early_stop: f32,
    /// `bounds_max − bounds_min` as the CPU computes it (the divisor of [`NgpModel::to_unit`]).
    pub bounds_size: [f32; 3],
    /// `steps_per_diagonal`: samples k run over `0..=max_steps`.
    pub max_steps: u32,
    pub background: [f32; 3],
    pub occupancy_resolution: u32,
    pub levels: u32,
    /// vec4s of the density network's input ([`encoding_vec4s`]).
    pub enc4: u32,
    pub ray_count: u32,
    /// Texel offsets of the layers in the weight texture: density 0 and 1, colour 0, 1 and 2.
    pub off_d0: u32,
    pub off_d1: u32,
    pub off_c0: u32,
    pub off_c1: u32,
    pub off_c2: u32,
    /// Per level: resolution, dense (0/1), first entry, entries.
    pub level: [[u32; 4]; MAX_LEVELS],
}
const _: () = assert!(std::mem::size_of::<NgpParams>() == 608);

/// Refuses fields the kernel cannot evaluate (it is written for instant-ngp's widths).
pub fn check_layout(field: &Field) -> Result<(), RenderError> {
    let levels = field.grid.levels.len();
    let encoding = FEATURES_PER_LEVEL * levels;
    let density = field.density_mlp.widths();
    let colour = field.colour_mlp.widths();
    let supported = (1..=MAX_LEVELS).contains(&levels)
        && density == [encoding, HIDDEN, GEO_FEATURES]
        && colour == [GEO_FEATURES + SH_COEFFS, HIDDEN, HIDDEN, 3]
        && field.grid.levels.iter().all(|l| l.resolution >= 1 && (l.dense || l.entries.is_power_of_two()));
    if supported {
        Ok(())
    } else {
        Err(RenderError::BadSettings(format!(
            "the wgpu i-NGP renderer supports 1..={MAX_LEVELS} hash levels, density MLP [2L, {HIDDEN}, {GEO_FEATURES}] and colour MLP \
             [{}, {HIDDEN}, {HIDDEN}, 3]; this field has {levels} levels, density {density:?}, colour {colour:?}",
            GEO_FEATURES + SH_COEFFS
        )))
    }
}

/// Appends the layers of `mlp` in the kernel's layout and their vec4 offsets: per layer, the
/// rows of `W` (`out × in`, row-major) each zero-padded to `⌈in/4⌉` vec4s (at least
/// `first_in4` for the first layer), zero rows up to a multiple of 4, then the biases.
fn pack_mlp(mlp: &Mlp, first_in4: usize, out: &mut Vec<[f32; 4]>, offsets: &mut Vec<u32>) {
    let params = mlp.params();
    let mut at = 0;
    for (l, w) in mlp.widths().windows(2).enumerate() {
        let (inputs, outputs) = (w[0], w[1]);
        let in4 = if l == 0 { first_in4.max(inputs.div_ceil(4)) } else { inputs.div_ceil(4) };
        offsets.push(out.len() as u32);
        let weights = &params[at..at + inputs * outputs];
        let bias = &params[at + inputs * outputs..at + inputs * outputs + outputs];
        for r in 0..4 * outputs.div_ceil(4) {
            let row = weights.get(r * inputs..(r + 1) * inputs).filter(|_| r < outputs);
            for q in 0..in4 {
                out.push(std::array::from_fn(|k| row.and_then(|row| row.get(4 * q + k)).copied().unwrap_or(0.0)));
            }
        }
        for q in 0..outputs.div_ceil(4) {
            out.push(std::array::from_fn(|k| bias.get(4 * q + k).copied().unwrap_or(0.0)));
        }
        at += inputs * outputs + outputs;
    }
}

/// Per-render buffers for chunks of up to `chunk` rays, with their bind group.
struct Scratch {
    chunk: usize,
    rays: wgpu::Buffer,
    state: wgpu::Buffer,
    out: wgpu::Buffer,
    readback: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
}

/// A trained i-NGP field on the GPU.
pub struct GpuNgp {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    params: wgpu::Buffer,
    weights: wgpu::TextureView,
    grid: wgpu::Buffer,
    occupancy: wgpu::Buffer,
    /// Params with `background` and `ray_count` left zero.
    base: NgpParams,
    scratch: Mutex<Option<Scratch>>,
    /// Set by [`Self::poison_output`].
    poison: bool,
}

impl GpuNgp {
    /// Uploads the field and occupancy grid (of an [`NgpModel`] or anything that lends one,
    /// such as the trainer) and builds the kernel. The hash grid is one storage buffer
    /// (≈ 67 MB for the full preset); [`GpuContext::new`] already asks for the adapter's own
    /// limits, so a grid beyond them is refused here with the sizes.
    pub fn new<'a>(ctx: Arc<GpuContext>, model: impl Into<NgpModel<'a>>) -> Result<Self, RenderError> {
        let model = model.into();
        let field = model.field;
        check_layout(field)?;
        if model.occupancy.bounds != model.bounds {
            return Err(RenderError::BadSettings(format!(
                "occupancy grid bounds {:?} differ from the scene bounds {:?}",
                model.occupancy.bounds, model.bounds
            )));
        }
        let limits = ctx.device.limits();
        let storage_limit = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size);
        let grid_bytes = std::mem::size_of_val(field.grid.params.as_slice()) as u64;
        if grid_bytes > storage_limit {
            return Err(RenderError::Gpu(format!(
                "the hash grid needs {:.1} MiB in one storage buffer; the adapter allows {:.1} MiB",
                grid_bytes as f64 / (1 << 20) as f64,
                storage_limit as f64 / (1 << 20) as f64
            )));
        }
        let levels = field.grid.levels.len();
        let enc4 = encoding_vec4s(levels);
        let mut weights = Vec::new();
        let mut offsets = Vec::with_capacity(5);
        pack_mlp(&field.density_mlp, enc4, &mut weights, &mut offsets);
        pack_mlp(&field.colour_mlp, 0, &mut weights, &mut offsets);
        debug_assert_eq!(offsets.len(), 5);
        if weights.len() > limits.max_texture_dimension_1d as usize {
            return Err(RenderError::Gpu(format!(
                "the MLPs need a 1D texture of {} texels; the adapter allows {}",
                weights.len(),
                limits.max_texture_dimension_1d
            )));
        }
        // Cell c is bit c % 64 of u64 word c / 64: as u32 words, low half first.
        let occupancy_words: Vec<u32> = model.occupancy.bits().iter().flat_map(|&w| [w as u32, (w >> 32) as u32]).collect();
        let mut level = [[0u32; 4]; MAX_LEVELS];
        for (slot, l) in level.iter_mut().zip(&field.grid.levels) {
            *slot = [l.resolution, l.dense as u32, l.first_entry as u32, l.entries as u32];
        }
        let base = NgpParams {
            bounds_min: model.bounds.min.to_array(),
            step: model.step_size(),
            bounds_max: model.bounds.max.to_array(),
            early_stop: model.early_stop_transmittance,
            bounds_size: model.bounds.size().to_array(),
            max_steps: model.steps_per_diagonal,
            background: [0.0; 3],
            occupancy_resolution: model.occupancy.resolution,
            levels: levels as u32,
            enc4: enc4 as u32,
            ray_count: 0,
            off_d0: offsets[0],
            off_d1: offsets[1],
            off_c0: offsets[2],
            off_c1: offsets[3],
            off_c2: offsets[4],
            level,
        };

        let device = &ctx.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor { label: Some("ngp"), source: wgpu::ShaderSource::Wgsl(NGP_WGSL.into()) });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("ngp_main"),
            layout: None,
            module: &module,
            entry_point: Some("ngp_main"),
            compilation_options: Default::default(),
            cache: None,
        });
        use wgpu::BufferUsages as U;
        let init = |label: &str, contents: &[u8], usage| device.create_buffer_init(&wgpu::util::BufferInitDescriptor { label: Some(label), contents, usage });
        let params = init("ngp params", bytemuck::bytes_of(&base), U::UNIFORM | U::COPY_DST);
        let texels = wgpu::Extent3d { width: weights.len() as u32, height: 1, depth_or_array_layers: 1 };
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("ngp weights"),
            size: texels,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D1,
            format: wgpu::TextureFormat::Rgba32Float,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        ctx.queue.write_texture(
            wgpu::TexelCopyTextureInfo { texture: &texture, mip_level: 0, origin: wgpu::Origin3d::ZERO, aspect: wgpu::TextureAspect::All },
            bytemuck::cast_slice(&weights),
            wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: None, rows_per_image: None },
            texels,
        );
        let weights = texture.create_view(&Default::default());
        let grid = init("ngp hash grid", bytemuck::cast_slice(&field.grid.params), U::STORAGE);
        let occupancy = init("ngp occupancy", bytemuck::cast_slice(&occupancy_words), U::STORAGE);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(gpu_err(e));
        }
        Ok(Self { ctx, pipeline, params, weights, grid, occupancy, base, scratch: Mutex::new(None), poison: false })
    }

    /// For tests: from now on, fill the output with NaN before every dispatch, so a ray the
    /// kernel does not write shows up as NaN rather than as an earlier call's value.
    #[doc(hidden)]
    pub fn poison_output(&mut self) {
        self.poison = true;
    }

    fn make_scratch(&self, chunk: usize) -> Scratch {
        let device = &self.ctx.device;
        use wgpu::BufferUsages as U;
        let buffer = |label, size: usize, usage| {
            device.create_buffer(&wgpu::BufferDescriptor { label: Some(label), size: size.max(16) as u64, usage, mapped_at_creation: false })
        };
        let rays = buffer("ngp rays", chunk * 32, U::STORAGE | U::COPY_DST);
        let state = buffer("ngp ray state", chunk * RAY_STATE_BYTES, U::STORAGE | U::COPY_DST);
        let out = buffer("ngp out", chunk * 16, U::STORAGE | U::COPY_SRC | U::COPY_DST);
        let readback = buffer("ngp readback", chunk * 16, U::MAP_READ | U::COPY_DST);
        let entries = [
            self.params.as_entire_binding(),
            wgpu::BindingResource::TextureView(&self.weights),
            self.grid.as_entire_binding(),
            self.occupancy.as_entire_binding(),
            rays.as_entire_binding(),
            out.as_entire_binding(),
            state.as_entire_binding(),
        ]
        .into_iter()
        .enumerate()
        .map(|(binding, resource)| wgpu::BindGroupEntry { binding: binding as u32, resource })
        .collect::<Vec<_>>();
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("ngp"),
            layout: &self.pipeline.get_bind_group_layout(0),
            entries: &entries,
        });
        Scratch { chunk, rays, state, out, readback, bind_group }
    }

    fn wait(&self) -> Result<(), RenderError> {
        self.ctx.device.poll(wgpu::PollType::wait_indefinitely()).map(|_| ()).map_err(gpu_err)
    }

    /// Renders rays (world origin, unit direction) over `background`, like
    /// [`NgpModel::render`]: (rgb, opacity) per ray, and the wall time in ms of the whole call
    /// (ray upload, dispatches, readback).
    pub fn render(&self, rays: &[(Vec3, Vec3)], background: Vec3) -> Result<(Vec<(Vec3, f32)>, f64), RenderError> {
        let start = Instant::now();
        if rays.is_empty() {
            return Ok((Vec::new(), 0.0));
        }
        let ctx = &*self.ctx;
        let chunk = rays.len().min(CHUNK_RAYS);
        // Kept between calls and regrown only when a call needs more room. Held for the whole
        // call: concurrent calls would also share the params buffer.
        let mut slot = self.scratch.lock().unwrap_or_else(|e| e.into_inner());
        if slot.as_ref().is_none_or(|s| s.chunk < chunk) {
            *slot = Some(self.make_scratch(chunk));
        }
        let Scratch { rays: rays_buf, state, out, readback, bind_group, .. } = slot.as_ref().expect("scratch was just made");
        let rounds = rounds(self.base.max_steps);
        let mut result = Vec::with_capacity(rays.len());
        for (index, part) in rays.chunks(CHUNK_RAYS).enumerate() {
            let _span = tracing::trace_span!("ngp chunk", index, rays = part.len()).entered();
            let n = part.len();
            let packed: Vec<[f32; 4]> = part.iter().flat_map(|(o, d)| [o.extend(0.0).to_array(), d.extend(0.0).to_array()]).collect();
            ctx.queue.write_buffer(rays_buf, 0, bytemuck::cast_slice(&packed));
            let params = NgpParams { background: background.to_array(), ray_count: n as u32, ..self.base };
            ctx.queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
            if self.poison {
                ctx.queue.write_buffer(out, 0, bytemuck::cast_slice(&vec![f32::NAN; 4 * n]));
            }
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            enc.clear_buffer(state, 0, Some((n * RAY_STATE_BYTES) as u64));
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, bind_group, &[]);
                let (x, y) = dispatch_2d((n as u32).div_ceil(64));
                for _ in 0..rounds {
                    pass.dispatch_workgroups(x, y, 1);
                }
            }
            enc.copy_buffer_to_buffer(out, 0, readback, 0, n as u64 * 16);
            ctx.queue.submit([enc.finish()]);
            self.wait()?;
            let slice = readback.slice(..n as u64 * 16);
            slice.map_async(wgpu::MapMode::Read, |_| {});
            self.wait()?;
            // Copy out, then unmap even on error: the buffer is reused by the next chunk.
            let copied = slice.get_mapped_range().map(|data| {
                let rgba: &[[f32; 4]] = bytemuck::cast_slice(&data);
                result.extend(rgba.iter().map(|&[r, g, b, a]| (Vec3::new(r, g, b), a)));
            });
            readback.unmap();
            copied.map_err(gpu_err)?;
        }
        Ok((result, start.elapsed().as_secs_f64() * 1e3))
    }
}

#[cfg(test)]
mod tests {
    use rand::{SeedableRng, rngs::SmallRng};

    use super::*;
    use crate::ngp::{FieldConfig, HashGridConfig};

    // The comparison with the CPU reference needs a trained field: it is in the nephele-train
    // crate (`trainer/gpu_tests.rs`).

    #[test]
    fn ngp_kernel_validates_and_structs_match() {
        let module = naga::front::wgsl::parse_str(NGP_WGSL).unwrap_or_else(|e| panic!("ngp.wgsl: {}", e.emit_to_string(NGP_WGSL)));
        naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all())
            .validate(&module)
            .unwrap_or_else(|e| panic!("ngp.wgsl: {e:?}"));
        let size_of = |ty: &str| {
            let (h, _) = module.types.iter().find(|(_, t)| t.name.as_deref() == Some(ty)).unwrap();
            module.types[h].inner.size(module.to_ctx()) as usize
        };
        assert_eq!(size_of("Params"), std::mem::size_of::<NgpParams>());
        assert_eq!(size_of("RayState"), RAY_STATE_BYTES);
        let constant = |name: &str| {
            let (_, c) = module.constants.iter().find(|(_, c)| c.name.as_deref() == Some(name)).unwrap();
            match module.global_expressions[c.init] {
                naga::Expression::Literal(naga::Literal::U32(v)) => v,
                ref e => panic!("{name} = {e:?}"),
            }
        };
        assert_eq!([constant("BATCH"), constant("ROUND_BATCHES"), constant("ROUND_POSITIONS")], [BATCH, ROUND_BATCHES, ROUND_POSITIONS]);
        assert_eq!([rounds(256), rounds(1024)], [3, 9]);
    }

    #[test]
    fn ngp_refuses_unsupported_layouts_and_packs_rows() {
        // instant-ngp's widths (those of every training preset), then one layer off each way.
        let mut config = FieldConfig {
            grid: HashGridConfig { levels: 8, log2_table_size: 14, base_resolution: 16, finest_resolution: 256 },
            density_hidden: vec![64],
            colour_hidden: vec![64, 64],
        };
        let field = |config: &FieldConfig| Field::new(config, &mut SmallRng::seed_from_u64(1));
        assert!(check_layout(&field(&config)).is_ok());
        config.density_hidden = vec![32];
        assert!(matches!(check_layout(&field(&config)), Err(RenderError::BadSettings(_))));
        config.density_hidden = vec![64];
        config.colour_hidden = vec![64];
        let err = check_layout(&field(&config)).unwrap_err().to_string();
        assert!(err.contains("colour [32, 64, 3]"), "{err}");

        // A [5, 3] layer: rows padded to 2 vec4s, a fourth zero row, then one bias vec4.
        let mut rng = SmallRng::seed_from_u64(3);
        let mut mlp = Mlp::new(&[5, 3], &mut rng);
        mlp.update(|p| p.iter_mut().enumerate().for_each(|(i, v)| *v = i as f32 + 1.0));
        let (mut out, mut offsets) = (Vec::new(), Vec::new());
        pack_mlp(&mlp, 0, &mut out, &mut offsets);
        assert_eq!(offsets, [0]);
        assert_eq!(out.len(), layer_vec4s(2, 3));
        assert_eq!(out[0..2], [[1.0, 2.0, 3.0, 4.0], [5.0, 0.0, 0.0, 0.0]]);
        assert_eq!(out[4..8], [[11.0, 12.0, 13.0, 14.0], [15.0, 0.0, 0.0, 0.0], [0.0; 4], [0.0; 4]]);
        assert_eq!(out[8], [16.0, 17.0, 18.0, 0.0]);
        // The density network's first layer is padded to the kernel's input width.
        let (mut out, mut offsets) = (Vec::new(), Vec::new());
        pack_mlp(&mlp, 4, &mut out, &mut offsets);
        assert_eq!(out.len(), layer_vec4s(4, 3));
        assert_eq!(out[0..4], [[1.0, 2.0, 3.0, 4.0], [5.0, 0.0, 0.0, 0.0], [0.0; 4], [0.0; 4]]);
        assert_eq!(out[16], [16.0, 17.0, 18.0, 0.0]);
        assert_eq!([1, 2, 8, 9, 16, 32].map(encoding_vec4s), [4, 4, 4, 8, 8, 16]);
    }
}
