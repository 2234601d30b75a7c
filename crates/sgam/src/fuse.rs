//! `sgam fuse`: TSDF fusion of a real RGB-D sequence into a coloured mesh.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use serde::Serialize;
use sgam_map::{TsdfConfig, TsdfMap};

use crate::guard::{check_output_file, in_range, positive};
use crate::progress;

/// Arguments of `sgam fuse`.
#[derive(Debug, Args)]
#[command(
    after_help = "Example:\n  sgam fuse ../shared/data/7scenes-redkitchen-50 --voxel-size 0.02 --out kitchen.ply \\\n      --trunc-voxels 4 --depth-max 4.0 --stats-json stats.json\n\nLayouts are detected: 7-Scenes/3DMatch (frame-NNNNNN.color.png/.depth.png/.pose.txt +\ncamera-intrinsics.txt, optionally under rgbd-frames/), the SGAM authors' CLEVR-Infinite\n(transforms.json + im_*.png + dm_*.npy), and NeRF-style transforms.json with depth paths."
)]
pub struct FuseArgs {
    /// Folder of the RGB-D sequence.
    pub sequence: PathBuf,
    /// Output mesh: .ply (binary, vertex colours), .obj or .glb.
    #[arg(long)]
    pub out: PathBuf,
    /// Voxel edge length in metres.
    #[arg(long, default_value_t = 0.02)]
    pub voxel_size: f32,
    /// Truncation distance as a multiple of the voxel size.
    #[arg(long, default_value_t = 4.0)]
    pub trunc_voxels: f32,
    /// Ignore depth beyond this many metres.
    #[arg(long, default_value_t = 4.0)]
    pub depth_max: f32,
    /// Ignore depth closer than this many metres.
    #[arg(long, default_value_t = 0.1)]
    pub depth_min: f32,
    /// Only frames A..B (half-open, indices into the sorted sequence), e.g. `0..20`.
    #[arg(long, value_parser = parse_range)]
    pub frames: Option<(usize, usize)>,
    /// Marching-cubes weight threshold (voxels observed fewer times are not meshed).
    #[arg(long, default_value_t = 1.0)]
    pub weight_threshold: f32,
    /// Re-mesh the changed blocks every N frames (1 = after every frame, as the generator does;
    /// 0 = only the final extraction, as Open3D's fusion examples do).
    #[arg(long, default_value_t = 0)]
    pub mesh_every: usize,
    /// Decode every frame (in parallel) before fusing, as Open3D's benchmark script does: the
    /// like-for-like timing against it, and faster I/O. Holds all frames in memory (about 16
    /// bytes per pixel: 5 MB per 640x480 frame); without it frames are read one at a time.
    #[arg(long)]
    pub preload: bool,
    /// Also save the TSDF map (versioned binary with checksum) for later use.
    #[arg(long)]
    pub save_map: Option<PathBuf>,
    /// Write timings and mesh statistics as JSON.
    #[arg(long)]
    pub stats_json: Option<PathBuf>,
}

fn parse_range(s: &str) -> std::result::Result<(usize, usize), String> {
    let (a, b) = s.split_once("..").ok_or_else(|| format!("'{s}' is not a range like 10..50"))?;
    let a: usize = if a.is_empty() { 0 } else { a.parse().map_err(|_| format!("bad range start '{a}'"))? };
    let b: usize = if b.is_empty() { usize::MAX } else { b.parse().map_err(|_| format!("bad range end '{b}'"))? };
    if a >= b {
        return Err(format!("empty range {s}"));
    }
    Ok((a, b))
}

/// What `--stats-json` writes.
#[derive(Debug, Serialize)]
pub struct FuseStats {
    /// Frames fused.
    pub frames: usize,
    /// TSDF update per frame, I/O excluded, milliseconds (mean).
    pub integrate_ms_per_frame: f64,
    /// Median of the per-frame TSDF update times, milliseconds.
    pub integrate_ms_median: f64,
    /// Incremental re-meshing amortised per frame, including the final extraction, milliseconds.
    pub mesh_ms_per_frame: f64,
    /// `integrate_ms_per_frame + mesh_ms_per_frame`.
    pub integrate_plus_mesh_ms_per_frame: f64,
    /// Reading and decoding the frames, seconds.
    pub io_s: f64,
    /// Final mesh vertices.
    pub vertices: usize,
    /// Final mesh triangles.
    pub triangles: usize,
    /// Allocated 8^3 blocks.
    pub blocks: usize,
    /// Map memory, bytes.
    pub map_bytes: usize,
    /// Voxel size, metres.
    pub voxel_size_m: f32,
    /// Truncation, metres.
    pub trunc_m: f32,
    /// Depth cut, metres.
    pub depth_max_m: f32,
}

impl FuseArgs {
    /// Checks every option (map parameters in range: the voxel-size floor keeps memory within
    /// the machine) and every output path, before any frame is read. Errors name the option and
    /// the accepted range.
    pub fn validate(&self) -> Result<()> {
        in_range("--voxel-size", self.voxel_size, sgam_map::MIN_VOXEL_M..=sgam_map::MAX_VOXEL_M)?;
        positive("--trunc-voxels", self.trunc_voxels, sgam_map::MAX_TRUNC_VOXELS)?;
        in_range("--depth-min", self.depth_min, 0.0..=sgam_map::MAX_DEPTH_M)?;
        in_range("--depth-max", self.depth_max, 0.0..=sgam_map::MAX_DEPTH_M)?;
        if self.depth_min >= self.depth_max {
            bail!("--depth-min {} must be below --depth-max {}", self.depth_min, self.depth_max);
        }
        in_range("--weight-threshold", self.weight_threshold, 0.0..=1e6)?;
        if !matches!(
            self.out.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref(),
            Some("ply" | "obj" | "glb")
        ) {
            bail!("--out {}: unknown mesh format (use .ply, .obj or .glb)", self.out.display());
        }
        check_output_file("--out", &self.out)?;
        if let Some(p) = &self.save_map {
            check_output_file("--save-map", p)?;
        }
        if let Some(p) = &self.stats_json {
            check_output_file("--stats-json", p)?;
        }
        let mut outputs = vec![("--out", self.out.as_path())];
        outputs.extend(self.save_map.as_deref().map(|p| ("--save-map", p)));
        outputs.extend(self.stats_json.as_deref().map(|p| ("--stats-json", p)));
        crate::guard::distinct_outputs(&outputs)?;
        Ok(())
    }
}

/// Runs `sgam fuse`.
pub fn run(args: FuseArgs) -> Result<()> {
    // check options and outputs before spending time on fusion
    args.validate()?;
    let config = TsdfConfig {
        voxel_size_m: args.voxel_size,
        trunc_voxels: args.trunc_voxels,
        depth_min_m: args.depth_min,
        depth_max_m: args.depth_max,
        weight_cap: None,
        weight_threshold: args.weight_threshold,
    };
    config.validate().context("invalid map parameters")?;
    let seq = sgam_io::Sequence::open(&args.sequence)?;
    let (a, b) = args.frames.unwrap_or((0, usize::MAX));
    let range = a.min(seq.len())..b.min(seq.len());
    if range.is_empty() {
        bail!("{}: frame range {a}..{b} selects none of its {} frames", args.sequence.display(), seq.len());
    }
    eprintln!("fusing {} frames of {} ({:?} layout)", range.len(), args.sequence.display(), seq.layout);
    let mut map = TsdfMap::new(config);
    let (mut io_s, mut integrate_ms, mut mesh_ms) = (0.0f64, Vec::new(), 0.0f64);
    let pb = progress::bar(range.len() as u64, "fusing");
    let mut preloaded = if args.preload {
        use rayon::prelude::*;
        let t = Instant::now();
        let frames: Vec<_> = range.clone().into_par_iter().map(|i| seq.read_frame(i)).collect::<Result<_, _>>()?;
        io_s += t.elapsed().as_secs_f64();
        frames.into_iter().map(Some).collect()
    } else {
        Vec::new()
    };
    for (n, i) in range.clone().enumerate() {
        let t = Instant::now();
        let frame = match preloaded.get_mut(n).and_then(Option::take) {
            Some(f) => f,
            None => seq.read_frame(i)?,
        };
        let camera = seq.camera(i);
        io_s += t.elapsed().as_secs_f64();
        let t = Instant::now();
        map.integrate(&frame, &camera);
        integrate_ms.push(t.elapsed().as_secs_f64() * 1e3);
        if args.mesh_every > 0 && (n + 1) % args.mesh_every == 0 {
            let t = Instant::now();
            map.update_mesh();
            mesh_ms += t.elapsed().as_secs_f64() * 1e3;
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    let t = Instant::now();
    let mesh = map.extract_mesh();
    mesh_ms += t.elapsed().as_secs_f64() * 1e3;
    sgam_io::write_mesh(&args.out, &mesh)?;
    if let Some(p) = &args.save_map {
        sgam_pipeline::save_map(p, &map)?;
    }
    let frames = range.len();
    let mean_int = integrate_ms.iter().sum::<f64>() / frames as f64;
    let stats = FuseStats {
        frames,
        integrate_ms_per_frame: mean_int,
        integrate_ms_median: sgam_metrics::median(&integrate_ms).unwrap_or(0.0),
        mesh_ms_per_frame: mesh_ms / frames as f64,
        integrate_plus_mesh_ms_per_frame: mean_int + mesh_ms / frames as f64,
        io_s,
        vertices: mesh.positions.len(),
        triangles: mesh.triangles.len(),
        blocks: map.block_count(),
        map_bytes: map.memory_bytes(),
        voxel_size_m: config.voxel_size_m,
        trunc_m: config.trunc_m(),
        depth_max_m: config.depth_max_m,
    };
    eprintln!(
        "fused {frames} frames: integrate {:.2} ms/frame, mesh {:.2} ms/frame, I/O {:.2} s; {} vertices, {} triangles -> {}",
        stats.integrate_ms_per_frame,
        stats.mesh_ms_per_frame,
        stats.io_s,
        stats.vertices,
        stats.triangles,
        args.out.display()
    );
    if let Some(p) = &args.stats_json {
        let json = serde_json::to_vec_pretty(&stats)?;
        sgam_io::write_atomic(p, |w| std::io::Write::write_all(w, &json))?;
    }
    Ok(())
}
