//! wgpu compute backend for i-NOLF. Density and diffuse bricks live in 3D texture atlases
//! (R16Float / Rgba16Float, or Rgba8Unorm for 8-bit diffuse; hardware trilinear filtering);
//! index grids, the perfect hash and the MLP weights share one storage buffer of words. A
//! batch of views of any sizes is one list of pixels, rendered in chunks: `march` (one thread
//! per pixel) appends hits, `args` sizes an indirect dispatch, `shade` (one thread per hit)
//! runs the networks — missed rays never touch the networks.

use std::{sync::Arc, time::Instant};

use bytemuck::{Pod, Zeroable};
use glam::{UVec3, Vec3};
use wgpu::util::DeviceExt;
pub use wgpu::DeviceType;

pub mod compose;
pub mod ngp;

use crate::{
    asset::Asset,
    camera::RayFrame,
    cubes::{CubeStorage, TextureCubes, atlas_bricks_per_axis},
    model::RenderSettings,
    render::{Backend, CancelFlag, Frame, PreparedAsset, RenderError, RenderOutput, RenderStats, ViewRequest, check_request},
};

/// WGSL sources; each kernel is the common prelude plus its own file.
pub const COMMON_WGSL: &str = include_str!("common.wgsl");
pub const MARCH_WGSL: &str = include_str!("march.wgsl");
pub const SHADE_WGSL: &str = include_str!("shade.wgsl");

pub fn kernel_sources() -> [(&'static str, String); 2] {
    [("march", format!("{COMMON_WGSL}\n{MARCH_WGSL}")), ("shade", format!("{COMMON_WGSL}\n{SHADE_WGSL}"))]
}

/// Pixels per chunk: bounds the hit list and output buffers (32 B + 8 B per pixel).
const CHUNK_PIXELS: u32 = 1 << 22;

/// Keep in sync with `Params` in common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Params {
    pub bounds_min: [f32; 3],
    pub step: f32,
    pub bounds_size: [f32; 3],
    pub alpha_min: f32,
    pub density_atlas_size: [f32; 3],
    pub stop_ratio: f32,
    pub diffuse_atlas_size: [f32; 3],
    pub early_stop: f32,
    pub density_atlas_bricks: [u32; 3],
    pub density_grid: u32,
    pub diffuse_atlas_bricks: [u32; 3],
    pub diffuse_grid: u32,
    pub density_brick: u32,
    pub diffuse_brick: u32,
    pub psh_grid: u32,
    pub table_edge: u32,
    pub offset_edge: u32,
    pub features: u32,
    pub feature_words: u32,
    pub mlp_input: u32,
    pub off_density_index: u32,
    pub off_diffuse_index: u32,
    pub off_psh_keys: u32,
    pub off_psh_offsets: u32,
    pub off_psh_values: u32,
    pub off_mlp: u32,
    pub view_count: u32,
    pub chunk_start: u32,
    pub chunk_len: u32,
    /// The multi-hit rule (`model::HitRule`); `hit_gap` in ray-parameter units.
    pub hit_tau: f32,
    pub max_hits: u32,
    pub hit_gap: f32,
}
const _: () = assert!(std::mem::size_of::<Params>() == 176);

/// Keep in sync with `View` in common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuView {
    pub origin_near: [f32; 3],
    pub t_shift: f32,
    pub rot0: [f32; 3],
    pub scale: f32,
    pub rot1: [f32; 3],
    pub pixel_offset: u32,
    pub rot2: [f32; 3],
    pub width: u32,
    pub intrinsics: [f32; 4],
    pub background: [f32; 3],
    pub height: u32,
}
const _: () = assert!(std::mem::size_of::<GpuView>() == 96);

/// Bytes of `Hit` in common.wgsl.
pub const HIT_BYTES: u64 = 32;

/// An adapter, device and the compiled kernels.
pub struct GpuContext {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    march: wgpu::ComputePipeline,
    args: wgpu::ComputePipeline,
    shade: wgpu::ComputePipeline,
    sampler: wgpu::Sampler,
}

pub(crate) fn gpu_err(e: impl std::fmt::Display) -> RenderError {
    RenderError::Gpu(e.to_string())
}

impl GpuContext {
    /// The default adapter (a real GPU if there is one, else lavapipe). Errors if none exists.
    pub fn new() -> Result<Arc<Self>, RenderError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            ..Default::default()
        }))
        .map_err(|e| RenderError::Gpu(format!("no GPU adapter (install mesa-vulkan-drivers for the software one): {e}")))?;
        let info = adapter.get_info();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("nephele"),
            required_features: wgpu::Features::empty(),
            required_limits: adapter.limits(),
            ..Default::default()
        }))
        .map_err(gpu_err)?;
        let module = |name: &str, src: &str| {
            device.create_shader_module(wgpu::ShaderModuleDescriptor { label: Some(name), source: wgpu::ShaderSource::Wgsl(src.into()) })
        };
        let [(_, march_src), (_, shade_src)] = kernel_sources();
        let march_mod = module("march", &march_src);
        let shade_mod = module("shade", &shade_src);
        let pipeline = |m: &wgpu::ShaderModule, entry: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: None,
                module: m,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("atlas"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        Ok(Arc::new(Self {
            march: pipeline(&march_mod, "march_main"),
            args: pipeline(&march_mod, "args_main"),
            shade: pipeline(&shade_mod, "shade_main"),
            sampler,
            device,
            queue,
            info,
        }))
    }

    pub fn describe(&self) -> String {
        format!("{} ({:?}, {:?})", self.info.name, self.info.backend, self.info.device_type)
    }
}

/// The wgpu backend.
pub struct GpuBackend {
    pub ctx: Arc<GpuContext>,
}

impl GpuBackend {
    pub fn new() -> Result<Self, RenderError> {
        Ok(Self { ctx: GpuContext::new()? })
    }
}

struct Atlas {
    view: wgpu::TextureView,
    bricks: UVec3,
    size: Vec3,
}

fn upload_atlas(ctx: &GpuContext, cubes: &TextureCubes, label: &str) -> Result<Atlas, RenderError> {
    let edge = cubes.brick + 1;
    let max_dim = ctx.device.limits().max_texture_dimension_3d;
    let bricks = atlas_bricks_per_axis(cubes.brick_count(), edge, max_dim)
        .ok_or_else(|| RenderError::Gpu(format!("{label}: {} bricks do not fit a {max_dim}³ atlas", cubes.brick_count())))?;
    let size = bricks * edge;
    let ch = cubes.channels as usize;
    let bpv = cubes.storage.bytes_per_value() as usize;
    let mut texels = vec![0u8; (size.x * size.y * size.z) as usize * ch * bpv];
    let e = edge as usize;
    for b in 0..cubes.brick_count() {
        let bu = b as u32;
        let origin = UVec3::new(bu % bricks.x, (bu / bricks.x) % bricks.y, bu / (bricks.x * bricks.y)) * edge;
        let src = &cubes.values[b * e * e * e * ch..(b + 1) * e * e * e * ch];
        for z in 0..e {
            for y in 0..e {
                let row = (origin.x as usize + size.x as usize * (origin.y as usize + y + size.y as usize * (origin.z as usize + z))) * ch;
                let from = (e * (y + e * z)) * ch;
                for (k, v) in src[from..from + e * ch].iter().enumerate() {
                    let at = (row + k) * bpv;
                    match cubes.storage {
                        CubeStorage::F16 => texels[at..at + 2].copy_from_slice(&half::f16::from_f32(*v).to_le_bytes()),
                        CubeStorage::Unorm8 => texels[at] = CubeStorage::unorm8(*v),
                    }
                }
            }
        }
    }
    use wgpu::TextureFormat as F;
    let format = match (ch, cubes.storage) {
        (1, CubeStorage::F16) => F::R16Float,
        (_, CubeStorage::F16) => F::Rgba16Float,
        (1, CubeStorage::Unorm8) => F::R8Unorm,
        (_, CubeStorage::Unorm8) => F::Rgba8Unorm,
    };
    let extent = wgpu::Extent3d { width: size.x, height: size.y, depth_or_array_layers: size.z };
    let texture = ctx.device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: extent,
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D3,
        format,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    ctx.queue.write_texture(
        wgpu::TexelCopyTextureInfo { texture: &texture, mip_level: 0, origin: wgpu::Origin3d::ZERO, aspect: wgpu::TextureAspect::All },
        &texels,
        wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: Some(size.x * (bpv * ch) as u32), rows_per_image: Some(size.y) },
        extent,
    );
    Ok(Atlas { view: texture.create_view(&Default::default()), bricks, size: size.as_vec3() })
}

/// The asset on the GPU.
struct GpuPrepared {
    ctx: Arc<GpuContext>,
    asset: Arc<Asset>,
    words: wgpu::Buffer,
    mlp: wgpu::Buffer,
    density: Atlas,
    diffuse: Atlas,
    /// Params with the per-render fields left zero.
    base: Params,
    scratch: std::sync::Mutex<Option<Scratch>>,
}

impl Backend for GpuBackend {
    fn name(&self) -> String {
        format!("wgpu: {}", self.ctx.describe())
    }

    fn prepare(&self, asset: Arc<Asset>) -> Result<Box<dyn PreparedAsset>, RenderError> {
        let ctx = self.ctx.clone();
        let a = &*asset;
        // One word buffer: index grids, PSH keys/offsets/values (f16 pairs), MLP (f32 bits).
        let mut words: Vec<u32> = Vec::new();
        let push = |w: &mut Vec<u32>, data: &[u32]| {
            let at = w.len() as u32;
            w.extend_from_slice(data);
            at
        };
        let off_density_index = push(&mut words, bytemuck::cast_slice(&a.density.index));
        let off_diffuse_index = push(&mut words, bytemuck::cast_slice(&a.diffuse.index));
        let off_psh_keys = push(&mut words, &a.psh.keys);
        let off_psh_offsets = push(&mut words, &a.psh.offsets);
        let features = a.psh.features as usize;
        let feature_words = features.div_ceil(2);
        let packed: Vec<u32> = a
            .psh
            .values
            .chunks_exact(features)
            .flat_map(|f| {
                (0..feature_words).map(move |k| {
                    let lo = half::f16::from_f32(f[2 * k]).to_bits() as u32;
                    let hi = f.get(2 * k + 1).map_or(0, |v| half::f16::from_f32(*v).to_bits() as u32);
                    lo | (hi << 16)
                })
            })
            .collect();
        let off_psh_values = push(&mut words, &packed);
        let mlp = ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("mlp"),
            contents: bytemuck::cast_slice(&pack_mlp(&a.mlp)),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let limit = ctx.device.limits().max_storage_buffer_binding_size as usize;
        if words.len() * 4 > limit {
            return Err(RenderError::Gpu(format!("asset needs {} MiB of storage; the adapter allows {}", words.len() >> 18, limit >> 20)));
        }
        let words = ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("asset words"),
            contents: bytemuck::cast_slice(&words),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let density = upload_atlas(&ctx, &a.density, "density atlas")?;
        let diffuse = upload_atlas(&ctx, &a.diffuse, "diffuse atlas")?;
        let base = Params {
            bounds_min: a.bounds.min.to_array(),
            step: a.march.step,
            bounds_size: a.bounds.size().to_array(),
            alpha_min: a.march.alpha_min,
            density_atlas_size: density.size.to_array(),
            stop_ratio: 1.0,
            diffuse_atlas_size: diffuse.size.to_array(),
            early_stop: 0.0,
            density_atlas_bricks: density.bricks.to_array(),
            density_grid: a.density.grid,
            diffuse_atlas_bricks: diffuse.bricks.to_array(),
            diffuse_grid: a.diffuse.grid,
            density_brick: a.density.brick,
            diffuse_brick: a.diffuse.brick,
            psh_grid: a.psh.grid,
            table_edge: a.psh.table_edge,
            offset_edge: a.psh.offset_edge,
            features: a.psh.features,
            feature_words: feature_words as u32,
            mlp_input: a.mlp.input as u32,
            off_density_index,
            off_diffuse_index,
            off_psh_keys,
            off_psh_offsets,
            off_psh_values,
            off_mlp: 0,
            view_count: 0,
            chunk_start: 0,
            chunk_len: 0,
            hit_tau: 1.0,
            max_hits: 1,
            hit_gap: 0.0,
        };
        Ok(Box::new(GpuPrepared { ctx, asset, words, mlp, density, diffuse, base, scratch: Default::default() }))
    }
}

/// vec4s of `Mlp` in common.wgsl.
pub const MLP_VEC4S: usize = 2145;

/// The specular MLP as vec4 rows for the uniform buffer: w0 (64 × in4, inputs zero-padded to a
/// multiple of 4), b0 (16), w1 (64 × 16), b1 (16), w2 (4 × 16), b2 (1); zero-filled to
/// [`MLP_VEC4S`].
pub fn pack_mlp(m: &crate::mlp::SpecularMlp) -> Vec<[f32; 4]> {
    use crate::mlp::HIDDEN;
    let in4 = m.input.div_ceil(4);
    let mut out = Vec::with_capacity(MLP_VEC4S);
    let rows = |out: &mut Vec<[f32; 4]>, w: &[f32], cols: usize| {
        for row in w.chunks_exact(cols) {
            for q in 0..cols.div_ceil(4) {
                out.push(std::array::from_fn(|i| row.get(4 * q + i).copied().unwrap_or(0.0)));
            }
        }
    };
    rows(&mut out, &m.w0, m.input);
    debug_assert_eq!(out.len(), HIDDEN * in4);
    rows(&mut out, &m.b0, HIDDEN);
    rows(&mut out, &m.w1, HIDDEN);
    rows(&mut out, &m.b1, HIDDEN);
    rows(&mut out, &m.w2, HIDDEN);
    rows(&mut out, &m.b2, 4);
    out.resize(MLP_VEC4S, [0.0; 4]);
    out
}

pub(crate) fn dispatch_2d(groups: u32) -> (u32, u32) {
    (groups.clamp(1, 65535), groups.div_ceil(65535).max(1))
}

/// Per-render buffers sized for `views` views and `chunk` pixels per chunk, with their bind groups.
struct Scratch {
    views: usize,
    chunk: u32,
    views_buf: wgpu::Buffer,
    params_buf: wgpu::Buffer,
    pixels: wgpu::Buffer,
    counter: wgpu::Buffer,
    args: wgpu::Buffer,
    readback: wgpu::Buffer,
    march_bg: wgpu::BindGroup,
    args_bg: wgpu::BindGroup,
    shade_bg: wgpu::BindGroup,
}

impl GpuPrepared {
    fn make_scratch(&self, views: usize, chunk: u32) -> Scratch {
        let ctx = &*self.ctx;
        let buffer = |label, size: u64, usage| {
            ctx.device.create_buffer(&wgpu::BufferDescriptor { label: Some(label), size: size.max(16), usage, mapped_at_creation: false })
        };
        use wgpu::BufferUsages as U;
        let views_buf = buffer("views", (views * std::mem::size_of::<GpuView>()) as u64, U::STORAGE | U::COPY_DST);
        let params_buf = buffer("params", std::mem::size_of::<Params>() as u64, U::UNIFORM | U::COPY_DST);
        let pixels = buffer("pixels", chunk as u64 * 8, U::STORAGE | U::COPY_SRC);
        let hits = buffer("hits", chunk as u64 * HIT_BYTES, U::STORAGE);
        let counter = buffer("counter", 16, U::STORAGE | U::COPY_SRC | U::COPY_DST);
        let args = buffer("args", 16, U::STORAGE | U::INDIRECT);
        let readback = buffer("readback", chunk as u64 * 8 + 16, U::MAP_READ | U::COPY_DST);
        let resources = [
            (0, params_buf.as_entire_binding()),
            (1, views_buf.as_entire_binding()),
            (2, self.words.as_entire_binding()),
            (3, wgpu::BindingResource::TextureView(&self.density.view)),
            (4, wgpu::BindingResource::Sampler(&ctx.sampler)),
            (5, wgpu::BindingResource::TextureView(&self.diffuse.view)),
            (6, pixels.as_entire_binding()),
            (7, hits.as_entire_binding()),
            (8, counter.as_entire_binding()),
            (9, args.as_entire_binding()),
            (10, self.mlp.as_entire_binding()),
        ];
        let march_bg = self.bind_group(&ctx.march, &[0, 1, 2, 3, 4, 6, 7, 8], &resources);
        let args_bg = self.bind_group(&ctx.args, &[8, 9], &resources);
        let shade_bg = self.bind_group(&ctx.shade, &[0, 1, 2, 4, 5, 6, 7, 8, 10], &resources);
        Scratch { views, chunk, views_buf, params_buf, pixels, counter, args, readback, march_bg, args_bg, shade_bg }
    }

    fn bind_group(&self, pipeline: &wgpu::ComputePipeline, used: &[u32], resources: &[(u32, wgpu::BindingResource<'_>)]) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = resources
            .iter()
            .filter(|(b, _)| used.contains(b))
            .map(|(b, r)| wgpu::BindGroupEntry { binding: *b, resource: r.clone() })
            .collect();
        self.ctx.device.create_bind_group(&wgpu::BindGroupDescriptor { label: None, layout: &pipeline.get_bind_group_layout(0), entries: &entries })
    }

    fn wait(&self) -> Result<(), RenderError> {
        self.ctx.device.poll(wgpu::PollType::wait_indefinitely()).map(|_| ()).map_err(gpu_err)
    }
}

impl PreparedAsset for GpuPrepared {
    fn asset(&self) -> &Arc<Asset> {
        &self.asset
    }

    fn render_cancellable(&self, views: &[ViewRequest], settings: &RenderSettings, cancel: &CancelFlag) -> Result<RenderOutput, RenderError> {
        check_request(views, settings)?;
        let ctx = &*self.ctx;
        let dev = &ctx.device;
        let a = &*self.asset;
        let settings = &settings.for_asset(&a.march);
        let rule = settings.hit_rule(&a.march.hits);
        let start = Instant::now();
        let mut gpu_views = Vec::with_capacity(views.len());
        let mut total: u64 = 0;
        for v in views {
            let f = RayFrame::new(&v.view, &v.instance, a.bounds.center(), a.bounds.radius());
            let k = f.intrinsics;
            gpu_views.push(GpuView {
                origin_near: f.origin_near_in_object.to_array(),
                t_shift: f.t_shift,
                rot0: f.object_from_camera[0].to_array(),
                scale: f.scale,
                rot1: f.object_from_camera[1].to_array(),
                pixel_offset: total as u32,
                rot2: f.object_from_camera[2].to_array(),
                width: k.width,
                intrinsics: [k.fx, k.fy, k.cx, k.cy],
                background: v.background.to_array(),
                height: k.height,
            });
            total += k.pixel_count();
        }
        if total > u32::MAX as u64 / 2 {
            return Err(RenderError::BadSettings(format!("batch of {total} pixels is too large")));
        }
        let chunk = (total as u32).min(CHUNK_PIXELS);
        // Per-frame buffers and bind groups are kept between calls and regrown only when a
        // batch needs more room: streaming renders the same sizes every frame.
        let mut scratch_slot = self.scratch.lock().unwrap_or_else(|e| e.into_inner());
        if !scratch_slot.as_ref().is_some_and(|s| s.views >= gpu_views.len() && s.chunk >= chunk) {
            *scratch_slot = Some(self.make_scratch(gpu_views.len(), chunk));
        }
        let scratch = scratch_slot.as_ref().expect("scratch was just made");
        ctx.queue.write_buffer(&scratch.views_buf, 0, bytemuck::cast_slice(&gpu_views));
        let Scratch { params_buf, pixels, counter, args, readback, march_bg, args_bg, shade_bg, .. } = scratch;

        let mut out_pixels: Vec<[u32; 2]> = Vec::with_capacity(total as usize);
        let mut stats = RenderStats { rays: total, ..Default::default() };
        let mut chunk_start = 0u32;
        while (chunk_start as u64) < total {
            cancel.check()?;
            let chunk_len = ((total - chunk_start as u64) as u32).min(CHUNK_PIXELS);
            let params = Params {
                step: a.march.step * settings.step_scale,
                alpha_min: settings.alpha_min.unwrap_or(a.march.alpha_min),
                stop_ratio: settings.stop_ratio,
                early_stop: settings.stop_below(),
                hit_tau: rule.tau,
                max_hits: if rule.one_hit() { 1 } else { rule.max_hits },
                hit_gap: rule.gap_steps * a.march.step * settings.step_scale,
                view_count: views.len() as u32,
                chunk_start,
                chunk_len,
                ..self.base
            };
            ctx.queue.write_buffer(params_buf, 0, bytemuck::bytes_of(&params));
            let t0 = Instant::now();
            let mut enc = dev.create_command_encoder(&Default::default());
            enc.clear_buffer(counter, 0, None);
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&ctx.march);
                pass.set_bind_group(0, march_bg, &[]);
                let (x, y) = dispatch_2d(chunk_len.div_ceil(64));
                pass.dispatch_workgroups(x, y, 1);
                pass.set_pipeline(&ctx.args);
                pass.set_bind_group(0, args_bg, &[]);
                pass.dispatch_workgroups(1, 1, 1);
            }
            ctx.queue.submit([enc.finish()]);
            self.wait()?;
            let t1 = Instant::now();
            let mut enc = dev.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&ctx.shade);
                pass.set_bind_group(0, shade_bg, &[]);
                pass.dispatch_workgroups_indirect(args, 0);
            }
            enc.copy_buffer_to_buffer(pixels, 0, readback, 0, chunk_len as u64 * 8);
            enc.copy_buffer_to_buffer(counter, 0, readback, chunk_len as u64 * 8, 16);
            ctx.queue.submit([enc.finish()]);
            self.wait()?;
            let t2 = Instant::now();
            stats.march_ms += (t1 - t0).as_secs_f64() * 1e3;
            stats.shade_ms += (t2 - t1).as_secs_f64() * 1e3;
            let slice = readback.slice(..chunk_len as u64 * 8 + 16);
            slice.map_async(wgpu::MapMode::Read, |_| {});
            self.wait()?;
            // Copy out, then unmap even on error: the buffer is reused by the next render.
            let hits = slice.get_mapped_range().map(|data| {
                let (px, tail) = data.split_at(chunk_len as usize * 8);
                out_pixels.extend_from_slice(bytemuck::cast_slice(px));
                u32::from_le_bytes([tail[0], tail[1], tail[2], tail[3]]) as u64
            });
            readback.unmap();
            stats.hits += hits.map_err(gpu_err)?;
            chunk_start += chunk_len;
        }
        let mut frames = Vec::with_capacity(views.len());
        let mut at = 0usize;
        for v in &gpu_views {
            let n = (v.width * v.height) as usize;
            let px = &out_pixels[at..at + n];
            frames.push(Frame {
                width: v.width,
                height: v.height,
                rgba: px.iter().flat_map(|p| p[0].to_le_bytes()).collect(),
                depth: px.iter().map(|p| f32::from_bits(p[1])).map(|d| if d < 0.0 { f32::INFINITY } else { d }).collect(),
            });
            at += n;
        }
        stats.total_ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(RenderOutput { frames, stats })
    }
}
