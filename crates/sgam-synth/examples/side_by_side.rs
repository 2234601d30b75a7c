//! Renders frame 0 of a scene next to the authors' template frame:
//! `cargo run --release -p sgam-synth --example side_by_side -- OUT.png [SEED] [TEMPLATE_DIR]`.
//! Prints ground brightness statistics of both (lit and shadowed ground pixels).

use sgam_synth::{dataset_cameras, RenderConfig, Renderer, Scene, SceneConfig, GROUND_ID};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let out = args.get(1).cloned().unwrap_or_else(|| "side_by_side.png".into());
    let seed: u64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1);
    let template = args.get(3).cloned().unwrap_or_else(|| "../shared/data/sgam-clevr-template".into());
    let scene = Scene::generate(seed, &SceneConfig::default());
    let renderer = Renderer::new(&scene);
    let cam = dataset_cameras(50, 256)[0].camera;
    let frame = renderer.render(&cam, &RenderConfig::default());
    let mut canvas = image::RgbImage::new(512 + 8, 256);
    let mut ours_ground = Vec::new();
    for v in 0..256u32 {
        for u in 0..256u32 {
            let c = frame.frame.colour.at(u, v);
            canvas.put_pixel(u, v, image::Rgb(c.map(|x| (x * 255.0).round() as u8)));
            if *frame.object_id.at(u, v) == GROUND_ID {
                ours_ground.push(c[0]);
            }
        }
    }
    if let Ok(t) = image::open(format!("{template}/im_00000.png")) {
        let t = t.to_rgb8();
        let mut theirs = Vec::new();
        for (u, v, p) in t.enumerate_pixels() {
            canvas.put_pixel(u + 264, v, *p);
            // near-grey pixels are ground (objects are saturated)
            let (mx, mn) = (p.0.iter().max().copied().unwrap_or(0), p.0.iter().min().copied().unwrap_or(0));
            if mx - mn < 6 {
                theirs.push(p.0[0] as f32 / 255.0);
            }
        }
        report("template ground", &mut theirs);
    }
    report("ours ground", &mut ours_ground);
    canvas.save(&out)?;
    println!("wrote {out}");
    Ok(())
}

fn report(name: &str, v: &mut [f32]) {
    v.sort_by(f32::total_cmp);
    let q = |p: f32| v.get(((v.len() as f32 - 1.0) * p) as usize).copied().unwrap_or(0.0);
    println!(
        "{name}: n {} p5 {:.3} p25 {:.3} p50 {:.3} p95 {:.3} max {:.3}",
        v.len(),
        q(0.05),
        q(0.25),
        q(0.5),
        q(0.95),
        q(1.0)
    );
}
