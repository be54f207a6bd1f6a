// ngp.wgsl — the instant-NGP baseline (Müller et al. 2022), one invocation per ray: clip to
// the scene box, fixed-step samples t0 + (k + ½)δ kept only in occupied cells, multiresolution
// hash encoding → density MLP [enc, 64, 16] → σ = exp(min(o₀, 15)); colour MLP
// [16 geometry features, SH4(dir); 64, 64, 3] → sigmoid; front-to-back compositing that stops
// after the sample where T < early_stop, then T·background. Mirrors `NgpModel::render`
// (ngp/model.rs `forward_chunk`, ngp/field.rs, hash_grid.rs, occupancy.rs, model.rs `clip_ray`).
// Keep `Params` and the weight layout in sync with `gpu/ngp.rs`.
//
// Speed on lavapipe (llvmpipe, Mesa 22.3), which runs 8 invocations per SIMD vector: a load
// from a buffer or private array at an index that is not a compile-time constant becomes a
// per-lane gather there (Mesa tests `nir_src_is_always_uniform`), even when every lane uses
// the same index, as the weights of a loop over a layer do. So the weights come from an
// rgba32f texture (one vector fetch per lane instead of four scalar gathers); the layer loops
// have constant trip counts, so they unroll and the activations are read at constant indices;
// and the next BATCH = 4 occupied samples of a ray go through the networks together, each
// weight fetched once for all four. Measured on a 96² view of the test field: plain loops over
// a uniform buffer 5.6 s, texture weights 3.1 s, constant trip counts 2.8 s, BATCH = 4 1.1 s,
// BATCH = 8 12 s (spills); the CPU reference 0.25 s. Samples after the early stop within a
// batch are evaluated and ignored, so the result is that of one sample at a time.
//
// llvmpipe also ends every loop of an invocation once all its loops together have run 65535
// iterations (LP_MAX_TGSI_LOOP_ITERATIONS), silently: a ray of a thousand samples got there.
// So a dispatch takes each ray at most ROUND_BATCHES batches and ROUND_POSITIONS sample
// positions further (a few thousand loop iterations), keeps its state in `ray_state`, and the
// host dispatches enough rounds for the longest ray; a finished ray returns at once.

const BIG: f32 = 1e30;
const TINY_DIR: f32 = 1e-12;
const MAX_LOG_DENSITY: f32 = 15.0;
const MAX_LEVELS: u32 = 32u;
// Per ray and dispatch: at most this many batches, and this many sample positions (`ROUND_*`
// in ngp.rs).
const ROUND_BATCHES: u32 = 32u;
const ROUND_POSITIONS: u32 = 2048u;
// vec4s of the widest activation (64 hidden units) and of the geometry features (16).
const HIDDEN4: u32 = 16u;
const GEO4: u32 = 4u;

struct Params {
    bounds_min: vec3<f32>, step: f32,
    bounds_max: vec3<f32>, early_stop: f32,
    bounds_size: vec3<f32>, max_steps: u32,
    background: vec3<f32>, occupancy_res: u32,
    // enc4: vec4s of the density network's input (2L features, zero-padded to 4, 8 or 16).
    levels: u32, enc4: u32, ray_count: u32, off_d0: u32,
    off_d1: u32, off_c0: u32, off_c1: u32, off_c2: u32,
    // Per level: resolution, dense (0/1), first entry, entries (a power of two if hashed).
    level: array<vec4<u32>, MAX_LEVELS>,
}

@group(0) @binding(0) var<uniform> params: Params;
// Both MLPs as one row of rgba32f texels, layer by layer at the `off_*` texels: output rows
// (zero-padded to a multiple of 4) of `in4` texels each, then the biases (`pack_mlp` in ngp.rs).
@group(0) @binding(1) var weights: texture_1d<f32>;
// Hash-grid features: one vec2 (F = 2) per entry, all levels back to back.
@group(0) @binding(2) var<storage, read> grid: array<vec2<f32>>;
// Occupancy bits, cell c at bit c % 32 of word c / 32 (the CPU's u64 words, little-endian).
@group(0) @binding(3) var<storage, read> occupancy: array<u32>;
// Per ray of the chunk: world origin (xyz, w unused), then unit direction.
@group(0) @binding(4) var<storage, read> rays: array<vec4<f32>>;
// Per ray: composited rgb over the background, opacity 1 − T (written once the ray is done).
@group(0) @binding(5) var<storage, read_write> out_rgba: array<vec4<f32>>;

// A ray between rounds; all zero (phase 0) before the first.
struct RayState {
    rgb: vec3<f32>,
    transmittance: f32,
    stop_transmittance: f32,
    // The next sample position k.
    next: u32,
    // 0 not started, 1 marching, 2 done.
    phase: u32,
    _pad: u32,
}
@group(0) @binding(6) var<storage, read_write> ray_state: array<RayState>;

// Activations of the BATCH samples evaluated together, one array per sample (a struct of four
// arrays passed to the layers by pointer made naga 30's SPIR-V writer panic): a layer reads
// act* and writes tmp*, or the other way round when `flip`.
const BATCH: u32 = 4u;
var<private> act0: array<vec4<f32>, HIDDEN4>;
var<private> act1: array<vec4<f32>, HIDDEN4>;
var<private> act2: array<vec4<f32>, HIDDEN4>;
var<private> act3: array<vec4<f32>, HIDDEN4>;
var<private> tmp0: array<vec4<f32>, HIDDEN4>;
var<private> tmp1: array<vec4<f32>, HIDDEN4>;
var<private> tmp2: array<vec4<f32>, HIDDEN4>;
var<private> tmp3: array<vec4<f32>, HIDDEN4>;

fn w(texel: u32) -> vec4<f32> {
    return textureLoad(weights, i32(texel), 0);
}

// acc + (w0·x, w1·x, w2·x, w3·x): four rows of a layer times one vec4 of its input.
fn mac(acc: vec4<f32>, w0: vec4<f32>, w1: vec4<f32>, w2: vec4<f32>, w3: vec4<f32>, x: vec4<f32>) -> vec4<f32> {
    return acc + vec4<f32>(dot(w0, x), dot(w1, x), dot(w2, x), dot(w3, x));
}

fn finish(acc: vec4<f32>, bias: vec4<f32>, relu: bool) -> vec4<f32> {
    let y = acc + bias;
    return select(y, max(y, vec4<f32>(0.0)), relu);
}

// (tmp* or act*) ← W·(act* or tmp*) + b for every sample of the batch: `out4` groups of 4 rows,
// ReLU when `relu`. The copies differ only in the input width (4, 8 or 16 vec4s), a constant
// so the inner loop unrolls and the activations are read at constant indices.
fn layer_in4(off: u32, out4: u32, relu: bool, flip: bool) {
    for (var j = 0u; j < out4; j++) {
        let r = off + 16u * j;
        var a0 = vec4<f32>(0.0);
        var a1 = vec4<f32>(0.0);
        var a2 = vec4<f32>(0.0);
        var a3 = vec4<f32>(0.0);
        for (var i = 0u; i < 4u; i++) {
            let w0 = w(r + i);
            let w1 = w(r + 4u + i);
            let w2 = w(r + 8u + i);
            let w3 = w(r + 12u + i);
            if flip {
                a0 = mac(a0, w0, w1, w2, w3, tmp0[i]);
                a1 = mac(a1, w0, w1, w2, w3, tmp1[i]);
                a2 = mac(a2, w0, w1, w2, w3, tmp2[i]);
                a3 = mac(a3, w0, w1, w2, w3, tmp3[i]);
            } else {
                a0 = mac(a0, w0, w1, w2, w3, act0[i]);
                a1 = mac(a1, w0, w1, w2, w3, act1[i]);
                a2 = mac(a2, w0, w1, w2, w3, act2[i]);
                a3 = mac(a3, w0, w1, w2, w3, act3[i]);
            }
        }
        let b = w(off + 16u * out4 + j);
        if flip {
            act0[j] = finish(a0, b, relu);
            act1[j] = finish(a1, b, relu);
            act2[j] = finish(a2, b, relu);
            act3[j] = finish(a3, b, relu);
        } else {
            tmp0[j] = finish(a0, b, relu);
            tmp1[j] = finish(a1, b, relu);
            tmp2[j] = finish(a2, b, relu);
            tmp3[j] = finish(a3, b, relu);
        }
    }
}

fn layer_in8(off: u32, out4: u32, relu: bool, flip: bool) {
    for (var j = 0u; j < out4; j++) {
        let r = off + 32u * j;
        var a0 = vec4<f32>(0.0);
        var a1 = vec4<f32>(0.0);
        var a2 = vec4<f32>(0.0);
        var a3 = vec4<f32>(0.0);
        for (var i = 0u; i < 8u; i++) {
            let w0 = w(r + i);
            let w1 = w(r + 8u + i);
            let w2 = w(r + 16u + i);
            let w3 = w(r + 24u + i);
            if flip {
                a0 = mac(a0, w0, w1, w2, w3, tmp0[i]);
                a1 = mac(a1, w0, w1, w2, w3, tmp1[i]);
                a2 = mac(a2, w0, w1, w2, w3, tmp2[i]);
                a3 = mac(a3, w0, w1, w2, w3, tmp3[i]);
            } else {
                a0 = mac(a0, w0, w1, w2, w3, act0[i]);
                a1 = mac(a1, w0, w1, w2, w3, act1[i]);
                a2 = mac(a2, w0, w1, w2, w3, act2[i]);
                a3 = mac(a3, w0, w1, w2, w3, act3[i]);
            }
        }
        let b = w(off + 32u * out4 + j);
        if flip {
            act0[j] = finish(a0, b, relu);
            act1[j] = finish(a1, b, relu);
            act2[j] = finish(a2, b, relu);
            act3[j] = finish(a3, b, relu);
        } else {
            tmp0[j] = finish(a0, b, relu);
            tmp1[j] = finish(a1, b, relu);
            tmp2[j] = finish(a2, b, relu);
            tmp3[j] = finish(a3, b, relu);
        }
    }
}

fn layer_in16(off: u32, out4: u32, relu: bool, flip: bool) {
    for (var j = 0u; j < out4; j++) {
        let r = off + 64u * j;
        var a0 = vec4<f32>(0.0);
        var a1 = vec4<f32>(0.0);
        var a2 = vec4<f32>(0.0);
        var a3 = vec4<f32>(0.0);
        for (var i = 0u; i < 16u; i++) {
            let w0 = w(r + i);
            let w1 = w(r + 16u + i);
            let w2 = w(r + 32u + i);
            let w3 = w(r + 48u + i);
            if flip {
                a0 = mac(a0, w0, w1, w2, w3, tmp0[i]);
                a1 = mac(a1, w0, w1, w2, w3, tmp1[i]);
                a2 = mac(a2, w0, w1, w2, w3, tmp2[i]);
                a3 = mac(a3, w0, w1, w2, w3, tmp3[i]);
            } else {
                a0 = mac(a0, w0, w1, w2, w3, act0[i]);
                a1 = mac(a1, w0, w1, w2, w3, act1[i]);
                a2 = mac(a2, w0, w1, w2, w3, act2[i]);
                a3 = mac(a3, w0, w1, w2, w3, act3[i]);
            }
        }
        let b = w(off + 64u * out4 + j);
        if flip {
            act0[j] = finish(a0, b, relu);
            act1[j] = finish(a1, b, relu);
            act2[j] = finish(a2, b, relu);
            act3[j] = finish(a3, b, relu);
        } else {
            tmp0[j] = finish(a0, b, relu);
            tmp1[j] = finish(a1, b, relu);
            tmp2[j] = finish(a2, b, relu);
            tmp3[j] = finish(a3, b, relu);
        }
    }
}

// Hash-grid encoding of a unit-cube point into out[0..enc4] (hash_grid.rs `corners`/`encode`).
fn encode(out: ptr<private, array<vec4<f32>, HIDDEN4>>, p01: vec3<f32>) {
    for (var i = 0u; i < HIDDEN4; i++) {
        (*out)[i] = vec4<f32>(0.0);
    }
    for (var l = 0u; l < params.levels; l++) {
        let lv = params.level[l];
        let res = lv.x;
        let pos = clamp(p01, vec3<f32>(0.0), vec3<f32>(1.0)) * f32(res);
        // pos ≥ 0, so the conversion truncates like the CPU's `as_uvec3`.
        let cell = min(vec3<u32>(pos), vec3<u32>(res - 1u));
        let frac = pos - vec3<f32>(cell);
        var acc = vec2<f32>(0.0);
        for (var c = 0u; c < 8u; c++) {
            let bit = vec3<u32>(c & 1u, (c >> 1u) & 1u, c >> 2u);
            let v = cell + bit;
            let w3 = select(vec3<f32>(1.0) - frac, frac, bit == vec3<u32>(1u));
            var e: u32;
            if lv.y != 0u {
                let side = res + 1u;
                e = v.x + side * (v.y + side * v.z);
            } else {
                e = (v.x ^ (v.y * 2654435761u) ^ (v.z * 805459861u)) & (lv.w - 1u);
            }
            acc += (w3.x * w3.y * w3.z) * grid[lv.z + e];
        }
        let k = (l & 1u) * 2u;
        (*out)[l >> 1u][k] = acc.x;
        (*out)[l >> 1u][k + 1u] = acc.y;
    }
}

// Occupancy of the cell holding the point `u` (unit-cube coordinates, unclamped).
fn occupied(u: vec3<f32>) -> bool {
    let r = f32(params.occupancy_res);
    let c = vec3<u32>(clamp(u * r, vec3<f32>(0.0), vec3<f32>(r - 1.0)));
    let n = params.occupancy_res;
    let cell = c.x + n * (c.y + n * c.z);
    return ((occupancy[cell >> 5u] >> (cell & 31u)) & 1u) == 1u;
}

// [t0, t1] of the ray inside the box; t1 ≤ t0 when it misses (model.rs `clip_ray`).
fn clip_ray(o: vec3<f32>, d: vec3<f32>) -> vec2<f32> {
    var t_near = -BIG;
    var t_far = BIG;
    for (var a = 0; a < 3; a++) {
        if abs(d[a]) < TINY_DIR {
            if o[a] < params.bounds_min[a] || o[a] > params.bounds_max[a] {
                return vec2<f32>(1.0, 0.0);
            }
        } else {
            let ta = (params.bounds_min[a] - o[a]) / d[a];
            let tb = (params.bounds_max[a] - o[a]) / d[a];
            t_near = max(t_near, min(ta, tb));
            t_far = min(t_far, max(ta, tb));
        }
    }
    let t0 = max(t_near, 0.0);
    if t_far > t0 {
        return vec2<f32>(t0, t_far);
    }
    return vec2<f32>(1.0, 0.0);
}

// 1 − exp(−x) for x ≥ 0, accurate for small x like the CPU's −expm1(−x).
fn one_minus_exp_neg(x: f32) -> f32 {
    if x < 0.1 {
        return x * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0 - x * (1.0 / 120.0)))));
    }
    return 1.0 - exp(-x);
}

fn sigmoid(x: vec3<f32>) -> vec3<f32> {
    // Clamped so exp stays finite; sigmoid(±80) is 0 or 1 in f32 anyway.
    return 1.0 / (1.0 + exp(-clamp(x, vec3<f32>(-80.0), vec3<f32>(80.0))));
}

// Real SH of degree 4 of a unit direction (sh.rs `sh4`: instant-ngp's constants and order).
fn view_encoding(d: vec3<f32>) -> array<vec4<f32>, 4> {
    let x = d.x;
    let y = d.y;
    let z = d.z;
    let xy = x * y;
    let yz = y * z;
    let xz = x * z;
    let x2 = x * x;
    let y2 = y * y;
    let z2 = z * z;
    return array<vec4<f32>, 4>(
        vec4<f32>(0.28209479, -0.48860251 * y, 0.48860251 * z, -0.48860251 * x),
        vec4<f32>(1.0925484 * xy, -1.0925484 * yz, 0.9461747 * z2 - 0.31539157, -1.0925484 * xz),
        vec4<f32>(0.5462742 * x2 - 0.5462742 * y2, 0.5900436 * y * (-3.0 * x2 + y2), 2.8906114 * xy * z, 0.4570458 * y * (1.0 - 5.0 * z2)),
        vec4<f32>(0.37317633 * z * (5.0 * z2 - 3.0), 0.4570458 * x * (1.0 - 5.0 * z2), 1.4453057 * z * (x2 - y2), 0.5900436 * x * (-x2 + 3.0 * y2)),
    );
}

// The ray's colour so far, its compositing transmittance ∏(1 − α) and the early-stop one
// ∏exp(−σδ), kept apart as on the CPU.
var<private> ray_rgb: vec3<f32>;
var<private> transmittance: f32;
var<private> stop_transmittance: f32;

// Adds one sample in front-to-back order; true once the ray counts as opaque.
fn composite(sigma: f32, raw_rgb: vec3<f32>) -> bool {
    let alpha = one_minus_exp_neg(sigma * params.step);
    ray_rgb += transmittance * alpha * sigmoid(raw_rgb);
    transmittance *= 1.0 - alpha;
    stop_transmittance *= exp(-sigma * params.step);
    return stop_transmittance < params.early_stop;
}

@compute @workgroup_size(64)
fn ngp_main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 64u;
    if i >= params.ray_count {
        return;
    }
    var state = ray_state[i];
    if state.phase == 2u {
        return;
    }
    if state.phase == 0u {
        state = RayState(vec3<f32>(0.0), 1.0, 1.0, 0u, 1u, 0u);
    }
    ray_rgb = state.rgb;
    transmittance = state.transmittance;
    stop_transmittance = state.stop_transmittance;
    let o = rays[2u * i].xyz;
    let d = rays[2u * i + 1u].xyz;
    let delta = params.step;
    var k = state.next;
    var done = true;
    let clip = clip_ray(o, d);
    if clip.y > clip.x {
        done = false;
        var sh = view_encoding(d);
        let k_end = min(k + ROUND_POSITIONS, params.max_steps + 1u);
        for (var batch = 0u; batch < ROUND_BATCHES; batch++) {
            // The next BATCH samples in occupied cells (fewer where the ray or round ends).
            var u: array<vec3<f32>, BATCH>;
            var n = 0u;
            loop {
                if n == BATCH || k >= k_end {
                    break;
                }
                let t = clip.x + (f32(k) + 0.5) * delta;
                if t >= clip.y {
                    k = params.max_steps + 1u;
                    break;
                }
                k++;
                let p = (o + t * d - params.bounds_min) / params.bounds_size;
                if occupied(p) {
                    u[n] = p;
                    n++;
                }
            }
            if n == 0u {
                break;
            }
            // A short batch repeats its last sample.
            encode(&act0, clamp(u[0], vec3<f32>(0.0), vec3<f32>(1.0)));
            encode(&act1, clamp(u[min(1u, n - 1u)], vec3<f32>(0.0), vec3<f32>(1.0)));
            encode(&act2, clamp(u[min(2u, n - 1u)], vec3<f32>(0.0), vec3<f32>(1.0)));
            encode(&act3, clamp(u[min(3u, n - 1u)], vec3<f32>(0.0), vec3<f32>(1.0)));
            switch params.enc4 {
                case 4u: { layer_in4(params.off_d0, HIDDEN4, true, false); }
                case 8u: { layer_in8(params.off_d0, HIDDEN4, true, false); }
                default: { layer_in16(params.off_d0, HIDDEN4, true, false); }
            }
            layer_in16(params.off_d1, GEO4, false, true);
            let raw = vec4<f32>(act0[0].x, act1[0].x, act2[0].x, act3[0].x);
            let sigma = exp(min(raw, vec4<f32>(MAX_LOG_DENSITY)));
            for (var q = 0u; q < 4u; q++) {
                act0[GEO4 + q] = sh[q];
                act1[GEO4 + q] = sh[q];
                act2[GEO4 + q] = sh[q];
                act3[GEO4 + q] = sh[q];
            }
            layer_in8(params.off_c0, HIDDEN4, true, false);
            layer_in16(params.off_c1, HIDDEN4, true, true);
            layer_in16(params.off_c2, 1u, false, false);
            var opaque = composite(sigma.x, tmp0[0].xyz);
            if !opaque && n > 1u {
                opaque = composite(sigma.y, tmp1[0].xyz);
            }
            if !opaque && n > 2u {
                opaque = composite(sigma.z, tmp2[0].xyz);
            }
            if !opaque && n > 3u {
                opaque = composite(sigma.w, tmp3[0].xyz);
            }
            if opaque {
                done = true;
                break;
            }
            if n < BATCH {
                break;
            }
        }
        done = done || k > params.max_steps;
    }
    if done {
        out_rgba[i] = vec4<f32>(ray_rgb + transmittance * params.background, 1.0 - transmittance);
        state.phase = 2u;
    }
    state.rgb = ray_rgb;
    state.transmittance = transmittance;
    state.stop_transmittance = stop_transmittance;
    state.next = k;
    ray_state[i] = state;
}
