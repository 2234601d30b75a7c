//! `sgam eval table`: the baselines table in the shape of the paper's Tables 1 and 2, plus our
//! world statistics, from `eval world` and `eval one-step` over a fixed set of refiners.

use std::io::Write;
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;

use crate::eval::OneStepArgs;
use crate::eval_world::WorldArgs;
use sgam_pipeline::settings::{PathSettings, RefinerKind, RefinerSettings, TrajectoryKind};
use sgam_pipeline::RunSettings;

/// Arguments of `sgam eval table`.
#[derive(Debug, Args)]
#[command(
    after_help = "Example:\n  sgam eval table --out runs/table      # writes runs/table/table.md and overviews.png\n\nRows: the bundled model sampled (default T) and argmin (T = 0), the null stand-in (push-pull),\n--no-map (warp from the previous frame only), --no-refine (guidance fused with its holes) and\nthe oracle. World columns come from `eval world` (held-out seeds, against the oracle), image\ncolumns from `eval one-step`. A second table follows the first row along each of --trajectories\n(against the oracle along the same one), every figure marked against its bar; overviews.png\nshows the first table's worlds, each labelled with its row."
)]
pub struct TableArgs {
    /// Held-out seeds per world evaluation.
    #[arg(long, default_value_t = 4)]
    pub seeds: u64,
    /// Steps per world.
    #[arg(long, default_value_t = 400)]
    pub steps: usize,
    /// Held-out scenes of the one-step evaluation.
    #[arg(long, default_value_t = 8)]
    pub one_step_scenes: u64,
    /// Model weights (default: the bundled model).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Output folder (worlds, table.md, table.json, overviews.png).
    #[arg(long, default_value = "runs/table")]
    pub out: PathBuf,
    /// Trajectories of the second table, comma-separated, each once (not `file`: it needs a pose
    /// file): the model (first row) grown along each with the same seeds and steps, against the
    /// oracle along the same one; worlds kept and reused in OUT/trajectory-NAME (the zig-zag's
    /// are the first row's).
    #[arg(long, value_name = "LIST", value_delimiter = ',', default_value = "zigzag", value_parser = crate::eval_trajectories::trajectory_parser())]
    pub trajectories: Vec<TrajectoryKind>,
}

struct Row {
    name: &'static str,
    refiner: RefinerKind,
    temperature: f32,
    no_map: bool,
    no_refine: bool,
}

/// The row the trajectory table follows (`ROWS[MODEL_ROW]`): the model as generation runs it.
const MODEL_ROW: usize = 0;

const ROWS: [Row; 6] = [
    Row {
        name: "model, sampled (default T)",
        refiner: RefinerKind::Auto,
        temperature: sgam_pipeline::settings::DEFAULT_TEMPERATURE,
        no_map: false,
        no_refine: false,
    },
    Row {
        name: "model, argmin (T = 0)",
        refiner: RefinerKind::Auto,
        temperature: 0.0,
        no_map: false,
        no_refine: false,
    },
    Row {
        name: "null stand-in (push-pull)",
        refiner: RefinerKind::Null,
        temperature: 0.0,
        no_map: false,
        no_refine: false,
    },
    Row {
        name: "--no-map (model, default T)",
        refiner: RefinerKind::Auto,
        temperature: sgam_pipeline::settings::DEFAULT_TEMPERATURE,
        no_map: true,
        no_refine: false,
    },
    Row { name: "--no-refine", refiner: RefinerKind::Auto, temperature: 0.0, no_map: false, no_refine: true },
    Row {
        name: "oracle (true world)",
        refiner: RefinerKind::Oracle,
        temperature: 0.0,
        no_map: false,
        no_refine: false,
    },
];

fn f(v: &serde_json::Value, digits: usize) -> String {
    match v.as_f64() {
        Some(x) if x.is_finite() => format!("{x:.digits$}"),
        _ => "-".into(),
    }
}

/// Runs `sgam eval table`.
pub fn run(a: &TableArgs) -> Result<()> {
    crate::eval_trajectories::check(&a.trajectories)?;
    // every row's options and the model file, before minutes of work
    for row in &ROWS {
        world_args(a, row).validate()?;
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("{}: cannot create", a.out.display()))?;
    let mut lines = Vec::new();
    let mut json_rows = Vec::new();
    let mut overviews = Vec::new();
    for row in &ROWS {
        eprintln!("== {}", row.name);
        let wa = world_args(a, row);
        let world = crate::eval_world::evaluate(&wa)?;
        let one = if row.refiner == RefinerKind::Oracle || row.no_map {
            serde_json::Value::Null
        } else {
            let os = OneStepArgs {
                scenes: a.one_step_scenes,
                views: 4,
                res: 256,
                refiner: row.refiner,
                model: a.model.clone(),
                regenerate_observed: false,
                autoencode: false,
                json: true,
            };
            match crate::generate::model_refiner(&row_settings(a, row))? {
                Some(mut m) if !row.no_refine => crate::eval::one_step(&os, &mut m)?,
                _ => crate::eval::one_step(&os, &mut sgam_pipeline::NullRefiner { fill: !row.no_refine })?,
            }
        };
        let g = &world["generated"];
        let sc = &world["scene"];
        lines.push(format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} / {} / {} | {} / {} | {} |",
            row.name,
            f(&one["psnr"], 2),
            f(&one["ssim"], 3),
            f(&world["kid"], 4),
            f(&sc["jsd"], 4),
            f(&sc["mmd"], 4),
            f(&sc["cov"], 3),
            f(&sc["min_dist"], 4),
            f(&sc["one_nna"], 3),
            f(&g["objects_per_100m2"], 2),
            f(&g["median_object_area_m2"], 2),
            f(&g["object_saturation"], 3),
            f(&g["ground_rms_mm"], 0),
            f(&g["object_shape"]["median_solidity"], 2),
            f(&g["object_shape"]["median_elongation"], 2),
            f(&g["object_shape"]["compact_share"], 2),
            f(&world["loop"]["psnr"], 1),
            f(&world["loop"]["ssim"], 3),
            f(&world["step_ms_median"], 0),
        ));
        let label_dir = a.out.join(format!("seed-{}", sgam_pipeline::HELD_OUT_SEED_BASE));
        let label = wa.label();
        overviews.push((label_dir.join(label).join("overview.png"), row.name));
        json_rows.push(serde_json::json!({ "row": row.name, "world": world, "one_step": one }));
    }
    let mut md = String::new();
    md += &format!(
        "Held-out seeds {}..{}, {}-step zig-zag (one world per seed and refiner, compared with the oracle's world of the same seed); one-step: {} held-out scenes x 4 views.\n\n",
        sgam_pipeline::HELD_OUT_SEED_BASE,
        sgam_pipeline::HELD_OUT_SEED_BASE + a.seeds - 1,
        a.steps,
        a.one_step_scenes
    );
    md += "| refiner | PSNR | SSIM | KID | JSD | MMD | COV | MinDist | 1-NNA | objects / 100 m² | median footprint m² | object saturation | ground RMS mm | object solidity / elongation / compact share | loop PSNR / SSIM | ms / step |\n";
    md += "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
    for l in &lines {
        md += l;
        md += "\n";
    }
    let trajectories = crate::eval_trajectories::evaluate(
        &a.trajectories,
        &world_args(a, &ROWS[MODEL_ROW]),
        &json_rows[MODEL_ROW]["world"],
        &a.out,
    )?;
    md += "\n";
    md += &crate::eval_trajectories::markdown(&trajectories);
    let md_path = a.out.join("table.md");
    sgam_io::write_atomic(&md_path, |w| w.write_all(md.as_bytes()))?;
    let json = serde_json::to_vec_pretty(
        &serde_json::json!({ "rows": json_rows, "trajectories": crate::eval_trajectories::to_json(&trajectories) }),
    )?;
    sgam_io::write_atomic(&a.out.join("table.json"), |w| w.write_all(&json))?;
    let pic = a.out.join("overviews.png");
    write_overviews(&overviews, &pic)?;
    print!("{md}");
    eprintln!("table: {}  overviews (rows in table order, 3 per line): {}", md_path.display(), pic.display());
    Ok(())
}

/// The run settings of `row`: the generation defaults but for the row's refiner, temperature
/// and ablations, and the table's model (for the model's rows).
fn row_settings(a: &TableArgs, row: &Row) -> RunSettings {
    let mut run = RunSettings {
        refiner: RefinerSettings {
            refiner: row.refiner,
            model: if row.refiner == RefinerKind::Auto && !row.no_refine { a.model.clone() } else { None },
            no_refine: row.no_refine,
            bank: sgam_pipeline::BankSpec::Auto,
            adapt: 0.0,
        },
        ..RunSettings::default()
    };
    run.sampling.temperature = row.temperature;
    run.map.no_map = row.no_map;
    run
}

/// `eval world`'s arguments for `row`: the table's seeds, steps and model along the zig-zag, the
/// generation defaults otherwise.
fn world_args(a: &TableArgs, row: &Row) -> WorldArgs {
    let run = row_settings(a, row);
    WorldArgs {
        seeds: a.seeds,
        first_seed: sgam_pipeline::HELD_OUT_SEED_BASE,
        steps: a.steps,
        path: PathSettings::default(),
        refiner: run.refiner,
        sampling: run.sampling,
        invented: run.invented,
        map: run.map,
        paper: false,
        region_size: 5.0,
        out: Some(a.out.clone()),
        keep_snapshots: false,
        loop_out: None,
        no_loop: false,
        json: true,
    }
}

/// The overview pictures side by side, 3 per line, each scaled to 480 px wide and labelled
/// underneath.
fn write_overviews(paths: &[(PathBuf, &str)], out: &std::path::Path) -> Result<()> {
    let tiles: Vec<image::RgbImage> = paths
        .iter()
        .filter_map(|(p, label)| Some((image::open(p).ok()?, label)))
        .map(|(i, label)| {
            crate::caption::with_caption(&i.resize(480, 300, image::imageops::FilterType::Triangle).to_rgb8(), label)
        })
        .collect();
    if tiles.is_empty() {
        return Ok(());
    }
    let (tw, th) = (480u32, tiles.iter().map(|t| t.height()).max().unwrap_or(300));
    let cols = 3u32;
    let rows = (tiles.len() as u32).div_ceil(cols);
    let mut canvas = image::RgbImage::from_pixel(tw * cols, th * rows, image::Rgb([255, 255, 255]));
    for (i, t) in tiles.iter().enumerate() {
        let (x, y) = ((i as u32 % cols) * tw, (i as u32 / cols) * th);
        image::imageops::overlay(&mut canvas, t, x as i64, y as i64);
    }
    let mut bytes = Vec::new();
    image::DynamicImage::ImageRgb8(canvas)
        .write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .context("encoding the overview picture")?;
    sgam_io::write_atomic(out, |w| w.write_all(&bytes))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_row_name_is_drawn_in_the_caption_font() {
        for row in &ROWS {
            assert!(row.name.chars().all(|c| crate::caption::glyph(c).is_some()), "{}", row.name);
        }
    }
}
