//! Metrics of the SGAM paper (image quality, geometry, scene- and world-level statistics). Pure
//! functions; no I/O.
//!
//! # Concepts
//! - Image metrics take `sgam_core::Image<[f32; 3]>` colour in `[0, 1]` and an optional pixel
//!   mask (`true` = counted). PSNR is on the 8-bit scale (values quantised to 8 bits first, as
//!   when comparing saved PNGs). SSIM is the Gaussian-window SSIM of Wang et al. (11x11,
//!   sigma 1.5, K1 0.01, K2 0.03, dynamic range 1), averaged over channels and (masked) pixels.
//! - Geometry metrics take point sets in metres: [`point_to_mesh_distances`] (exact
//!   point-to-triangle distance through a uniform grid), [`chamfer`].
//! - Scene metrics ([`scene`]) compare sets of regions (occupancy histograms) with the
//!   point-cloud GAN metrics of Achlioptas et al.: JSD, MMD, COV, MinDist, 1-NNA.
//! - World metrics ([`world`]) read a whole generated mesh (z up) as a 10 cm height field and
//!   report, outside the seed's footprint, objects per 100 m^2, their footprints and colour
//!   saturation, their shape (solidity against the convex hull, elongation, the compact share),
//!   and ground roughness.
//! - [`kid`]: kernel inception distance on any feature vectors (weight-free when the features
//!   come from our own encoder).
//! - [`noref`]: no-reference checks of a world grown from a real seed: the new area's look
//!   against the seed's, and geometry floating outside the seed's heights.

mod geometry;
mod image;
pub mod kid;
pub mod noref;
pub mod scene;
pub mod world;

pub use geometry::{chamfer, median, point_to_mesh_distances, Sortable};
pub use image::{disparity_l1, psnr, psnr_db, ssim, ssim_map};
