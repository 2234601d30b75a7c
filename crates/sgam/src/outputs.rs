//! What `sgam generate` shows and writes around the pipeline's run: the progress bar and the live
//! viewer ([`CliObserver`]), per-step extras (millimetre depth PNGs, intermediate meshes) and the
//! end-of-run outputs ([`finish_outputs`]: mesh, map, transforms.json, fly-through, overview,
//! run.json, world.html).

use std::path::Path;

use anyhow::{Context, Result};
use indicatif::ProgressBar;
use sgam_core::{Camera, TriMesh};
use sgam_pipeline::run::RunGenerator;
use sgam_pipeline::{
    frame_file_names, Generated, Keyframes, RunConfig, RunObserver, Seed, StepTimings, TrajectorySpec,
};

use crate::generate::DEPTH_PNG_MAX_M;
use crate::live::LiveView;
use crate::progress;

type ObserverResult = std::result::Result<(), sgam_pipeline::PipelineError>;

/// Progress bar, live viewer and per-step extras of a run on the command line.
#[derive(Debug)]
pub struct CliObserver<'a> {
    dir: &'a Path,
    config: &'a RunConfig,
    /// `--view`, `--view-port`, `--view-every`.
    view: (bool, u16, usize),
    live: Option<LiveView>,
    pb: Option<ProgressBar>,
}

impl<'a> CliObserver<'a> {
    /// An observer of the run `config` in `dir`; the viewer is served when `view.0`.
    pub fn new(dir: &'a Path, config: &'a RunConfig, view: (bool, u16, usize)) -> Self {
        Self { dir, config, view, live: None, pb: None }
    }

    /// Clears the progress bar.
    pub fn finish_progress(&mut self) {
        if let Some(pb) = self.pb.take() {
            pb.finish_and_clear();
        }
    }

    /// Stops the live viewer after its last refresh.
    pub fn finish_live(&mut self, cameras: &[Camera]) {
        if let Some(live) = self.live.take() {
            live.finish(cameras);
        }
    }
}

fn output_error(e: anyhow::Error) -> sgam_pipeline::PipelineError {
    sgam_pipeline::PipelineError::Output(e.into())
}

impl RunObserver for CliObserver<'_> {
    fn adapting(&mut self, p: &sgam_pipeline::adapt::AdaptProgress) -> ObserverResult {
        let pb = self.pb.get_or_insert_with(|| progress::bar(p.budget_s.ceil() as u64, "adapting to the seed (s)"));
        pb.set_position((p.elapsed_s as u64).min(p.budget_s.ceil() as u64));
        pb.set_message(format!("step {}, {:.1} dB", p.step, p.psnr_db));
        Ok(())
    }

    fn adapted(&mut self, o: &sgam_pipeline::adapt::AdaptOutcome) -> ObserverResult {
        self.finish_progress();
        let trips = match o.trips {
            0 => "none on round trips (no camera of the path loses 3-50 % of the seed)".to_string(),
            n => format!("half of them on {n} round trips of it"),
        };
        eprintln!(
            "adapted to the seed: {} steps in {:.0} s, {trips}; the seed through the autoencoder: {:.1} dB -> {:.1} dB",
            o.steps, o.seconds, o.psnr_before_db, o.psnr_after_db
        );
        Ok(())
    }

    fn after_seed(&mut self, generator: &mut RunGenerator) -> ObserverResult {
        if self.config.outputs.depth_png {
            write_depth_png(self.dir, 0, &generator.keyframes.frame(0)?.depth_m).map_err(output_error)?;
        }
        Ok(())
    }

    fn started(&mut self, resumed: bool, total: usize, done: usize, seed: &Seed) -> ObserverResult {
        eprintln!(
            "{} {}: {} steps from {} ({} x {} px) -> {}",
            if resumed { "resuming" } else { "generating" },
            trajectory_name(&self.config.trajectory),
            total - 1,
            seed.name,
            seed.camera.intrinsics.width,
            seed.camera.intrinsics.height,
            self.dir.display()
        );
        if !resumed && seed.renderer.is_none() {
            domain_check(self.config, seed);
        }
        let (on, port, every) = self.view;
        self.live = Some(LiveView::start_if(on, self.dir, port, every).map_err(output_error)?);
        let pb = progress::bar(total as u64 - 1, "steps");
        pb.set_position((done - 1) as u64);
        self.pb = Some(pb);
        Ok(())
    }

    fn after_step(&mut self, i: usize, total: usize, generator: &mut RunGenerator, t: &StepTimings) -> ObserverResult {
        if let Some(live) = &mut self.live {
            live.after_step(i, total, &mut generator.map, generator.keyframes.cameras());
        }
        if let Some(pb) = &self.pb {
            pb.inc(1);
            pb.set_message(format!("{:.0} ms/step, {:.0}% invented", t.total_ms, 100.0 * t.missing_fraction));
        }
        let outputs = &self.config.outputs;
        if outputs.depth_png {
            write_depth_png(self.dir, i, &generator.keyframes.frame(i)?.depth_m).map_err(output_error)?;
        }
        if outputs.guidance_png {
            let fin = generator.keyframes.frame(i)?;
            if let Some((guidance, raw)) = generator.last_guidance() {
                let panel = sgam_pipeline::guidance_view::step_panel(guidance, raw, &fin);
                let dir = self.dir.join("guidance");
                std::fs::create_dir_all(&dir).map_err(|e| sgam_io::IoError::Io { path: dir.clone(), source: e })?;
                sgam_io::write_rgb_png(&dir.join(format!("{i:05}.png")), &panel)?;
            }
        }
        if outputs.mesh_every > 0 && i.is_multiple_of(outputs.mesh_every) {
            sgam_io::write_mesh(&self.dir.join(format!("mesh-{i:05}.ply")), &generator.map.extract_mesh())?;
        }
        Ok(())
    }
}

/// Says how far a seed from outside the synthetic world is from what the model learned (its
/// reconstruction PSNR against [`sgam_pipeline::DOMAIN_PSNR_DB`]), and what to do about it.
fn domain_check(config: &RunConfig, seed: &Seed) {
    let sgam_pipeline::RefinerSpec::Model { model, bank, adapt_s, .. } = &config.refiner else { return };
    if *adapt_s > 0.0 {
        // the adaptation has said how well the model draws the seed, before and after
        return;
    }
    match sgam_pipeline::seed_reconstruction_psnr(model.as_deref(), seed) {
        Ok(psnr) if psnr < sgam_pipeline::DOMAIN_PSNR_DB && *bank == sgam_pipeline::BankSpec::Seed => eprintln!(
            "note: the model reconstructs this seed at {psnr:.1} dB, far below the ~30 dB of the synthetic \
             CLEVR-Infinite frames it was trained on, so it does not draw the new area: every hole is quilted \
             from the seed's own pixels (--bank seed), and the world grows in the seed's look, repeating its \
             parts. `sgam eval seed RUN` compares the new area with the seed"
        ),
        Ok(psnr) if psnr < sgam_pipeline::DOMAIN_PSNR_DB => eprintln!(
            "warning: the model reconstructs this seed at {psnr:.1} dB, far below the ~30 dB of the synthetic \
             CLEVR-Infinite frames it was trained on: it has not seen scenes like this one, and what it invents \
             will look like CLEVR's grey floor and coloured solids. Judge the new area by eye (--guidance-png \
             shows every step), quilt the holes from the seed itself with --bank seed, or grow with --refiner \
             null for a neutral fill"
        ),
        Ok(psnr) => {
            eprintln!("domain check: the model reconstructs this seed at {psnr:.1} dB (synthetic CLEVR frames: ~30 dB)")
        }
        Err(e) => eprintln!("domain check skipped: {e}"),
    }
}

/// The trajectory's name as the command line spells it.
fn trajectory_name(t: &TrajectorySpec) -> &'static str {
    match t {
        TrajectorySpec::Zigzag { .. } => "zigzag",
        TrajectorySpec::Boustrophedon { .. } => "boustrophedon",
        TrajectorySpec::Line { .. } => "line",
        TrajectorySpec::Circle { .. } => "circle",
        TrajectorySpec::Spiral { .. } => "spiral",
        TrajectorySpec::File { .. } => "file",
        TrajectorySpec::Greedy { .. } => "greedy",
    }
}

/// Writes `depth/NNNNN.png` (millimetres) of keyframe `index`; depth beyond what 16 bits hold is
/// stored as invalid (0), not clipped to a wrong value.
fn write_depth_png(dir: &Path, index: usize, depth_m: &sgam_core::Image<f32>) -> Result<()> {
    let (_, path) = Keyframes::frame_paths(dir, index);
    let mut depth = depth_m.clone();
    for d in &mut depth.data {
        if *d > DEPTH_PNG_MAX_M {
            *d = 0.0;
        }
    }
    sgam_io::write_depth_png_mm(&path.with_extension("png"), &depth)?;
    Ok(())
}

/// Writes the end-of-run outputs: mesh (PLY + GLB), map, transforms.json, fly-through, overview,
/// run.json and world.html.
pub fn finish_outputs(config: &RunConfig, dir: &Path, run: &mut Generated) -> Result<()> {
    let (generator, timings, wall_s) = (&mut run.generator, &run.timings, run.wall_s);
    let outputs = &config.outputs;
    // a world partly in tiles is written tile by tile, and as one mesh only when it is small
    // enough to build
    let mut tiled = if run.streaming.tiles.is_empty() {
        None
    } else {
        Some(crate::tiled::write_mesh_tiles(
            dir,
            &mut generator.map,
            &run.streaming,
            outputs.single_mesh_max_triangles,
        )?)
    };
    let single = tiled.as_ref().is_none_or(|t| t.single.is_some());
    let mesh = match &mut tiled {
        Some(t) => t.single.take().unwrap_or_default(),
        None => generator.map.extract_mesh(),
    };
    if single {
        sgam_io::write_mesh(&dir.join("mesh.ply"), &mesh)?;
        sgam_io::write_mesh(&dir.join("mesh.glb"), &mesh)?;
    }
    // a world too large for one mesh, or whose map is in tiles, leaves no stale one behind (a
    // resumed run rewrites its outputs)
    let stale: &[&str] = match (single, tiled.is_some()) {
        (true, false) => &[],
        (true, true) => &["map.bin"],
        (false, _) => &["mesh.ply", "mesh.glb", "map.bin"],
    };
    for name in stale {
        match std::fs::remove_file(dir.join(name)) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(anyhow::Error::new(e).context(format!("{}: cannot remove", dir.join(name).display())))
            }
            _ => {}
        }
    }
    if tiled.is_none() {
        // an earlier finish of this run may have left a tiled world's files
        let old = dir.join(crate::tiled::MESH_TILES_DIR);
        if old.is_dir() {
            std::fs::remove_dir_all(&old).with_context(|| format!("{}: cannot remove", old.display()))?;
        }
        sgam_pipeline::save_map(&dir.join("map.bin"), &generator.map)?;
    }
    let cams = generator.keyframes.cameras();
    let frames = (0..cams.len())
        .map(|i| {
            let (rgb, depth) = frame_file_names(i);
            sgam_io::NerfFrame {
                file_path: rgb,
                depth_file_path: Some(depth),
                world_from_camera: cams[i].world_from_camera,
                intrinsics: None,
            }
        })
        .collect();
    let transforms =
        sgam_io::NerfTransforms { intrinsics: cams[0].intrinsics, frames, depth_png_metres_per_unit: 0.001 };
    sgam_io::write_nerf_transforms(&dir.join("transforms.json"), &transforms)?;
    if outputs.video {
        write_flythrough(dir, cams.len())?;
    }
    if outputs.video && outputs.mp4 {
        crate::video::write_flythrough_mp4(dir, cams.len())?;
    }
    if outputs.orbit_video && tiled.is_none() {
        crate::video::write_orbit_mp4(&dir.join("orbit.mp4"), &generator.map, &mesh, crate::view::up_world(&cams[0]))?;
    }
    match &tiled {
        None => {
            if let Some((cam, near, far)) = crate::overview::overview_camera(&mesh, &cams[0], 1280, 800) {
                let img = crate::overview::render_overview(&generator.map, &cam, near, far);
                sgam_io::write_rgb_png(&dir.join("overview.png"), &img)?;
            }
        }
        Some(t) => {
            // framed on the world's bounds, drawn tile by tile
            let corners = t.bounds().map(|(lo, hi)| TriMesh {
                positions: (0..8)
                    .map(|i| {
                        let pick = |bit: usize, a: f32, b: f32| if i & bit == 0 { a } else { b };
                        sgam_core::Vec3::new(pick(1, lo.x, hi.x), pick(2, lo.y, hi.y), pick(4, lo.z, hi.z))
                    })
                    .collect(),
                ..TriMesh::default()
            });
            if let Some((cam, near, far)) =
                corners.and_then(|c| crate::overview::overview_camera(&c, &cams[0], 1280, 800))
            {
                let r = crate::tiled::rasterize_world(&generator.map, &run.streaming, &cam, near, far)?;
                sgam_io::write_rgb_png(&dir.join("overview.png"), &crate::overview::shade_overview(&r, &cam))?;
            }
        }
    }
    sgam_io::write_rgb_png(&dir.join("strip.png"), &crate::overview::frame_strip(dir, cams.len(), 6)?)?;
    let median = |v: &[f64]| sgam_metrics::median(v).unwrap_or(0.0);
    let col = |f: fn(&StepTimings) -> f64| median(&timings.iter().map(f).collect::<Vec<_>>());
    let summary = serde_json::json!({
        "config": config,
        "steps": timings.len(),
        "keyframes": cams.len(),
        "wall_s_this_invocation": wall_s,
        "median_ms": {
            "total": col(|t| t.total_ms), "sources": col(|t| t.sources_ms), "render": col(|t| t.render_ms),
            "warp": col(|t| t.warp_ms), "refine": col(|t| t.refine_ms), "integrate": col(|t| t.integrate_ms),
            "mesh": col(|t| t.mesh_ms), "write": col(|t| t.write_ms),
        },
        "median_missing_fraction": median(&timings.iter().map(|t| t.missing_fraction as f64).collect::<Vec<_>>()),
        "map": { "blocks": generator.map.block_count(), "bytes": generator.map.memory_bytes(),
                 "vertices": mesh.positions.len(),
                 "triangles": tiled.as_ref().map_or(mesh.triangles.len() as u64, |t| t.triangles),
                 "max_map_mb": config.max_map_mb,
                 "tiles_on_disk": run.streaming.tiles.len(),
                 "tiles_disk_bytes": run.streaming.tiles.disk_bytes(),
                 "tile_blocks": run.streaming.tiles.entries().map(|e| e.blocks as u64).sum::<u64>(),
                 "tiles_written_this_invocation": run.streaming.evicted,
                 "peak_bytes_this_invocation": run.streaming.peak_bytes,
                 "over_bound_this_invocation": run.streaming.over_bound,
                 "tiles_taken_back_this_invocation": run.streaming.restored },
        "step_ms": timings.iter().map(|t| (t.total_ms * 1000.0).round() / 1000.0).collect::<Vec<_>>(),
        // flatness over a long run at a glance: the median step of each 1000 steps (the last
        // entry covers what remains)
        "per_1000_median_ms": timings.chunks(1000).map(|c| median(&c.iter().map(|t| t.total_ms).collect::<Vec<_>>())).collect::<Vec<_>>(),
    });
    let bytes = serde_json::to_vec_pretty(&summary)?;
    sgam_io::write_atomic(&dir.join("run.json"), |w| std::io::Write::write_all(w, &bytes))?;
    // a tiled world's page opens on its coarse world (mesh-tiles/coarse.glb)
    let page = crate::view::write_world_html(dir, crate::view::DEFAULT_EMBED_LIMIT_BYTES)?;
    eprintln!(
        "done: {} steps, median {:.1} ms/step (refine {:.1}, map {:.1})",
        timings.len(),
        col(|t| t.total_ms),
        col(|t| t.refine_ms),
        col(|t| t.render_ms + t.warp_ms + t.integrate_ms + t.mesh_ms)
    );
    if single {
        eprintln!("  mesh:        {}  ({} vertices)", dir.join("mesh.ply").display(), mesh.positions.len());
        eprintln!("  mesh (glTF): {}", dir.join("mesh.glb").display());
    }
    if let Some(t) = &tiled {
        eprintln!(
            "  mesh tiles:  {}/  ({} tiles, {} triangles; index.json lists them){}",
            dir.join(crate::tiled::MESH_TILES_DIR).display(),
            t.tiles.len(),
            t.triangles,
            if single {
                String::new()
            } else {
                format!(
                    "; no single mesh.ply/mesh.glb: the world has more than --single-mesh-max-mtri {} million triangles",
                    outputs.single_mesh_max_triangles as f64 / 1e6
                )
            }
        );
        eprintln!(
            "  map:         {} blocks in memory, {} tiles in {} ({:.0} MB; --max-map-mb {})",
            generator.map.block_count(),
            run.streaming.tiles.len(),
            dir.join(sgam_pipeline::tiles::TILES_DIR).display(),
            run.streaming.tiles.disk_bytes() as f64 / 1e6,
            config.max_map_mb
        );
    }
    if outputs.video {
        eprintln!("  fly-through: {}", dir.join("flythrough.gif").display());
    }
    if outputs.video && outputs.mp4 {
        eprintln!("  video:       {}", dir.join("flythrough.mp4").display());
    }
    if outputs.orbit_video && tiled.is_none() {
        eprintln!("  orbit:       {}", dir.join("orbit.mp4").display());
    } else if outputs.orbit_video {
        eprintln!("  orbit:       not written: the orbit renders map.bin, and this world's map is in tiles");
    }
    eprintln!(
        "  viewer:      {}  (open it in a browser{})",
        page.path.display(),
        if tiled.is_some() {
            format!(
                "; the whole world coarse, and served (sgam view {} --serve) full detail near the view",
                dir.display()
            )
        } else if page.mesh_embedded {
            String::new()
        } else {
            format!("; large mesh: sgam view {} --serve", dir.display())
        }
    );
    if run.streaming.over_bound > 0 {
        eprintln!(
            "warning: the map stayed above --max-map-mb {} {} times (peak {:.0} MB): what a step can see (--depth-max {} m) \
             held more than that; raise --max-map-mb or lower --depth-max",
            config.max_map_mb,
            run.streaming.over_bound,
            run.streaming.peak_bytes as f64 / 1e6,
            config.map.depth_max_m
        );
    }
    eprintln!("  overview:    {}  (and strip.png: 6 frames)", dir.join("overview.png").display());
    eprintln!("  poses:       {}  (nerfstudio / instant-ngp)", dir.join("transforms.json").display());
    eprintln!("  frames:      {}/rgb, {}/depth", dir.display(), dir.display());
    Ok(())
}

/// An animated GIF of (at most 200 evenly chosen) generated frames, 10 frames/s.
fn write_flythrough(dir: &Path, n: usize) -> Result<()> {
    use image::codecs::gif::{GifEncoder, Repeat};
    let stride = n.div_ceil(200).max(1);
    let path = dir.join("flythrough.gif");
    let mut frames = Vec::new();
    for i in (0..n).step_by(stride) {
        let (rgb, _) = Keyframes::frame_paths(dir, i);
        let img = image::open(&rgb).with_context(|| format!("{}: cannot read frame", rgb.display()))?.to_rgba8();
        frames.push(image::Frame::from_parts(img, 0, 0, image::Delay::from_numer_denom_ms(100, 1)));
    }
    sgam_io::write_atomic(&path, |w| {
        let mut enc = GifEncoder::new_with_speed(w, 20);
        enc.set_repeat(Repeat::Infinite).map_err(std::io::Error::other)?;
        enc.encode_frames(frames).map_err(std::io::Error::other)
    })?;
    Ok(())
}
