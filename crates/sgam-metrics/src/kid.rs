//! Kernel Inception Distance (Binkowski et al. 2018) on arbitrary feature vectors: the unbiased
//! MMD^2 estimate with the cubic polynomial kernel `k(x, y) = (x . y / d + 1)^3`. Weight-free
//! when the features come from a network we train ourselves (e.g. our VQ encoder).

/// Unbiased KID between two feature sets (rows of length `d`). `None` with fewer than two rows
/// in either set or mismatched dimensions.
pub fn kid(x: &[Vec<f32>], y: &[Vec<f32>]) -> Option<f64> {
    let d = x.first()?.len();
    if x.len() < 2 || y.len() < 2 || d == 0 || x.iter().chain(y).any(|r| r.len() != d) {
        return None;
    }
    let k = |a: &[f32], b: &[f32]| {
        let dot: f64 = a.iter().zip(b).map(|(p, q)| *p as f64 * *q as f64).sum();
        (dot / d as f64 + 1.0).powi(3)
    };
    let within = |s: &[Vec<f32>]| {
        let n = s.len();
        let mut acc = 0.0;
        for i in 0..n {
            for j in 0..n {
                if i != j {
                    acc += k(&s[i], &s[j]);
                }
            }
        }
        acc / (n * (n - 1)) as f64
    };
    let mut cross = 0.0;
    for a in x {
        for b in y {
            cross += k(a, b);
        }
    }
    cross /= (x.len() * y.len()) as f64;
    Some(within(x) + within(y) - 2.0 * cross)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn kid_separates_shifted_distributions() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut draw = |shift: f32| -> Vec<Vec<f32>> {
            (0..60).map(|_| (0..8).map(|_| rng.random_range(-1.0..1.0) + shift).collect()).collect()
        };
        let (a, b, c) = (draw(0.0), draw(0.0), draw(1.0));
        let same = kid(&a, &b).unwrap();
        let diff = kid(&a, &c).unwrap();
        assert!(same.abs() < 0.05, "same {same}");
        assert!(diff > 10.0 * same.abs().max(1e-3), "diff {diff} same {same}");
        assert!(kid(&a[..1], &b).is_none());
    }
}
