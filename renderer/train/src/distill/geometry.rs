//! Stage 2 of distillation: the box fitted to what the images show, the density cubes baked
//! from the teacher's σ, every training ray marched through them by the renderer's own rule
//! (its hit points and coarse opacity), the teacher's colours near each query, and the
//! perfect spatial hash's vertex set.

use super::*;

/// The box to model: the object as the training images show it. Density cubes over the
/// teacher's whole box are marched with every training ray; the box of the hits whose pixel
/// is at least half opaque in the ground truth (its 0.05–99.95% quantiles per axis), grown by
/// one coarse cell and made a cube inside the teacher's box, is kept. Faint haze the field
/// left where no image shows anything (common in corners) stays outside.
/// Images without transparency count every hit.
pub fn fit_bounds(teacher: &Trainer, data: &Dataset, cfg: &DistillConfig) -> Option<Aabb> {
    let whole = teacher.config.bounds;
    let coarse = bake_density(teacher, whole, cfg);
    let hits = march_rays(&coarse, cfg.step(&whole), cfg.alpha_min, cfg.geometry_early_stop(), &model::HitRule::default(), data, cfg.error_tile);
    let has_alpha = data.images.iter().any(|im| im.rgba.chunks_exact(4).any(|p| p[3] < 0.5));
    let points: Vec<Vec3> = hits
        .rays
        .iter()
        .filter(|h| !has_alpha || data.images[h.image as usize].pixel(h.x_px as u32, h.y_px as u32)[3] >= 0.5)
        .map(|h| h.p_hit)
        .collect();
    if points.is_empty() {
        return None;
    }
    // Robust extent: the 0.05% and 99.95% quantiles per axis, so a few hits on faint haze
    // (an edge pixel's ray passing the object) do not stretch the box.
    let quantile = |axis: usize, q: f64| {
        let mut v: Vec<f32> = points.iter().map(|p| p[axis]).collect();
        let k = ((v.len() - 1) as f64 * q).round() as usize;
        *v.select_nth_unstable_by(k, f32::total_cmp).1
    };
    let lo = Vec3::new(quantile(0, 0.0005), quantile(1, 0.0005), quantile(2, 0.0005));
    let hi = Vec3::new(quantile(0, 0.9995), quantile(1, 0.9995), quantile(2, 0.9995));
    // A cube, so cells are cubes: one grid size serves all axes, and a flat object does not
    // get finer cells (and more bricks) along its short axes than along its long one.
    let margin = whole.size().max_element() / cfg.density_grid as f32;
    let half = (0.5 * (hi - lo).max_element() + margin).min(0.5 * whole.size().min_element());
    let centre = (0.5 * (lo + hi)).clamp(whole.min + half, whole.max - half);
    let fitted = Aabb { min: centre - half, max: centre + half };
    fitted.is_valid().then_some(fitted)
}

/// Teacher σ at object-space points (batched).
pub(super) fn teacher_sigma(teacher: &Trainer, points: &[Vec3]) -> Vec<f32> {
    let points01: Vec<Vec3> = points.iter().map(|&p| teacher.to_unit(p).clamp(Vec3::ZERO, Vec3::ONE)).collect();
    teacher.field.density(&points01)
}

/// Stage 2a: density cubes from the teacher over `bounds`; a cell gets a brick if the teacher's
/// occupancy grid marks any point of it (corners and centre) and its largest σ makes a step
/// of `δ` at least `min_step_opacity` opaque.
pub fn bake_density(teacher: &Trainer, bounds: Aabb, cfg: &DistillConfig) -> TextureCubes {
    let b = cfg.density_grid;
    let cell_size = bounds.size() / b as f32;
    let occupied = |c: UVec3| {
        let lo = bounds.min + c.as_vec3() * cell_size;
        (0..9u32).any(|k| {
            let f = if k == 8 { Vec3::splat(0.5) } else { Vec3::new((k & 1) as f32, (k >> 1 & 1) as f32, (k >> 2) as f32) * 0.98 + 0.01 };
            teacher.occupancy.is_occupied(lo + f * cell_size)
        })
    };
    // Every candidate brick with the teacher's σ evaluated in one batch, then drop the ones
    // that stay transparent.
    let candidates = TextureCubes::bake_batched(bounds, b, cfg.density_brick, 1, occupied, |points| {
        teacher_sigma(teacher, points).into_iter().map(|s| s.min(65504.0)).collect()
    });
    let sigma_min = -(1.0 - cfg.min_step_opacity).ln() / cfg.step(&bounds);
    candidates.retain(|_, sigma| sigma.iter().any(|&s| s >= sigma_min))
}

/// One training ray that hits the density cubes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HitRay {
    pub image: u32,
    pub x_px: u16,
    pub y_px: u16,
    pub p_hit: Vec3,
    pub alpha_c: f32,
    pub more: MoreHits,
}

impl HitRay {
    /// Every point this ray queries the network at.
    pub fn points(&self) -> impl Iterator<Item = Vec3> + '_ {
        self.more.queries(self.p_hit).map(|(p, _)| p)
    }
}

/// A ray's queries beyond its primary hit `p_hit` (the multi-hit rule, [`model::MultiHit`]),
/// and the blend weights of all of them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MoreHits {
    pub p: [Vec3; model::MAX_HITS - 1],
    /// Blend weights, primary first; sum to 1.
    pub beta: [f32; model::MAX_HITS],
    pub count: u8,
}

impl Default for MoreHits {
    /// One hit.
    fn default() -> Self {
        let mut beta = [0.0; model::MAX_HITS];
        beta[0] = 1.0;
        Self { p: [Vec3::ZERO; model::MAX_HITS - 1], beta, count: 1 }
    }
}

impl MoreHits {
    /// From a march result along `o + t·d`.
    pub fn of(m: &model::MultiHit, o: Vec3, d: Vec3) -> Self {
        let mut out = Self { beta: m.beta, count: m.count.max(1) as u8, ..Self::default() };
        for i in 1..m.count as usize {
            out.p[i - 1] = o + m.t[i] * d;
        }
        out
    }

    /// `(point, blend weight)` of every query, primary first.
    pub fn queries(&self, p_hit: Vec3) -> impl Iterator<Item = (Vec3, f32)> + '_ {
        std::iter::once(p_hit).chain(self.p.iter().copied()).zip(self.beta).take(self.count as usize)
    }
}

/// Most degrees a teacher view's camera is turned from the training camera it starts from.
pub const TEACHER_VIEW_TURN_DEG: f64 = 20.0;

/// The images plus `count` views rendered by the teacher (RGB and α, straight) from cameras
/// the images do not have: each is a random training camera turned about the point the
/// training cameras look at (their least-squares meeting point) by up to
/// [`TEACHER_VIEW_TURN_DEG`] about a random axis, so it sees the object from between and
/// around the captured views, with the same intrinsics and up vector as the camera it came
/// from. The student then learns the teacher's appearance there too, instead of only at the
/// captured pixels (at 400×400 on lego, a student fitted to 70 views alone overfits: finer
/// diffuse cubes raise its training PSNR and lower its held-out PSNR).
pub fn with_teacher_views(teacher: &Trainer, data: &Dataset, count: usize, seed: u64, progress: &(dyn Fn(usize) + Sync)) -> Dataset {
    let mut out = data.clone();
    if count == 0 || data.images.is_empty() {
        return out;
    }
    // Where the training cameras look: the point nearest to all their optical axes.
    let (mut a, mut b) = (glam::DMat3::ZERO, glam::DVec3::ZERO);
    for im in &data.images {
        let m = im.view.world_from_camera;
        let (o, d) = (m.w_axis.truncate(), -m.z_axis.truncate().normalize());
        let p = glam::DMat3::IDENTITY - glam::DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += p;
        b += p * o;
    }
    let centre = if a.determinant().abs() > 1e-9 { a.inverse() * b } else { glam::DVec3::ZERO };
    let mut rng = SmallRng::seed_from_u64(seed ^ 0x0074_6561_6368_6572);
    let views: Vec<(usize, glam::DMat4)> = (0..count)
        .map(|_| {
            let j = rng.random_range(0..data.images.len());
            let axis = glam::DVec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)).normalize_or(glam::DVec3::Z);
            let angle = rng.random_range(0.0..TEACHER_VIEW_TURN_DEG).to_radians();
            let turn = glam::DMat4::from_translation(centre) * glam::DMat4::from_axis_angle(axis, angle) * glam::DMat4::from_translation(-centre);
            (j, turn * data.images[j].view.world_from_camera)
        })
        .collect();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let rendered: Vec<DatasetImage> = views
        .iter()
        .enumerate()
        .map(|(i, &(j, world_from_camera))| {
            let like = &data.images[j];
            let mut image = DatasetImage { view: View { world_from_camera, intrinsics: like.view.intrinsics }, width: like.width, height: like.height, rgba: Vec::new(), path: format!("teacher view {i} (from {})", like.path.display()).into() };
            let rays: Vec<(Vec3, Vec3)> = image.rays().collect();
            // Over black the colour is premultiplied by α.
            image.rgba = teacher
                .render(&rays, Vec3::ZERO)
                .into_iter()
                .flat_map(|(premultiplied, alpha)| {
                    let rgb = if alpha > 1e-4 { (premultiplied / alpha).clamp(Vec3::ZERO, Vec3::ONE) } else { Vec3::ZERO };
                    [rgb.x, rgb.y, rgb.z, alpha.clamp(0.0, 1.0)]
                })
                .collect();
            progress(done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1);
            image
        })
        .collect();
    out.images.extend(rendered);
    out
}

/// The per-query colour targets of [`DistillConfig::teacher_query_weight`]: per hit ray and
/// query, the teacher's colour averaged by weight over its own march samples within `window`
/// (ray-parameter units; the multi-hit rule's segment gap) of the query, and that weight
/// (≤ 1; 0 where the teacher has less than 10⁻³ of its weight there: no target). On the
/// oracle rows of `bench tradeoff`, such averaged colours are the ones that come within
/// 0.1 dB of the teacher on lego.
pub fn teacher_query_targets(teacher: &Trainer, data: &Dataset, hits: &Hits, window: f32) -> Vec<[[f32; 4]; model::MAX_HITS]> {
    hits.rays
        .par_chunks(teacher.model().rays_per_chunk.max(1))
        .flat_map_iter(|chunk| {
            let rays: Vec<NgpRay> = chunk
                .iter()
                .map(|h| {
                    let (origin, dir) = data.images[h.image as usize].ray(h.x_px as u32, h.y_px as u32);
                    NgpRay { origin, dir, background: Vec3::ZERO, jitter: 0.5 }
                })
                .collect();
            let samples = teacher_samples(teacher, &rays);
            chunk.iter().zip(rays).zip(samples).map(move |((h, ray), (samples, _))| {
                let mut acc = [[0.0f32; 4]; model::MAX_HITS];
                for (a, p) in acc.iter_mut().zip(h.points()) {
                    if let Some((c, w)) = teacher_colour_near(&samples, ray.dir.dot(p - ray.origin), window) {
                        *a = [c.x, c.y, c.z, w.min(1.0)];
                    }
                }
                acc
            })
        })
        .collect()
}

/// The teacher's colour averaged by weight over its samples within `window` of `t_q` along
/// the ray, and that weight; `None` where the weight there is below 10⁻³.
pub fn teacher_colour_near(samples: &[(f32, f32, Vec3)], t_q: f32, window: f32) -> Option<(Vec3, f32)> {
    let (sum, w) = samples.iter().filter(|s| (s.0 - t_q).abs() <= window).fold((Vec3::ZERO, 0.0f32), |(c, w), s| (c + s.1 * s.2, w + s.1));
    (w > 1e-3).then(|| (sum / w, w))
}

/// One ray's march by the teacher: its samples `(t, weight, colour)` front to back, and the
/// transmittance left at the end.
pub type TeacherMarch = (Vec<(f32, f32, Vec3)>, f32);

/// The teacher's march along `rays` (one chunk): per ray, its samples front to back as
/// `(t, weight, colour)`, with `t` along the ray's direction and weight `T·α`, and the
/// transmittance left at the end (α = 1 − that).
pub fn teacher_samples(teacher: &Trainer, rays: &[NgpRay]) -> Vec<TeacherMarch> {
    let m = teacher.model();
    let delta = m.step_size();
    let out = m.forward_chunk(rays);
    let mut k0 = 0;
    rays.iter()
        .zip(&out.used)
        .map(|(ray, rows)| {
            let mut transmittance = 1.0f32;
            let samples = rows
                .iter()
                .enumerate()
                .map(|(i, &row)| {
                    let p = m.bounds.min + out.points01[row as usize] * m.bounds.size();
                    let alpha = -(-out.tape.sigma[row as usize] * delta).exp_m1();
                    let w = transmittance * alpha;
                    transmittance *= 1.0 - alpha;
                    (ray.dir.dot(p - ray.origin), w, Vec3::from_slice(&out.tape.rgb[3 * (k0 + i)..3 * (k0 + i) + 3]))
                })
                .collect();
            k0 += rows.len();
            (samples, transmittance)
        })
        .collect()
}

/// Stage 2b output: hits grouped by error-map tile.
#[derive(Debug, Clone)]
pub struct Hits {
    pub rays: Vec<HitRay>,
    /// `tile_start[t]..tile_start[t + 1]` are the hits of tile `t` (tiles are numbered image
    /// by image, row-major within an image).
    pub tile_start: Vec<usize>,
    pub tiles_x: u32,
    pub tiles_y: u32,
    pub total_rays: usize,
    /// Missed rays whose ground truth is at least half opaque (what the cubes lose).
    pub missed_opaque: usize,
}

/// Stage 2b: marches every pixel of every image through `density`.
pub fn march_rays(density: &TextureCubes, step: f32, alpha_min: f32, early_stop: f32, rule: &model::HitRule, data: &Dataset, tile: u32) -> Hits {
    let settings = RenderSettings { early_stop: Some(early_stop), ..Default::default() };
    let (w, h) = data.images.first().map_or((0, 0), |im| (im.width, im.height));
    let (tiles_x, tiles_y) = (w.div_ceil(tile), h.div_ceil(tile));
    let per_image: Vec<(Vec<HitRay>, Vec<usize>, usize)> = data
        .images
        .par_iter()
        .enumerate()
        .map(|(i, image)| {
            let mut rays = Vec::new();
            let mut counts = Vec::with_capacity((tiles_x * tiles_y) as usize);
            let mut missed = 0;
            for ty in 0..tiles_y {
                for tx in 0..tiles_x {
                    let before = rays.len();
                    for y in ty * tile..((ty + 1) * tile).min(image.height) {
                        for x in tx * tile..((tx + 1) * tile).min(image.width) {
                            let (o, d) = image.ray(x, y);
                            let hit = model::march_multi(density, o, d, step, &settings, rule);
                            if hit.march.alpha_c >= alpha_min {
                                let (p_hit, more) = (o + hit.march.t_hit * d, MoreHits::of(&hit, o, d));
                                rays.push(HitRay { image: i as u32, x_px: x as u16, y_px: y as u16, p_hit, alpha_c: hit.march.alpha_c, more });
                            } else if image.pixel(x, y)[3] >= 0.5 {
                                missed += 1;
                            }
                        }
                    }
                    counts.push(rays.len() - before);
                }
            }
            (rays, counts, missed)
        })
        .collect();
    let mut hits = Hits {
        rays: Vec::new(),
        tile_start: vec![0],
        tiles_x,
        tiles_y,
        total_rays: data.images.iter().map(|im| (im.width * im.height) as usize).sum(),
        missed_opaque: 0,
    };
    for (rays, counts, missed) in per_image {
        hits.rays.extend(rays);
        for c in counts {
            let last = *hits.tile_start.last().expect("starts with 0");
            hits.tile_start.push(last + c);
        }
        hits.missed_opaque += missed;
    }
    hits
}

/// Sets bit `i`.
pub(super) fn set_bit(bits: &mut [u64], i: usize) {
    bits[i / 64] |= 1 << (i % 64);
}
pub(super) fn get_bit(bits: &[u64], i: usize) -> bool {
    bits[i / 64] >> (i % 64) & 1 == 1
}

/// Cells of an `n³` grid over `bounds` holding any of `points`, dilated by `dilation` cells
/// (as sorted coordinates of an `(n + extra)³` lattice when `extra` is 1: grid vertices).
pub(super) fn marked_cells(bounds: &Aabb, n: u32, extra: u32, points: impl Iterator<Item = Vec3>, dilation: u32) -> Vec<UVec3> {
    let side = (n + extra) as usize;
    let index = |v: UVec3| v.x as usize + side * (v.y as usize + side * v.z as usize);
    let mut bits = vec![0u64; (side * side * side).div_ceil(64)];
    for p in points {
        let g = ((p - bounds.min) / bounds.size() * n as f32).clamp(Vec3::ZERO, Vec3::splat(n as f32 - 1.0)).as_uvec3();
        // The cell's own corners (vertex lattice) or the cell itself.
        for c in 0..if extra == 1 { 8 } else { 1 } {
            set_bit(&mut bits, index(g + UVec3::new(c & 1, c >> 1 & 1, c >> 2)));
        }
    }
    let d = dilation as i32;
    let mut out = Vec::new();
    let mut dilated = bits.clone();
    for i in 0..side * side * side {
        if !get_bit(&bits, i) {
            continue;
        }
        let v = UVec3::new((i % side) as u32, (i / side % side) as u32, (i / (side * side)) as u32).as_ivec3();
        for dz in -d..=d {
            for dy in -d..=d {
                for dx in -d..=d {
                    let u = v + glam::IVec3::new(dx, dy, dz);
                    if u.min_element() >= 0 && u.max_element() < side as i32 {
                        set_bit(&mut dilated, index(u.as_uvec3()));
                    }
                }
            }
        }
    }
    for i in 0..side * side * side {
        if get_bit(&dilated, i) {
            out.push(UVec3::new((i % side) as u32, (i / side % side) as u32, (i / (side * side)) as u32));
        }
    }
    out
}

/// The PSH's vertices (of an `n³` grid over `bounds`): the corners of the cells holding hit
/// points, dilated by `dilation` vertices for views the cameras did not see, less those of no
/// cell that overlaps a density brick. A ray hits only inside density bricks, so a vertex
/// outside them is never read and the dilation costs only where a view can land.
pub(super) fn psh_vertex_set(bounds: &Aabb, n: u32, density: &TextureCubes, hits: &Hits, dilation: u32) -> Vec<UVec3> {
    let near = marked_cells(bounds, n, 1, hits.rays.iter().flat_map(HitRay::points), dilation);
    if dilation == 0 {
        return near;
    }
    let side = n as usize + 1;
    let mut reachable = vec![0u64; (side * side * side).div_ceil(64)];
    let b = density.grid as usize;
    let n = n as usize;
    for (i, _) in density.index.iter().enumerate().filter(|(_, brick)| **brick >= 0) {
        let cell = [i % b, i / b % b, i / (b * b)];
        // PSH cells overlapping index cell `cell`, then their corners.
        let lo = cell.map(|c| c * n / b);
        let hi = cell.map(|c| ((c + 1) * n).div_ceil(b).min(n));
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    set_bit(&mut reachable, x + side * (y + side * z));
                }
            }
        }
    }
    near.into_iter().filter(|v| get_bit(&reachable, v.x as usize + side * (v.y as usize + side * v.z as usize))).collect()
}

/// `cells` of `cubes`' index grid as a mask over its cell indices.
pub(super) fn cell_mask(cubes: &TextureCubes, cells: &[UVec3]) -> Vec<bool> {
    let mut mask = vec![false; cubes.index.len()];
    for &c in cells.iter().filter(|c| c.max_element() < cubes.grid) {
        mask[cubes.cell_index(c)] = true;
    }
    mask
}

/// What the geometry stage made, with counts for the log.
#[derive(Debug, Clone)]
pub struct Geometry {
    pub bounds: Aabb,
    pub step: f32,
    pub density: TextureCubes,
    pub hits: Hits,
    pub psh_vertices: Vec<UVec3>,
}

/// Stage 2: fitted box, density cubes, hits of every training ray, PSH vertex set.
pub fn geometry(teacher: &Trainer, data: &Dataset, cfg: &DistillConfig) -> Result<Geometry, String> {
    cfg.validate()?;
    if data.images.iter().any(|im| im.width > u16::MAX as u32 + 1 || im.height > u16::MAX as u32 + 1) {
        return Err("images wider or taller than 65536 pixels are not supported; use --downscale".into());
    }
    let bounds = fit_bounds(teacher, data, cfg).ok_or("no training ray hits the field's density: nothing to model")?;
    let step = cfg.step(&bounds);
    let baked = bake_density(teacher, bounds, cfg);
    let first = march_rays(&baked, step, cfg.alpha_min, cfg.geometry_early_stop(), &cfg.hits, data, cfg.error_tile);
    // Keep only bricks near surfaces the cameras reach, then march again with exactly the
    // cubes (and the early stop) that will be stored.
    let near = cell_mask(&baked, &marked_cells(&bounds, cfg.density_grid, 0, first.rays.iter().flat_map(HitRay::points), cfg.density_dilation));
    let density = baked.retain(|i, _| near[i]);
    let hits = march_rays(&density, step, cfg.alpha_min, cfg.early_stop, &cfg.hits, data, cfg.error_tile);
    if hits.rays.is_empty() {
        return Err("no training ray hits the baked density: nothing to model".into());
    }
    let psh_vertices = psh_vertex_set(&bounds, cfg.psh_grid, &density, &hits, cfg.psh_dilation);
    Ok(Geometry { bounds, step, density, hits, psh_vertices })
}

impl Geometry {
    /// The same geometry with the PSH vertex set for another grid `N` (for the PSH variants).
    pub fn with_psh_grid(&self, psh_grid: u32, dilation: u32) -> Self {
        let psh_vertices = psh_vertex_set(&self.bounds, psh_grid, &self.density, &self.hits, dilation);
        Self { psh_vertices, ..self.clone() }
    }
}
