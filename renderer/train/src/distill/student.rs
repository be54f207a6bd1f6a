//! Stage 3's student: the diffuse net, the specular encoding (PSH or hash grid) and the
//! specular MLP; their forward pass exactly as the renderer shades, and hand-derived
//! gradients (checked by finite differences in the tests).

use super::*;

/// The diffuse net: `E_d(P_h)` (multi-resolution hash grid over the box) → 64 → 4 (c_d, tint).
#[derive(Debug, Clone)]
pub struct DiffuseNet {
    pub grid: HashGrid,
    pub mlp: Mlp,
}

/// The specular net's position encoding `E_s`.
#[derive(Debug, Clone)]
pub enum SpecularEncoding {
    /// A single-resolution grid stored in a perfect spatial hash: what an asset holds.
    /// Its values are the trainable features (f32 while training).
    Psh(SpatialHash),
    /// A multi-resolution hash grid over the box: the ablation rows of NEPHELE's Table 5
    /// before "+ PSH". Such a student renders only through [`super::variants`].
    HashGrid(HashGrid),
}

impl SpecularEncoding {
    /// Values per point.
    pub fn width(&self) -> usize {
        match self {
            Self::Psh(psh) => psh.features as usize,
            Self::HashGrid(grid) => grid.output_width(),
        }
    }

    pub fn params(&self) -> &[f32] {
        match self {
            Self::Psh(psh) => &psh.values,
            Self::HashGrid(grid) => &grid.params,
        }
    }

    pub fn params_mut(&mut self) -> &mut Vec<f32> {
        match self {
            Self::Psh(psh) => &mut psh.values,
            Self::HashGrid(grid) => &mut grid.params,
        }
    }

    /// Bytes stored: PSH keys, offsets and f16 features, or the f32 hash table.
    pub fn stored_bytes(&self) -> u64 {
        match self {
            Self::Psh(psh) => psh.stored_bytes(),
            Self::HashGrid(grid) => 4 * grid.params.len() as u64,
        }
    }

    /// `E_s` at object-space `p` (`p01` is the same point in the unit cube of the box).
    pub(super) fn encode(&self, p: Vec3, p01: Vec3, out: &mut [f32]) {
        match self {
            Self::Psh(psh) => psh.encode(p, out),
            Self::HashGrid(grid) => grid.encode(p01, out),
        }
    }

    /// Adds `∂loss/∂params` given `∂loss/∂E_s` per point (`points × width`).
    pub(super) fn backward(&self, points: &[Vec3], points01: &[Vec3], d_encoded: &[f32], grad: &mut [f32]) {
        match self {
            Self::Psh(psh) => {
                let f = psh.features as usize;
                for (&p, d) in points.iter().zip(d_encoded.chunks_exact(f)) {
                    for (slot, w) in psh.corner_slots(p) {
                        for (g, v) in grad[slot * f..(slot + 1) * f].iter_mut().zip(d) {
                            *g += w * v;
                        }
                    }
                }
            }
            Self::HashGrid(grid) => grid.backward(points01, d_encoded, grad),
        }
    }
}

/// The nets of stage 3.
#[derive(Debug, Clone)]
pub struct Student {
    pub bounds: Aabb,
    /// `None` in the "base" ablation rows: no diffuse/specular split, the specular net's
    /// colour is the whole colour (`c_d = 0`, tint 1).
    pub diffuse: Option<DiffuseNet>,
    /// When set, the diffuse net is read as the renderer reads the baked cubes: evaluated at
    /// the 8 corners of the cell of this fine lattice (cells per axis over `bounds`) around
    /// the hit, outputs blended trilinearly. Training then optimises what is baked.
    pub diffuse_lattice: Option<u32>,
    pub encoding: SpecularEncoding,
    /// `[E_s, SH4, α_c] → 64 → 64 → 4` (c_s, α).
    pub specular_mlp: Mlp,
}

/// Gradients of every [`Student`] parameter group (empty for a group the student lacks).
#[derive(Debug, Clone, Default)]
pub struct StudentGradients {
    pub diffuse_grid: Vec<f32>,
    pub diffuse_mlp: Vec<f32>,
    pub encoding: Vec<f32>,
    pub specular_mlp: Vec<f32>,
}

/// One ray of a batch: its hit and target.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StudentRay {
    /// The primary hit; `more` holds the others and every query's blend weight.
    pub p_hit: Vec3,
    pub more: MoreHits,
    pub dir: Vec3,
    pub alpha_c: f32,
    /// Straight RGB and alpha of the pixel.
    pub rgb: Vec3,
    pub alpha: f32,
    pub background: Vec3,
    /// Per query (primary first): a straight RGB target and its loss weight (0: none).
    pub query_targets: [[f32; 4]; model::MAX_HITS],
}

/// Forward results of one ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StudentOutput {
    /// Pixel over the ray's background, and α.
    pub pixel: Vec3,
    pub alpha: f32,
    /// `‖pixel − target‖²` and `(α − α_gt)²`.
    pub rgb_error: f32,
    pub alpha_error: f32,
    /// `Σ_q w_q β_q ‖c_q − c_q,target‖²` over the queries' colours and targets.
    pub target_error: f32,
}

/// Where a chunk's diffuse colour and tint come from.
#[derive(Clone, Copy)]
pub(super) enum DiffuseSource<'a> {
    /// The student's own net (or constant `c_d = 0`, tint 1 without one).
    Own,
    /// Read from baked cubes (`[r, g, b, tint]`) at each query.
    Cubes(&'a TextureCubes),
}

#[derive(Default)]
pub(super) struct ChunkGradients {
    /// Where the diffuse net was evaluated (rows of `d_diffuse_encoded`).
    pub(super) diffuse_points01: Vec<Vec3>,
    pub(super) diffuse_mlp: Vec<f32>,
    pub(super) specular_mlp: Vec<f32>,
    pub(super) d_diffuse_encoded: Vec<f32>,
    pub(super) d_specular_encoded: Vec<f32>,
    /// Where the specular encoding was read (rows of `d_specular_encoded`).
    pub(super) specular_points: Vec<Vec3>,
    pub(super) outputs: Vec<StudentOutput>,
}

pub(super) fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

impl Student {
    /// The student `cfg` describes: E_s from `psh`, or from `cfg.specular_hash_grid` when
    /// set; a diffuse net when `cfg.diffuse_net`.
    pub fn new(bounds: Aabb, psh: SpatialHash, cfg: &DistillConfig, rng: &mut impl Rng) -> Self {
        let diffuse = cfg.diffuse_net.then(|| {
            let grid = HashGrid::new(cfg.diffuse_encoding, rng);
            let mut mlp = Mlp::new(&[grid.output_width(), HIDDEN, 4], rng);
            // The specular term starts off (tint ≈ 0.02) and earns its place, so noise in the
            // per-vertex features is not mixed into every colour from the first step.
            let tint_bias = mlp.params().len() - 1;
            mlp.update(|p| p[tint_bias] = -4.0);
            DiffuseNet { grid, mlp }
        });
        let encoding = match cfg.specular_hash_grid {
            Some(grid) => SpecularEncoding::HashGrid(HashGrid::new(grid, rng)),
            None => SpecularEncoding::Psh(psh),
        };
        let specular_mlp = Mlp::new(&[encoding.width() + SH_COEFFS + 1, HIDDEN, HIDDEN, 4], rng);
        let diffuse_lattice = (cfg.diffuse_net && cfg.train_on_bake_lattice).then_some(cfg.diffuse_grid * cfg.diffuse_brick);
        Self { bounds, diffuse, diffuse_lattice, encoding, specular_mlp }
    }

    pub fn to_unit(&self, p: Vec3) -> Vec3 {
        ((p - self.bounds.min) / self.bounds.size()).clamp(Vec3::ZERO, Vec3::ONE)
    }

    pub fn zero_gradients(&self) -> StudentGradients {
        let (grid, mlp) = self.diffuse.as_ref().map_or((0, 0), |d| (d.grid.params.len(), d.mlp.params().len()));
        StudentGradients {
            diffuse_grid: vec![0.0; grid],
            diffuse_mlp: vec![0.0; mlp],
            encoding: vec![0.0; self.encoding.params().len()],
            specular_mlp: vec![0.0; self.specular_mlp.params().len()],
        }
    }

    /// Bytes of every trained parameter as stored for rendering (f32 nets and hash tables,
    /// the PSH as an asset stores it).
    pub fn stored_bytes(&self) -> u64 {
        let diffuse = self.diffuse.as_ref().map_or(0, |d| d.grid.params.len() + d.mlp.params().len());
        4 * (diffuse + self.specular_mlp.params().len()) as u64 + self.encoding.stored_bytes()
    }

    /// Diffuse colour and tint at object-space points: `points × 4` (`c_d = 0`, tint 1
    /// without a diffuse net).
    pub fn diffuse(&self, points: &[Vec3]) -> Vec<f32> {
        let Some(net) = &self.diffuse else {
            return points.iter().flat_map(|_| [0.0, 0.0, 0.0, 1.0]).collect();
        };
        points
            .par_chunks(1024)
            .flat_map_iter(|chunk| {
                let points01: Vec<Vec3> = chunk.iter().map(|&p| self.to_unit(p)).collect();
                let mut enc = vec![0.0; points01.len() * net.grid.output_width()];
                net.grid.encode_batch(&points01, &mut enc);
                let mut tape = MlpTape::default();
                net.mlp.forward(&enc, &mut tape);
                tape.output().iter().map(|&o| sigmoid(o)).collect::<Vec<_>>()
            })
            .collect()
    }

    /// Where the diffuse net is evaluated for a hit and with what weights: the hit itself, or
    /// the 8 lattice corners around it (the trilinear rule of [`TextureCubes::sample`]).
    pub(super) fn diffuse_taps(&self, p: Vec3, points01: &mut Vec<Vec3>, weights: &mut Vec<f32>) {
        let Some(res) = self.diffuse_lattice else {
            points01.push(self.to_unit(p));
            weights.push(1.0);
            return;
        };
        let n = res as f32;
        let g = ((p - self.bounds.min) * (n / self.bounds.size())).clamp(Vec3::ZERO, Vec3::splat(n));
        let base = g.as_uvec3().as_vec3().min(Vec3::splat(n - 1.0));
        let f = g - base;
        for corner in 0..8u32 {
            let d = Vec3::new((corner & 1) as f32, (corner >> 1 & 1) as f32, (corner >> 2) as f32);
            let w = Vec3::select(d.cmpeq(Vec3::ONE), f, Vec3::ONE - f);
            points01.push((base + d) / n);
            weights.push(w.x * w.y * w.z);
        }
    }

    /// Forward, and with `loss_scale` the backward pass of
    /// `loss_scale · Σ (‖e_rgb‖² + e_α² + target error)`.
    /// A ray's queries (one per hit, [`MoreHits`]) are shaded each as [`model::shade`] does
    /// and blended by their weights `β`: pixel `= Σ β_q pixel_q`, α `= Σ β_q α_q`.
    pub(super) fn run_chunk(&self, rays: &[StudentRay], diffuse_source: DiffuseSource<'_>, loss_scale: Option<f32>) -> ChunkGradients {
        // Every query of the chunk: (ray, point, β).
        let queries: Vec<(usize, Vec3, f32)> = rays.iter().enumerate().flat_map(|(i, r)| r.more.queries(r.p_hit).map(move |(p, b)| (i, p, b))).collect();
        // Each query's place in its ray (for its target).
        let slots: Vec<usize> = rays.iter().flat_map(|r| 0..r.more.queries(r.p_hit).count()).collect();
        let nq = queries.len();
        let net = match diffuse_source {
            DiffuseSource::Own => self.diffuse.as_ref(),
            DiffuseSource::Cubes(_) => None,
        };
        // Diffuse colour and tint per query: the net's taps, blended, or given.
        let taps = if self.diffuse_lattice.is_some() { 8 } else { 1 };
        let (mut tap_points01, mut tap_weights) = (Vec::new(), Vec::new());
        let mut enc = Vec::new();
        let mut tape_d = MlpTape::default();
        let mut diffuse_out = Vec::new();
        let blended: Vec<[f32; 4]> = match (net, diffuse_source) {
            (_, DiffuseSource::Cubes(cubes)) => queries.iter().map(|q| cubes.sample::<4>(q.1)).collect(),
            (None, _) => vec![[0.0, 0.0, 0.0, 1.0]; nq],
            (Some(net), _) => {
                for &(_, p, _) in &queries {
                    self.diffuse_taps(p, &mut tap_points01, &mut tap_weights);
                }
                enc = vec![0.0; nq * taps * net.grid.output_width()];
                net.grid.encode_batch(&tap_points01, &mut enc);
                net.mlp.forward(&enc, &mut tape_d);
                diffuse_out = tape_d.output().iter().map(|&o| sigmoid(o)).collect();
                (0..nq)
                    .map(|q| {
                        let mut b = [0.0f32; 4];
                        for t in q * taps..(q + 1) * taps {
                            for (b, v) in b.iter_mut().zip(&diffuse_out[4 * t..4 * t + 4]) {
                                *b += tap_weights[t] * v;
                            }
                        }
                        b
                    })
                    .collect()
            }
        };
        // The specular net, once per query.
        let f = self.encoding.width();
        let ws = f + SH_COEFFS + 1;
        let mut xs = vec![0.0; nq * ws];
        let points: Vec<Vec3> = queries.iter().map(|q| q.1).collect();
        let points01: Vec<Vec3> = points.iter().map(|&p| self.to_unit(p)).collect();
        for ((&(i, p, _), &p01), x) in queries.iter().zip(&points01).zip(xs.chunks_exact_mut(ws)) {
            self.encoding.encode(p, p01, &mut x[..f]);
            x[f..f + SH_COEFFS].copy_from_slice(&sh4(rays[i].dir));
            x[f + SH_COEFFS] = rays[i].alpha_c;
        }
        let mut tape_s = MlpTape::default();
        self.specular_mlp.forward(&xs, &mut tape_s);
        // Each query's colour (before and after the clamp), specular colour and α.
        struct Shaded {
            u: Vec3,
            c: Vec3,
            c_s: Vec3,
            alpha: f32,
        }
        let shaded: Vec<Shaded> = (0..nq)
            .map(|q| {
                let os = &tape_s.output()[4 * q..4 * q + 4];
                let [r, g, b, tint] = blended[q];
                let c_s = Vec3::new(sigmoid(os[0]), sigmoid(os[1]), sigmoid(os[2]));
                let u = Vec3::new(r, g, b) + tint * c_s;
                Shaded { u, c: u.clamp(Vec3::ZERO, Vec3::ONE), c_s, alpha: sigmoid(os[3]) }
            })
            .collect();
        // Per ray: the blend, its errors, and d(loss)/d(pixel), d(loss)/d(α).
        let mut out = ChunkGradients::default();
        let (mut pixel, mut alpha, mut target_error) = (vec![Vec3::ZERO; rays.len()], vec![0.0f32; rays.len()], vec![0.0f32; rays.len()]);
        for ((&(i, _, beta), sh), &slot) in queries.iter().zip(&shaded).zip(&slots) {
            let bg = rays[i].background;
            pixel[i] += beta * (sh.alpha * sh.c + (1.0 - sh.alpha) * bg);
            alpha[i] += beta * sh.alpha;
            let [r, g, b, w] = rays[i].query_targets[slot];
            target_error[i] += w * beta * (sh.c - Vec3::new(r, g, b)).length_squared();
        }
        let mut d_ray = Vec::with_capacity(rays.len());
        for (i, ray) in rays.iter().enumerate() {
            let target = ray.alpha * ray.rgb + (1.0 - ray.alpha) * ray.background;
            let e = pixel[i] - target;
            let ea = alpha[i] - ray.alpha;
            out.outputs.push(StudentOutput { pixel: pixel[i], alpha: alpha[i], rgb_error: e.length_squared(), alpha_error: ea * ea, target_error: target_error[i] });
            if let Some(s) = loss_scale {
                d_ray.push((2.0 * s * e, 2.0 * s * ea));
            }
        }
        if loss_scale.is_none() {
            return out;
        }
        // Per query: the chain through the blend (× β) and [`model::shade`].
        let sig_d = |y: f32| y * (1.0 - y);
        let (mut d_od, mut d_os) = (vec![0.0; diffuse_out.len()], vec![0.0; nq * 4]);
        for (q, (&(i, _, beta), sh)) in queries.iter().zip(&shaded).enumerate() {
            let (d_pixel, d_alpha_loss) = d_ray[i];
            let tint = blended[q][3];
            let d_pixel = beta * d_pixel;
            let d_alpha = d_pixel.dot(sh.c - rays[i].background) + beta * d_alpha_loss;
            let inside = Vec3::select(sh.u.cmpgt(Vec3::ZERO) & sh.u.cmplt(Vec3::ONE), Vec3::ONE, Vec3::ZERO);
            let [r, g, b, w] = rays[i].query_targets[slots[q]];
            let d_target = 2.0 * loss_scale.unwrap_or(0.0) * w * beta * (sh.c - Vec3::new(r, g, b));
            let d_c = (sh.alpha * d_pixel + d_target) * inside;
            let d_cs = tint * d_c;
            if net.is_some() {
                let d_blended = [d_c.x, d_c.y, d_c.z, d_c.dot(sh.c_s)];
                for t in q * taps..(q + 1) * taps {
                    for ch in 0..4 {
                        d_od[4 * t + ch] = tap_weights[t] * d_blended[ch] * sig_d(diffuse_out[4 * t + ch]);
                    }
                }
            }
            let c_s = sh.c_s;
            d_os[4 * q..4 * q + 4].copy_from_slice(&[d_cs.x * sig_d(c_s.x), d_cs.y * sig_d(c_s.y), d_cs.z * sig_d(c_s.z), d_alpha * sig_d(sh.alpha)]);
        }
        if let Some(net) = net {
            out.diffuse_mlp = vec![0.0; net.mlp.params().len()];
            out.d_diffuse_encoded = vec![0.0; enc.len()];
            net.mlp.backward(&enc, &tape_d, &d_od, &mut out.diffuse_mlp, Some(&mut out.d_diffuse_encoded));
            out.diffuse_points01 = tap_points01;
        }
        out.specular_mlp = vec![0.0; self.specular_mlp.params().len()];
        let mut d_xs = vec![0.0; nq * ws];
        self.specular_mlp.backward(&xs, &tape_s, &d_os, &mut out.specular_mlp, Some(&mut d_xs));
        out.d_specular_encoded = d_xs.chunks_exact(ws).flat_map(|row| row[..f].iter().copied()).collect();
        out.specular_points = points;
        out
    }

    /// Per-ray results without gradients.
    pub fn forward(&self, rays: &[StudentRay], rays_per_chunk: usize) -> Vec<StudentOutput> {
        rays.par_chunks(rays_per_chunk.max(1)).flat_map_iter(|c| self.run_chunk(c, DiffuseSource::Own, None).outputs).collect()
    }

    /// Per-ray results with the diffuse colour and tint given per ray (read from baked
    /// cubes) instead of the diffuse net.
    pub fn forward_with_diffuse(&self, rays: &[StudentRay], diffuse: &TextureCubes, rays_per_chunk: usize) -> Vec<StudentOutput> {
        rays.par_chunks(rays_per_chunk.max(1)).flat_map_iter(|c| self.run_chunk(c, DiffuseSource::Cubes(diffuse), None).outputs).collect()
    }

    /// Adds the gradients of the batch loss `mean over rays of (‖e_rgb‖² + e_α² + target
    /// error) / 4` to `grads`; returns the per-ray results.
    pub fn gradients(&self, rays: &[StudentRay], rays_per_chunk: usize, grads: &mut StudentGradients) -> Vec<StudentOutput> {
        let scale = 1.0 / (4 * rays.len().max(1)) as f32;
        let chunks: Vec<ChunkGradients> = rays.par_chunks(rays_per_chunk.max(1)).map(|c| self.run_chunk(c, DiffuseSource::Own, Some(scale))).collect();
        let mut outputs = Vec::with_capacity(rays.len());
        let (mut d_diffuse, mut d_specular, mut diffuse_points01, mut points) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for c in chunks {
            diffuse_points01.extend(c.diffuse_points01);
            points.extend(c.specular_points);
            grads.diffuse_mlp.iter_mut().zip(&c.diffuse_mlp).for_each(|(g, d)| *g += d);
            grads.specular_mlp.iter_mut().zip(&c.specular_mlp).for_each(|(g, d)| *g += d);
            d_diffuse.extend(c.d_diffuse_encoded);
            d_specular.extend(c.d_specular_encoded);
            outputs.extend(c.outputs);
        }
        if let Some(net) = &self.diffuse {
            net.grid.backward(&diffuse_points01, &d_diffuse, &mut grads.diffuse_grid);
        }
        let points01: Vec<Vec3> = points.iter().map(|&p| self.to_unit(p)).collect();
        self.encoding.backward(&points, &points01, &d_specular, &mut grads.encoding);
        outputs
    }

    /// The specular MLP in the asset's layout.
    pub fn specular_for_asset(&self) -> SpecularMlp {
        let p = self.specular_mlp.params();
        let input = self.specular_mlp.input_width();
        let (l0, l1) = (input * HIDDEN + HIDDEN, HIDDEN * HIDDEN + HIDDEN);
        SpecularMlp {
            input,
            w0: p[..input * HIDDEN].to_vec(),
            b0: p[input * HIDDEN..l0].to_vec(),
            w1: p[l0..l0 + HIDDEN * HIDDEN].to_vec(),
            b1: p[l0 + HIDDEN * HIDDEN..l0 + l1].to_vec(),
            w2: p[l0 + l1..l0 + l1 + 4 * HIDDEN].to_vec(),
            b2: p[l0 + l1 + 4 * HIDDEN..].to_vec(),
        }
    }
}
