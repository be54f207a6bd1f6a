//! Cost estimates before rendering (NEPHELE §6.1): each view of an object gets `n_pixel`,
//! the pixels the object will cover, and `avg_depth`, its mean distance from the camera,
//! from a coarse proxy — the occupied cells of the asset's density index grid, merged to at
//! most [`PROXY_GRID`]³ cells, projected to the screen as discs and counted on a coarse tile
//! grid. No network query, a few thousand operations per view. Tasks with many pixels or a
//! close object are heavy; the thresholds live here and nowhere else.

use glam::{DMat4, Vec3};
use nephele_renderer::{Instance, View, cubes::TextureCubes};

use super::task::TaskClass;

/// Proxy cells per axis, at most.
pub const PROXY_GRID: u32 = 16;
/// Tiles per image edge on which the proxy is rasterised.
pub const TILES_PER_EDGE: u32 = 32;
/// A task is heavy when its views cover at least this many pixels in all…
pub const HEAVY_MIN_PIXELS: u64 = 250_000;
/// …or when an object is this close: mean depth within this many bounding radii of the camera.
pub const HEAVY_MAX_DEPTH_RADII: f64 = 1.5;

/// Occupied coarse cells of an asset, object space.
#[derive(Debug, Clone, PartialEq)]
pub struct Proxy {
    pub centers: Vec<Vec3>,
    /// Radius of the sphere around one coarse cell, object units.
    pub cell_radius: f32,
    /// Bounding-sphere radius of the whole asset, object units.
    pub bound_radius: f32,
}

impl Proxy {
    /// Merges the density index grid's occupied cells into at most `PROXY_GRID`³ cells.
    pub fn from_density(density: &TextureCubes) -> Self {
        let b = density.grid.max(1);
        let coarse = b.min(PROXY_GRID);
        let per = b.div_ceil(coarse);
        let mut occupied = vec![false; (coarse * coarse * coarse) as usize];
        for (i, &brick) in density.index.iter().enumerate() {
            if brick < 0 {
                continue;
            }
            let i = i as u32;
            let (x, y, z) = (i % b / per, i / b % b / per, i / (b * b) / per);
            occupied[(x + coarse * (y + coarse * z)) as usize] = true;
        }
        let size = density.bounds.size() / coarse as f32;
        let centers = occupied
            .iter()
            .enumerate()
            .filter(|(_, o)| **o)
            .map(|(i, _)| {
                let i = i as u32;
                let cell = Vec3::new((i % coarse) as f32, (i / coarse % coarse) as f32, (i / (coarse * coarse)) as f32);
                density.bounds.min + (cell + 0.5) * size
            })
            .collect();
        Self { centers, cell_radius: 0.5 * size.length(), bound_radius: density.bounds.radius() }
    }
}

/// What the proxy predicts for one view.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Estimate {
    /// Pixels the object covers (a multiple of the tile area, at most the image).
    pub n_pixel: u64,
    /// Mean camera distance of the visible proxy cells, scene units (∞ if none is visible).
    pub avg_depth: f64,
}

/// Projects the proxy into `view` with the object placed by `instance`.
pub fn estimate(proxy: &Proxy, view: &View, instance: &Instance) -> Estimate {
    let k = view.intrinsics;
    let camera_from_object: DMat4 = view.world_from_camera.inverse() * instance.world_from_object();
    let (tiles_x, tiles_y) = (TILES_PER_EDGE.min(k.width).max(1), TILES_PER_EDGE.min(k.height).max(1));
    let (tile_w, tile_h) = (f64::from(k.width) / f64::from(tiles_x), f64::from(k.height) / f64::from(tiles_y));
    let mut covered = vec![false; (tiles_x * tiles_y) as usize];
    let radius = f64::from(proxy.cell_radius) * instance.scale;
    let (mut depth_sum, mut visible) = (0.0, 0u32);
    for c in &proxy.centers {
        let p = camera_from_object.transform_point3(c.as_dvec3());
        let z = -p.z; // OpenGL camera looks down −z
        if z < -radius {
            continue;
        }
        if z <= radius {
            // The camera is inside or touching this cell: it covers the screen.
            covered.iter_mut().for_each(|t| *t = true);
            depth_sum += z.max(0.0);
            visible += 1;
            continue;
        }
        let (u, v) = (f64::from(k.fx) * p.x / z + f64::from(k.cx), f64::from(k.cy) - f64::from(k.fy) * p.y / z);
        let (ru, rv) = (f64::from(k.fx) * radius / z, f64::from(k.fy) * radius / z);
        let (x0, x1) = (((u - ru) / tile_w).floor(), ((u + ru) / tile_w).floor());
        let (y0, y1) = (((v - rv) / tile_h).floor(), ((v + rv) / tile_h).floor());
        if x1 < 0.0 || y1 < 0.0 || x0 >= f64::from(tiles_x) || y0 >= f64::from(tiles_y) {
            continue;
        }
        depth_sum += z;
        visible += 1;
        let clamp_x = |t: f64| t.clamp(0.0, f64::from(tiles_x - 1)) as u32;
        let clamp_y = |t: f64| t.clamp(0.0, f64::from(tiles_y - 1)) as u32;
        for ty in clamp_y(y0)..=clamp_y(y1) {
            for tx in clamp_x(x0)..=clamp_x(x1) {
                // The tile's nearest point to the disc's centre must lie in the ellipse.
                let nx = (u / tile_w).clamp(f64::from(tx), f64::from(tx) + 1.0) * tile_w;
                let ny = (v / tile_h).clamp(f64::from(ty), f64::from(ty) + 1.0) * tile_h;
                let (dx, dy) = ((nx - u) / ru.max(1e-9), (ny - v) / rv.max(1e-9));
                if dx * dx + dy * dy <= 1.0 {
                    covered[(tx + tiles_x * ty) as usize] = true;
                }
            }
        }
    }
    let tiles = covered.iter().filter(|c| **c).count() as u64;
    let n_pixel = (tiles * k.pixel_count()).div_ceil(u64::from(tiles_x * tiles_y)).min(k.pixel_count());
    let avg_depth = if visible > 0 { depth_sum / f64::from(visible) } else { f64::INFINITY };
    Estimate { n_pixel, avg_depth }
}

/// Heavy when the views cover many pixels, or an object is close (within
/// [`HEAVY_MAX_DEPTH_RADII`] of its scaled bounding radius).
pub fn classify(total_pixels: u64, min_depth: f64, bound_radius_scene: f64) -> TaskClass {
    if total_pixels >= HEAVY_MIN_PIXELS || min_depth <= HEAVY_MAX_DEPTH_RADII * bound_radius_scene {
        TaskClass::Heavy
    } else {
        TaskClass::Light
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;
    use nephele_renderer::{Intrinsics, cubes::Aabb};

    /// A density grid of 32³ cells with a ball of radius 0.5 occupied, in [-1, 1]³.
    fn ball() -> TextureCubes {
        let b = 32u32;
        let mut index = vec![-1; (b * b * b) as usize];
        let mut n = 0;
        for z in 0..b {
            for y in 0..b {
                for x in 0..b {
                    let p = (Vec3::new(x as f32, y as f32, z as f32) + 0.5) / b as f32 * 2.0 - 1.0;
                    if p.length() < 0.5 {
                        index[(x + b * (y + b * z)) as usize] = n;
                        n += 1;
                    }
                }
            }
        }
        TextureCubes { bounds: Aabb::cube(1.0), grid: b, brick: 1, channels: 1, index, values: vec![0.0; n as usize * 8], storage: Default::default() }
    }

    #[test]
    fn coverage_and_depth_follow_the_camera() {
        let proxy = Proxy::from_density(&ball());
        assert!(!proxy.centers.is_empty() && proxy.centers.len() <= (PROXY_GRID * PROXY_GRID * PROXY_GRID) as usize);
        let k = Intrinsics::from_fov_x(640, 480, 0.8);
        let at = |d: f64| estimate(&proxy, &View::orbit(DVec3::ZERO, d, 30.0, 20.0, k), &Instance::default());
        let (near, mid, far) = (at(2.0), at(4.0), at(16.0));
        // A ball of radius 0.5 at distance d covers π (f·0.5/d)² pixels; the proxy is coarser
        // (cells are whole) so it over-estimates, but within a small factor and in order.
        let f = f64::from(k.fx);
        let exact = |d: f64| std::f64::consts::PI * (f * 0.5 / d).powi(2);
        for (e, d) in [(near, 2.0), (mid, 4.0), (far, 16.0)] {
            let ratio = e.n_pixel as f64 / exact(d);
            assert!((0.8..4.0).contains(&ratio), "d={d}: {} vs {:.0} px", e.n_pixel, exact(d));
            assert!((e.avg_depth - d).abs() < 0.6, "d={d}: depth {}", e.avg_depth);
        }
        assert!(near.n_pixel > mid.n_pixel && mid.n_pixel > far.n_pixel);
        // Looking away: nothing; from inside: everything, at depth ~0.
        let away = View::look_at(DVec3::new(4.0, 0.0, 0.0), DVec3::new(8.0, 0.0, 0.0), DVec3::Z, k);
        assert_eq!(estimate(&proxy, &away, &Instance::default()).n_pixel, 0);
        let inside = View::look_at(DVec3::new(0.1, 0.0, 0.0), DVec3::new(1.0, 0.0, 0.0), DVec3::Z, k);
        let e = estimate(&proxy, &inside, &Instance::default());
        assert_eq!(e.n_pixel, k.pixel_count());
        // Scaling the instance up by 2 at twice the distance looks the same.
        let big = Instance { scale: 2.0, ..Instance::default() };
        let e2 = estimate(&proxy, &View::orbit(DVec3::ZERO, 8.0, 30.0, 20.0, k), &big);
        assert_eq!(e2.n_pixel, mid.n_pixel);
        assert!((e2.avg_depth - 2.0 * mid.avg_depth).abs() < 1e-9);
    }

    #[test]
    fn extremes_stay_finite_and_bounded() {
        let proxy = Proxy::from_density(&ball());
        for (w, h) in [(1, 1), (7, 3), (3840, 2160)] {
            let k = Intrinsics::from_fov_x(w, h, 0.8);
            for d in [0.0f64, 1e-3, 1e6] {
                let e = estimate(&proxy, &View::orbit(DVec3::ZERO, d.max(1e-9), 10.0, 10.0, k), &Instance::default());
                assert!(e.n_pixel <= k.pixel_count());
                assert!(!e.avg_depth.is_nan());
            }
        }
        let empty = Proxy { centers: vec![], cell_radius: 0.1, bound_radius: 1.0 };
        let e = estimate(&empty, &View::orbit(DVec3::ZERO, 4.0, 0.0, 0.0, Intrinsics::from_fov_x(64, 64, 0.8)), &Instance::default());
        assert_eq!((e.n_pixel, e.avg_depth), (0, f64::INFINITY));
    }

    #[test]
    fn classification_thresholds() {
        assert_eq!(classify(HEAVY_MIN_PIXELS, 100.0, 1.0), TaskClass::Heavy);
        assert_eq!(classify(HEAVY_MIN_PIXELS - 1, 100.0, 1.0), TaskClass::Light);
        assert_eq!(classify(10, 1.5, 1.0), TaskClass::Heavy);
        assert_eq!(classify(10, 1.6, 1.0), TaskClass::Light);
        assert_eq!(classify(0, f64::INFINITY, 1.0), TaskClass::Light);
    }
}
