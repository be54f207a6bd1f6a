// shade.wgsl — i-NOLF pass 2 (docs/architecture.md §3 steps 4–8), one thread per hit ray only: diffuse
// atlas (hardware trilinear) → c_d and tint; perfect spatial hash (Lefebvre & Hoppe 2006)
// → E_s; SH degree 4 → E_v; specular MLP [E_s, E_v, α_c] → 64 → 64 → 4; composite over the
// view's background; a multi-hit ray's queries are blended by their weights. Mirrors
// `model::shade` and `model::shade_multi`.

fn psh_find(p: vec3<u32>) -> i32 {
    let m = params.table_edge;
    let r = params.offset_edge;
    let pr = p % vec3<u32>(r);
    let off = asset[params.off_psh_offsets + pr.x + r * (pr.y + r * pr.z)];
    let phi = vec3<u32>(off & 1023u, (off >> 10u) & 1023u, (off >> 20u) & 1023u);
    let s = (p % vec3<u32>(m) + phi) % vec3<u32>(m);
    let slot = s.x + m * (s.y + m * s.z);
    if asset[params.off_psh_keys + slot] == (p.x | (p.y << 10u) | (p.z << 20u)) {
        return i32(slot);
    }
    return -1;
}

fn diffuse_at(p: vec3<f32>) -> vec4<f32> {
    let r = f32(params.diffuse_brick);
    let g = (p - params.bounds_min) * (f32(params.diffuse_grid * params.diffuse_brick) / params.bounds_size);
    let cell = clamp(floor(g / r), vec3<f32>(0.0), vec3<f32>(f32(params.diffuse_grid) - 1.0));
    let u = clamp(g - cell * r, vec3<f32>(0.0), vec3<f32>(r));
    let c = vec3<u32>(cell);
    let b = params.diffuse_grid;
    let brick = bitcast<i32>(asset[params.off_diffuse_index + c.x + b * (c.y + b * c.z)]);
    if brick < 0 { return vec4<f32>(0.0); }
    let coord = atlas_coord(u32(brick), u, r, params.diffuse_atlas_bricks, params.diffuse_atlas_size);
    return textureSampleLevel(diffuse_atlas, atlas_sampler, coord, 0.0);
}

fn sigmoid(x: f32) -> f32 {
    return 1.0 / (1.0 + exp(-x));
}

// One query at `p`: (rgb over `bg`, α).
fn query(p: vec3<f32>, d: vec3<f32>, alpha_c: f32, bg: vec3<f32>) -> vec4<f32> {
    var x: array<f32, 64>;
    // E_s: trilinear blend of the 8 PSH corners; absent vertices are zero.
    let nf = params.features;
    let n = f32(params.psh_grid);
    let g = (p - params.bounds_min) / params.bounds_size * n;
    let base_f = clamp(floor(g), vec3<f32>(0.0), vec3<f32>(n - 1.0));
    let f = clamp(g - base_f, vec3<f32>(0.0), vec3<f32>(1.0));
    let base = vec3<u32>(base_f);
    for (var corner = 0u; corner < 8u; corner++) {
        let dc = vec3<u32>(corner & 1u, (corner >> 1u) & 1u, corner >> 2u);
        let w3 = select(vec3<f32>(1.0) - f, f, dc == vec3<u32>(1u));
        let w = w3.x * w3.y * w3.z;
        let slot = psh_find(base + dc);
        if slot >= 0 {
            let at = params.off_psh_values + u32(slot) * params.feature_words;
            for (var k = 0u; k < nf; k += 2u) {
                let pair = unpack2x16float(asset[at + k / 2u]);
                x[k] += w * pair.x;
                if k + 1u < nf { x[k + 1u] += w * pair.y; }
            }
        }
    }
    // E_v: SH degree 4 (instant-ngp constants), then α_c.
    let xx = d.x * d.x;
    let yy = d.y * d.y;
    let zz = d.z * d.z;
    x[nf + 0u] = 0.28209479177387814;
    x[nf + 1u] = -0.48860251190291987 * d.y;
    x[nf + 2u] = 0.48860251190291987 * d.z;
    x[nf + 3u] = -0.48860251190291987 * d.x;
    x[nf + 4u] = 1.0925484305920792 * d.x * d.y;
    x[nf + 5u] = -1.0925484305920792 * d.y * d.z;
    x[nf + 6u] = 0.94617469575755997 * zz - 0.31539156525251999;
    x[nf + 7u] = -1.0925484305920792 * d.x * d.z;
    x[nf + 8u] = 0.54627421529603959 * xx - 0.54627421529603959 * yy;
    x[nf + 9u] = 0.59004358992664352 * d.y * (-3.0 * xx + yy);
    x[nf + 10u] = 2.8906114426405538 * d.x * d.y * d.z;
    x[nf + 11u] = 0.45704579946446572 * d.y * (1.0 - 5.0 * zz);
    x[nf + 12u] = 0.3731763325901154 * d.z * (5.0 * zz - 3.0);
    x[nf + 13u] = 0.45704579946446572 * d.x * (1.0 - 5.0 * zz);
    x[nf + 14u] = 1.4453057213202769 * d.z * (xx - yy);
    x[nf + 15u] = 0.59004358992664352 * d.x * (-xx + 3.0 * yy);
    x[nf + 16u] = alpha_c;

    // Specular MLP in vec4s: w0 (64 rows × in4), b0 (16), w1 (64 × 16), b1 (16), w2 (4 × 16), b2 (1).
    let in4 = (params.mlp_input + 3u) / 4u;
    var x4: array<vec4<f32>, 16>;
    for (var q = 0u; q < in4; q++) {
        x4[q] = vec4<f32>(x[4u * q], x[4u * q + 1u], x[4u * q + 2u], x[4u * q + 3u]);
    }
    let b0 = HIDDEN * in4;
    let w1 = b0 + 16u;
    let b1 = w1 + HIDDEN * 16u;
    let w2 = b1 + 16u;
    let b2 = w2 + 64u;
    var h0: array<vec4<f32>, 16>;
    for (var j = 0u; j < HIDDEN; j++) {
        var acc = 0.0;
        for (var q = 0u; q < in4; q++) { acc += dot(mlp.w[j * in4 + q], x4[q]); }
        h0[j / 4u][j % 4u] = max(mlp.w[b0 + j / 4u][j % 4u] + acc, 0.0);
    }
    var h1: array<vec4<f32>, 16>;
    for (var j = 0u; j < HIDDEN; j++) {
        var acc = 0.0;
        for (var q = 0u; q < 16u; q++) { acc += dot(mlp.w[w1 + j * 16u + q], h0[q]); }
        h1[j / 4u][j % 4u] = max(mlp.w[b1 + j / 4u][j % 4u] + acc, 0.0);
    }
    var o = mlp.w[b2];
    for (var j = 0u; j < 4u; j++) {
        var acc = 0.0;
        for (var q = 0u; q < 16u; q++) { acc += dot(mlp.w[w2 + j * 16u + q], h1[q]); }
        o[j] += acc;
    }
    let c_s = vec3<f32>(sigmoid(o.x), sigmoid(o.y), sigmoid(o.z));
    let alpha = sigmoid(o.w);
    let cd = diffuse_at(p);
    let c = clamp(cd.rgb + cd.a * c_s, vec3<f32>(0.0), vec3<f32>(1.0));
    return vec4<f32>(alpha * c + (1.0 - alpha) * bg, alpha);
}

@compute @workgroup_size(64)
fn shade_main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg);
    if i >= atomicLoad(&counter.hits) { return; }
    let h = hits[i];
    let v = views[h.view];
    let ray = ray_of_pixel(h.pixel, h.view);
    var px = query(ray.o + h.t_hit * ray.d, ray.d, h.alpha_c, v.background);
    if h.beta_more.x > 0.0 {
        px *= 1.0 - h.beta_more.x - h.beta_more.y;
        px += h.beta_more.x * query(ray.o + h.t_more.x * ray.d, ray.d, h.alpha_c, v.background);
        if h.beta_more.y > 0.0 {
            px += h.beta_more.y * query(ray.o + h.t_more.y * ray.d, ray.d, h.alpha_c, v.background);
        }
    }
    out_pixels[h.pixel] = vec2<u32>(pack4x8unorm(px), bitcast<u32>((v.t_shift + h.t_hit) * v.scale));
}
