//! Timing of the map's hot loops (not a test). Run with
//! `cargo bench -p sgam-map --bench map_bench [-- 7scenes-dir]`.
//!
//! 1. `clevr256`: a synthetic CLEVR-like scene at 256x256 (5 cm voxels, 0.5 m truncation,
//!    depth <= 20 m): per step integrate + incremental re-mesh + rasterize + warp from 5 sources.
//! 2. `7scenes640`: if a 7-Scenes layout folder is given (or `../shared/data/7scenes-redkitchen-50`
//!    exists), 2 cm voxels, 8 cm truncation, 4 m depth cut: integrate + incremental mesh per frame.
//!
//! Prints one JSON line per subject with median milliseconds.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::time::Instant;

use sgam_core::{Camera, Image, Intrinsics, RgbdFrame, Rigid3, Vec2, Vec3};
use sgam_map::{warp_colour, SourceView, TsdfConfig, TsdfMap, WarpConfig};

/// CPU time of this process (all threads) in milliseconds, from /proc (Linux); 0 elsewhere.
/// Unlike wall time it does not count time spent waiting for a core on a loaded machine.
fn cpu_ms() -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else { return 0.0 };
    tasks
        .filter_map(|t| t.ok())
        .filter_map(|t| std::fs::read_to_string(t.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next().and_then(|x| x.parse::<f64>().ok()))
        .sum::<f64>()
        / 1e6
}

fn median(v: Vec<f64>) -> f64 {
    sgam_metrics::median(&v).unwrap_or(f64::NAN)
}

/// Ground plane at z = -11.695 with spheres on it; camera pitched down, OpenCV axes.
fn clevr_frame(cam: &Camera) -> RgbdFrame {
    let k = cam.intrinsics;
    let mut f = RgbdFrame::empty(k.width, k.height);
    let ground = -11.695f32;
    let spheres: Vec<(Vec3, f32, [f32; 3])> = (0..400)
        .map(|i| {
            let (x, y) = ((i % 20) as f32 * 2.1 - 20.0, (i / 20) as f32 * 2.1 - 16.0);
            let c = [(i * 37 % 100) as f32 / 100.0, (i * 61 % 100) as f32 / 100.0, (i * 13 % 100) as f32 / 100.0];
            (Vec3::new(x, y, ground + 1.0), if i % 3 == 0 { 0.7 } else { 1.0 }, c)
        })
        .collect();
    let o = cam.centre_world();
    for v in 0..k.height {
        for u in 0..k.width {
            let d = cam.world_from_camera.transform_vector(k.ray_z1(Vec2::new(u as f32, v as f32)));
            let mut best = f32::INFINITY;
            let mut col = [0.0; 3];
            if d.z < 0.0 {
                best = (ground - o.z) / d.z;
                let p = o + d * best;
                col = [0.6 + 0.2 * (p.x).sin(), 0.6, 0.6 + 0.2 * (p.y).cos()];
            }
            for (c, r, sc) in &spheres {
                let oc = o - *c;
                let (a, b, cc) = (d.dot(d), oc.dot(d), oc.dot(oc) - r * r);
                let disc = b * b - a * cc;
                if disc > 0.0 {
                    let t = (-b - disc.sqrt()) / a;
                    if t > 0.0 && t < best {
                        best = t;
                        col = *sc;
                    }
                }
            }
            if best.is_finite() {
                *f.depth_m.at_mut(u, v) = best;
                *f.colour.at_mut(u, v) = col;
            }
        }
    }
    f
}

fn clevr_camera(x: f32, y: f32) -> Camera {
    // Blender camera-to-world Rx(0.3) converted to OpenCV axes.
    let k = Intrinsics::from_fov_x(256, 256, 0.69111);
    let gl = Rigid3::new(sgam_core::Mat3::from_rotation_x(0.3), Vec3::new(x, y, 0.0));
    Camera::new(k, Rigid3::from_opengl_camera(gl))
}

fn bench_clevr() {
    let mut map = TsdfMap::new(TsdfConfig::default());
    let steps = 60;
    let cams: Vec<Camera> = (0..steps).map(|i| clevr_camera(-20.0 + 0.408 * i as f32, -20.0)).collect();
    let frames: Vec<RgbdFrame> = cams.iter().map(clevr_frame).collect();
    let (mut t_int, mut t_mesh, mut t_render, mut t_warp, mut t_all) = (vec![], vec![], vec![], vec![], vec![]);
    let mut cpu: [Vec<f64>; 5] = Default::default();
    for i in 0..steps {
        let c0 = cpu_ms();
        let t0 = Instant::now();
        let rendered = map.remesh_and_rasterize_depth(&cams[i]);
        let c1 = cpu_ms();
        let t1 = Instant::now();
        let sources: Vec<SourceView> =
            (i.saturating_sub(5)..i).map(|j| SourceView { camera: &cams[j], frame: &frames[j] }).collect();
        let warped = warp_colour(&cams[i], &rendered, &sources, &WarpConfig::default());
        let c2 = cpu_ms();
        let t2 = Instant::now();
        map.integrate(&frames[i], &cams[i]);
        let c3 = cpu_ms();
        let t3 = Instant::now();
        map.update_mesh();
        let c4 = cpu_ms();
        let t4 = Instant::now();
        std::hint::black_box(&warped);
        if i >= 5 {
            t_render.push((t1 - t0).as_secs_f64() * 1e3);
            t_warp.push((t2 - t1).as_secs_f64() * 1e3);
            t_int.push((t3 - t2).as_secs_f64() * 1e3);
            t_mesh.push((t4 - t3).as_secs_f64() * 1e3);
            t_all.push((t4 - t0).as_secs_f64() * 1e3);
            cpu[0].push(c3 - c2);
            cpu[1].push(c4 - c3);
            cpu[2].push(c1 - c0);
            cpu[3].push(c2 - c1);
            cpu[4].push(c4 - c0);
        }
    }
    let [c_int, c_mesh, c_render, c_warp, c_all] = cpu.map(median);
    println!(
        "{{\"subject\":\"clevr256_cpu\",\"integrate_ms\":{c_int:.3},\"mesh_ms\":{c_mesh:.3},\"render_ms\":{c_render:.3},\"warp_ms\":{c_warp:.3},\"median_ms\":{c_all:.3}}}"
    );
    println!(
        "{{\"subject\":\"clevr256\",\"steps\":{},\"integrate_ms\":{:.3},\"mesh_ms\":{:.3},\"render_ms\":{:.3},\"warp_ms\":{:.3},\"median_ms\":{:.3},\"blocks\":{}}}",
        t_all.len(),
        median(t_int),
        median(t_mesh),
        median(t_render),
        median(t_warp),
        median(t_all),
        map.block_count()
    );
}

fn read_7scenes(dir: &Path) -> Option<(Intrinsics, Vec<(Camera, RgbdFrame)>)> {
    let frames_dir = if dir.join("rgbd-frames").is_dir() { dir.join("rgbd-frames") } else { dir.to_path_buf() };
    let kt = std::fs::read_to_string(dir.join("camera-intrinsics.txt")).ok()?;
    let kv: Vec<f32> = kt.split_whitespace().map(|s| s.parse().unwrap()).collect();
    let mut poses: Vec<PathBuf> = std::fs::read_dir(&frames_dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.to_string_lossy().ends_with(".pose.txt"))
        .collect();
    poses.sort();
    let mut out = Vec::new();
    let mut k = None;
    for p in poses {
        let stem = p.to_string_lossy().trim_end_matches(".pose.txt").to_string();
        let depth = image::open(format!("{stem}.depth.png")).ok()?.into_luma16();
        let colour = image::open(format!("{stem}.color.png")).ok()?.into_rgb8();
        let (w, h) = depth.dimensions();
        let intr = *k.get_or_insert(Intrinsics::try_new(w, h, kv[0], kv[4], kv[2], kv[5]).ok()?);
        let d: Vec<f32> = depth
            .pixels()
            .map(|px| if px.0[0] == 0 || px.0[0] == 65535 { 0.0 } else { px.0[0] as f32 / 1000.0 })
            .collect();
        let c: Vec<[f32; 3]> = colour.pixels().map(|px| px.0.map(|x| x as f32 / 255.0)).collect();
        let rows: Vec<f64> = std::fs::read_to_string(&p).ok()?.split_whitespace().map(|s| s.parse().unwrap()).collect();
        let m: [[f64; 4]; 4] = std::array::from_fn(|r| std::array::from_fn(|c| rows[r * 4 + c]));
        let pose = Rigid3::try_from_rows(m).ok()?.orthonormalized();
        out.push((
            Camera::new(intr, pose),
            RgbdFrame::try_new(Image::try_from_vec(w, h, c).ok()?, Image::try_from_vec(w, h, d).ok()?).ok()?,
        ));
    }
    Some((k?, out))
}

fn bench_7scenes(dir: &Path) {
    let Some((_, frames)) = read_7scenes(dir) else {
        eprintln!("7scenes640: no readable sequence at {}", dir.display());
        return;
    };
    let cfg = TsdfConfig {
        voxel_size_m: 0.02,
        trunc_voxels: 4.0,
        depth_min_m: 0.1,
        depth_max_m: 4.0,
        weight_cap: None,
        weight_threshold: 1.0,
    };
    for repeat in 0..2 {
        let mut map = TsdfMap::new(cfg);
        let (mut t_int, mut t_mesh) = (vec![], vec![]);
        let start = Instant::now();
        let (mut c_int, mut c_mesh) = (0.0, 0.0);
        for (cam, f) in &frames {
            let c0 = cpu_ms();
            let t0 = Instant::now();
            map.integrate(f, cam);
            let c1 = cpu_ms();
            let t1 = Instant::now();
            map.update_mesh();
            c_int += c1 - c0;
            c_mesh += cpu_ms() - c1;
            t_int.push((t1 - t0).as_secs_f64() * 1e3);
            t_mesh.push(t1.elapsed().as_secs_f64() * 1e3);
        }
        let t_extract = Instant::now();
        let mesh = map.extract_mesh();
        let extract_ms = t_extract.elapsed().as_secs_f64() * 1e3;
        let total = start.elapsed().as_secs_f64() * 1e3;
        let n = frames.len() as f64;
        println!(
            "{{\"subject\":\"7scenes640\",\"repeat\":{repeat},\"frames\":{},\"integrate_ms\":{:.3},\"mesh_ms\":{:.3},\"extract_ms\":{:.3},\"total_ms_per_frame\":{:.3},\"blocks\":{},\"vertices\":{},\"triangles\":{},\"memory_mb\":{:.1},\"cpu_integrate_ms_mean\":{:.3},\"cpu_mesh_ms_mean\":{:.3}}}",
            frames.len(),
            median(t_int),
            median(t_mesh),
            extract_ms,
            total / n,
            map.block_count(),
            mesh.positions.len(),
            mesh.triangles.len(),
            map.memory_bytes() as f64 / 1e6,
            c_int / n,
            c_mesh / n
        );
    }
}

fn main() {
    let arg = std::env::args().skip(1).find(|a| !a.starts_with('-'));
    if std::env::var_os("SGAM_BENCH_SKIP_CLEVR").is_none() {
        bench_clevr();
    }
    let dir = arg
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/7scenes-redkitchen-50"));
    bench_7scenes(&dir);
}
