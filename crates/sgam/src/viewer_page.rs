//! The viewer page `RUN/world.html` that `sgam view` and `sgam generate --view` write: one
//! self-contained file that opens from `file://` without network: the vendored three.js bundle,
//! the page's code, the run's data (poses, frame thumbnails) and the mesh (`mesh.glb`, base64)
//! all inside.
//!
//! Page data (the JSON in `<script id="sgam-data">`, read by `assets/viewer/viewer.js`):
//! - `three_from_world`: row-major 3x3 rotation from the run's world axes (z up for synthetic
//!   worlds) to the page's (glTF / three.js, y up); the same rotation `sgam_io::world_to_gltf`
//!   writes `mesh.glb` with, so poses drawn through it land on the mesh.
//! - `up_world`: the world's up direction (world axes).
//! - `poses[i]`: `world_from_camera` of frame `i`, OpenCV camera axes, 3x4 row-major (metres).
//! - `intrinsics`: pixels; `seed`: index of the seed frame; `frames[i]`: `rgb/NNNNN.png`.
//! - `thumbs`: `rgb[i]` JPEG data URIs (and `guidance` / `missing` when the run kept
//!   `guidance/NNNNN.png` / `missing/NNNNN.png`); past 500 frames only every k-th frame has
//!   one (the others are `""`, and the page shows the full-size frame).
//! - `mesh`: `embedded` (base64 GLB in `<script id="sgam-mesh">`) or loaded from `src` next to
//!   the page (needs `sgam view RUN --serve`), `bytes`, `vertices`, `triangles`.
//! - `tiles`: `null`, or for a world written in tiles (`--max-map-mb`) its viewer cells: the
//!   mesh above is then the coarse world (`mesh-tiles/coarse.glb`), each cell a range of its
//!   triangles (`first`, `count`) with a box (page axes) and its tiles' files in `dir`; served,
//!   the page loads the cells within `fine_within_m` of the view in full detail (at most
//!   `max_fine_cells`) and hides their coarse triangles.
//! - `live`: `null`, or the state URL the live page polls (`sgam generate --view`).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use rayon::prelude::*;
use serde::Serialize;
use sgam_core::{Camera, Mat3, Vec3};

use crate::view::{MAX_FRUSTUMS, THREE_BUNDLE, THUMB_SIDE, VIEWER_HTML, VIEWER_JS};

/// What [`write_world_html`] wrote.
#[derive(Debug, Clone)]
pub struct PageInfo {
    pub path: PathBuf,
    /// Size of world.html, bytes.
    pub bytes: u64,
    pub mesh_embedded: bool,
    /// Size of mesh.glb, bytes.
    pub mesh_bytes: u64,
    pub vertices: u64,
    pub frames: usize,
}

#[derive(Debug, Serialize)]
struct PageIntrinsics {
    width: u32,
    height: u32,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
}

#[derive(Debug, Default, Serialize)]
struct Thumbs {
    rgb: Vec<String>,
    guidance: Option<Vec<String>>,
    missing: Option<Vec<String>>,
}

#[derive(Debug, Serialize)]
struct MeshRef {
    embedded: bool,
    src: String,
    bytes: u64,
    vertices: u64,
    triangles: u64,
    version: u64,
}

/// A world written in tiles (`mesh-tiles/index.json`): the page shows the coarse world (the
/// page's mesh) and, served, loads the cells near the view in full detail.
#[derive(Debug, Serialize)]
struct TilesRef {
    /// Folder of the tiles' files, relative to the page.
    dir: String,
    /// Cells whose box is within this distance of the view's centre load in full detail, page
    /// units (metres).
    fine_within_m: f32,
    /// At most this many cells in full detail at once.
    max_fine_cells: usize,
    cells: Vec<PageCell>,
}

/// A cell: its box (page axes), its triangles in the coarse mesh, its tiles' files.
#[derive(Debug, Serialize)]
struct PageCell {
    min: [f32; 3],
    max: [f32; 3],
    first: usize,
    count: usize,
    files: Vec<String>,
}

/// Frames beyond this many get no thumbnail of their own (a 100,000-frame page stays small):
/// every k-th frame has one, and the others show their full-size frame.
const MAX_THUMBS: usize = 500;

#[derive(Debug, Serialize)]
struct LiveRef {
    state: String,
    every_ms: u32,
}

/// The page's data (see the module documentation).
#[derive(Debug, Serialize)]
struct PageData {
    format: u32,
    name: String,
    three_from_world: [f32; 9],
    up_world: [f32; 3],
    intrinsics: PageIntrinsics,
    poses: Vec<[f32; 12]>,
    seed: usize,
    frames: Vec<String>,
    thumbs: Thumbs,
    frustum_every: usize,
    mesh: MeshRef,
    tiles: Option<TilesRef>,
    live: Option<LiveRef>,
}

/// The rotation from world axes to the page's (glTF, y up), row-major: columns are
/// `sgam_io::world_to_gltf` of the world axes, so it is the GLB writer's rotation by
/// construction.
pub fn three_from_world() -> [f32; 9] {
    let m = Mat3::from_cols(
        sgam_io::world_to_gltf(Vec3::X),
        sgam_io::world_to_gltf(Vec3::Y),
        sgam_io::world_to_gltf(Vec3::Z),
    );
    m.transpose().to_cols_array() // the columns of the transpose are the rows
}

/// The world's up direction (world axes) for a run whose seed camera is `seed`: +z (the
/// synthetic worlds' convention) when the seed camera is upright or looks down in a z-up world;
/// otherwise the seed image's up direction (`-y` of the OpenCV camera) rounded to the nearest
/// axis (RGB seeds, whose world is the seed camera's frame).
pub fn up_world(seed: &Camera) -> Vec3 {
    let r = seed.world_from_camera.rotation;
    let image_up = -r.y_axis;
    let forward = r.z_axis;
    if image_up.z > 0.1 || forward.z < -0.2 {
        return Vec3::Z;
    }
    let axes = [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z];
    axes.into_iter().max_by(|a, b| a.dot(image_up).total_cmp(&b.dot(image_up))).unwrap_or(Vec3::Z)
}

/// `world_from_camera` as 3x4 row-major numbers.
fn pose_rows(c: &Camera) -> [f32; 12] {
    let (r, t) = (c.world_from_camera.rotation, c.world_from_camera.translation);
    let row = |i: usize| [r.x_axis[i], r.y_axis[i], r.z_axis[i], t[i]];
    let (a, b, d) = (row(0), row(1), row(2));
    [a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3], d[0], d[1], d[2], d[3]]
}

/// Standard base64 (RFC 4648, with padding), as data URIs and the embedded mesh need.
pub fn base64(bytes: &[u8]) -> String {
    use base64::Engine;
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// Vertex and triangle counts of a GLB written by `sgam_io::write_glb`; a cut file is refused.
pub fn glb_counts(path: &Path, glb: &[u8]) -> Result<(u64, u64)> {
    Ok(sgam_io::glb_counts(path, glb)?)
}

/// A frame as a JPEG data URI at most [`THUMB_SIDE`] pixels a side.
fn thumbnail(path: &Path) -> Result<String> {
    let img = image::open(path).with_context(|| format!("{}: cannot read frame", path.display()))?.to_rgb8();
    let (w, h) = img.dimensions();
    let s = (THUMB_SIDE as f32 / w.max(h) as f32).min(1.0);
    let img = if s < 1.0 {
        let (tw, th) = (((w as f32 * s).round() as u32).max(1), ((h as f32 * s).round() as u32).max(1));
        image::imageops::resize(&img, tw, th, image::imageops::FilterType::Triangle)
    } else {
        img
    };
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 80)
        .encode_image(&img)
        .with_context(|| format!("{}: cannot encode the thumbnail", path.display()))?;
    Ok(format!("data:image/jpeg;base64,{}", base64(&jpeg)))
}

/// Thumbnails of `dir/kind/NNNNN.png` for `n` frames, `None` unless every one is there.
fn optional_thumbs(dir: &Path, kind: &str, n: usize) -> Result<Option<Vec<String>>> {
    let paths: Vec<PathBuf> = (0..n).map(|i| dir.join(kind).join(format!("{i:05}.png"))).collect();
    if n == 0 || !paths.iter().all(|p| p.is_file()) {
        return Ok(None);
    }
    Ok(Some(paths.par_iter().map(|p| thumbnail(p)).collect::<Result<_>>()?))
}

/// JSON safe inside a `<script>` element: `<` (only ever inside strings) as `\u003c`.
fn script_json<T: Serialize>(value: &T) -> Result<String> {
    Ok(serde_json::to_string(value)?.replace('<', "\\u003c"))
}

fn html_escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// The template with its `{{KEY}}`s replaced, in one pass (inserted text is never rescanned).
fn fill_template(template: &str, values: &[(&str, &str)]) -> Result<String> {
    let extra: usize = values.iter().map(|(_, v)| v.len()).sum();
    let mut out = String::with_capacity(template.len() + extra);
    let mut rest = template;
    while let Some(start) = rest.find("{{") {
        let end = rest[start..].find("}}").map(|e| start + e).context("viewer template: unclosed {{")?;
        let key = &rest[start + 2..end];
        let value = values.iter().find(|(k, _)| *k == key).map(|(_, v)| *v);
        let Some(value) = value else { bail!("viewer template: no value for {{{{{key}}}}}") };
        out.push_str(&rest[..start]);
        out.push_str(value);
        rest = &rest[end + 2..];
    }
    out.push_str(rest);
    Ok(out)
}

/// The page: template, data, mesh (base64, or empty when loaded from a file), bundle, code.
fn page_html(data: &PageData, mesh_base64: &str) -> Result<String> {
    let title = html_escape(&data.name);
    fill_template(
        VIEWER_HTML,
        &[
            ("TITLE", &title),
            ("DATA", &script_json(data)?),
            ("MESH", mesh_base64),
            ("THREE", THREE_BUNDLE),
            ("VIEWER", VIEWER_JS),
        ],
    )
}

/// The viewer's cells of a tiled world from its `mesh-tiles/index.json`, in page axes.
fn tiles_ref(index: &Path) -> Result<TilesRef> {
    let bad = |what: &str| anyhow::anyhow!("{}: {what}", index.display());
    let json: serde_json::Value = serde_json::from_slice(
        &std::fs::read(index).with_context(|| format!("{}: cannot read the tiles' index", index.display()))?,
    )
    .with_context(|| format!("{}: not the tiles' index", index.display()))?;
    let super_m = json["super_block_m"].as_f64().ok_or_else(|| bad("no super_block_m"))? as f32;
    let v3 = |v: &serde_json::Value| -> Result<Vec3> {
        let a: Vec<f32> = v.as_array().into_iter().flatten().filter_map(|x| x.as_f64()).map(|x| x as f32).collect();
        match a.as_slice() {
            [x, y, z] => Ok(Vec3::new(*x, *y, *z)),
            _ => Err(bad("a cell's bounds are not 3 numbers")),
        }
    };
    let mut cells = Vec::new();
    for c in json["cells"].as_array().ok_or_else(|| bad("no cells"))? {
        let (lo, hi) = (sgam_io::world_to_gltf(v3(&c["min"])?), sgam_io::world_to_gltf(v3(&c["max"])?));
        let count = |k: &str| c[k].as_u64().map(|n| n as usize).ok_or_else(|| bad("a cell has no triangle range"));
        let files: Vec<String> =
            c["files"].as_array().into_iter().flatten().filter_map(|f| f.as_str().map(str::to_string)).collect();
        if files.iter().any(|f| crate::serve::request_path(&format!("/{f}")).is_none()) {
            return Err(bad("a tile's file name is not a plain name"));
        }
        cells.push(PageCell {
            min: lo.min(hi).to_array(),
            max: lo.max(hi).to_array(),
            first: count("first")?,
            count: count("count")?,
            files,
        });
    }
    Ok(TilesRef {
        dir: format!("{}/", crate::tiled::MESH_TILES_DIR),
        fine_within_m: 1.5 * super_m * crate::tiled::CELL_SUPERS as f32,
        max_fine_cells: 12,
        cells,
    })
}

/// Cameras of a run folder from its `transforms.json`, with their frames' relative paths.
pub fn run_cameras(dir: &Path) -> Result<(Vec<Camera>, Vec<String>)> {
    let path = dir.join("transforms.json");
    if !path.is_file() {
        bail!("{}: missing (is {} a finished `sgam generate` run?)", path.display(), dir.display());
    }
    let t = sgam_io::read_nerf_transforms(&path)?;
    let cams = (0..t.frames.len()).map(|i| Camera::new(t.frame_intrinsics(i), t.frames[i].world_from_camera)).collect();
    let frames = t.frames.iter().map(|f| f.file_path.clone()).collect();
    Ok((cams, frames))
}

fn frustum_every(n: usize) -> usize {
    n.div_ceil(MAX_FRUSTUMS).max(1)
}

fn run_name(dir: &Path) -> String {
    let abs = dir.canonicalize().unwrap_or_else(|_| dir.to_path_buf());
    abs.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "world".into())
}

fn intrinsics_of(cams: &[Camera]) -> PageIntrinsics {
    let k = cams.first().map(|c| c.intrinsics).unwrap_or_else(|| sgam_core::Intrinsics::from_fov_x(1, 1, 1.0));
    PageIntrinsics { width: k.width, height: k.height, fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy }
}

/// Writes `dir/world.html` (atomically) from the run's `mesh.glb`, `transforms.json` and
/// frames: the mesh is embedded when `mesh.glb` has at most `embed_limit_bytes` bytes, else the
/// page loads it from the neighbouring file (served by `sgam view --serve`).
pub fn write_world_html(dir: &Path, embed_limit_bytes: u64) -> Result<PageInfo> {
    let (cams, frames) = run_cameras(dir)?;
    let index = dir.join(crate::tiled::MESH_TILES_DIR).join(crate::tiled::INDEX_FILE);
    let (src, tiles) = if index.is_file() {
        (format!("{}/{}", crate::tiled::MESH_TILES_DIR, crate::tiled::COARSE_FILE), Some(tiles_ref(&index)?))
    } else {
        ("mesh.glb".to_string(), None)
    };
    let glb_path = dir.join(&src);
    let glb = std::fs::read(&glb_path).with_context(|| format!("{}: cannot read the mesh", glb_path.display()))?;
    let (vertices, triangles) = glb_counts(&glb_path, &glb)?;
    let embedded = glb.len() as u64 <= embed_limit_bytes;
    let every = frames.len().div_ceil(MAX_THUMBS).max(1);
    let rgb: Vec<String> = frames
        .par_iter()
        .enumerate()
        .map(|(i, f)| if i % every == 0 || i + 1 == frames.len() { thumbnail(&dir.join(f)) } else { Ok(String::new()) })
        .collect::<Result<_>>()?;
    let thumbs = Thumbs {
        rgb,
        guidance: optional_thumbs(dir, "guidance", cams.len())?,
        missing: optional_thumbs(dir, "missing", cams.len())?,
    };
    let data = PageData {
        format: 1,
        name: run_name(dir),
        three_from_world: three_from_world(),
        up_world: cams.first().map(up_world).unwrap_or(Vec3::Z).to_array(),
        intrinsics: intrinsics_of(&cams),
        poses: cams.iter().map(pose_rows).collect(),
        seed: 0,
        frames,
        thumbs,
        frustum_every: frustum_every(cams.len()),
        mesh: MeshRef { embedded, src, bytes: glb.len() as u64, vertices, triangles, version: 0 },
        tiles,
        live: None,
    };
    let mesh_b64 = if embedded { base64(&glb) } else { String::new() };
    drop(glb);
    let html = page_html(&data, &mesh_b64)?;
    let path = dir.join("world.html");
    sgam_io::write_atomic(&path, |w| std::io::Write::write_all(w, html.as_bytes()))?;
    Ok(PageInfo {
        path,
        bytes: html.len() as u64,
        mesh_embedded: embedded,
        mesh_bytes: data.mesh.bytes,
        vertices,
        frames: cams.len(),
    })
}

/// The live page (`sgam generate --view`): no mesh, no poses; it polls `live.json`.
pub fn live_page_html(name: &str, every_ms: u32) -> Result<String> {
    let data = PageData {
        format: 1,
        name: name.to_string(),
        three_from_world: three_from_world(),
        up_world: Vec3::Z.to_array(),
        intrinsics: intrinsics_of(&[]),
        poses: Vec::new(),
        seed: 0,
        frames: Vec::new(),
        thumbs: Thumbs::default(),
        frustum_every: 1,
        mesh: MeshRef { embedded: false, src: String::new(), bytes: 0, vertices: 0, triangles: 0, version: 0 },
        tiles: None,
        live: Some(LiveRef { state: "live.json".into(), every_ms }),
    };
    page_html(&data, "")
}

/// The live state the live page polls: poses and frames so far, and the mesh (`MeshRef`'s
/// fields, `src` with its version) once there is one.
#[derive(Debug, Serialize)]
pub struct LiveState {
    pub step: usize,
    pub total: usize,
    pub finished: bool,
    pub up_world: [f32; 3],
    pub poses: Vec<[f32; 12]>,
    pub frames: Vec<String>,
    pub mesh: Option<serde_json::Value>,
}

impl LiveState {
    /// The state after `step` of `total` with these keyframe cameras (no mesh yet).
    pub fn new(step: usize, total: usize, cameras: &[Camera]) -> Self {
        Self {
            step,
            total,
            finished: false,
            up_world: cameras.first().map(up_world).unwrap_or(Vec3::Z).to_array(),
            poses: cameras.iter().map(pose_rows).collect(),
            frames: (0..cameras.len()).map(|i| sgam_pipeline::frame_file_names(i).0).collect(),
            mesh: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sgam_core::{Intrinsics, Rigid3};

    #[test]
    fn a_cut_glb_is_refused_and_a_whole_one_counted() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("mesh.glb");
        let mesh = sgam_core::TriMesh {
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z],
            colours: Vec::new(),
            triangles: vec![[0, 1, 2], [0, 2, 3]],
        };
        sgam_io::write_glb(&path, &mesh).unwrap();
        let glb = std::fs::read(&path).unwrap();
        assert_eq!(glb_counts(&path, &glb).unwrap(), (4, 2));
        let err = glb_counts(&path, &glb[..glb.len() - 8]).unwrap_err().to_string();
        assert!(err.contains("mesh.glb") && err.contains("cut or damaged"), "{err}");
    }

    #[test]
    fn base64_matches_rfc_4648_vectors() {
        for (input, want) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(input.as_bytes()), want);
        }
        assert_eq!(base64(&[0xff, 0xfe, 0x00]), "//4A");
    }

    #[test]
    fn the_page_rotation_is_the_glb_writers() {
        let r = three_from_world();
        let m = Mat3::from_cols_array(&r).transpose(); // row-major numbers
        for p in [Vec3::new(0.25, -0.5, 2.0), Vec3::new(-20.0, 3.0, -11.7), Vec3::X, Vec3::Z] {
            assert!((m * p - sgam_io::world_to_gltf(p)).length() < 1e-6, "{p}");
        }
        // world +z (up) is glTF / three +y (up)
        assert!((m * Vec3::Z - Vec3::Y).length() < 1e-6);
    }

    #[test]
    fn up_is_z_for_synthetic_seeds_and_image_up_for_rgb_seeds() {
        let synthetic = sgam_pipeline::synthetic_seed_camera(32);
        assert_eq!(up_world(&synthetic), Vec3::Z);
        let rgb_seed = Camera::new(Intrinsics::from_fov_x(32, 32, 1.0), Rigid3::IDENTITY);
        assert_eq!(up_world(&rgb_seed), Vec3::NEG_Y);
    }

    #[test]
    fn templates_fill_once_and_refuse_unknown_keys() {
        let t = fill_template("a{{X}}b{{Y}}c", &[("X", "{{Y}}"), ("Y", "2")]).unwrap();
        assert_eq!(t, "a{{Y}}b2c");
        assert!(fill_template("{{Z}}", &[]).is_err());
        assert!(fill_template("{{Z", &[("Z", "")]).is_err());
    }

    #[test]
    fn page_parts_cannot_close_their_script_elements() {
        for (name, text) in [("three bundle", THREE_BUNDLE), ("viewer.js", VIEWER_JS)] {
            let lower = text.to_ascii_lowercase();
            assert!(!lower.contains("</script") && !lower.contains("<!--"), "{name} would end its <script> early");
        }
        let json = script_json(&serde_json::json!({"name": "</script><b>"})).unwrap();
        assert!(!json.contains('<'));
        assert_eq!(serde_json::from_str::<serde_json::Value>(&json).unwrap()["name"], "</script><b>");
    }
}
