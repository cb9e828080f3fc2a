//! Image metrics: PSNR and SSIM, as the paper's tables report them, and [`lpips`], the
//! third metric of its tables.

pub mod lpips;

/// `-10 log10(mse)`, for images in [0, 1].
pub fn psnr_from_mse(mse: f64) -> f32 {
    (-10.0 * mse.max(1e-20).log10()) as f32
}

/// PSNR between two packed images of the same size.
pub fn psnr(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let mse = a
        .iter()
        .zip(b)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        / a.len().max(1) as f64;
    psnr_from_mse(mse)
}

/// SSIM (Wang et al. 2004) of two packed RGB images: 11x11 Gaussian window (sigma 1.5),
/// K1 = 0.01, K2 = 0.03, data range 1, over the window positions fully inside the image
/// ("valid", as the reference evaluation did), averaged over pixels and channels.
pub fn ssim(a: &[f32], b: &[f32], width: usize, height: usize) -> f32 {
    const R: usize = 5;
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    let g: Vec<f64> = {
        let raw: Vec<f64> = (0..=2 * R)
            .map(|i| (-((i as f64 - R as f64).powi(2)) / (2.0 * 1.5 * 1.5)).exp())
            .collect();
        let s: f64 = raw.iter().sum();
        raw.iter().map(|v| v / s).collect()
    };
    if width <= 2 * R || height <= 2 * R {
        return f32::NAN;
    }
    let (ow, oh) = (width - 2 * R, height - 2 * R);
    // Separable blur of a full-size map to the valid region.
    let blur = |m: &[f64]| -> Vec<f64> {
        let mut rows = vec![0.0; ow * height];
        for y in 0..height {
            for x in 0..ow {
                rows[y * ow + x] = (0..=2 * R).map(|k| g[k] * m[y * width + x + k]).sum();
            }
        }
        let mut out = vec![0.0; ow * oh];
        for y in 0..oh {
            for x in 0..ow {
                out[y * ow + x] = (0..=2 * R).map(|k| g[k] * rows[(y + k) * ow + x]).sum();
            }
        }
        out
    };
    let mut total = 0.0;
    for c in 0..3 {
        let x: Vec<f64> = a.iter().skip(c).step_by(3).map(|&v| v as f64).collect();
        let y: Vec<f64> = b.iter().skip(c).step_by(3).map(|&v| v as f64).collect();
        let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
        let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
        let xy: Vec<f64> = x.iter().zip(&y).map(|(p, q)| p * q).collect();
        let (mx, my, sxx, syy, sxy) = (blur(&x), blur(&y), blur(&xx), blur(&yy), blur(&xy));
        let mut sum = 0.0;
        for i in 0..ow * oh {
            let (vx, vy, cov) = (
                sxx[i] - mx[i] * mx[i],
                syy[i] - my[i] * my[i],
                sxy[i] - mx[i] * my[i],
            );
            sum += ((2.0 * mx[i] * my[i] + c1) * (2.0 * cov + c2))
                / ((mx[i] * mx[i] + my[i] * my[i] + c1) * (vx + vy + c2));
        }
        total += sum / (ow * oh) as f64;
    }
    (total / 3.0) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn psnr_of_known_error() {
        let a = vec![0.5; 300];
        let b = vec![0.6; 300];
        assert!((psnr(&a, &b) - 20.0).abs() < 1e-3);
    }

    #[test]
    fn ssim_is_one_for_equal_images_and_drops_with_noise() {
        let (w, h) = (32, 24);
        let mut rng = Rng::new(4);
        let a: Vec<f32> = (0..w * h * 3)
            .map(|i| 0.5 + 0.4 * ((i / 3 % w) as f32 * 0.3).sin())
            .collect();
        assert!((ssim(&a, &a, w, h) - 1.0).abs() < 1e-6);
        let noisy: Vec<f32> = a.iter().map(|v| v + rng.range(-0.1, 0.1)).collect();
        let very: Vec<f32> = a.iter().map(|v| v + rng.range(-0.4, 0.4)).collect();
        let (s1, s2) = (ssim(&a, &noisy, w, h), ssim(&a, &very, w, h));
        assert!(s1 < 0.99 && s2 < s1, "{s1} {s2}");
        // A constant offset of luminance only: SSIM stays high, PSNR falls.
        let shifted: Vec<f32> = a.iter().map(|v| v + 0.05).collect();
        assert!(ssim(&a, &shifted, w, h) > 0.95);
    }
}
