//! Fixtures shared by the model's test files.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sgam_core::{Image, RgbdFrame};

/// A `w x h` frame of random colours and depths in 8-14 m, drawn from `seed`.
pub fn frame(w: u32, h: u32, seed: u64) -> RgbdFrame {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let colour = (0..w * h).map(|_| [rng.random(), rng.random(), rng.random()]).collect();
    let depth = (0..w * h).map(|_| rng.random_range(8.0..14.0)).collect();
    RgbdFrame {
        colour: Image { width: w, height: h, data: colour },
        depth_m: Image { width: w, height: h, data: depth },
    }
}
