//! Times one CLEVR-Infinite scene: `cargo run --release -p sgam-synth --example synth_bench -- [frames] [spp]`.
use sgam_synth::{time_scene_render, RenderConfig, DATASET_GRID, DATASET_RES};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let frames = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(2500);
    let spp = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(4);
    let config = RenderConfig { samples_per_pixel: spp, ..RenderConfig::default() };
    let t = time_scene_render(1, frames, DATASET_GRID, DATASET_RES, &config);
    println!(
        "frames {} spp {} threads {}: setup {:.3} s, render {:.2} s, {:.1} frames/s ({:.1} ms/frame)",
        t.frames,
        spp,
        rayon::current_num_threads(),
        t.setup_s,
        t.render_s,
        t.frames_per_s,
        1e3 * t.render_s / t.frames as f64
    );
}
