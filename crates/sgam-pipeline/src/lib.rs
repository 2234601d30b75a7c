//! sgam-pipeline: the SGAM loop as a library — grow a world from one RGB-D frame by repeating
//! generative sensing (render the map, complete it with a refiner) and mapping (fuse, re-mesh).
//! The `sgam` binary parses arguments and formats output around it; a Rust program can embed
//! the same generator.
//!
//! # Concepts
//! - **[`WorldGenerator`]**: the orchestrator; [`WorldGenerator::step`] is the recipe of one
//!   step (sources, guidance, refine, integrate, re-mesh, keep). Generic over the
//!   [`sgam_core::Refiner`].
//! - **Guidance** ([`render_guidance`]): the map's mesh rasterized to depth at the target camera,
//!   colour inverse-warped from source keyframes with a geometry check. The one function that
//!   generation, the training pairs ([`SynthPairs`], [`codepairs`]) and the evaluation call, with
//!   the one CLEVR preset [`clevr_generator_config`].
//! - **[`Keyframes`]**: generated frames; cameras in RAM in a spatial grid, pixels paged to the
//!   run folder (`rgb/NNNNN.png`, `depth/NNNNN.npy`) behind a small LRU cache.
//! - **Pose sources** ([`PoseSource`]): precomputed trajectories ([`PrecomputedPoses`], from a
//!   [`TrajectorySpec`]) and the [`GreedyPlanner`], which picks each next pose from the map.
//! - **Refiners**: [`build_refiner`] turns a [`RefinerSpec`] into the learned model or a stand-in
//!   ([`NullRefiner`]: push-pull hole filling; [`OracleRefiner`]: ground truth of the synthetic
//!   world), so the whole loop runs in tests without weights.
//! - **Runs** ([`run::generate`]): a resolved, versioned [`RunConfig`] (seed, trajectory,
//!   refiner, map, outputs), snapshots ([`snapshot`]) for resuming with identical results, and a
//!   [`RunObserver`] for the caller's progress display and per-step outputs.
//! - Conventions follow `sgam-core`: OpenCV camera axes, `world_from_camera` poses, planar depth
//!   in metres, sRGB colour in `[0, 1]`; every random draw comes from a seed passed in.

pub mod adapt;
pub mod bank;
pub mod codepairs;
mod config;
mod error;
mod generator;
mod greedy;
pub mod guidance_view;
mod keyframes;
mod pairs;
mod poses;
mod refiners;
pub mod roundtrip;
pub mod run;
mod seeds;
pub mod settings;
pub mod snapshot;
pub mod tiles;

pub use bank::BankSpec;
pub use config::{OutputSettings, RunConfig, MAX_GRID, MAX_RES, MAX_STEPS, RUN_CONFIG_VERSION};
pub use error::{PipelineError, Result};
pub use generator::{clevr_generator_config, render_guidance, GeneratorConfig, StepTimings, WorldGenerator};
pub use greedy::GreedyPlanner;
pub use keyframes::{frame_file_names, quantise_colour, Keyframes};
pub use pairs::SynthPairs;
pub use poses::{read_pose_file, PoseSource, PrecomputedPoses, TrajectorySpec, MAX_EXTENT_M};
pub use refiners::{
    build_refiner, model_refiner, push_pull_fill, sampling, seed_reconstruction_psnr, AnyRefiner, NullRefiner,
    OracleRefiner, RefinerSpec, BUNDLED_BANK, BUNDLED_MODEL, DOMAIN_PSNR_DB,
};
pub use run::{Generated, Quiet, Resume, RunObserver};
pub use seeds::{
    check_intrinsics, synthetic_seed_camera, Preset, Seed, SeedSpec, CLEVR, GOOGLE_EARTH, HELD_OUT_SEED_BASE, RGBD,
};
pub use settings::RunSettings;
pub use snapshot::save_map;
