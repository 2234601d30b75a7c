//! `sgam`: grow a large, consistent, textured 3D world from one RGB-D image (SGAM, NeurIPS 2022).
//!
//! The binary holds the CLI: argument parsing, progress display and output formatting. The loop
//! lives in `sgam-pipeline`, every algorithm in the library crates (`sgam-map`, `sgam-synth`,
//! `sgam-model`, `sgam-metrics`, `sgam-io`).

mod bench;
mod caption;
mod convert;
mod eval;
mod eval_grow;
mod eval_report;
mod eval_seed;
mod eval_table;
mod eval_trajectories;
mod eval_world;
mod fuse;
mod generate;
mod guard;
mod live;
mod outputs;
mod overview;
mod progress;
mod serve;
mod synth;
mod tiled;
mod train;
mod train_bank;
mod train_common;
mod train_context;
mod train_decoder;
mod train_sampler;
mod train_world;
mod video;
mod view;
mod viewer_page;

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

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
    /// (Re)write a run's browser viewer RUN/world.html (self-contained, works offline) and open
    /// it; --serve serves the run folder on 127.0.0.1.
    View(view::ViewArgs),
}

fn main() -> std::process::ExitCode {
    let matches = Cli::command().get_matches();
    let cli = match Cli::from_arg_matches(&matches) {
        Ok(cli) => cli,
        Err(e) => e.exit(),
    };
    let result = match cli.command {
        Command::Generate(a) => {
            let given = matches.subcommand_matches("generate").map(given_options).unwrap_or_default();
            generate::check_command_line(&a, &given).and_then(|()| generate::run(*a))
        }
        Command::Fuse(a) => fuse::run(a),
        Command::Synth(a) => synth::run(a),
        Command::Bench(a) => bench::run(a),
        Command::Eval(c) => eval::run(c),
        Command::Train(c) => train::run(c),
        Command::ConvertCheckpoint(a) => convert::run(a),
        Command::View(a) => view::run(a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", error_message(&e));
            std::process::ExitCode::FAILURE
        }
    }
}

/// The options of `sgam generate` given on the command line (not defaults), as `--long-name`.
fn given_options(m: &clap::ArgMatches) -> Vec<String> {
    let cli = Cli::command();
    let Some(generate) = cli.find_subcommand("generate") else { return Vec::new() };
    generate
        .get_arguments()
        .filter(|a| m.value_source(a.get_id().as_str()) == Some(clap::parser::ValueSource::CommandLine))
        .map(|a| format!("--{}", a.get_long().unwrap_or(a.get_id().as_str())))
        .collect()
}

/// The error and its causes joined by ": ", each said once: a cause whose text an outer message
/// already holds (libraries that print their source) is not repeated.
fn error_message(e: &anyhow::Error) -> String {
    let mut msg = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if text.is_empty() || msg.contains(&text) {
            continue;
        }
        if !msg.is_empty() {
            msg.push_str(": ");
        }
        msg.push_str(&text);
    }
    msg
}
