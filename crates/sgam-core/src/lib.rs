//! Core types shared by every sgam-rs crate. This crate touches no files.
//!
//! # Concepts
//! - **Camera axes are OpenCV**: x right, y down, z forward. A camera pose is a
//!   [`Rigid3`] named `world_from_camera` (camera-to-world); transforms are named `a_from_b`
//!   and applied right to left: `p_world = world_from_camera.transform_point(p_camera)`.
//! - **Pixels**: integer pixel `(u, v)` = (column, row); its centre is at continuous
//!   `(u, v)` in the intrinsics' frame (OpenCV). [`Intrinsics`] holds `fx, fy, cx, cy` in pixels.
//! - **Depth** is planar z in metres, `f32`; `0`, negative or non-finite means invalid
//!   ([`is_valid_depth`]).
//! - **Colour** is sRGB as stored in 8-bit images, as `f32` in `[0, 1]`.
//! - Images are row-major `[H, W]` ([`Image`]); an [`RgbdFrame`] pairs colour and depth.
//! - The pipeline is generic over the [`Refiner`] trait: incomplete RGB-D + missing mask in,
//!   complete RGB-D out.

mod camera;
mod colour;
pub mod edges;
mod error;
pub mod freespace;
pub mod ground;
mod image;
mod mesh;
mod refiner;
mod rigid;
pub mod solid;
pub mod trajectory;

pub use camera::{Camera, Intrinsics};
pub use colour::{linear_to_srgb, srgb_to_linear};
pub use error::CoreError;
pub use image::{is_valid_depth, Image, RgbdFrame};
pub use mesh::TriMesh;
pub use refiner::{Guidance, Refiner};
pub use rigid::Rigid3;

pub use glam::{Mat3, Mat4, Vec2, Vec3};
