//! What model sizes fit the step budget: the refiner's worst case (a quarter of a 256x256 frame
//! missing, sampled in passes as `sgam bench refine` does) for the compact model and wider or
//! deeper variants of it (untrained weights: the cost is the same), in the CPU kernels and in
//! burn's pass, interleaved. One line per variant.
//! `cargo run --release -p sgam-model --example capacity -- 10`
use sgam_core::{Intrinsics, RgbdFrame};
use sgam_model::{default_device, flops, ModelConfig, RefinerOptions, Sampling, VqModel, VqRefiner};

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let reps: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(10).max(1);
    // the bundled model's design: code head, ray channels, a trained temperature
    let base = ModelConfig { code_head: true, ray_channels: true, code_tau: Some(1.0), ..ModelConfig::compact() };
    let variants: Vec<(&str, ModelConfig)> = vec![
        ("compact (bundled design)", base.clone()),
        ("ch 48", ModelConfig { ch: 48, ..base.clone() }),
        ("ch 64", ModelConfig { ch: 64, ..base.clone() }),
        ("2 blocks a level", ModelConfig { num_res_blocks: 2, ..base.clone() }),
        ("ch 64, 2 blocks a level", ModelConfig { ch: 64, num_res_blocks: 2, ..base.clone() }),
        ("ch 96, 2 blocks a level", ModelConfig { ch: 96, num_res_blocks: 2, ..base }),
    ];
    let (w, h) = (256u32, 256u32);
    let mut frame = RgbdFrame::empty(w, h);
    for (i, c) in frame.colour.data.iter_mut().enumerate() {
        let (x, y) = (i % w as usize, i / w as usize);
        *c = [(x % 37) as f32 / 37.0, (y % 23) as f32 / 23.0, 0.4];
    }
    frame.depth_m.data.iter_mut().enumerate().for_each(|(i, d)| *d = 8.0 + (i / w as usize) as f32 * 0.02);
    let missing: Vec<bool> = (0..(w * h) as usize).map(|i| i % w as usize > 3 * w as usize / 4).collect();
    let options = RefinerOptions {
        sampling: Sampling::Temperature { temperature: 1.0, top_k: usize::MAX },
        ..RefinerOptions::default()
    };
    let k = Intrinsics::from_fov_x(w, h, 1.0);
    let device = default_device();
    println!("| model | parameters | GFLOP per refine | passes | CPU kernels ms | burn ms | GFLOP/s |");
    println!("|---|---|---|---|---|---|---|");
    for (name, cfg) in variants {
        let model = VqModel::new(&cfg, 0, &device)?;
        let params = model.num_params_total();
        let mut r = VqRefiner::new(model, cfg.clone(), options, device.clone());
        r.complete_at(&frame, &missing, Some(&k))?; // warm-up
        let (mut ours, mut theirs) = (Vec::new(), Vec::new());
        for _ in 0..reps {
            r.set_cpu_kernels(true);
            let t = std::time::Instant::now();
            r.complete_at(&frame, &missing, Some(&k))?;
            ours.push(t.elapsed().as_secs_f64() * 1e3);
            r.set_cpu_kernels(false);
            let t = std::time::Instant::now();
            r.complete_at(&frame, &missing, Some(&k))?;
            theirs.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let passes = r.trace().passes.len().max(1) as u64;
        let pass = flops::pass_macs(&cfg, h as usize, w as usize);
        let gflop = 2.0 * (passes * (pass.encoder + pass.decoder)) as f64 / 1e9;
        let (a, b) = (median(&mut ours), median(&mut theirs));
        println!(
            "| {name} | {:.2} M | {gflop:.1} | {passes} | {a:.0} | {b:.0} | {:.0} |",
            params as f64 / 1e6,
            gflop / (a / 1e3)
        );
    }
    Ok(())
}
