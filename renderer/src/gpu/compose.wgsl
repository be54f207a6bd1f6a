// compose.wgsl — depth composition of premultiplied layers (one thread per pixel).
// Same rule as `compose.rs` (the CPU reference): layers ordered by depth, nearest first
// (ties keep the layer order, misses last), blended front to back, background last.
// Keep `ComposeParams` in sync with `gpu/compose.rs`.

struct ComposeParams {
    pixels: u32,
    layers: u32,
    _pad0: u32,
    _pad1: u32,
    background: vec4<f32>,
}

const MAX_LAYERS: u32 = 16u;
const BIG: f32 = 3.0e38;

@group(0) @binding(0) var<uniform> cp: ComposeParams;
// Layer l, pixel p at index l * pixels + p: packed RGBA8 and depth bits (misses: any
// non-finite or negative value).
@group(0) @binding(1) var<storage, read> colors: array<u32>;
@group(0) @binding(2) var<storage, read> depths: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<vec2<u32>>;

fn sort_key(d: f32) -> f32 {
    // Misses (∞, NaN, or the renderer's negative sentinel) sort last.
    if (!(d >= 0.0) || d > BIG) {
        return BIG;
    }
    return d;
}

fn to_unorm(x: f32) -> u32 {
    return u32(round(clamp(x, 0.0, 1.0) * 255.0));
}

@compute @workgroup_size(64)
fn compose_main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let p = gid.x + gid.y * groups.x * 64u;
    if (p >= cp.pixels) {
        return;
    }
    var keys: array<f32, 16>;
    var idx: array<u32, 16>;
    let n = min(cp.layers, MAX_LAYERS);
    // Insertion sort: stable, n ≤ 16.
    for (var l = 0u; l < n; l = l + 1u) {
        let k = sort_key(depths[l * cp.pixels + p]);
        var j = l;
        loop {
            if (j == 0u || keys[j - 1u] <= k) {
                break;
            }
            keys[j] = keys[j - 1u];
            idx[j] = idx[j - 1u];
            j = j - 1u;
        }
        keys[j] = k;
        idx[j] = l;
    }
    var c = vec3<f32>(0.0);
    var t = 1.0;
    for (var s = 0u; s < n; s = s + 1u) {
        let px = unpack4x8unorm(colors[idx[s] * cp.pixels + p]);
        c = c + t * px.rgb;
        t = t * (1.0 - px.a);
    }
    let o = c + t * cp.background.rgb;
    let rgba = to_unorm(o.r) | (to_unorm(o.g) << 8u) | (to_unorm(o.b) << 16u) | (to_unorm(1.0 - t) << 24u);
    var depth = depths[idx[0] * cp.pixels + p];
    if (keys[0] >= BIG) {
        depth = -1.0;
    }
    out[p] = vec2<u32>(rgba, bitcast<u32>(depth));
}
