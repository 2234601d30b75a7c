//! The SGAM map: a voxel-hashed colour TSDF with incremental marching cubes, a z-buffered mesh
//! rasterizer, a TSDF ray-cast, inverse colour warping with a geometry check, and versioned
//! binary persistence. No file paths here: persistence reads/writes `std::io` streams.
//!
//! # Concepts
//! - **Voxel grid**: global voxel `g` (integer, world axes) is centred at
//!   `(g + 0.5) * voxel_size_m`. Voxels live in dense 8^3 [`Block`]s kept in a hash map keyed by
//!   block coordinates (`g.div_euclid(8)`); only blocks near observed surfaces exist.
//! - **TSDF**: each voxel stores the truncated signed distance normalised to `[-1, 1]`
//!   (positive = free space in front of the surface), a weight (number of observations, 0 =
//!   unknown) and an sRGB colour. [`TsdfMap::integrate`] applies the paper's running average
//!   `M = (w M + O) / (w + 1), w += 1` with the *planar* signed distance `depth - z`.
//! - **Meshes**: each block caches the marching-cubes mesh of the cells whose lowest corner it
//!   holds; integration marks blocks dirty and [`TsdfMap::update_mesh`] re-meshes only dirty
//!   blocks and their lower neighbours. Vertices are identified by their global grid edge, so
//!   block meshes weld into a crack-free world mesh ([`TsdfMap::extract_mesh`]). Triangles wind
//!   counter-clockwise seen from free space.
//! - **Guidance**: [`TsdfMap::remesh_and_rasterize`] rasterizes the block meshes in the camera frustum
//!   (planar depth, colour, coverage); [`TsdfMap::ray_cast`] marches the TSDF instead.
//!   [`warp_colour`] fills colour from source keyframes, accepting a source only where its own
//!   depth, sampled at the projected location, agrees with the target depth.
//! - Cameras follow `sgam-core`: OpenCV axes, `world_from_camera` poses, planar depth in metres.
//! - **Cost**: integration, re-meshing and rendering visit the blocks of one frame / frustum,
//!   never the whole map, so a step costs the same after 10,000 steps.

mod allocate;
mod block;
mod config;
mod error;
mod layer;
mod map;
mod mc_table;
mod mesh;
mod persist;
mod render;
mod solid;
mod stream;
mod warp;

pub use block::{Block, Voxel, BLOCK_SIZE, BLOCK_VOXELS};
pub use config::{TsdfConfig, MAX_DEPTH_M, MAX_TRUNC_VOXELS, MAX_VOXEL_M, MIN_VOXEL_M};
pub use error::MapError;
pub use map::{IntegrateStats, TsdfMap};
pub use render::Rendered;
pub use stream::{blocks_mesh, read_tile, super_block_of, write_tile, EvictedBlock, ViewReach};
pub use warp::{warp_colour, SourceSelection, SourceView, WarpConfig, Warped};
