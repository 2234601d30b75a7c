//! `sgam eval world` and `sgam eval table`: judge generated worlds against the true world of
//! the same held-out seed along the same trajectory (world-level statistics, KID, loop
//! consistency).
//!
//! For each held-out seed scene (from 1,000,000; never used in training) the refiner and the
//! oracle (ground truth of the synthetic world) are unrolled along the same trajectory by the
//! real generator (`sgam generate`), and the two final meshes are compared over the area that
//! is *new* (outside the seed frame's ground footprint grown by 1 m):
//! - object statistics (`sgam_metrics::world`): objects per 100 m², footprints, cover, colour
//!   saturation, ground roughness;
//! - the paper's scene metrics (Table 2): the new area cut into square regions, each voxelised
//!   into a 15³ occupancy histogram; JSD / MMD / COV / MinDist / 1-NNA of the generated regions
//!   against the oracle's;
//! - KID between the generated frames and the oracle's frames (real renders of held-out
//!   scenes), on features of a frozen encoder shipped in the repo (`models/features.safetensors`:
//!   the stage-1/2 compact encoder trained on the synthetic world; per frame the mean and
//!   standard deviation of each of its 64 latent channels over the 32x32 cells).
//!
//! Runs are kept under the output folder (`seed-N/LABEL`) and reused when complete, so the
//! oracle worlds are grown once for every refiner of a table.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::json;
use sgam_core::{TriMesh, Vec2, Vec3};
use sgam_metrics::world::{Exclusion, PooledStats, WorldStats, WorldStatsConfig};

use sgam_pipeline::settings::{
    FreeSpace, InventedPixelSettings, MapSettings, PathSettings, RefinerKind, RefinerSettings, SamplingSettings,
    TrajectoryKind, DEFAULT_CELLS_PER_PASS, DEFAULT_FLYING_PIXELS, DEFAULT_TOP_K,
};
use sgam_pipeline::HELD_OUT_SEED_BASE;

use sgam_model::features::FeatureExtractor;

/// Arguments of `sgam eval world`.
#[derive(Debug, Clone, Args)]
#[command(
    after_help = "Examples:\n  sgam eval world                         # 4 held-out seeds x 400-step zig-zag, bundled model\n  sgam eval world --refiner null --json   # the push-pull stand-in\n  sgam eval world --paper                 # the paper's 10 seeds x 900 steps\n  sgam eval world --first-seed 7 --seeds 2 # tune on training scenes, not held-out ones\n\nEach seed's world is grown twice along the same trajectory, by the refiner and by the oracle\n(ground truth); runs are kept in --out (seed-N/LABEL) and reused. Statistics are computed over\nthe area outside the seed frame's footprint grown by 1 m (the area the refiner invented)."
)]
pub struct WorldArgs {
    /// Held-out seed scenes (1000000, 1000001, ...).
    #[arg(long, default_value_t = 4)]
    pub seeds: u64,
    /// First seed scene. Judge on the held-out seeds (the default, 1000000); tune on training
    /// seeds (below 1000000) so the held-out ones stay unseen.
    #[arg(long, default_value_t = HELD_OUT_SEED_BASE)]
    pub first_seed: u64,
    /// Generation steps per world.
    #[arg(long, default_value_t = 400)]
    pub steps: usize,
    /// The camera path (the same for the refiner and the oracle).
    #[command(flatten)]
    pub path: PathSettings,
    /// The refiner judged.
    #[command(flatten)]
    pub refiner: RefinerSettings,
    /// Its sampling.
    #[command(flatten)]
    pub sampling: SamplingSettings,
    /// Its invented-pixel policy (never applied to the oracle).
    #[command(flatten)]
    pub invented: InventedPixelSettings,
    /// The map and sources (the same for the refiner and the oracle).
    #[command(flatten)]
    pub map: MapSettings,
    /// The paper's protocol: 10 seeds x 900 steps (overrides --seeds and --steps).
    #[arg(long)]
    pub paper: bool,
    /// Side of the square regions of the scene metrics, metres.
    #[arg(long, default_value_t = 5.0)]
    pub region_size: f32,
    /// Folder for the worlds (default runs/eval-world).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Keep each finished world's resume files (snapshot.bin, map.bin: half of a world's 360 MB).
    /// By default they are deleted once the world is finished: a finished world is reused from
    /// its mesh, frames and run.json, and never resumed.
    #[arg(long)]
    pub keep_snapshots: bool,
    /// Folder of the loop-consistency runs, which do not depend on the trajectory (default: the
    /// worlds' folder); eval table's trajectory rows share the zig-zag's.
    #[arg(skip)]
    pub loop_out: Option<PathBuf>,
    /// Skip the loop-consistency runs (a training run's short worlds: its loop is NaN).
    #[arg(skip)]
    pub no_loop: bool,
    /// Print only the JSON line.
    #[arg(long)]
    pub json: bool,
}

impl WorldArgs {
    /// The trajectory the worlds follow: `auto` is the zig-zag for the synthetic seeds
    /// evaluated here.
    pub fn trajectory(&self) -> TrajectoryKind {
        match self.path.trajectory {
            TrajectoryKind::Auto => TrajectoryKind::Zigzag,
            kind => kind,
        }
    }

    /// The folder name of this refiner's worlds: its weights (CRC-32) and every option that
    /// changes them, so worlds grown otherwise are never reused.
    pub fn label(&self) -> String {
        let r = &self.refiner;
        let kind = r.effective();
        let mut label = match kind {
            RefinerKind::Oracle => return self.oracle_label(),
            _ if r.no_refine => "no-refine".to_string(),
            RefinerKind::Null => "null".to_string(),
            // the model's weights name its runs: another model never reuses them
            _ => {
                let bytes = match &r.model {
                    Some(p) => std::fs::read(p).unwrap_or_default(),
                    None => sgam_pipeline::BUNDLED_MODEL.to_vec(),
                };
                let stem = match &r.model {
                    Some(p) => {
                        p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "model".into())
                    }
                    None => "model".to_string(),
                };
                format!("{stem}-{:08x}", crc32fast::hash(&bytes))
            }
        };
        let s = &self.sampling;
        if matches!(kind, RefinerKind::Auto | RefinerKind::Model) {
            label.push_str(&format!("-t{}", s.temperature));
            if s.cells_per_pass != DEFAULT_CELLS_PER_PASS {
                label.push_str(&format!("-c{}", s.cells_per_pass));
            }
            if s.max_passes != sgam_pipeline::settings::DEFAULT_MAX_PASSES {
                label.push_str(&format!("-p{}", s.max_passes));
            }
            if s.class_coherence != sgam_pipeline::settings::DEFAULT_CLASS_COHERENCE {
                label.push_str(&format!("-cc{}", s.class_coherence));
            }
            if s.hue_coherence != sgam_pipeline::settings::DEFAULT_HUE_COHERENCE {
                label.push_str(&format!("-hue{}", s.hue_coherence));
            }
            if s.top_k != DEFAULT_TOP_K {
                label.push_str(&format!("-k{}", s.top_k));
            }
            // always named when on, so worlds grown before it existed keep their folder
            if s.within_temperature > 0.0 {
                label.push_str(&format!("-w{}", s.within_temperature));
            }
            if s.seed != 0 {
                label.push_str(&format!("-s{}", s.seed));
            }
            if s.regenerate_observed {
                label.push_str("-regen");
            }
            // the bank's bytes name it, like the weights
            // (its worlds are 256 px synthetic ones: the bundled bank fits)
            let bank = r.bank.resolve_for(&sgam_pipeline::SeedSpec::Synthetic { scene: 0, res: 256 });
            // worlds grown before --bands-wait existed: a bank's holes waited below 3 cells,
            // the model's own draws never
            let banked = !matches!(bank, sgam_pipeline::BankSpec::None | sgam_pipeline::BankSpec::Auto);
            let auto_wait = match bank {
                sgam_pipeline::BankSpec::Seed => sgam_pipeline::CLEVR.quilt_bands_wait,
                _ if banked => sgam_model::refiner::DEFAULT_BANDS_WAIT,
                _ => 0,
            };
            if let sgam_pipeline::settings::BandsWait::Cells(n) = s.bands_wait {
                if n != auto_wait {
                    label.push_str(&format!("-bw{n}"));
                }
            }
            match &bank {
                sgam_pipeline::BankSpec::None | sgam_pipeline::BankSpec::Auto => {}
                sgam_pipeline::BankSpec::Bundled => {
                    label.push_str(&format!("-bank{:08x}", sgam_pipeline::bank::bank_id(sgam_pipeline::BUNDLED_BANK)))
                }
                sgam_pipeline::BankSpec::File(p) => label.push_str(&format!(
                    "-bank{:08x}",
                    sgam_pipeline::bank::bank_id(&std::fs::read(p).unwrap_or_default())
                )),
                sgam_pipeline::BankSpec::Seed => {
                    label.push_str("-bankseed");
                    // the quilting's tile, when not the synthetic seeds' preset
                    if let Some(tile) = s.quilt_tile.filter(|&t| t != sgam_pipeline::CLEVR.quilt_tile) {
                        label.push_str(&format!("-qt{tile}"));
                    }
                }
            }
            if s.whole_objects {
                label.push_str("-whole");
            }
            if r.adapt > 0.0 {
                label.push_str(&format!("-adapt{}", r.adapt));
            }
        }
        let p = &self.invented;
        if kind != RefinerKind::Oracle {
            if p.ground_snap > 0.0 {
                label.push_str(&format!("-g{}", p.ground_snap));
                if p.ground_flatten > 0.0 {
                    label.push_str(&format!("-flat{}", p.ground_flatten));
                }
            }
            if p.flying_pixels != DEFAULT_FLYING_PIXELS {
                label.push_str(&format!("-f{:?}", p.flying_pixels).to_lowercase());
            }
            // always named when on, so worlds grown before it existed keep their folder
            if p.free_space == FreeSpace::Carve {
                label.push_str("-carve");
            }
            // the synthetic seeds' preset when not given
            let (solid, cap) = (p.solid_objects_m(&sgam_pipeline::CLEVR), p.max_object_m2(&sgam_pipeline::CLEVR));
            if solid > 0.0 {
                label.push_str(&format!("-solid{solid}"));
            }
            if cap > 0.0 {
                label.push_str(&format!("-cap{cap}"));
            }
            let length = p.max_object_length_m(&sgam_pipeline::CLEVR);
            if length > 0.0 {
                label.push_str(&format!("-len{length}"));
            }
            let colour = p.object_colour(&sgam_pipeline::CLEVR);
            if colour > 0.0 {
                label.push_str(&format!("-oc{colour}"));
            }
        }
        if self.map.no_map {
            label.push_str("-nomap");
        }
        label + &self.map_suffix()
    }

    /// The oracle's folder name: the map options name it too.
    pub fn oracle_label(&self) -> String {
        format!("oracle{}", self.map_suffix())
    }

    /// Empty for the default map, else a hash of the map options given.
    fn map_suffix(&self) -> String {
        let map = MapSettings { no_map: false, ..self.map.clone() };
        if map == MapSettings::default() {
            return String::new();
        }
        format!("-map{:08x}", crc32fast::hash(format!("{map:?}").as_bytes()))
    }

    /// Seeds and steps per world (`--paper` sets both).
    pub fn seeds_steps(&self) -> (u64, usize) {
        if self.paper {
            (10, 900)
        } else {
            (self.seeds, self.steps)
        }
    }

    /// Checks every option and the model file before any world is grown.
    pub fn validate(&self) -> Result<()> {
        if let Some(m) = &self.refiner.model {
            crate::guard::check_input_file("--model", m)?;
        }
        let (seeds, steps) = self.seeds_steps();
        if seeds == 0 || seeds > 1000 {
            bail!("--seeds {seeds} must be in 1..=1000");
        }
        if self.first_seed > u64::MAX - seeds {
            bail!("--first-seed {} + --seeds {seeds} overflows the seed range", self.first_seed);
        }
        if !(10..=100_000).contains(&steps) {
            bail!("--steps {steps} must be in 10..=100000");
        }
        self.path.validate()?;
        self.refiner.validate()?;
        self.sampling.validate()?;
        self.invented.validate()?;
        self.map.validate()?;
        if !(self.region_size.is_finite() && self.region_size >= 1.0 && self.region_size <= 100.0) {
            bail!("--region-size {} must be between 1 and 100 metres", self.region_size);
        }
        if let Some(s) = self.path.step {
            if s >= 10.0 {
                bail!("--step {s} must be a positive distance below 10 m");
            }
        }
        Ok(())
    }
}

/// The seed frame's footprint on the ground plane: its four corner rays cut with the plane
/// z = `sgam_synth::GROUND_Z_M`.
fn seed_footprint(res: u32) -> Vec<Vec2> {
    let camera = sgam_pipeline::synthetic_seed_camera(res);
    let k = camera.intrinsics;
    let (w, h) = (k.width as f32, k.height as f32);
    let corners = [(0.0, 0.0), (w, 0.0), (w, h), (0.0, h)];
    let origin = camera.world_from_camera.transform_point(Vec3::ZERO);
    corners
        .iter()
        .filter_map(|&(u, v)| {
            let dir = camera.world_from_camera.transform_vector(k.ray_z1(Vec2::new(u - 0.5, v - 0.5)));
            let t = (sgam_synth::GROUND_Z_M - origin.z) / dir.z;
            (t.is_finite() && t > 0.0).then(|| {
                let p = origin + dir * t;
                Vec2::new(p.x, p.y)
            })
        })
        .collect()
}

/// Image features of a run's frames for KID: per frame, the mean and standard deviation of each
/// latent channel of the frozen feature encoder (every `stride`-th frame, seed excluded).
fn frame_features(dir: &Path, frames: usize, stride: usize, extractor: &FeatureExtractor) -> Result<Vec<Vec<f32>>> {
    let mut out = Vec::new();
    for i in (1..frames).step_by(stride.max(1)) {
        let (rgb, depth) = sgam_pipeline::Keyframes::frame_paths(dir, i);
        let colour = sgam_io::read_rgb(&rgb)?;
        let depth_m = sgam_io::read_npy_f32(&depth)?;
        out.push(extractor.features(&sgam_core::RgbdFrame { colour, depth_m })?);
    }
    Ok(out)
}

/// One judged world pair.
struct SeedResult {
    generated: WorldStats,
    oracle: WorldStats,
    gen_regions: Vec<Vec<f32>>,
    ref_regions: Vec<Vec<f32>>,
    gen_features: Vec<Vec<f32>>,
    ref_features: Vec<Vec<f32>>,
    step_ms: f64,
    loop_psnr_ssim: (f64, f64),
}

fn read_mesh(dir: &Path) -> Result<TriMesh> {
    sgam_io::read_ply(&dir.join("mesh.ply")).with_context(|| format!("{}: cannot read the world mesh", dir.display()))
}

fn median_step_ms(dir: &Path) -> f64 {
    std::fs::read(dir.join("run.json"))
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|v| v["median_ms"]["total"].as_f64())
        .unwrap_or(f64::NAN)
}

/// Judges the refiner of `args` on every seed; returns the JSON result.
pub fn evaluate(args: &WorldArgs) -> Result<serde_json::Value> {
    args.validate()?;
    let (seeds, steps) = args.seeds_steps();
    let root = args.out.clone().unwrap_or_else(|| PathBuf::from("runs/eval-world"));
    let loop_root = args.loop_out.clone().unwrap_or_else(|| root.clone());
    let label = args.label();
    let cfg = WorldStatsConfig::default();
    let exclusion = Exclusion { polygon_xy_m: seed_footprint(256) };
    let extractor = FeatureExtractor::new()?;
    let stride = (steps / 100).max(1);
    let started = std::time::Instant::now();
    let mut results = Vec::new();
    for s in 0..seeds {
        let scene = args.first_seed + s;
        let oracle_dir = crate::eval_grow::grow(args, scene, RefinerKind::Oracle, &args.oracle_label(), &root)?;
        let gen_dir = if args.refiner.effective() == RefinerKind::Oracle {
            oracle_dir.clone()
        } else {
            crate::eval_grow::grow(args, scene, args.refiner.effective(), &label, &root)?
        };
        let (gm, om) = (read_mesh(&gen_dir)?, read_mesh(&oracle_dir)?);
        let generated = sgam_metrics::world::world_stats(&gm, &exclusion, &cfg);
        let oracle = sgam_metrics::world::world_stats(&om, &exclusion, &cfg);
        let (gp, op) = (
            sgam_metrics::world::new_area_points(&gm, &exclusion, &cfg),
            sgam_metrics::world::new_area_points(&om, &exclusion, &cfg),
        );
        // one region grid per seed: the oracle's new area and ground, shared by both worlds
        let (gen_regions, ref_regions) =
            match sgam_metrics::world::new_area_region_spec(&op, oracle.ground_height_m, args.region_size, 15) {
                Some(spec) => {
                    let nonempty =
                        |h: Vec<Vec<f32>>| h.into_iter().filter(|r| r.iter().any(|v| *v > 0.0)).collect::<Vec<_>>();
                    let g = sgam_metrics::scene::region_histograms(&gp, &spec);
                    let r = sgam_metrics::scene::region_histograms(&op, &spec);
                    (nonempty(g), nonempty(r))
                }
                None => (Vec::new(), Vec::new()),
            };
        let gen_features = frame_features(&gen_dir, steps + 1, stride, &extractor)?;
        let ref_features = frame_features(&oracle_dir, steps + 1, stride, &extractor)?;
        results.push(SeedResult {
            generated,
            oracle,
            gen_regions,
            ref_regions,
            gen_features,
            ref_features,
            step_ms: median_step_ms(&gen_dir),
            loop_psnr_ssim: if args.no_loop {
                (f64::NAN, f64::NAN)
            } else {
                crate::eval_grow::loop_consistency(args, scene, args.refiner.effective(), &label, &loop_root)?
            },
        });
    }
    let gen_stats: Vec<WorldStats> = results.iter().map(|r| r.generated.clone()).collect();
    let ref_stats: Vec<WorldStats> = results.iter().map(|r| r.oracle.clone()).collect();
    let (gp, op) = (PooledStats::of(&gen_stats), PooledStats::of(&ref_stats));
    let gen_regions: Vec<Vec<f32>> = results.iter().flat_map(|r| r.gen_regions.clone()).collect();
    let ref_regions: Vec<Vec<f32>> = results.iter().flat_map(|r| r.ref_regions.clone()).collect();
    let scene = sgam_metrics::scene::scene_metrics(&gen_regions, &ref_regions);
    let gf: Vec<Vec<f32>> = results.iter().flat_map(|r| r.gen_features.clone()).collect();
    let rf: Vec<Vec<f32>> = results.iter().flat_map(|r| r.ref_features.clone()).collect();
    let kid = sgam_metrics::kid::kid(&gf, &rf);
    let step_ms: Vec<f64> = results.iter().map(|r| r.step_ms).collect();
    let loop_psnr: Vec<f64> = results.iter().map(|r| r.loop_psnr_ssim.0.min(99.0)).collect();
    let loop_ssim: Vec<f64> = results.iter().map(|r| r.loop_psnr_ssim.1).collect();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    Ok(json!({
        "refiner": label, "seeds": seeds, "steps": steps,
        "trajectory": format!("{:?}", args.trajectory()).to_lowercase(),
        "temperature": args.sampling.temperature,
        "ground_snap_m": args.invented.ground_snap,
        "ground_flatten_m": args.invented.ground_flatten,
        "flying_pixels": args.invented.flying_pixels,
        "free_space": args.invented.free_space,
        "solid_objects_m": args.invented.solid_objects_m(&sgam_pipeline::CLEVR),
        "max_object_m2": args.invented.max_object_m2(&sgam_pipeline::CLEVR),
        "max_object_length_m": args.invented.max_object_length_m(&sgam_pipeline::CLEVR),
        "object_colour": args.invented.object_colour(&sgam_pipeline::CLEVR),
        "top_k": args.sampling.top_k,
        "within_temperature": args.sampling.within_temperature,
        "generated": gp, "oracle": op,
        "ratio_to_oracle": ratios_to_oracle(&gp, &op),
        "scene": scene, "regions": { "generated": gen_regions.len(), "oracle": ref_regions.len(), "size_m": args.region_size },
        "kid": kid, "kid_frames": { "generated": gf.len(), "oracle": rf.len() },
        "per_seed": results.iter().enumerate().map(|(i, r)| json!({
            "seed_scene": args.first_seed + i as u64, "generated": r.generated, "oracle": r.oracle,
            "ratio_to_oracle": ratios_to_oracle(
                &PooledStats::of(std::slice::from_ref(&r.generated)),
                &PooledStats::of(std::slice::from_ref(&r.oracle)),
            ),
        })).collect::<Vec<_>>(),
        "loop": { "steps": crate::eval_grow::LOOP_STEPS, "psnr": mean(&loop_psnr), "ssim": mean(&loop_ssim) },
        "step_ms_median": sgam_metrics::median(&step_ms).unwrap_or(0.0),
        "out": root.display().to_string(),
        "wall_s": started.elapsed().as_secs_f64(),
    }))
}

/// The generated world's statistics over the oracle's (NaN where the oracle's is 0): pooled
/// over every scene, or of one scene's world (a pool of one).
fn ratios_to_oracle(g: &PooledStats, o: &PooledStats) -> serde_json::Value {
    let ratio = |a: f64, b: f64| if b.abs() > 0.0 { a / b } else { f64::NAN };
    let compact = |s: &PooledStats| s.object_shape.compact_share.map_or(f64::NAN, f64::from);
    json!({
        "objects_per_100m2": ratio(g.objects_per_100m2, o.objects_per_100m2),
        "median_object_area": ratio(g.median_object_area_m2, o.median_object_area_m2),
        "p90_object_area": ratio(g.p90_object_area_m2, o.p90_object_area_m2),
        "object_saturation": ratio(g.object_saturation, o.object_saturation),
        "ground_rms": ratio(g.ground_rms_mm, o.ground_rms_mm),
        "compact_object_share": ratio(compact(g), compact(o)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_seed_footprint_is_the_ground_quadrilateral_ahead_of_the_seed_camera() {
        let p = seed_footprint(256);
        assert_eq!(p.len(), 4);
        // the camera at (-20, -20), 11.695 m above the ground, looks towards +y, down at 72.8
        // degrees with a 40-degree field of view: the image's bottom edge looks 2.8 degrees
        // behind the vertical (y = -20 - 11.695 tan 2.8 deg = -20.6), its top edge 37.2
        // degrees ahead (y = -20 + 11.695 tan 37.2 deg = -11.1); a trapezoid wider far away
        let ys: Vec<f32> = p.iter().map(|v| v.y).collect();
        assert!((ys[0] + 11.1).abs() < 0.3 && (ys[2] + 20.6).abs() < 0.3, "{p:?}");
        let near = (p[3].x - p[2].x).abs();
        let far = (p[0].x - p[1].x).abs();
        assert!(far > near && near > 2.0 && far < 15.0, "{p:?}");
    }

    #[derive(clap::Parser)]
    struct Cli {
        #[command(flatten)]
        world: WorldArgs,
    }

    fn label(args: &[&str]) -> String {
        use clap::Parser;
        Cli::try_parse_from(std::iter::once("world").chain(args.iter().copied())).unwrap().world.label()
    }

    #[test]
    fn a_worlds_folder_names_every_option_that_changes_it_and_keeps_older_names() {
        // the default's folder is the one sessions 29-32 grew their worlds in (reused, never
        // regrown): a new option that is off must not rename it
        let default = label(&[]);
        let crc = crc32fast::hash(sgam_pipeline::BUNDLED_MODEL);
        assert_eq!(default, format!("model-{crc:08x}-t1.3-w0.6-g1-flat0.3-carve-solid1-cap6"));
        assert_eq!(label(&["--object-colour", "1"]), format!("{default}-oc1"));
        assert_eq!(label(&["--class-coherence", "1"]), default.replace("-t1.3-", "-t1.3-cc1-"));
        // the seed's own pixels: the tile is named when it is not the preset's
        let seed = label(&["--bank", "seed"]);
        assert!(seed.contains("-bankseed") && !seed.contains("-qt"), "{seed}");
        assert_eq!(label(&["--bank", "seed", "--quilt-tile", "8"]), seed);
        let tiled = label(&["--bank", "seed", "--quilt-tile", "12"]);
        assert!(tiled.contains("-bankseed-qt12"), "{tiled}");
        assert_eq!(label(&["--refiner", "oracle"]), "oracle");
    }
}
