//! View encoding E_v: real spherical harmonics of degree 4 (16 values) of a unit direction,
//! with the same constants and ordering as instant-ngp's `SphericalHarmonics` encoding.

use glam::Vec3;

pub const SH_COEFFS: usize = 16;

pub fn sh4(d: Vec3) -> [f32; SH_COEFFS] {
    let (x, y, z) = (d.x, d.y, d.z);
    let (xy, yz, xz) = (x * y, y * z, x * z);
    let (x2, y2, z2) = (x * x, y * y, z * z);
    [
        0.282_094_79,
        -0.488_602_51 * y,
        0.488_602_51 * z,
        -0.488_602_51 * x,
        1.092_548_4 * xy,
        -1.092_548_4 * yz,
        0.946_174_7 * z2 - 0.315_391_57,
        -1.092_548_4 * xz,
        0.546_274_2 * x2 - 0.546_274_2 * y2,
        0.590_043_6 * y * (-3.0 * x2 + y2),
        2.890_611_4 * xy * z,
        0.457_045_8 * y * (1.0 - 5.0 * z2),
        0.373_176_33 * z * (5.0 * z2 - 3.0),
        0.457_045_8 * x * (1.0 - 5.0 * z2),
        1.445_305_7 * z * (x2 - y2),
        0.590_043_6 * x * (-x2 + 3.0 * y2),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Real SH are orthonormal on the sphere: check by Monte-Carlo-free quadrature on a
    /// Fibonacci sphere.
    #[test]
    fn basis_is_orthonormal() {
        let n = 20_000;
        let mut gram = [[0.0f64; SH_COEFFS]; SH_COEFFS];
        for i in 0..n {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let phi = i as f64 * std::f64::consts::PI * (3.0 - 5f64.sqrt());
            let r = (1.0 - z * z).sqrt();
            let v = sh4(Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32));
            for a in 0..SH_COEFFS {
                for b in 0..SH_COEFFS {
                    gram[a][b] += v[a] as f64 * v[b] as f64 * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for a in 0..SH_COEFFS {
            for b in 0..SH_COEFFS {
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((gram[a][b] - want).abs() < 2e-3, "<{a},{b}> = {}", gram[a][b]);
            }
        }
    }
}
