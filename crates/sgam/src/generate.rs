//! `sgam generate`: its arguments, their checks and their resolution into the pipeline's
//! [`RunConfig`]; the run itself is [`sgam_pipeline::run::generate`], its outputs
//! [`crate::outputs`].

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::Args;
use sgam_pipeline::snapshot::SNAPSHOT_FILE;
use sgam_pipeline::{BankSpec, RefinerSpec, RunSettings};

use crate::guard::{in_range, RunLock};

pub use sgam_pipeline::settings::{RefinerKind, TrajectoryKind};

/// Arguments of `sgam generate`.
#[derive(Debug, Clone, Args)]
#[command(
    after_help = "Examples:\n  sgam generate                                  # 100 steps from a synthetic seed\n  sgam generate --steps 900 --out runs/big       # the paper's 30x30 zig-zag world\n  sgam generate --resume runs/big                # continue after an interruption\n  sgam generate --steps 100000 --grid 317 --refiner null --res 128 --out runs/huge\n                                                 # any length: the map stays under --max-map-mb\n  sgam generate --seed-template ../shared/data/sgam-clevr-template\n  sgam generate --seed-rgb im.png --seed-depth d.png --intrinsics 500,500,320,240 \\\n      --trajectory line --step 0.1 --steps 50\n\nOutputs in the run folder: rgb/NNNNN.png, depth/NNNNN.npy (+ .png in mm with --depth-png),\nguidance/NNNNN.png (with --guidance-png), transforms.json (nerfstudio / instant-ngp), mesh.ply and mesh.glb, flythrough.gif, run.json\n(config, per-stage timings, map statistics) and snapshot.bin (for --resume).\nA world whose map outgrows --max-map-mb also has tiles/ (the map away from memory; resume\nneeds them) and mesh-tiles/ (a glTF per 3.2 m tile, coarse.glb, index.json); world.html then\nopens on the coarse world, and `sgam view RUN --serve` adds full detail near the view."
)]
pub struct GenerateArgs {
    /// Run folder (default: runs/world-NNN, the next free number).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Continue an interrupted run from its last snapshot (other options are taken from it).
    #[arg(long, conflicts_with = "out")]
    pub resume: Option<PathBuf>,
    /// What the run grows and writes (the library's [`RunSettings`]: seed, path, steps, refiner,
    /// sampling, invented-pixel policy, map, outputs).
    #[command(flatten)]
    pub run: RunSettings,
    /// Serve the viewer on 127.0.0.1 while the world grows (mesh and poses refresh every
    /// --view-every steps; the results are unchanged).
    #[arg(long)]
    pub view: bool,
    /// Port of --view (a taken port falls back to a free one).
    #[arg(long, default_value_t = crate::view::DEFAULT_PORT)]
    pub view_port: u16,
    /// Steps between mesh refreshes of --view.
    #[arg(long, default_value_t = crate::live::DEFAULT_EVERY)]
    pub view_every: usize,
    /// Stop after this many steps of this invocation (for tests of --resume; the run stays
    /// resumable).
    #[arg(long, hide = true)]
    pub stop_after: Option<usize>,
    /// Replace the outputs of an earlier run in --out (by default a folder that holds files is
    /// refused).
    #[arg(long, conflicts_with = "resume")]
    pub force: bool,
}

impl GenerateArgs {
    /// A new run of `run` into `out` (the next free `runs/world-NNN` when `None`), without the
    /// live viewer: what the evaluation commands run.
    pub fn new(run: RunSettings, out: Option<PathBuf>) -> Self {
        Self {
            out,
            resume: None,
            run,
            view: false,
            view_port: crate::view::DEFAULT_PORT,
            view_every: crate::live::DEFAULT_EVERY,
            stop_after: None,
            force: false,
        }
    }

    /// Continues the run in `dir`.
    pub fn resume(dir: PathBuf) -> Self {
        Self { resume: Some(dir), ..Self::new(RunSettings::default(), None) }
    }
}

pub use sgam_pipeline::settings::DEPTH_PNG_MAX_M;
pub use sgam_pipeline::{MAX_RES, MAX_STEPS};

/// The files and folders a run writes (what `--force` removes before a new run).
pub const RUN_OUTPUTS: &[&str] = &[
    "rgb",
    "depth",
    "snapshot.bin",
    "mesh.ply",
    "mesh.glb",
    "map.bin",
    "transforms.json",
    "flythrough.gif",
    "flythrough.mp4",
    "orbit.mp4",
    "world.html",
    "overview.png",
    "strip.png",
    "run.json",
    "mesh-*",
    sgam_pipeline::tiles::TILES_DIR,
    crate::tiled::MESH_TILES_DIR,
];

impl GenerateArgs {
    /// Checks every option: the run's ([`RunSettings::validate`]: numbers finite and in range,
    /// with upper bounds that keep memory within the machine, and the combinations that would
    /// otherwise be silently ignored) and the viewer's. Errors name the option and the accepted
    /// range.
    pub fn validate(&self) -> Result<()> {
        self.run.validate()?;
        if self.view {
            in_range("--view-every", self.view_every, 1..=MAX_STEPS)?;
        }
        if let Some(n) = self.stop_after {
            in_range("--stop-after", n, 1..=MAX_STEPS)?;
        }
        Ok(())
    }
}

/// Checks of the command line that the arguments alone cannot tell: options given with
/// `--resume` (a resumed run keeps its own) and the synthetic seed's options with another seed.
/// `given` are the options written on the command line. (Evaluation commands that build
/// arguments themselves skip this.)
pub fn check_command_line(args: &GenerateArgs, given: &[String]) -> Result<()> {
    if args.resume.is_some() {
        let ignored: Vec<&str> = given
            .iter()
            .map(String::as_str)
            .filter(|o| !matches!(*o, "--resume" | "--stop-after" | "--view" | "--view-port" | "--view-every"))
            .collect();
        if !ignored.is_empty() {
            bail!(
                "--resume continues a run with the options it was started with; {} cannot be changed (leave {} out, \
                 or start a new run)",
                ignored.join(", "),
                if ignored.len() == 1 { "it" } else { "them" }
            );
        }
    }
    // the synthetic seed's options do nothing for a seed read from files (after the options'
    // own checks, which name a bad seed file first)
    if args.resume.is_none() {
        args.validate()?;
    }
    let s = &args.run.seed;
    if let Some(seed) = [
        (s.seed_rgb.is_some(), "--seed-rgb"),
        (s.seed_template.is_some(), "--seed-template"),
        (s.seed_google_earth.is_some(), "--seed-google-earth"),
    ]
    .into_iter()
    .find_map(|(given, name)| given.then_some(name))
    {
        for option in ["--res", "--seed-scene"] {
            if given.iter().any(|g| g == option) {
                bail!("{option} applies to synthetic seeds only; {seed} gives the seed frame (leave {option} out)");
            }
        }
    }
    Ok(())
}

/// The learned refiner `run` names (`None` for the stand-ins), with the code bank it resolves
/// to, for the evaluation and benchmark commands that call a refiner directly. Resolved as a
/// run is, so the seed's preset fills the options left to it (a Google Earth seed's quilting).
pub fn model_refiner(run: &RunSettings) -> Result<Option<sgam_model::VqRefiner>> {
    let resolved = run.resolve()?;
    Ok(match resolved.refiner {
        RefinerSpec::Model { model, options, bank, .. } => {
            let mut r = sgam_pipeline::model_refiner(model.as_deref(), options)?;
            let seed = resolved.seed;
            // only the seed's own bank reads the seed frame
            let frame = match bank {
                BankSpec::Seed => Some(seed.load()?),
                _ => None,
            };
            bank.load_into(&mut r, frame.as_ref())?;
            Some(r)
        }
        RefinerSpec::Null { .. } | RefinerSpec::Oracle => None,
    })
}

fn next_run_dir() -> PathBuf {
    (1..)
        .map(|i| PathBuf::from(format!("runs/world-{i:03}")))
        .find(|p| !p.exists())
        .unwrap_or_else(|| PathBuf::from("runs/world"))
}

/// CRC-32 of the model file the run's refiner loads (`--model`, or the bundled model); `None`
/// for the stand-ins.
fn model_crc32(refiner: &RefinerSpec) -> Result<Option<u32>> {
    if let RefinerSpec::Model { model: Some(p), .. } = refiner {
        crate::guard::check_input_file("--model", p)?;
    }
    if let RefinerSpec::Model { bank: sgam_pipeline::BankSpec::File(p), .. } = refiner {
        crate::guard::check_input_file("--bank", p)?;
    }
    Ok(refiner.model_crc32()?)
}

/// Runs `sgam generate`. The run folder is locked for the whole run; a new run needs an empty
/// folder (or `--force`); a resumed run checks its snapshot and that its model file is the same.
pub fn run(args: GenerateArgs) -> Result<()> {
    let (dir, resuming) = match &args.resume {
        Some(dir) => {
            if !dir.is_dir() {
                bail!("--resume {}: no such run folder", dir.display());
            }
            if !dir.join(SNAPSHOT_FILE).exists() {
                bail!("--resume {}: no snapshot.bin to resume from (is it a run folder?)", dir.display());
            }
            (dir.clone(), true)
        }
        None => {
            args.validate()?;
            (args.out.clone().unwrap_or_else(next_run_dir), false)
        }
    };
    let _lock = RunLock::acquire(&dir)?;
    crate::guard::remove_stale_temp_files(&dir, &["rgb", "depth"])?;
    let (config, resume, stamp) = if resuming {
        let (state, map) = sgam_pipeline::snapshot::read_snapshot(&dir)?;
        if let Some(n) = args.stop_after {
            in_range("--stop-after", n, 1..=MAX_STEPS)?;
        }
        if model_crc32(&state.config.refiner)? != state.model_crc32 {
            let model = match &state.config.refiner {
                RefinerSpec::Model { model: Some(p), .. } => p.display().to_string(),
                _ => "bundled".into(),
            };
            bail!(
                "{}: the model ({model}) or its code bank is not the file this run started with; resume with that file, or start a new run",
                dir.display(),
            );
        }
        let stamp = state.model_crc32;
        (state.config.clone(), Some(sgam_pipeline::Resume { state, map }), stamp)
    } else {
        let hint = if dir.join(SNAPSHOT_FILE).exists() {
            format!("continue it with --resume {}, or ", dir.display())
        } else {
            String::new()
        };
        crate::guard::claim_empty_folder(&dir, args.force, RUN_OUTPUTS, &hint)?;
        let config = args.run.resolve()?;
        let stamp = model_crc32(&config.refiner)?;
        (config, None, stamp)
    };
    let mut observer = crate::outputs::CliObserver::new(&dir, &config, (args.view, args.view_port, args.view_every));
    let generated = sgam_pipeline::run::generate(&dir, &config, resume, stamp, args.stop_after, &mut observer)?;
    observer.finish_progress();
    if !generated.finished {
        eprintln!(
            "stopped after {} steps; continue with: sgam generate --resume {}",
            generated.steps_this_run,
            dir.display()
        );
        return Ok(());
    }
    let mut generated = generated;
    crate::outputs::finish_outputs(&config, &dir, &mut generated)?;
    observer.finish_live(generated.generator.keyframes.cameras());
    Ok(())
}

#[cfg(test)]
mod tests {
    use clap::{CommandFactory, Parser};

    use super::*;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        generate: GenerateArgs,
    }

    /// Options whose default is the seed's preset (CLEVR shown), not a fixed value.
    fn preset_default(long: &str) -> Option<String> {
        let p = sgam_pipeline::CLEVR;
        Some(match long {
            "step" => format!("{} (CLEVR preset)", p.step_m),
            "voxel-size" => format!("{} (CLEVR preset)", p.voxel_size_m),
            "trunc-voxels" => format!("{} (CLEVR preset)", p.trunc_voxels),
            "k-sources" => format!("{} (CLEVR preset)", p.k_sources),
            "source-radius" => format!("{} (CLEVR preset)", p.source_radius_m),
            "solid-objects" => format!("{} (CLEVR preset)", p.solid_objects_m),
            "max-object-m2" => format!("{} (CLEVR preset)", p.max_object_m2),
            "max-object-length" => format!("{} (CLEVR preset)", p.max_object_length_m),
            "object-colour" => format!("{} (CLEVR preset)", p.object_colour),
            "quilt-tile" => format!("{} (CLEVR preset)", p.quilt_tile),
            _ => return None,
        })
    }

    /// The rows README's defaults table must hold: every visible option of `sgam generate` with
    /// the default its `--help` shows and the first sentence of its help.
    fn expected_rows() -> Vec<(String, String, String)> {
        Cli::command()
            .get_arguments()
            .filter(|a| !a.is_hide_set())
            .filter_map(|a| {
                let long = a.get_long()?;
                let values: Vec<String> =
                    a.get_default_values().iter().map(|v| v.to_string_lossy().into_owned()).collect();
                let default = match values.as_slice() {
                    _ if matches!(a.get_action(), clap::ArgAction::SetTrue) => "off".into(),
                    [] => preset_default(long).unwrap_or_else(|| "none".into()),
                    _ => values.join(","),
                };
                let help = a.get_help().map(|h| h.to_string()).unwrap_or_default().replace('\n', " ");
                let first = help.split(". ").next().unwrap_or("").trim_end_matches('.').replace('|', "\\|");
                Some((format!("--{long}"), default, first))
            })
            .collect()
    }

    #[test]
    fn readme_defaults_table_equals_generate_help() {
        let readme = include_str!("../../../README.md");
        let begin = "<!-- generate-defaults:begin -->";
        let end = "<!-- generate-defaults:end -->";
        let expected = expected_rows();
        let table: String = expected.iter().map(|(o, d, h)| format!("| `{o}` | `{d}` | {h} |\n")).collect();
        let hint = format!(
            "README.md's table should read:\n{begin}\n| option | default | what |\n|---|---|---|\n{table}{end}"
        );
        let (Some(a), Some(b)) = (readme.find(begin), readme.find(end)) else { panic!("no defaults table; {hint}") };
        let rows: Vec<(String, String, String)> = readme[a + begin.len()..b]
            .lines()
            .filter_map(|l| {
                let cells: Vec<&str> = l.strip_prefix("| `")?.splitn(3, " | ").collect();
                let [o, d, h] = cells.as_slice() else { return None };
                let h = h.strip_suffix(" |").unwrap_or(h);
                Some((o.trim_end_matches('`').to_string(), d.trim_matches('`').to_string(), h.to_string()))
            })
            .collect();
        assert!(expected.len() > 40, "{} options: the help lost its options?", expected.len());
        assert_eq!(rows, expected, "{hint}");
    }

    #[test]
    fn the_generate_command_line_defaults_are_the_librarys() {
        let parsed = Cli::parse_from(["sgam"]).generate;
        assert_eq!(parsed.run, RunSettings::default());
        let fresh = GenerateArgs::new(RunSettings::default(), None);
        assert_eq!((parsed.view, parsed.view_port, parsed.view_every), (fresh.view, fresh.view_port, fresh.view_every));
        assert_eq!((parsed.force, parsed.stop_after, parsed.resume), (false, None, None));
    }
}
