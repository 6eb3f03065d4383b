//! Error of an AO image against a reference: RMSE, bias, SSIM and
//! equal-error rays, over the pixels where both have a value.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Comparison {
    /// Pixels where both images have a value.
    pub pixels: usize,
    /// sqrt(mean (ao − ref)²), as measured (includes the reference's own noise).
    pub rmse: f64,
    /// mean (ao − ref): > 0 means the AO is too bright (too little occlusion).
    pub bias: f64,
    pub mae: f64,
    pub max_abs: f64,
    /// Mean SSIM over those pixels (Gaussian window σ = 1.5, 11×11, L = 1,
    /// C1 = 0.01², C2 = 0.03²; the window only sees pixels valid in both).
    pub ssim: f64,
    /// mean σ²: the per-pixel variance of a one-ray estimate of V (sample
    /// variance of w over the reference's rays), averaged.
    pub one_ray_variance: f64,
    /// mean σ² / N: the reference's own contribution to the measured MSE.
    pub reference_mse: f64,
    /// Equal-error rays per pixel: k with mean(σ²) / k = the renderer's MSE
    /// against the true V, estimated as measured MSE − reference_mse (an
    /// unbiased estimate, since the reference's noise is independent of the
    /// renderer). A k-ray estimate's expected MSE is mean σ² / k; solving
    /// gives k = mean σ² / MSE. `null` when the renderer's MSE is below what
    /// the reference can resolve (then k ≥ N is all that can be said).
    pub equal_error_rays: Option<f64>,
}

/// Compares `ao` with `reference` (both W·H, NaN = no value). `variance` is
/// the per-pixel one-ray variance of the reference, `rays` its ray count.
pub fn compare(
    ao: &[f32],
    reference: &[f32],
    variance: &[f32],
    rays: u32,
    width: u32,
    height: u32,
) -> Comparison {
    let valid: Vec<bool> = ao.iter().zip(reference).map(|(a, r)| a.is_finite() && r.is_finite()).collect();
    let (mut n, mut se, mut sum, mut sa, mut max_abs, mut var) = (0usize, 0.0, 0.0, 0.0, 0f64, 0.0);
    for i in 0..ao.len() {
        if !valid[i] {
            continue;
        }
        let d = ao[i] as f64 - reference[i] as f64;
        n += 1;
        se += d * d;
        sum += d;
        sa += d.abs();
        max_abs = max_abs.max(d.abs());
        var += if variance[i].is_finite() { variance[i] as f64 } else { 0.0 };
    }
    let k = n.max(1) as f64;
    let mse = se / k;
    let one_ray_variance = var / k;
    let reference_mse = one_ray_variance / rays.max(1) as f64;
    let true_mse = mse - reference_mse;
    let equal_error_rays =
        (n > 0 && true_mse > reference_mse * 0.1 && true_mse > 0.0).then(|| one_ray_variance / true_mse);
    Comparison {
        pixels: n,
        rmse: mse.sqrt(),
        bias: sum / k,
        mae: sa / k,
        max_abs,
        ssim: ssim(ao, reference, &valid, width as usize, height as usize),
        one_ray_variance,
        reference_mse,
        equal_error_rays,
    }
}

/// Mean SSIM over the pixels where `valid`, each window restricted to valid pixels.
pub fn ssim(a: &[f32], b: &[f32], valid: &[bool], width: usize, height: usize) -> f64 {
    const RADIUS: isize = 5;
    const SIGMA: f64 = 1.5;
    let (c1, c2) = (0.01f64 * 0.01, 0.03f64 * 0.03);
    let kernel: Vec<f64> =
        (-RADIUS..=RADIUS).map(|i| (-(i * i) as f64 / (2.0 * SIGMA * SIGMA)).exp()).collect();
    let (mut total, mut count) = (0.0, 0usize);
    for y in 0..height as isize {
        for x in 0..width as isize {
            if !valid[y as usize * width + x as usize] {
                continue;
            }
            let (mut sw, mut ma, mut mb, mut aa, mut bb, mut ab) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
            for dy in -RADIUS..=RADIUS {
                let yy = y + dy;
                if yy < 0 || yy >= height as isize {
                    continue;
                }
                for dx in -RADIUS..=RADIUS {
                    let xx = x + dx;
                    if xx < 0 || xx >= width as isize {
                        continue;
                    }
                    let j = yy as usize * width + xx as usize;
                    if !valid[j] {
                        continue;
                    }
                    let w = kernel[(dy + RADIUS) as usize] * kernel[(dx + RADIUS) as usize];
                    let (va, vb) = (a[j] as f64, b[j] as f64);
                    sw += w;
                    ma += w * va;
                    mb += w * vb;
                    aa += w * va * va;
                    bb += w * vb * vb;
                    ab += w * va * vb;
                }
            }
            let (ma, mb) = (ma / sw, mb / sw);
            let va = (aa / sw - ma * ma).max(0.0);
            let vb = (bb / sw - mb * mb).max(0.0);
            let cov = ab / sw - ma * mb;
            total += ((2.0 * ma * mb + c1) * (2.0 * cov + c2)) / ((ma * ma + mb * mb + c1) * (va + vb + c2));
            count += 1;
        }
    }
    if count == 0 { f64::NAN } else { total / count as f64 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_images_are_perfect_and_an_offset_is_bias() {
        let (w, h) = (16, 8);
        let a: Vec<f32> = (0..w * h).map(|i| (i % 7) as f32 / 7.0).collect();
        let var = vec![0.1f32; w * h];
        let same = compare(&a, &a, &var, 1000, w as u32, h as u32);
        assert_eq!(same.rmse, 0.0);
        assert!((same.ssim - 1.0).abs() < 1e-9);
        assert!(same.equal_error_rays.is_none(), "no measurable error: {same:?}");
        let b: Vec<f32> = a.iter().map(|v| v + 0.1).collect();
        let off = compare(&b, &a, &var, 1000, w as u32, h as u32);
        assert!((off.bias - 0.1).abs() < 1e-6 && (off.rmse - 0.1).abs() < 1e-6);
        // σ² = 0.1, MSE ≈ 0.01 − 0.0001: k ≈ 10.1.
        let k = off.equal_error_rays.unwrap();
        assert!((k - 0.1 / (0.01 - 0.0001)).abs() < 0.01, "{k}");
        assert!(off.ssim < 1.0);
    }

    #[test]
    fn nan_pixels_are_left_out() {
        let a = [0.5f32, f32::NAN, 0.25, 0.75];
        let b = [0.5f32, 0.1, f32::NAN, 0.75];
        let c = compare(&a, &b, &[0.0; 4], 16, 2, 2);
        assert_eq!(c.pixels, 2);
        assert_eq!(c.rmse, 0.0);
        assert!(c.ssim.is_finite());
    }
}
