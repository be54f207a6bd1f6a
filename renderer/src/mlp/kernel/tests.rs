//! The fast kernels against the plain network: bit-identical in f32, within the rounding
//! bound in 8 bits.

use super::*;
use crate::mlp::SpecularMlp;
use rand::{Rng, SeedableRng, rngs::SmallRng};

#[test]
fn kernel_is_bit_identical_to_the_reference() {
    let mut rng = SmallRng::seed_from_u64(7);
    for input in [1, 5, 21, 64] {
        let mut m = SpecularMlp::zeros(input);
        for w in [&mut m.w0, &mut m.b0, &mut m.w1, &mut m.b1, &mut m.w2, &mut m.b2] {
            w.iter_mut().for_each(|v| *v = rng.random_range(-1.0..1.0));
        }
        let k = m.kernel();
        for _ in 0..200 {
            let x: Vec<f32> = (0..input).map(|_| rng.random_range(-3.0..3.0)).collect();
            let (a, b) = (m.forward(&x), k.forward(&x));
            assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits), "input {input}: {a:?} vs {b:?}");
        }
    }
}

/// The vector kernels skip the inputs that are zero for the whole tile (dead ReLUs): the
/// same bits as the fused portable body, which takes every input in the same order.
#[cfg(target_arch = "x86_64")]
#[test]
fn skipping_zero_rows_changes_no_bit() {
    if simd::level() == simd::Level::Portable {
        eprintln!("no AVX2 on this CPU: only the portable path exists");
        return;
    }
    let mut rng = SmallRng::seed_from_u64(12);
    for input in [5, 25, 64] {
        let mut m = SpecularMlp::zeros(input);
        for w in [&mut m.w0, &mut m.b0, &mut m.w1, &mut m.b1, &mut m.w2, &mut m.b2] {
            w.iter_mut().for_each(|v| *v = rng.random_range(-0.5..0.5));
        }
        // A third of each hidden layer is off for every input, as dead ReLUs are; the
        // rest is on for some rays of a tile and off for others.
        for j in (0..HIDDEN).step_by(3) {
            (m.b0[j], m.b1[(j + 1) % HIDDEN]) = (-100.0, -100.0);
        }
        let k = m.kernel();
        for _ in 0..50 {
            let mut x = [[0.0f32; TILE]; MAX_INPUT];
            for row in x.iter_mut().take(input) {
                row.iter_mut().for_each(|v| *v = rng.random_range(-3.0..3.0));
            }
            let fused = tile_body::<8, true>(&k, &x);
            let bits = |o: [[f32; TILE]; 4]| o.map(|r| r.map(f32::to_bits));
            assert_eq!(bits(simd::tile_avx2(&k, &x)), bits(fused), "AVX2, input {input}");
            if simd::level() == simd::Level::Avx512 {
                assert_eq!(bits(simd::tile_avx512(&k, &x)), bits(fused), "AVX-512, input {input}");
            }
        }
    }
}

#[test]
fn tile_kernel_agrees_with_the_reference() {
    let mut rng = SmallRng::seed_from_u64(9);
    for input in [1, 21, 37, 64] {
        let mut m = SpecularMlp::zeros(input);
        for w in [&mut m.w0, &mut m.b0, &mut m.w1, &mut m.b1, &mut m.w2, &mut m.b2] {
            w.iter_mut().for_each(|v| *v = rng.random_range(-0.5..0.5));
        }
        let k = m.kernel();
        let mut x = [[0.0f32; TILE]; MAX_INPUT];
        for row in x.iter_mut().take(input) {
            row.iter_mut().for_each(|v| *v = rng.random_range(-3.0..3.0));
        }
        let got = k.forward_tile(&x);
        let portable = tile_body::<8, false>(&k, &x);
        // Every vector level this CPU has, not only the widest.
        #[cfg(target_arch = "x86_64")]
        let avx2 = (simd::level() != simd::Level::Portable).then(|| simd::tile_avx2(&k, &x));
        #[cfg(not(target_arch = "x86_64"))]
        let avx2: Option<[[f32; TILE]; 4]> = None;
        for l in 0..TILE {
            let xs: Vec<f32> = (0..input).map(|i| x[i][l]).collect();
            let want = m.forward(&xs);
            for j in 0..4 {
                // Sums of ≤ 64 products of size ≲ 10: f32 rounding differences ≲ 1e-5.
                let tol = 1e-5 * (1.0 + want[j].abs());
                assert!((got[j][l] - want[j]).abs() <= tol, "input {input} lane {l} out {j}: {} vs {}", got[j][l], want[j]);
                assert!((portable[j][l] - want[j]).abs() <= tol);
                assert!(avx2.is_none_or(|a| (a[j][l] - want[j]).abs() <= tol), "AVX2, input {input}");
            }
        }
    }
}

/// The 8-bit hidden layer errs as its rounding predicts. Per product w·h the rounding
/// adds at most |w|·λ/2 + h·s/2 + s·λ/4 (λ = the query's largest hidden value / 255,
/// s = the row's largest |w| / 127), carried through layer 2 by |w2|: a hard bound on
/// every output. Treating the roundings as independent and uniform, the error's standard
/// deviation is the root of Σ w²λ²/12 + h²s²/12 (through |w2|²): the errors' RMS over
/// the tiles must be within 1.5 of it and none beyond 6 (a kernel that mixed up its
/// bytes would be off by the outputs' own size). Extremes: a query whose hidden vector
/// is all zero (then the f32 kernel's bits), one with a single tiny input, inputs
/// scaled by 10⁻⁴ and 10³.
#[cfg(target_arch = "x86_64")]
#[test]
fn int8_hidden_layer_errs_within_its_rounding_bound() {
    if !simd::vnni() && simd::level() != simd::Level::Avx2 {
        eprintln!("this CPU has neither AVX-512 VNNI nor AVX2 without AVX-512: the 8-bit hidden layer is never used here (the f32 kernel is)");
        assert!(!SpecularMlp::zeros(4).kernel().with_int8_hidden().int8_hidden());
        return;
    }
    let mut rng = SmallRng::seed_from_u64(21);
    let (mut z_sq, mut z_max, mut count) = (0.0f64, 0.0f64, 0usize);
    for (input, scale) in [(25, 1.0f32), (25, 1e-4), (25, 1e3), (64, 1.0), (7, 1.0)] {
        let mut m = SpecularMlp::zeros(input);
        for w in [&mut m.w0, &mut m.b0, &mut m.w1, &mut m.b1, &mut m.w2, &mut m.b2] {
            w.iter_mut().for_each(|v| *v = rng.random_range(-0.5..0.5));
        }
        if input == 7 {
            m.b0.iter_mut().for_each(|b| *b = -b.abs() - 0.01);
        }
        let k = m.kernel().with_int8_hidden();
        assert!(k.int8_hidden());
        let weight_levels = k.hidden8.as_ref().map_or(0.0, |q| q.weight_levels);
        let mut x = [[0.0f32; TILE]; MAX_INPUT];
        for row in x.iter_mut().take(input) {
            row.iter_mut().for_each(|v| *v = scale * rng.random_range(-3.0..3.0));
        }
        // Lane 0 without input (with negative biases: every hidden unit off); lane 1 with
        // one tiny input.
        let all_off = input == 7;
        x.iter_mut().take(input).for_each(|row| (row[0], row[1]) = (0.0, 0.0));
        x[0][1] = 1e-6;
        let got = k.forward_tile(&x);
        let f32_tile = m.kernel().forward_tile(&x);
        for l in 0..TILE {
            let xs: Vec<f32> = (0..input).map(|i| x[i][l]).collect();
            let h0: Vec<f32> = (0..HIDDEN).map(|j| (m.b0[j] + (0..input).map(|i| m.w0[j * input + i] * xs[i]).sum::<f32>()).max(0.0)).collect();
            let lambda = h0.iter().fold(0.0f32, |a, &v| a.max(v)) / 255.0;
            let (bound1, var1): (Vec<f32>, Vec<f64>) = (0..HIDDEN)
                .map(|j| {
                    let row = &m.w1[j * HIDDEN..(j + 1) * HIDDEN];
                    let s = row.iter().fold(0.0f32, |a, v| a.max(v.abs())) / weight_levels;
                    let size: f32 = m.b1[j].abs() + row.iter().zip(&h0).map(|(w, h)| (w * h).abs()).sum::<f32>();
                    let bound = row.iter().zip(&h0).map(|(w, h)| w.abs() * lambda / 2.0 + h * s / 2.0 + s * lambda / 4.0).sum::<f32>() + 1e-5 * size;
                    let var = row.iter().zip(&h0).map(|(&w, &h)| ((w * lambda).powi(2) + (h * s).powi(2)) as f64 / 12.0).sum::<f64>();
                    (bound, var)
                })
                .unzip();
            let want = m.forward(&xs);
            for (o, (got_o, want_o)) in got.iter().zip(want).enumerate() {
                let bound = (0..HIDDEN).map(|j| m.w2[o * HIDDEN + j].abs() * bound1[j]).sum::<f32>() + 1e-5 * (1.0 + want_o.abs());
                let err = (got_o[l] - want_o).abs();
                assert!(err <= bound, "input {input} ×{scale} lane {l} out {o}: {} vs {want_o} (bound {bound})", got_o[l]);
                if l == 0 && all_off {
                    assert_eq!(got_o[l], f32_tile[o][l], "no hidden value: the f32 kernel's bits");
                    continue;
                }
                let std = (0..HIDDEN).map(|j| (m.w2[o * HIDDEN + j] as f64).powi(2) * var1[j]).sum::<f64>().sqrt();
                let z = err as f64 / (std + 1e-6 * (1.0 + want_o.abs() as f64));
                (z_sq, z_max, count) = (z_sq + z * z, z_max.max(z), count + 1);
            }
        }
    }
    let z_rms = (z_sq / count as f64).sqrt();
    eprintln!("errors in predicted standard deviations: RMS {z_rms:.2}, largest {z_max:.2} over {count} outputs");
    assert!(z_rms <= 1.5 && z_max <= 6.0, "RMS {z_rms}, largest {z_max}");
}
