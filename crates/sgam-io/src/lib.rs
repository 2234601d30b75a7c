//! sgam-io: every file format of sgam-rs. No algorithms live here.
//!
//! # Concepts
//! - **Convert once, at the file boundary.** Readers return planar depth in metres (`f32`,
//!   `0` = invalid), sRGB colour as `f32` in `[0, 1]`, poses as OpenCV `world_from_camera`
//!   ([`sgam_core::Rigid3`]) and pinhole [`sgam_core::Intrinsics`] whose pixel `(u, v)` centre is at
//!   `(u, v)`. Blender / OpenGL / NeRF camera-to-world matrices are converted with
//!   [`sgam_core::Rigid3::from_opengl_camera`]; ray-length depth is converted to planar depth.
//! - **Formats**: 8-bit colour PNG/JPEG ([`read_rgb`], [`write_rgb_png`]); 16-bit millimetre depth
//!   PNG ([`read_depth_png_mm`], 0 and 65535 invalid); NumPy `.npy` ([`read_npy_f32`],
//!   [`read_npy_matrix`]); pose text files, TUM and KITTI trajectories ([`read_pose_txt`],
//!   [`read_tum_trajectory`], [`read_kitti_trajectory`]); meshes as PLY, OBJ and GLB
//!   ([`write_ply`], [`read_ply`], [`write_obj`], [`write_glb`]).
//! - **Sequences** ([`Sequence`]): 7-Scenes/3DMatch folders, the SGAM authors' CLEVR-Infinite
//!   scenes and NeRF-style `transforms.json` (our export format) behind one lazy reader
//!   ([`Sequence::open`] detects the [`Layout`]; frames are read on demand).
//! - **Seeds** ([`SeedImage`]): any RGB + depth + intrinsics, the authors' CLEVR template and
//!   Google Earth seeds.
//! - **Every writer is atomic** ([`write_atomic`]: temporary file in the same folder, fsync,
//!   rename), and **every error names the file** and the problem ([`IoError`]); bad input never
//!   panics.

mod atomic;
mod clevr;
mod depth;
mod error;
mod h264mp4;
mod images;
mod mesh;
mod nerf;
mod npy;
mod poses;
mod seeds;
mod sequence;
mod snapshot;

pub use atomic::write_atomic;
pub use clevr::{
    clevr_colour_path, clevr_depth_path, read_clevr_transforms, write_clevr_frame, write_clevr_transforms,
    ClevrFrameMeta, ClevrTransforms,
};
pub use depth::{
    planar_to_ray_length_image, ray_length_to_planar_image, read_depth_any, require_some_valid, sanitize_float_depth,
    DepthType, NPY_DEPTH_INVALID_MIN,
};
pub use error::IoError;
pub use h264mp4::{split_annex_b, write_h264_mp4};
pub use images::{
    depth_to_mm, image_size, read_depth_png_mm, read_depth_png_scaled, read_rgb, to_srgb8, write_depth_png_mm,
    write_rgb_png, DEPTH_PNG_INVALID_MAX, DEPTH_PNG_MAX_MM,
};
pub use mesh::{glb_counts, read_ply, world_to_gltf, write_glb, write_mesh, write_obj, write_ply};
pub use nerf::{read_nerf_transforms, write_nerf_transforms, NerfFrame, NerfTransforms};
pub use npy::{read_npy_f32, read_npy_matrix, write_npy_f32, write_npy_f64};
pub use poses::{
    intrinsics_from_k, read_intrinsics_txt, read_kitti_trajectory, read_pose_txt, read_tum_trajectory,
    read_tum_trajectory_timed, write_kitti_trajectory, write_pose_txt, write_tum_trajectory,
};
pub use seeds::{read_clevr_template, read_google_earth_seed, read_seed_rgbd, SeedImage, GOOGLE_EARTH_FOCAL_PX_AT_512};
pub use sequence::{detect_layout, Layout, Sequence};
/// The sRGB transfer (glTF vertex colours are linear); defined in `sgam-core`.
pub use sgam_core::srgb_to_linear;
pub use snapshot::{
    encode_snapshot, parse_snapshot, read_snapshot, write_snapshot, write_snapshot_with, SNAPSHOT_MAGIC,
};
