//! Evaluation of a trained field on held-out views: full-image renders, PSNR, SSIM and
//! side-by-side comparison images.
//!
//! SSIM follows Wang et al. 2004 as NeRF papers report it (the mip-NeRF / JAX reference
//! code): an 11×11 Gaussian window with σ = 1.5, `K1 = 0.01`, `K2 = 0.03`, data range 1,
//! "valid" filtering (only windows fully inside the image), computed **per RGB channel** and
//! averaged over channels and window positions. Images smaller than 11 pixels on a side use
//! the largest odd window that fits (same σ, renormalised).

use std::path::Path;

use glam::Vec3;

use super::Trainer;
use crate::dataset::DatasetImage;

pub const SSIM_WINDOW: usize = 11;
pub const SSIM_SIGMA: f64 = 1.5;
pub const SSIM_K1: f64 = 0.01;
pub const SSIM_K2: f64 = 0.03;

/// Normalised 1-D Gaussian of `size` taps.
fn gaussian(size: usize, sigma: f64) -> Vec<f64> {
    let c = (size as f64 - 1.0) / 2.0;
    let w: Vec<f64> = (0..size).map(|i| (-((i as f64 - c).powi(2)) / (2.0 * sigma * sigma)).exp()).collect();
    let sum: f64 = w.iter().sum();
    w.into_iter().map(|v| v / sum).collect()
}

/// "Valid" separable filtering of a `width × height` plane: `(width−k+1) × (height−k+1)`.
fn filter_valid(plane: &[f64], width: usize, height: usize, taps: &[f64]) -> Vec<f64> {
    let k = taps.len();
    let (ow, oh) = (width + 1 - k, height + 1 - k);
    let mut rows = vec![0.0; ow * height];
    for y in 0..height {
        for x in 0..ow {
            rows[y * ow + x] = taps.iter().enumerate().map(|(i, t)| t * plane[y * width + x + i]).sum();
        }
    }
    let mut out = vec![0.0; ow * oh];
    for y in 0..oh {
        for x in 0..ow {
            out[y * ow + x] = taps.iter().enumerate().map(|(i, t)| t * rows[(y + i) * ow + x]).sum();
        }
    }
    out
}

/// Mean SSIM of two interleaved images (`width × height × channels`, values in 0..1),
/// per channel and averaged (see the module docs).
pub fn ssim(a: &[f32], b: &[f32], width: usize, height: usize, channels: usize) -> f64 {
    assert_eq!(a.len(), width * height * channels);
    assert_eq!(b.len(), a.len());
    if a.is_empty() {
        return 1.0;
    }
    let mut size = SSIM_WINDOW.min(width).min(height);
    if size.is_multiple_of(2) {
        size -= 1;
    }
    let taps = gaussian(size, SSIM_SIGMA);
    let (c1, c2) = (SSIM_K1 * SSIM_K1, SSIM_K2 * SSIM_K2);
    let mut total = 0.0;
    let mut count = 0usize;
    for ch in 0..channels {
        let x: Vec<f64> = a.iter().skip(ch).step_by(channels).map(|&v| v as f64).collect();
        let y: Vec<f64> = b.iter().skip(ch).step_by(channels).map(|&v| v as f64).collect();
        let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
        let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
        let xy: Vec<f64> = x.iter().zip(&y).map(|(p, q)| p * q).collect();
        let [mx, my, exx, eyy, exy] = [&x, &y, &xx, &yy, &xy].map(|p| filter_valid(p, width, height, &taps));
        for i in 0..mx.len() {
            let (vx, vy, cov) = (exx[i] - mx[i] * mx[i], eyy[i] - my[i] * my[i], exy[i] - mx[i] * my[i]);
            let num = (2.0 * mx[i] * my[i] + c1) * (2.0 * cov + c2);
            let den = (mx[i] * mx[i] + my[i] * my[i] + c1) * (vx + vy + c2);
            total += num / den;
        }
        count += mx.len();
    }
    total / count as f64
}

/// PSNR in dB of two images in 0..1 (peak 1), over all values.
pub fn psnr(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    let mse: f64 = a.iter().zip(b).map(|(p, q)| ((p - q) as f64).powi(2)).sum::<f64>() / a.len().max(1) as f64;
    -10.0 * mse.max(1e-12).log10()
}

/// Writes `ground truth | render | |error|×4` side by side as an 8-bit RGB PNG
/// (`3·width × height`); inputs are interleaved RGB in 0..1.
pub fn write_comparison_png(path: &Path, truth: &[f32], render: &[f32], width: u32, height: u32) -> Result<(), String> {
    let (w, h) = (width as usize, height as usize);
    assert_eq!(truth.len(), w * h * 3);
    assert_eq!(render.len(), truth.len());
    let q = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    let mut out = Vec::with_capacity(w * h * 9);
    for y in 0..h {
        let row = y * w * 3..(y + 1) * w * 3;
        out.extend(truth[row.clone()].iter().map(|&v| q(v)));
        out.extend(render[row.clone()].iter().map(|&v| q(v)));
        out.extend(truth[row.clone()].iter().zip(&render[row]).map(|(t, r)| q(4.0 * (t - r).abs())));
    }
    let err = |e: &dyn std::fmt::Display| format!("cannot write {}: {e}", path.display());
    let file = std::fs::File::create(path).map_err(|e| err(&e))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), 3 * width, height);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header().and_then(|mut wr| wr.write_image_data(&out)).map_err(|e| err(&e))
}

impl Trainer {
    /// Renders every pixel of a dataset view over `background`: interleaved RGB, row-major
    /// from the top row (the layout of [`DatasetImage::composite_over`]).
    pub fn render_image(&self, image: &DatasetImage, background: Vec3) -> Vec<f32> {
        let rays: Vec<(Vec3, Vec3)> = image.rays().collect();
        self.render(&rays, background).into_iter().flat_map(|(c, _)| c.to_array()).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn train_ssim_identity_noise_and_hand_cases() {
        let (w, h) = (24, 20);
        let img: Vec<f32> = (0..w * h * 3).map(|i| (i * 37 % 101) as f32 / 100.0).collect();
        assert!((ssim(&img, &img, w, h, 3) - 1.0).abs() < 1e-12);
        // More noise, lower SSIM.
        let noisy = |amp: f32| -> Vec<f32> { img.iter().enumerate().map(|(i, &v)| (v + amp * (((i * 7919) % 13) as f32 / 6.0 - 1.0)).clamp(0.0, 1.0)).collect() };
        let (s1, s2) = (ssim(&img, &noisy(0.05), w, h, 3), ssim(&img, &noisy(0.2), w, h, 3));
        assert!(s1 < 1.0 && s2 < s1, "{s1} {s2}");
        // One 11×11 window: constant images a and b have zero variance, so SSIM is the
        // luminance term (2ab + C1) / (a² + b² + C1).
        let c1 = 1e-4;
        let (a, b) = (vec![0.5f32; 121], vec![0.25f32; 121]);
        let want = (2.0 * 0.5 * 0.25 + c1) / (0.25 + 0.0625 + c1);
        assert!((ssim(&a, &b, 11, 11, 1) - want).abs() < 1e-6, "{} vs {want}", ssim(&a, &b, 11, 11, 1));
        // A horizontal ramp (symmetric about the centre, so its Gaussian mean is the centre
        // value 0.3) and the same ramp + 0.1: equal variances and covariance = variance, so
        // the contrast-structure term is 1 and SSIM = (2·0.3·0.4 + C1) / (0.3² + 0.4² + C1).
        let x: Vec<f32> = (0..121).map(|i| 0.3 + 0.02 * ((i % 11) as f32 - 5.0)).collect();
        let y: Vec<f32> = x.iter().map(|v| v + 0.1).collect();
        let want = (2.0 * 0.3 * 0.4 + c1) / (0.09 + 0.16 + c1);
        assert!((ssim(&x, &y, 11, 11, 1) - want).abs() < 1e-5, "{} vs {want}", ssim(&x, &y, 11, 11, 1));
    }

    #[test]
    fn train_psnr_of_a_known_error() {
        let a = vec![0.5f32; 300];
        let b = vec![0.6f32; 300];
        assert!((psnr(&a, &b) - 20.0).abs() < 1e-4);
    }
}
