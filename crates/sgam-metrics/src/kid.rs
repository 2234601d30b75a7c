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

    #[test]
    fn kid_of_tiny_sets_equals_the_hand_computed_estimate() {
        // d = 2, k(a, b) = (a.b / 2 + 1)^3. X = {(1, 0), (0, 1)}: the one off-diagonal pair has
        // a.b = 0, k = 1, so the within-X mean is 1 (the diagonal, k = 1.5^3 = 3.375, is left
        // out: with it the mean would be 2.1875). Y = {(2, 2), (2, 2)}: a.b = 8, k = 5^3 = 125.
        // Cross: every x.y = 2, k = 2^3 = 8. KID = 1 + 125 - 2 * 8 = 110.
        let x = vec![vec![1.0f32, 0.0], vec![0.0, 1.0]];
        let y = vec![vec![2.0f32, 2.0], vec![2.0, 2.0]];
        assert_eq!(kid(&x, &y), Some(110.0));
        assert_eq!(kid(&y, &x), Some(110.0), "symmetric");
        // The unbiased estimate can be negative. d = 1, X = {0, 1}, Y = {0, 2}: within X
        // k(0, 1) = 1, within Y k(0, 2) = 1, cross (1 + 1 + 1 + 3^3) / 4 = 7.5: 1 + 1 - 15 = -13.
        assert_eq!(kid(&[vec![0.0], vec![1.0]], &[vec![0.0], vec![2.0]]), Some(-13.0));
        // Three rows: the within mean divides by n (n - 1) = 6 ordered pairs. X = {(1, 0),
        // (0, 1), (0, 0)}: every pair has a.b = 0, within mean 1; Y as above; cross: x.y is 2,
        // 2, 0, k = 8, 8, 1 per y row, mean (8 + 8 + 1) / 3 = 17 / 3. KID = 1 + 125 - 34 / 3.
        let x3 = vec![vec![1.0f32, 0.0], vec![0.0, 1.0], vec![0.0, 0.0]];
        let got = kid(&x3, &y).unwrap();
        assert!((got - (126.0 - 34.0 / 3.0)).abs() < 1e-12, "{got}");
        // rows of another length are refused
        assert!(kid(&x, &[vec![1.0], vec![2.0]]).is_none());
    }
}
