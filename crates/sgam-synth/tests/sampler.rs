//! The on-the-fly training sampler.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::sync::Arc;

use rand::SeedableRng;
use sgam_synth::*;

fn config(on_grid: bool) -> SamplerConfig {
    SamplerConfig {
        scene_seeds: vec![3, 4, 5],
        scene: SceneConfig { object_count: 300, ..SceneConfig::default() },
        res: 32,
        k_sources: 3,
        radius_m: 1.0,
        on_grid,
        target_jitter: CameraJitter { position_m: 0.1, height_m: 0.2, pitch_rad: 0.05, yaw_rad: 0.1 },
        source_jitter: CameraJitter { position_m: 0.0, height_m: 0.1, pitch_rad: 0.02, yaw_rad: 0.0 },
        cache_scenes: 2,
        ..SamplerConfig::default()
    }
}

#[test]
fn samples_are_deterministic_given_the_rng() {
    for on_grid in [true, false] {
        let mut a = Sampler::new(config(on_grid));
        let mut b = Sampler::new(config(on_grid));
        let mut ra = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let mut rb = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        for _ in 0..4 {
            let sa = a.sample(&mut ra);
            let sb = b.sample(&mut rb);
            assert_eq!(sa, sb);
        }
    }
}

#[test]
fn sources_lie_within_the_radius_and_frames_are_rendered() {
    for on_grid in [true, false] {
        let cfg = config(on_grid);
        let mut s = Sampler::new(cfg.clone());
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        for _ in 0..5 {
            let sample = s.sample(&mut rng);
            assert!(cfg.scene_seeds.contains(&sample.scene_seed));
            assert_eq!(sample.sources.len(), cfg.k_sources);
            let t = sample.target.0.centre_world();
            for (cam, frame) in &sample.sources {
                let d = (cam.centre_world() - t).truncate().length();
                // Target position jitter 0.1 per axis adds at most 0.1 * sqrt(2).
                assert!(d <= cfg.radius_m + 0.15, "source {d} m from the target");
                assert!(cam.centre_world().z.abs() <= 0.1 + 1e-6);
                assert_eq!((frame.width(), frame.height()), (32, 32));
                assert!(frame.valid_fraction() > 0.99);
            }
            assert!(sample.target.0.centre_world().z.abs() <= 0.2 + 1e-6);
        }
    }
}

#[test]
fn scenes_are_cached_lru() {
    // Capacity 2 (`cache_scenes`). A cache hit hands out the cached Arc; an evicted scene's Arc is
    // held only by the caller (strong count 1) and asking again builds a fresh one.
    let mut s = Sampler::new(config(true));
    let a = s.scene(3);
    assert!(Arc::ptr_eq(&a, &s.scene(3)));
    let b = s.scene(4);
    assert!(Arc::ptr_eq(&a, &s.scene(3))); // 3 is most recent now: [4, 3]
    let c = s.scene(5); // evicts 4, the least recently used: [3, 5]
    assert_eq!(Arc::strong_count(&b), 1, "4 was evicted");
    assert_eq!((Arc::strong_count(&a), Arc::strong_count(&c)), (2, 2), "3 and 5 are cached");
    assert!(Arc::ptr_eq(&a, &s.scene(3))); // [5, 3]
    let b2 = s.scene(4); // a miss: rebuilt, evicts 5: [3, 4]
    assert!(!Arc::ptr_eq(&b, &b2));
    assert_eq!(b.0, b2.0, "a rebuilt scene equals the evicted one");
    assert_eq!(Arc::strong_count(&c), 1, "5 was evicted");
    assert!(Arc::ptr_eq(&a, &s.scene(3)));
    assert!(Arc::ptr_eq(&b2, &s.scene(4)));
    assert_eq!(a.0, Scene::generate(3, &config(true).scene));
}

#[test]
fn bad_configs_are_errors() {
    assert!(Sampler::try_new(SamplerConfig { scene_seeds: vec![], ..SamplerConfig::default() }).is_err());
    assert!(Sampler::try_new(SamplerConfig { res: 0, ..SamplerConfig::default() }).is_err());
    assert!(Sampler::try_new(SamplerConfig { radius_m: f32::NAN, ..SamplerConfig::default() }).is_err());
    assert!(Sampler::try_new(SamplerConfig::default()).is_ok());
}
