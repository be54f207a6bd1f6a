// march.wgsl — i-NOLF pass 1 (docs/architecture.md §3 steps 1–3): clip each pixel's ray to the box, DDA over
// the density index grid, fixed-step samples of the density atlas (hardware trilinear), the
// max-weight hit and coarse opacity with the exact early stop, and with `max_hits` > 1 the
// multi-hit segments. Misses get the background; hits are appended to `hits` for the shading
// pass. Mirrors `model::march_with` and `model::Segments`.

// Density at `p`, read from `brick` whose atlas texel origin is `origin` and whose index cell
// is `cell` (model.rs `sample_in_brick`).
fn density_in_brick(origin: vec3<f32>, cell: vec3<f32>, p: vec3<f32>) -> f32 {
    let r = f32(params.density_brick);
    let g = (p - params.bounds_min) * (f32(params.density_grid * params.density_brick) / params.bounds_size);
    let u = clamp(g - cell * r, vec3<f32>(0.0), vec3<f32>(r));
    return textureSampleLevel(density_atlas, atlas_sampler, (origin + u + 0.5) / params.density_atlas_size, 0.0).r;
}

fn brick_of(cell: vec3<i32>) -> i32 {
    let b = i32(params.density_grid);
    return bitcast<i32>(asset[params.off_density_index + u32(cell.x + b * (cell.y + b * cell.z))]);
}

struct March {
    t_hit: f32,
    alpha_c: f32,
}

// The multi-hit segment tracker (model.rs `Segments`): closed segments (summed weight, peak
// t), the open one, and which one holds the max-weight sample.
struct Segments {
    w: array<f32, 4>,
    t: array<f32, 4>,
    n_closed: u32,
    primary: i32,
    has_open: bool,
    open_primary: bool,
    open_w: f32,
    open_peak_w: f32,
    open_peak_t: f32,
}

fn seg_close(s: ptr<function, Segments>) {
    if !(*s).has_open { return; }
    (*s).has_open = false;
    let is_primary = (*s).open_primary;
    (*s).open_primary = false;
    var slot = -1;
    if (*s).n_closed < 4u {
        slot = i32((*s).n_closed);
        (*s).n_closed += 1u;
    } else {
        // The lightest closed segment that is not the primary gives way.
        var lightest = -1;
        for (var i = 0; i < 4; i++) {
            if i != (*s).primary && (lightest < 0 || (*s).w[i] < (*s).w[lightest]) { lightest = i; }
        }
        if is_primary || (*s).w[lightest] < (*s).open_w { slot = lightest; }
    }
    if slot >= 0 {
        (*s).w[slot] = (*s).open_w;
        (*s).t[slot] = (*s).open_peak_t;
        if is_primary { (*s).primary = slot; }
    }
}

fn seg_sample(s: ptr<function, Segments>, t: f32, w: f32, new_max: bool) {
    if !(w > 0.0) { return; }
    if (*s).has_open && t - (*s).open_peak_t > params.hit_gap { seg_close(s); }
    if !(*s).has_open {
        (*s).has_open = true;
        (*s).open_w = 0.0;
        (*s).open_peak_w = 0.0;
        (*s).open_peak_t = t;
    }
    (*s).open_w += w;
    if w > (*s).open_peak_w {
        (*s).open_peak_w = w;
        (*s).open_peak_t = t;
    }
    if new_max {
        (*s).open_primary = true;
        (*s).primary = -1;
    }
}

fn march(o_in: vec3<f32>, d_in: vec3<f32>, segs: ptr<function, Segments>) -> March {
    var o = o_in;
    var d = d_in;
    var res = March(0.0, 0.0);
    let bmin = params.bounds_min;
    let bmax = params.bounds_min + params.bounds_size;
    var t_near = -BIG;
    var t_far = BIG;
    for (var a = 0; a < 3; a++) {
        if abs(d[a]) < TINY_DIR {
            if o[a] < bmin[a] || o[a] > bmax[a] { return res; }
        } else {
            let ta = (bmin[a] - o[a]) / d[a];
            let tb = (bmax[a] - o[a]) / d[a];
            t_near = max(t_near, min(ta, tb));
            t_far = min(t_far, max(ta, tb));
        }
    }
    let t0 = max(t_near, 0.0);
    let t1 = t_far;
    if !(t1 > t0) { return res; }

    let step = params.step;
    let b = i32(params.density_grid);
    let cell_size = params.bounds_size / f32(b);
    let p0 = o + t0 * d;
    var cell = clamp(vec3<i32>(floor((p0 - bmin) / cell_size)), vec3<i32>(0), vec3<i32>(b - 1));
    var dir_step = vec3<i32>(0);
    var t_max = vec3<f32>(BIG);
    var t_delta = vec3<f32>(BIG);
    for (var a = 0; a < 3; a++) {
        if abs(d[a]) >= TINY_DIR {
            dir_step[a] = select(-1, 1, d[a] > 0.0);
            let boundary = bmin[a] + f32(cell[a] + select(0, 1, d[a] > 0.0)) * cell_size[a];
            t_max[a] = t0 + (boundary - p0[a]) / d[a];
            t_delta[a] = cell_size[a] / abs(d[a]);
        }
    }
    var transmittance = 1.0;
    var w_max = 0.0;
    var t_hit = 0.0;
    var t_enter = t0;
    var k_next = 0;
    var done = false;
    for (var it = 0; it < 3 * b + 3; it++) {
        if done || t_enter >= t1 { break; }
        let t_exit = min(min(min(t_max.x, t_max.y), t_max.z), t1);
        let brick = brick_of(cell);
        if brick >= 0 {
            let bu = u32(brick);
            let nb = params.density_atlas_bricks;
            let origin = vec3<f32>(vec3<u32>(bu % nb.x, (bu / nb.x) % nb.y, bu / (nb.x * nb.y))) * f32(params.density_brick + 1u);
            let cell_f = vec3<f32>(cell);
            let k_a = max(k_next, i32(ceil((t_enter - t0) / step - 0.5)));
            let k_b = i32(ceil((t_exit - t0) / step - 0.5));
            for (var k = k_a; k < k_b; k++) {
                let t = t0 + (f32(k) + 0.5) * step;
                let sigma = density_in_brick(origin, cell_f, o + t * d);
                let alpha = 1.0 - exp(-sigma * step);
                let w = transmittance * alpha;
                let new_max = w > w_max;
                if new_max {
                    w_max = w;
                    t_hit = t;
                }
                if params.max_hits > 1u { seg_sample(segs, t, w, new_max); }
                transmittance *= 1.0 - alpha;
                if transmittance < params.stop_ratio * w_max || transmittance < params.early_stop {
                    done = true;
                    break;
                }
            }
            k_next = max(k_next, k_b);
        }
        var axis = 2;
        if t_max.x <= t_max.y && t_max.x <= t_max.z { axis = 0; } else if t_max.y <= t_max.z { axis = 1; }
        cell[axis] += dir_step[axis];
        if cell[axis] < 0 || cell[axis] >= b { break; }
        t_enter = t_exit;
        t_max[axis] += t_delta[axis];
    }
    res.t_hit = t_hit;
    res.alpha_c = 1.0 - transmittance;
    return res;
}

@compute @workgroup_size(64)
fn march_main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let local = linear_id(gid, nwg);
    if local >= params.chunk_len { return; }
    let vi = find_view(params.chunk_start + local);
    let ray = ray_of_pixel(local, vi);
    var segs: Segments;
    segs.n_closed = 0u;
    segs.primary = -1;
    segs.has_open = false;
    segs.open_primary = false;
    let m = march(ray.o, ray.d, &segs);
    if m.alpha_c < params.alpha_min {
        out_pixels[local] = vec2<u32>(pack4x8unorm(vec4<f32>(views[vi].background, 0.0)), bitcast<u32>(-1.0));
        return;
    }
    // The queries beyond the primary: heaviest other segments holding ≥ τ·α_c, up to
    // `max_hits` in all, blended by weight (model.rs `Segments::choose`).
    var t_more = vec2<f32>(0.0);
    var w_more = vec2<f32>(0.0);
    var w_total = 1.0;
    if params.max_hits > 1u {
        seg_close(&segs);
        if segs.primary >= 0 {
            w_total = segs.w[segs.primary];
            var taken = array<bool, 4>(false, false, false, false);
            taken[segs.primary] = true;
            for (var k = 0u; k + 1u < params.max_hits && k < 2u; k++) {
                var best = -1;
                for (var i = 0; i < i32(segs.n_closed); i++) {
                    if !taken[i] && (best < 0 || segs.w[i] > segs.w[best]) { best = i; }
                }
                if best < 0 || segs.w[best] < params.hit_tau * m.alpha_c { break; }
                taken[best] = true;
                t_more[k] = segs.t[best];
                w_more[k] = segs.w[best];
                w_total += segs.w[best];
            }
        }
    }
    let slot = atomicAdd(&counter.hits, 1u);
    hits[slot] = Hit(local, vi, m.t_hit, m.alpha_c, t_more, w_more / w_total);
}

// One thread: turn the hit count into an indirect dispatch for the shading pass.
@compute @workgroup_size(1)
fn args_main() {
    let groups = (atomicLoad(&counter.hits) + 63u) / 64u;
    dispatch_args[0] = min(groups, 65535u);
    dispatch_args[1] = max((groups + 65534u) / 65535u, 1u);
    dispatch_args[2] = 1u;
}
