//! Where do the smears come from: the sampler's choice of codes, or the codebook and decoder?
//!
//! For recorded generation pairs (a `sgam train context` run's `pairs-2.bin`, its validation
//! stream), decodes each pair's guidance three ways and writes one picture per pair, colour over
//! disparity: the guidance (holes magenta), the refiner's own completion (generation's sampling),
//! and the guidance with the *true frame's codes* in its holes (the best any sampler can do with
//! this codebook and decoder). Prints the mean absolute disparity error of the sampled completion
//! in the holes, against the true-code decode.
//!
//! ```sh
//! cargo run --release -p sgam-pipeline --example decode_true_codes -- \
//!     runs/ctx2/pairs-2.bin OUT_DIR [N=12] [MODEL]
//! ```
//! The cache key must be the validation stream of `sgam train context` with its defaults and
//! `--seed 2` (edit `key` below for another run).

use sgam_pipeline::codepairs::{read_cache, CacheKey};
use sgam_pipeline::guidance_view::step_panel;
use sgam_pipeline::settings::SamplingSettings;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(cache), Some(out)) = (args.get(1), args.get(2)) else {
        return Err("usage: decode_true_codes PAIRS.bin OUT_DIR [N] [MODEL]".into());
    };
    let n: usize = args.get(3).map(|s| s.parse()).transpose()?.unwrap_or(12);
    let model = args.get(4).map(std::path::PathBuf::from);
    let key = CacheKey {
        version: sgam_pipeline::codepairs::CACHE_VERSION,
        pairs: 256,
        steps_per_run: 40,
        steps_per_run_mix: Vec::new(),
        crop: 128,
        scenes: 100_000,
        seed: 2,
        stream: 2,
        closed_loop: 0.0,
        closed_loop_steps: 1.0,
        recorded_with: None,
        closed_loop_filters: false,
    };
    let pairs = read_cache(std::path::Path::new(cache), &key)?.ok_or("the cache was recorded with another key")?;
    std::fs::create_dir_all(out)?;
    let options = SamplingSettings::default().refiner_options();
    let mut refiner = sgam_pipeline::model_refiner(model.as_deref(), options)?;
    let (mut err_sampled, mut shown) = (Vec::new(), 0);
    for (i, p) in pairs.iter().enumerate() {
        let holes = p.missing.iter().filter(|m| **m).count();
        // pairs whose hole is at least 5 % of the crop: the ones that grow a world
        if holes * 20 < p.missing.len() {
            continue;
        }
        let sampled = refiner.complete_at(&p.input, &p.missing, Some(&p.intrinsics))?;
        let truth = refiner.complete_with_codes(&p.input, &p.missing, &p.intrinsics, &p.codes)?;
        let disp = |d: f32| if d > 0.0 && d.is_finite() { 1.0 / d } else { 0.0 };
        let mae = |f: &sgam_core::RgbdFrame| {
            let s: f32 = (0..p.missing.len())
                .filter(|&j| p.missing[j])
                .map(|j| (disp(f.depth_m.data[j]) - disp(truth.depth_m.data[j])).abs())
                .sum();
            s / holes as f32
        };
        err_sampled.push(mae(&sampled));
        let camera = sgam_core::Camera::new(p.intrinsics, Default::default());
        let guidance = sgam_core::Guidance { camera, frame: p.input.clone(), missing: p.missing.clone(), seed: 0 };
        let panel = step_panel(&guidance, &sampled, &truth);
        sgam_io::write_rgb_png(&std::path::Path::new(out).join(format!("pair-{i:03}.png")), &panel)?;
        shown += 1;
        if shown == n {
            break;
        }
    }
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len().max(1) as f32;
    println!(
        "{shown} pairs: mean |disparity| error of the sampled completion in the holes {:.4} 1/m \
         (against the true-code decode)",
        mean(&err_sampled)
    );
    Ok(())
}
