// common.wgsl — bindings, structs and ray helpers shared by the i-NOLF kernels.
// Keep the structs in sync with `gpu/mod.rs` (`Params`, `GpuView`, `Hit`).
// Maths mirrors `model.rs` / `camera.rs` (docs/architecture.md §3); see there for the derivations.

const BIG: f32 = 1e30;
const TINY_DIR: f32 = 1e-12;
const HIDDEN: u32 = 64u;

struct Params {
    bounds_min: vec3<f32>, step: f32,
    bounds_size: vec3<f32>, alpha_min: f32,
    density_atlas_size: vec3<f32>, stop_ratio: f32,
    diffuse_atlas_size: vec3<f32>, early_stop: f32,
    density_atlas_bricks: vec3<u32>, density_grid: u32,
    diffuse_atlas_bricks: vec3<u32>, diffuse_grid: u32,
    density_brick: u32, diffuse_brick: u32, psh_grid: u32, table_edge: u32,
    offset_edge: u32, features: u32, feature_words: u32, mlp_input: u32,
    off_density_index: u32, off_diffuse_index: u32, off_psh_keys: u32, off_psh_offsets: u32,
    off_psh_values: u32, off_mlp: u32, view_count: u32, chunk_start: u32,
    chunk_len: u32, hit_tau: f32, max_hits: u32, hit_gap: f32,
}

struct View {
    origin_near: vec3<f32>, t_shift: f32,
    rot0: vec3<f32>, scale: f32,
    rot1: vec3<f32>, pixel_offset: u32,
    rot2: vec3<f32>, width: u32,
    intr: vec4<f32>,
    background: vec3<f32>, height: u32,
}

// A hit ray: its primary query at `t_hit` and up to two more at `t_more` with blend weights
// `beta_more` (0 when absent); the primary's weight is 1 − their sum (model.rs `MultiHit`).
struct Hit {
    pixel: u32,
    view: u32,
    t_hit: f32,
    alpha_c: f32,
    t_more: vec2<f32>,
    beta_more: vec2<f32>,
}

struct Counter {
    hits: atomic<u32>,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> views: array<View>;
// Index grids, PSH tables (f16 pairs) and MLP weights (f32 bits), at word offsets in `params`.
@group(0) @binding(2) var<storage, read> asset: array<u32>;
@group(0) @binding(3) var density_atlas: texture_3d<f32>;
@group(0) @binding(4) var atlas_sampler: sampler;
@group(0) @binding(5) var diffuse_atlas: texture_3d<f32>;
// Per pixel of the chunk: packed RGBA8 and depth bits (negative depth = miss).
@group(0) @binding(6) var<storage, read_write> out_pixels: array<vec2<u32>>;
@group(0) @binding(7) var<storage, read_write> hits: array<Hit>;
@group(0) @binding(8) var<storage, read_write> counter: Counter;
@group(0) @binding(9) var<storage, read_write> dispatch_args: array<u32, 3>;
// Specular MLP as vec4 rows (inputs padded to `mlp_in4` vec4s) in a uniform buffer: 8× faster
// than storage on lavapipe. Loads at a loop index are still per-lane gathers there (Mesa 22.3
// llvmpipe); `ngp.wgsl` avoids them with a weight texture and constant-trip loops. Layout in
// `gpu::pack_mlp`.
const MLP_VEC4S: u32 = 2145u;
struct Mlp {
    w: array<vec4<f32>, MLP_VEC4S>,
}
@group(0) @binding(10) var<uniform> mlp: Mlp;

// Linear invocation index of a 2D dispatch of 64-wide workgroups.
fn linear_id(gid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return gid.x + gid.y * nwg.x * 64u;
}

// The view a chunk-global pixel belongs to (views sorted by pixel_offset).
fn find_view(pixel: u32) -> u32 {
    var lo = 0u;
    var hi = params.view_count - 1u;
    loop {
        if lo >= hi { break; }
        let mid = (lo + hi + 1u) / 2u;
        if views[mid].pixel_offset <= pixel { lo = mid; } else { hi = mid - 1u; }
    }
    return lo;
}

struct Ray {
    o: vec3<f32>,
    d: vec3<f32>,
}

// Offset-form primary ray, object space (camera.rs `RayFrame::ray`).
fn make_ray(v: View, px: u32, py: u32) -> Ray {
    let x = (f32(px) + 0.5 - v.intr.z) / v.intr.x;
    let y = -(f32(py) + 0.5 - v.intr.w) / v.intr.y;
    let r2 = x * x + y * y;
    let len = sqrt(1.0 + r2);
    let d = v.rot0 * (x / len) + v.rot1 * (y / len) + v.rot2 * (-1.0 / len);
    let off = v.rot0 * (x / len) + v.rot1 * (y / len) + v.rot2 * (r2 / (len * (len + 1.0)));
    return Ray(v.origin_near + v.t_shift * off, d);
}

fn ray_of_pixel(pixel_in_chunk: u32, view_index: u32) -> Ray {
    let v = views[view_index];
    let p = params.chunk_start + pixel_in_chunk - v.pixel_offset;
    return make_ray(v, p % v.width, p / v.width);
}

// Atlas texture coordinate of fine-grid point `g` in the cubes' brick `brick`.
fn atlas_coord(brick: u32, u: vec3<f32>, r: f32, bricks: vec3<u32>, size: vec3<f32>) -> vec3<f32> {
    let b = vec3<u32>(brick % bricks.x, (brick / bricks.x) % bricks.y, brick / (bricks.x * bricks.y));
    return (vec3<f32>(b) * (r + 1.0) + u + 0.5) / size;
}
