//! Fits the compact model to one fixed batch (four coloured squares on grey, 300 steps, no
//! quantization) and prints the loss and the output colour at each square's centre: the
//! experiment that measured the gradient-L1 perceptual term's effect (docs/MODEL.md).
//!
//! `cargo run --release -p sgam-model --example fit_fixed_batch -- [LR] [PERCEPTUAL_WEIGHT] [BETA1]`
#![allow(clippy::unwrap_used, clippy::expect_used)]
use sgam_core::{Image, RgbdFrame};
use sgam_model::{ModelConfig, Stage, TrainConfig, TrainPair, Trainer};

fn frame(c: [f32; 3], s: usize) -> RgbdFrame {
    let mut f = RgbdFrame { colour: Image::filled(64, 64, [0.7f32; 3]), depth_m: Image::filled(64, 64, 10.0f32) };
    for v in 8 + s..40 + s {
        for u in 16..48 {
            *f.colour.at_mut(u as u32, v as u32) = c;
            *f.depth_m.at_mut(u as u32, v as u32) = 9.0;
        }
    }
    f
}

fn main() {
    let lr: f64 = std::env::args().nth(1).map(|s| s.parse().unwrap()).unwrap_or(1e-3);
    let mut cfg = TrainConfig::new(Stage::One, 1000);
    cfg.lr = lr;
    cfg.perceptual_weight = std::env::args().nth(2).map(|s| s.parse().unwrap()).unwrap_or(0.1);
    cfg.beta1 = std::env::args().nth(3).map(|s| s.parse().unwrap()).unwrap_or(0.5);
    cfg.warmup_no_quant_steps = 100_000;
    cfg.batch = 4;
    let mc = ModelConfig::compact();
    let mut t = Trainer::new(&mc, &cfg).unwrap();
    let cols = [[1.0f32, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 0.0]];
    let batch: Vec<TrainPair> = cols
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let f = frame(*c, i * 4);
            TrainPair { input: f.clone(), missing: vec![false; 64 * 64], target: f }
        })
        .collect();
    for s in 0..300 {
        let r = t.step_on(&batch).unwrap();
        if s % 25 == 0 {
            println!("step {} l1 {:.4} psnr {:.2}", r.step, r.l1, r.psnr);
        }
    }
    let (_, imgs) = t.validate(&batch).unwrap();
    for (c, im) in cols.iter().zip(&imgs) {
        let p = im.output.colour.at(32, 30);
        println!("{c:?} -> {p:?}");
    }
}
