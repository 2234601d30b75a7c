//! Times `TsdfMap::integrate` alone on an RGB-D sequence (frames decoded up front), a few
//! passes over fresh maps: `cargo run --release -p sgam-map --example fuse_seq -- SEQ [PASSES]`.
//! Used to tune the integration without the CLI's I/O in the way (`perf record` friendly).

use std::time::Instant;

use sgam_map::{TsdfConfig, TsdfMap};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let dir = args.next().ok_or("usage: fuse_seq SEQ_DIR [PASSES]")?;
    let passes: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(5);
    let seq = sgam_io::Sequence::open(std::path::Path::new(&dir))?;
    let frames: Vec<_> =
        (0..seq.len()).map(|i| seq.read_frame(i).map(|f| (f, seq.camera(i)))).collect::<Result<_, _>>()?;
    let cfg = TsdfConfig { voxel_size_m: 0.02, trunc_voxels: 4.0, depth_max_m: 4.0, ..TsdfConfig::default() };
    let interleave = std::env::var_os("INTERLEAVE").is_some();
    let wake = std::env::var_os("WAKE").is_some();
    let mut per_pass = Vec::new();
    for _ in 0..passes {
        let mut map = TsdfMap::new(cfg);
        let (mut touched, mut voxels) = (0usize, 0usize);
        let mut elapsed = std::time::Duration::ZERO;
        for (i, (f, c)) in frames.iter().enumerate() {
            // INTERLEAVE=1: decode each frame right before integrating it, as `sgam fuse` does
            let fresh = if interleave { Some(seq.read_frame(i)?) } else { None };
            let f = fresh.as_ref().unwrap_or(f);
            if wake {
                // WAKE=1: busy the pool's workers just before timing (are they asleep?)
                use rayon::prelude::*;
                let _: u64 = (0..200_000u64).into_par_iter().map(|x| x ^ (x >> 3)).sum();
            }
            let t = Instant::now();
            let s = map.integrate(f, c);
            elapsed += t.elapsed();
            touched += s.blocks_touched;
            voxels += s.voxels_updated;
        }
        let ms = elapsed.as_secs_f64() * 1e3 / frames.len() as f64;
        per_pass.push(ms);
        eprintln!(
            "{ms:.3} ms/frame; {:.0} blocks touched, {:.0} voxels updated per frame; {} blocks",
            touched as f64 / frames.len() as f64,
            voxels as f64 / frames.len() as f64,
            map.block_count()
        );
    }
    per_pass.sort_by(f64::total_cmp);
    println!("median {:.3} ms/frame over {passes} passes", per_pass[passes / 2]);
    Ok(())
}
