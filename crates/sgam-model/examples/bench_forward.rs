//! Times one forward pass (encode + quantize + decode) of a preset at a resolution.
//! `cargo run --release -p sgam-model --example bench_forward -- compact 256 15`
use rand::SeedableRng;
use sgam_model::burn::tensor::{Distribution, Tensor};
use sgam_model::{default_device, quantize, ModelConfig, Sampling, VqModel};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let preset = args.get(1).map(String::as_str).unwrap_or("compact");
    let res: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(256);
    let reps: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(15);
    let mut cfg = match preset {
        "paper" => ModelConfig::paper(),
        "tiny" => ModelConfig::tiny(),
        _ => ModelConfig::compact(),
    };
    if let Ok(json) = std::env::var("SGAM_MODEL_CONFIG") {
        cfg = serde_json::from_str(&json)?;
    }
    let device = default_device();
    let model = VqModel::new(&cfg, 0, &device)?;
    println!("{preset}: {} parameters", model.num_params_total());
    let x = Tensor::<4>::random([1, 5, res, res], Distribution::Uniform(-1.0, 1.0), &device);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut times = Vec::new();
    for _ in 0..reps {
        let t0 = std::time::Instant::now();
        let z = model.encode(x.clone());
        let q = quantize::quantize(&model, z, Sampling::Argmin, None, 0.25, &mut rng)?;
        let y = model.decode(q.z_q);
        let _ = y.into_data();
        times.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    let mut sorted = times.clone();
    sorted.sort_by(|a, b| a.total_cmp(b));
    println!("{preset} {res}x{res}: median {:.1} ms, min {:.1} ms ({reps} runs)", sorted[reps / 2], sorted[0]);
    Ok(())
}
