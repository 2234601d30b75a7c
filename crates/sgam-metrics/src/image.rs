use sgam_core::Image;

fn q8(x: f32) -> f64 {
    (x.clamp(0.0, 1.0) * 255.0).round() as f64
}

/// Peak signal-to-noise ratio in dB of a mean squared error `mse` for signals whose peak is
/// `peak` (255 for 8-bit levels, 1 for `[0, 1]` values): `10 log10(peak^2 / mse)`. The one PSNR
/// formula of the workspace ([`psnr`] and the trainer's reports use it).
pub fn psnr_db(mse: f64, peak: f64) -> f64 {
    10.0 * (peak * peak / mse).log10()
}

/// PSNR (dB) between two colour images on the 8-bit scale, over pixels where `mask` is true
/// (all pixels when `None`). Returns `None` when no pixel is counted or sizes differ; identical
/// images give `f64::INFINITY`.
pub fn psnr(a: &Image<[f32; 3]>, b: &Image<[f32; 3]>, mask: Option<&[bool]>) -> Option<f64> {
    if a.size() != b.size() {
        return None;
    }
    let (mut se, mut n) = (0.0f64, 0usize);
    for (i, (pa, pb)) in a.data.iter().zip(&b.data).enumerate() {
        if mask.is_some_and(|m| !m[i]) {
            continue;
        }
        for c in 0..3 {
            let d = q8(pa[c]) - q8(pb[c]);
            se += d * d;
        }
        n += 3;
    }
    if n == 0 {
        return None;
    }
    let mse = se / n as f64;
    Some(if mse == 0.0 { f64::INFINITY } else { psnr_db(mse, 255.0) })
}

fn gaussian_kernel() -> [f64; 11] {
    let mut k = [0.0f64; 11];
    for (i, x) in k.iter_mut().enumerate() {
        let d = i as f64 - 5.0;
        *x = (-d * d / (2.0 * 1.5 * 1.5)).exp();
    }
    let s: f64 = k.iter().sum();
    k.map(|x| x / s)
}

/// Separable 11-tap Gaussian blur with the window clipped at borders (renormalised), so every
/// pixel gets an SSIM value.
fn blur(src: &[f64], w: usize, h: usize, k: &[f64; 11]) -> Vec<f64> {
    let mut tmp = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let (mut acc, mut ws) = (0.0, 0.0);
            for (t, kv) in k.iter().enumerate() {
                let xx = x as isize + t as isize - 5;
                if xx >= 0 && (xx as usize) < w {
                    acc += kv * src[y * w + xx as usize];
                    ws += kv;
                }
            }
            tmp[y * w + x] = acc / ws;
        }
    }
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let (mut acc, mut ws) = (0.0, 0.0);
            for (t, kv) in k.iter().enumerate() {
                let yy = y as isize + t as isize - 5;
                if yy >= 0 && (yy as usize) < h {
                    acc += kv * tmp[yy as usize * w + x];
                    ws += kv;
                }
            }
            out[y * w + x] = acc / ws;
        }
    }
    out
}

/// Per-pixel SSIM map (mean over the three channels), row-major, same size as the inputs.
/// Returns `None` when sizes differ.
pub fn ssim_map(a: &Image<[f32; 3]>, b: &Image<[f32; 3]>) -> Option<Vec<f64>> {
    if a.size() != b.size() {
        return None;
    }
    let (w, h) = (a.width as usize, a.height as usize);
    let k = gaussian_kernel();
    let (c1, c2) = ((0.01f64).powi(2), (0.03f64).powi(2));
    let mut total = vec![0.0f64; w * h];
    for c in 0..3 {
        let x: Vec<f64> = a.data.iter().map(|p| p[c].clamp(0.0, 1.0) as f64).collect();
        let y: Vec<f64> = b.data.iter().map(|p| p[c].clamp(0.0, 1.0) as f64).collect();
        let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
        let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
        let xy: Vec<f64> = x.iter().zip(&y).map(|(p, q)| p * q).collect();
        let (mx, my) = (blur(&x, w, h, &k), blur(&y, w, h, &k));
        let (sxx, syy, sxy) = (blur(&xx, w, h, &k), blur(&yy, w, h, &k), blur(&xy, w, h, &k));
        for i in 0..w * h {
            let (vx, vy, cxy) = (sxx[i] - mx[i] * mx[i], syy[i] - my[i] * my[i], sxy[i] - mx[i] * my[i]);
            let s = ((2.0 * mx[i] * my[i] + c1) * (2.0 * cxy + c2))
                / ((mx[i] * mx[i] + my[i] * my[i] + c1) * (vx + vy + c2));
            total[i] += s / 3.0;
        }
    }
    Some(total)
}

/// Mean SSIM over pixels where `mask` is true (all when `None`); `None` when nothing is counted.
pub fn ssim(a: &Image<[f32; 3]>, b: &Image<[f32; 3]>, mask: Option<&[bool]>) -> Option<f64> {
    let map = ssim_map(a, b)?;
    let (mut s, mut n) = (0.0, 0usize);
    for (i, v) in map.iter().enumerate() {
        if mask.is_none_or(|m| m[i]) {
            s += v;
            n += 1;
        }
    }
    (n > 0).then(|| s / n as f64)
}

/// Mean absolute difference of disparity `1/z` (1/m) over pixels where both depths are valid
/// and `mask` is true.
pub fn disparity_l1(a_depth_m: &Image<f32>, b_depth_m: &Image<f32>, mask: Option<&[bool]>) -> Option<f64> {
    if a_depth_m.size() != b_depth_m.size() {
        return None;
    }
    let (mut s, mut n) = (0.0f64, 0usize);
    for (i, (da, db)) in a_depth_m.data.iter().zip(&b_depth_m.data).enumerate() {
        if mask.is_some_and(|m| !m[i]) || !sgam_core::is_valid_depth(*da) || !sgam_core::is_valid_depth(*db) {
            continue;
        }
        s += (1.0 / *da as f64 - 1.0 / *db as f64).abs();
        n += 1;
    }
    (n > 0).then(|| s / n as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn noise_image(seed: u64, w: u32, h: u32) -> Image<[f32; 3]> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let data = (0..w * h).map(|_| [rng.random(), rng.random(), rng.random()]).collect();
        Image::try_from_vec(w, h, data).unwrap()
    }

    #[test]
    fn psnr_of_known_error() {
        let a = Image::filled(8, 8, [0.5f32; 3]);
        let mut b = a.clone();
        // shift every value by exactly 10 levels: mse = 100 -> psnr = 10 log10(65025/100)
        for p in &mut b.data {
            *p = [(128.0 + 10.0) / 255.0; 3];
        }
        let expected = 10.0 * (65025.0f64 / 100.0).log10();
        assert!((psnr(&a, &b, None).unwrap() - expected).abs() < 1e-9);
        assert_eq!(psnr(&a, &a, None), Some(f64::INFINITY));
        let none = vec![false; 64];
        assert_eq!(psnr(&a, &b, Some(&none)), None);
    }

    #[test]
    fn ssim_identity_and_degradation() {
        let a = noise_image(1, 32, 24);
        assert!((ssim(&a, &a, None).unwrap() - 1.0).abs() < 1e-9);
        let mut b = a.clone();
        for (i, p) in b.data.iter_mut().enumerate() {
            if i % 3 == 0 {
                *p = [p[0] * 0.5, p[1], 1.0 - p[2]];
            }
        }
        let s = ssim(&a, &b, None).unwrap();
        assert!(s < 0.95 && s > 0.0, "ssim {s}");
        let c = noise_image(2, 32, 24);
        assert!(ssim(&a, &c, None).unwrap() < 0.1);
        // Two flat images have zero variance and covariance, so SSIM is the luminance term alone,
        // (2 mx my + c1) / (mx^2 + my^2 + c1) with c1 = 0.01^2, at every pixel (the blur of a
        // constant is that constant up to f64 rounding, ~1e-16).
        let f = Image::filled(16, 16, [0.5f32; 3]);
        let g = Image::filled(16, 16, [0.55f32; 3]);
        let (mx, my, c1) = (0.5f64, 0.55f32 as f64, 1e-4);
        let expected = (2.0 * mx * my + c1) / (mx * mx + my * my + c1); // 0.99548...
        let sf = ssim(&f, &g, None).unwrap();
        assert!((sf - expected).abs() < 1e-9, "{sf} vs {expected}");
        assert!(ssim_map(&f, &g).unwrap().iter().all(|s| (s - expected).abs() < 1e-9));
    }

    #[test]
    fn disparity_l1_ignores_invalid() {
        let a = Image::try_from_vec(2, 1, vec![2.0, 0.0]).unwrap();
        let b = Image::try_from_vec(2, 1, vec![4.0, 3.0]).unwrap();
        assert!((disparity_l1(&a, &b, None).unwrap() - 0.25).abs() < 1e-12);
    }
}
