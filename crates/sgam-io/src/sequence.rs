//! RGB-D sequence folders: layout detection and a lazy frame reader.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use sgam_core::{Camera, Image, Intrinsics, RgbdFrame};

use crate::clevr::{read_clevr_transforms, ClevrTransforms};
use crate::depth::{ray_length_to_planar_image, require_some_valid, sanitize_float_depth, DepthType};
use crate::images::{image_size, read_depth_png_scaled, read_rgb};
use crate::nerf::{read_nerf_transforms, resolve_colour_path};
use crate::poses::{read_intrinsics_txt, read_pose_txt};
use crate::IoError;

/// The sequence layouts [`Sequence::open`] understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// 7-Scenes / 3DMatch: `frame-NNNNNN.color.png|.color.jpg`, `frame-NNNNNN.depth.png`
    /// (uint16 mm, 0 and 65535 invalid), `frame-NNNNNN.pose.txt` (4x4 camera-to-world, OpenCV),
    /// `camera-intrinsics.txt` (3x3 K) in the frames' folder or a parent; frames directly in the
    /// folder, under `rgbd-frames/`, or under a single `seq-NN/`.
    SevenScenes,
    /// The SGAM authors' CLEVR-Infinite scene (see [`crate::read_clevr_transforms`]); frames
    /// whose `im_NNNNN.png` is missing are not part of the sequence.
    ClevrAuthors,
    /// A NeRF / nerfstudio / instant-ngp `transforms.json` with per-frame depth paths (our
    /// export format, see [`crate::write_nerf_transforms`]).
    NerfTransforms,
}

const LOOKED_FOR: &str = "transforms.json (CLEVR-Infinite or NeRF style), or frame-NNNNNN.depth.png + \
    frame-NNNNNN.pose.txt + camera-intrinsics.txt (7-Scenes/3DMatch) in the folder, in rgbd-frames/ or in seq-NN/";

/// How a frame's depth file is stored.
#[derive(Debug, Clone, Copy, PartialEq)]
enum DepthEncoding {
    /// 16-bit PNG, metres per unit (0 and 65535 invalid).
    Png(f64),
    /// Float NPY of planar metres.
    NpyPlanar,
    /// Float NPY of ray length in metres.
    NpyRayLength,
}

#[derive(Debug, Clone)]
struct FrameEntry {
    name: String,
    colour_path: PathBuf,
    depth_path: PathBuf,
    depth: DepthEncoding,
    camera: Camera,
}

/// A lazily read RGB-D sequence: cameras are indexed when opening, images are read by
/// [`Sequence::read_frame`] (so long sequences do not fill memory).
#[derive(Debug, Clone)]
pub struct Sequence {
    /// The detected layout.
    pub layout: Layout,
    /// The folder holding the frames (or the `transforms.json`'s folder).
    pub root: PathBuf,
    frames: Vec<FrameEntry>,
}

fn list_dir(dir: &Path) -> Result<Vec<String>, IoError> {
    let mut names = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| IoError::io(dir, e))? {
        let entry = entry.map_err(|e| IoError::io(dir, e))?;
        names.push(entry.file_name().to_string_lossy().into_owned());
    }
    names.sort();
    Ok(names)
}

/// `frame-000150.depth.png` -> `(150, "frame-000150")`.
fn seven_scenes_frame(name: &str) -> Option<(u64, &str)> {
    let stem = name.strip_suffix(".depth.png")?;
    let digits = stem.strip_prefix("frame-")?;
    Some((digits.parse().ok()?, stem))
}

/// The folder holding 7-Scenes frames below `dir`, if any.
fn seven_scenes_frame_dir(dir: &Path) -> Result<Option<PathBuf>, IoError> {
    let has_frames = |d: &Path| -> Result<bool, IoError> {
        Ok(d.is_dir() && list_dir(d)?.iter().any(|n| seven_scenes_frame(n).is_some()))
    };
    if has_frames(dir)? {
        return Ok(Some(dir.to_path_buf()));
    }
    let rgbd = dir.join("rgbd-frames");
    if has_frames(&rgbd)? {
        return Ok(Some(rgbd));
    }
    let mut seqs = Vec::new();
    for name in list_dir(dir)? {
        let p = dir.join(&name);
        if name.starts_with("seq-") && has_frames(&p)? {
            seqs.push(p);
        }
    }
    match seqs.len() {
        0 => Ok(None),
        1 => Ok(seqs.pop()),
        _ => Err(IoError::invalid(
            dir,
            format!(
                "several sequences ({}); open one of them",
                seqs.iter().filter_map(|p| p.file_name()).map(|n| n.to_string_lossy()).collect::<Vec<_>>().join(", ")
            ),
        )),
    }
}

/// Classifies a `transforms.json`: NeRF style when it has pinhole keys (`fl_x`, `w`,
/// `camera_model`) or per-frame depth paths; CLEVR-Infinite when it has `camera_angle_x` and
/// `grid_i` keys or `im_*.png` files beside it; otherwise a `camera_angle_x`-only file is a NeRF
/// (Blender) dataset.
fn classify_transforms(path: &Path) -> Result<Layout, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, e))?;
    let v: serde_json::Value =
        serde_json::from_slice(&bytes).map_err(|e| IoError::format(path, format!("malformed JSON: {e}")))?;
    let obj = v.as_object().ok_or_else(|| IoError::format(path, "expected a JSON object"))?;
    let frames =
        obj.get("frames").and_then(|f| f.as_array()).ok_or_else(|| IoError::format(path, "no \"frames\" array"))?;
    let nerf_keys = ["fl_x", "w", "camera_model"].iter().any(|k| obj.contains_key(*k));
    let depth_paths = frames.iter().any(|f| f.get("depth_file_path").is_some() || f.get("depth_path").is_some());
    let grid_keys = frames.iter().any(|f| f.get("grid_i").is_some());
    let clevr_images = || -> Result<bool, IoError> {
        let dir = path.parent().unwrap_or(Path::new("."));
        Ok(list_dir(dir)?.iter().any(|n| n.starts_with("im_") && n.ends_with(".png")))
    };
    if nerf_keys || depth_paths {
        Ok(Layout::NerfTransforms)
    } else if obj.contains_key("camera_angle_x") && (grid_keys || frames.is_empty() || clevr_images()?) {
        Ok(Layout::ClevrAuthors)
    } else if obj.contains_key("camera_angle_x") {
        // A NeRF (Blender) dataset without depth paths: reported as such by the NeRF reader.
        Ok(Layout::NerfTransforms)
    } else {
        Err(IoError::format(
            path,
            "neither a NeRF-style (fl_x/w/h or depth paths) nor a CLEVR-Infinite (camera_angle_x) transforms.json",
        ))
    }
}

/// The json file of a transforms layout given a folder or the json itself.
fn transforms_path(dir: &Path) -> Option<PathBuf> {
    if dir.is_file() && dir.extension().is_some_and(|e| e == "json") {
        return Some(dir.to_path_buf());
    }
    let p = dir.join("transforms.json");
    p.is_file().then_some(p)
}

/// Detects the layout of a sequence folder (or of a `transforms.json` file).
pub fn detect_layout(dir: &Path) -> Result<Layout, IoError> {
    if let Some(json) = transforms_path(dir) {
        return classify_transforms(&json);
    }
    if !dir.is_dir() {
        return Err(IoError::io(
            dir,
            std::io::Error::new(std::io::ErrorKind::NotFound, "not a folder or transforms.json"),
        ));
    }
    if seven_scenes_frame_dir(dir)?.is_some() {
        return Ok(Layout::SevenScenes);
    }
    Err(IoError::UnknownLayout { path: dir.to_path_buf(), looked_for: LOOKED_FOR.into() })
}

fn missing(path: PathBuf, what: &str) -> IoError {
    IoError::Io { path, source: std::io::Error::new(std::io::ErrorKind::NotFound, what.to_string()) }
}

impl Sequence {
    /// Detects the layout and indexes the frames (sorted by frame number). Poses and intrinsics
    /// are read and checked here; images are read later by [`Sequence::read_frame`].
    /// A sequence without frames is an error.
    pub fn open(dir: &Path) -> Result<Sequence, IoError> {
        let layout = detect_layout(dir)?;
        let seq = match layout {
            Layout::SevenScenes => Self::open_seven_scenes(dir)?,
            Layout::ClevrAuthors => Self::open_clevr(dir)?,
            Layout::NerfTransforms => Self::open_nerf(dir)?,
        };
        if seq.frames.is_empty() {
            return Err(IoError::EmptySequence {
                path: dir.to_path_buf(),
                msg: format!("no frame with colour and depth files ({layout:?} layout)"),
            });
        }
        Ok(seq)
    }

    fn open_seven_scenes(dir: &Path) -> Result<Sequence, IoError> {
        let root = seven_scenes_frame_dir(dir)?.unwrap_or_else(|| dir.to_path_buf());
        let names = list_dir(&root)?;
        let mut numbered: Vec<(u64, String)> =
            names.iter().filter_map(|n| seven_scenes_frame(n)).map(|(i, s)| (i, s.to_string())).collect();
        numbered.sort();
        if numbered.is_empty() {
            return Err(IoError::EmptySequence { path: root, msg: "no frame-NNNNNN.depth.png".into() });
        }
        // a frame with a pose but no depth image is an error, as a frame without a pose is (it
        // used to drop out of the sequence without a word)
        for name in &names {
            if let Some(stem) = name.strip_suffix(".pose.txt").filter(|s| s.starts_with("frame-")) {
                if !root.join(format!("{stem}.depth.png")).is_file() {
                    return Err(missing(
                        root.join(format!("{stem}.depth.png")),
                        "missing depth image (its pose is there)",
                    ));
                }
            }
        }
        let candidates: Vec<PathBuf> = [Some(root.as_path()), root.parent(), Some(dir)]
            .into_iter()
            .flatten()
            .map(|d| d.join("camera-intrinsics.txt"))
            .collect();
        let k_path =
            candidates.iter().find(|p| p.is_file()).cloned().ok_or_else(|| {
                missing(root.join("camera-intrinsics.txt"), "missing (also looked in the parent folder)")
            })?;
        let first_depth = root.join(format!("{}.depth.png", numbered[0].1));
        let (w, h) = image_size(&first_depth)?;
        let intrinsics = read_intrinsics_txt(&k_path, w, h)?;
        let mut frames = Vec::with_capacity(numbered.len());
        for (_, stem) in numbered {
            let depth_path = root.join(format!("{stem}.depth.png"));
            let colour_path = ["color.png", "color.jpg"]
                .iter()
                .map(|ext| root.join(format!("{stem}.{ext}")))
                .find(|p| p.is_file())
                .ok_or_else(|| {
                    missing(
                        root.join(format!("{stem}.color.png")),
                        "missing colour image (looked for .color.png and .color.jpg)",
                    )
                })?;
            let pose_path = root.join(format!("{stem}.pose.txt"));
            let world_from_camera = read_pose_txt(&pose_path)?;
            frames.push(FrameEntry {
                name: stem,
                colour_path,
                depth_path,
                depth: DepthEncoding::Png(1e-3),
                camera: Camera::new(intrinsics, world_from_camera),
            });
        }
        Ok(Sequence { layout: Layout::SevenScenes, root, frames })
    }

    fn open_clevr(dir: &Path) -> Result<Sequence, IoError> {
        let json_path = transforms_path(dir).unwrap_or_else(|| dir.join("transforms.json"));
        let root = json_path.parent().unwrap_or(Path::new(".")).to_path_buf();
        let transforms: ClevrTransforms = read_clevr_transforms(&json_path)?;
        let names = list_dir(&root)?;
        // index -> depth file names, from one listing (the authors' template names its depth
        // `dm_00000_00_00.npy`).
        let mut depth_files: BTreeMap<u32, Vec<&str>> = BTreeMap::new();
        for n in &names {
            if let Some(rest) = n.strip_prefix("dm_").filter(|_| n.ends_with(".npy")) {
                let digits: String = rest.chars().take_while(|c| c.is_ascii_digit()).collect();
                let after = &rest[digits.len()..];
                if let (Ok(i), true) = (digits.parse::<u32>(), after == ".npy" || after.starts_with('_')) {
                    depth_files.entry(i).or_default().push(n);
                }
            }
        }
        let has_name: std::collections::BTreeSet<&str> = names.iter().map(String::as_str).collect();
        let depth_encoding = match transforms.effective_depth_type() {
            DepthType::RayLength => DepthEncoding::NpyRayLength,
            DepthType::Planar => DepthEncoding::NpyPlanar,
        };
        let mut intrinsics: Option<Intrinsics> = None;
        let mut frames = Vec::new();
        let mut metas: Vec<_> = transforms.frames.iter().collect();
        metas.sort_by_key(|m| m.index);
        for meta in metas {
            let colour_name = format!("im_{:05}.png", meta.index);
            if !has_name.contains(colour_name.as_str()) {
                continue;
            }
            let colour_path = root.join(&colour_name);
            let exact = format!("dm_{:05}.npy", meta.index);
            let depth_name = match depth_files.get(&meta.index) {
                Some(list) if list.contains(&exact.as_str()) => exact,
                Some(list) if !list.is_empty() => list[0].to_string(),
                _ => {
                    return Err(missing(
                        root.join(&exact),
                        "missing depth for an existing colour image (looked for dm_NNNNN.npy and dm_NNNNN_*.npy)",
                    ))
                }
            };
            let k = match intrinsics {
                Some(k) => k,
                None => {
                    let (w, h) = image_size(&colour_path)?;
                    let k = transforms.intrinsics(w, h);
                    intrinsics = Some(k);
                    k
                }
            };
            frames.push(FrameEntry {
                name: format!("{:05}", meta.index),
                colour_path,
                depth_path: root.join(depth_name),
                depth: depth_encoding,
                camera: Camera::new(k, meta.world_from_camera),
            });
        }
        Ok(Sequence { layout: Layout::ClevrAuthors, root, frames })
    }

    fn open_nerf(dir: &Path) -> Result<Sequence, IoError> {
        let json_path = transforms_path(dir).unwrap_or_else(|| dir.join("transforms.json"));
        let root = json_path.parent().unwrap_or(Path::new(".")).to_path_buf();
        let t = read_nerf_transforms(&json_path)?;
        let mut frames = Vec::with_capacity(t.frames.len());
        for (i, f) in t.frames.iter().enumerate() {
            let depth_rel = f.depth_file_path.as_ref().ok_or_else(|| {
                IoError::invalid(&json_path, format!("frames[{i}] ({}) has no depth_file_path", f.file_path))
            })?;
            let depth_path = root.join(depth_rel);
            let depth = match crate::depth::extension(&depth_path).as_deref() {
                Some("png") => DepthEncoding::Png(t.depth_png_metres_per_unit),
                Some("npy") => DepthEncoding::NpyPlanar,
                _ => return Err(IoError::format(&depth_path, "unsupported depth file type (expected .png or .npy)")),
            };
            let colour_path = resolve_colour_path(&root, &f.file_path);
            let name =
                colour_path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| format!("{i:05}"));
            frames.push(FrameEntry {
                name,
                colour_path,
                depth_path,
                depth,
                camera: Camera::new(t.frame_intrinsics(i), f.world_from_camera),
            });
        }
        Ok(Sequence { layout: Layout::NerfTransforms, root, frames })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// True when there is no frame (never for an opened sequence).
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Intrinsics and `world_from_camera` (OpenCV) of frame `i`. Panics when `i >= len()`
    /// (a caller bug, not bad input); see [`Sequence::get_camera`].
    pub fn camera(&self, i: usize) -> Camera {
        self.frames[i].camera
    }

    /// Like [`Sequence::camera`], `None` out of range.
    pub fn get_camera(&self, i: usize) -> Option<Camera> {
        self.frames.get(i).map(|f| f.camera)
    }

    /// Name of frame `i` (`frame-000150`, `00012`, or the NeRF colour file's stem); empty out of
    /// range.
    pub fn frame_name(&self, i: usize) -> String {
        self.frames.get(i).map(|f| f.name.clone()).unwrap_or_default()
    }

    /// `(colour, depth)` file paths of frame `i`.
    pub fn frame_paths(&self, i: usize) -> Option<(&Path, &Path)> {
        self.frames.get(i).map(|f| (f.colour_path.as_path(), f.depth_path.as_path()))
    }

    /// Reads frame `i`: colour in `[0, 1]` and planar depth in metres.
    ///
    /// Checks: colour and depth sizes match each other and the intrinsics (errors name both
    /// files); depth PNG 0/65535 are invalid; float depth (NPY) NaN/inf/0/`>= 65504` are
    /// legitimate "no measurement" encodings (e.g. CLEVR sky) and become invalid, negative values
    /// are errors; ray length is converted to planar depth; a frame with no valid depth pixel is
    /// an error.
    pub fn read_frame(&self, i: usize) -> Result<RgbdFrame, IoError> {
        let f = self.frames.get(i).ok_or_else(|| {
            IoError::invalid(&self.root, format!("frame index {i} out of range (the sequence has {})", self.len()))
        })?;
        // The two images decode in parallel (a colour error is reported first).
        let (colour, depth) = rayon::join(
            || read_rgb(&f.colour_path),
            || match f.depth {
                DepthEncoding::Png(scale) => read_depth_png_scaled(&f.depth_path, scale),
                DepthEncoding::NpyPlanar | DepthEncoding::NpyRayLength => {
                    let mut d = crate::read_npy_f32(&f.depth_path)?;
                    sanitize_float_depth(&f.depth_path, &mut d)?;
                    Ok(d)
                }
            },
        );
        let (colour, mut depth): (_, Image<f32>) = (colour?, depth?);
        if colour.size() != depth.size() {
            return Err(IoError::invalid(
                &f.depth_path,
                format!(
                    "depth is {}x{} but colour {} is {}x{}",
                    depth.width,
                    depth.height,
                    f.colour_path.display(),
                    colour.width,
                    colour.height
                ),
            ));
        }
        let k = &f.camera.intrinsics;
        if (k.width, k.height) != colour.size() {
            return Err(IoError::invalid(
                &f.colour_path,
                format!(
                    "image is {}x{} but the sequence's intrinsics are for {}x{}",
                    colour.width, colour.height, k.width, k.height
                ),
            ));
        }
        if f.depth == DepthEncoding::NpyRayLength {
            ray_length_to_planar_image(&mut depth, k);
        }
        require_some_valid(&f.depth_path, &depth)?;
        Ok(RgbdFrame { colour, depth_m: depth })
    }
}
