//! Measures stage-1 training throughput (images/s) of the compact preset at crop 128, batch 4.
//! `cargo run --release -p sgam-model --example bench_train -- 5`
use sgam_core::{Image, RgbdFrame};
use sgam_model::train::{Stage, TrainConfig, TrainPair, Trainer};
use sgam_model::ModelConfig;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let steps: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(5);
    let disc = std::env::args().nth(2).is_some_and(|s| s == "disc");
    let size = 128u32;
    let frame = RgbdFrame {
        colour: Image::filled(size, size, [0.4, 0.5, 0.6]),
        depth_m: Image {
            width: size,
            height: size,
            data: (0..size * size).map(|i| 8.0 + (i % size) as f32 / 32.0).collect(),
        },
    };
    let pairs: Vec<TrainPair> = (0..4)
        .map(|_| TrainPair {
            input: frame.clone(),
            missing: vec![false; (size * size) as usize],
            target: frame.clone(),
        })
        .collect();
    let mut tc = TrainConfig::new(Stage::One, steps as u64);
    tc.disc_start = if disc { 0 } else { u64::MAX };
    let mut trainer = Trainer::new(&ModelConfig::compact(), &tc)?;
    trainer.step_on(&pairs)?; // warm-up
    let t0 = std::time::Instant::now();
    for _ in 0..steps {
        trainer.step_on(&pairs)?;
    }
    let s = t0.elapsed().as_secs_f64() / steps as f64;
    println!("compact train step (batch 4, 128x128, disc {disc}): {:.2} s/step, {:.2} images/s", s, 4.0 / s);
    Ok(())
}
