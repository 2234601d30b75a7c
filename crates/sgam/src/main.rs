//! `sgam`: grow a large, consistent, textured 3D world from one RGB-D image (SGAM, NeurIPS 2022).
//!
//! The binary holds the CLI and the pipeline orchestrator; every algorithm lives in the library
//! crates (`sgam-map`, `sgam-synth`, `sgam-model`, `sgam-metrics`, `sgam-io`).

mod bench;
mod codepairs;
mod convert;
mod eval;
mod eval_table;
mod eval_world;
mod fuse;
mod generate;
mod generator;
mod greedy;
mod keyframes;
mod overview;
mod pairs;
mod progress;
mod refiners;
mod synth;
mod train;
mod train_sampler;

use clap::{Parser, Subcommand};

/// SGAM: Simultaneous Generation And Mapping.
///
/// Grow a 3D world step by step along a camera trajectory: render the map at the next camera,
/// complete the incomplete RGB-D image with a VQ model, fuse it into a TSDF map, re-mesh.
/// Start with `sgam generate` (no arguments needed: bundled model, synthetic seed).
#[derive(Debug, Parser)]
#[command(name = "sgam", version, about, long_about = None, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Grow a world from a seed RGB-D frame along a trajectory (the SGAM loop).
    Generate(Box<generate::GenerateArgs>),
    /// Fuse a real RGB-D sequence (7-Scenes/3DMatch, CLEVR-Infinite, NeRF transforms.json) into a
    /// coloured mesh with the TSDF map.
    Fuse(fuse::FuseArgs),
    /// Render the procedural CLEVR-Infinite dataset in the SGAM authors' layout.
    Synth(synth::SynthArgs),
    /// Time a hot path on a built-in synthetic scene and print one JSON line.
    Bench(bench::BenchArgs),
    /// Train the VQ model on the synthetic world (stage 1: autoencoder, stage 2: completion).
    #[command(subcommand)]
    Train(train::TrainCommand),
    /// Measure results (one-step completion quality, mesh-to-mesh distances).
    #[command(subcommand)]
    Eval(eval::EvalCommand),
    /// Import the SGAM authors' PyTorch Lightning checkpoint (`last.ckpt`) as a safetensors model.
    ConvertCheckpoint(convert::ConvertArgs),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Generate(a) => generate::run(*a),
        Command::Fuse(a) => fuse::run(a),
        Command::Synth(a) => synth::run(a),
        Command::Bench(a) => bench::run(a),
        Command::Eval(c) => eval::run(c),
        Command::Train(c) => train::run(c),
        Command::ConvertCheckpoint(a) => convert::run(a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
