//! `sgam eval world`'s text report: the JSON result of [`crate::eval_world::evaluate`] as a
//! table a person reads (ratios to the oracle, the scene metrics, KID, loop consistency, object
//! shapes).

/// Fewest objects (in each of the generated and the oracle's worlds, all seeds) and regions
/// below which the report gives no bar verdicts: medians and densities of a handful of objects
/// say nothing.
pub const MIN_OBJECTS_TO_JUDGE: f64 = 10.0;
/// See [`MIN_OBJECTS_TO_JUDGE`].
pub const MIN_REGIONS_TO_JUDGE: u64 = 4;

/// Why `v`'s worlds are too small for its statistics, or `None` when they are not.
pub fn too_short(v: &serde_json::Value) -> Option<String> {
    let objects = |w: &str| {
        let g = &v[w];
        (g["objects_per_100m2"].as_f64().unwrap_or(0.0) * g["new_area_m2"].as_f64().unwrap_or(0.0) / 100.0).round()
    };
    let (og, oo) = (objects("generated"), objects("oracle"));
    let regions = v["regions"]["generated"].as_u64().unwrap_or(0).min(v["regions"]["oracle"].as_u64().unwrap_or(0));
    (og < MIN_OBJECTS_TO_JUDGE || oo < MIN_OBJECTS_TO_JUDGE || regions < MIN_REGIONS_TO_JUDGE).then(|| {
        format!(
            "warning: these worlds are too small for their statistics ({og} generated and {oo} true objects, \
             {regions} regions; at least {MIN_OBJECTS_TO_JUDGE} objects each and {MIN_REGIONS_TO_JUDGE} regions are \
             needed): no bar verdicts; grow longer worlds (--steps 400, the default) or more seeds\n"
        )
    })
}

/// Plain-text summary of an [`evaluate`] result.
pub fn summary_text(v: &serde_json::Value) -> String {
    let short = too_short(v);
    let bar = |b: &'static str| if short.is_some() { "" } else { b };
    let row = |name: &str, key: &str, unit: &str| {
        format!(
            "  {name:<28} {:>10.3} {:>10.3} {:>8.2}x{unit}\n",
            v["generated"][key].as_f64().unwrap_or(f64::NAN),
            v["oracle"][key].as_f64().unwrap_or(f64::NAN),
            v["generated"][key].as_f64().unwrap_or(f64::NAN) / v["oracle"][key].as_f64().unwrap_or(f64::NAN),
        )
    };
    let mut s = format!(
        "world statistics: {} vs oracle, {} seeds x {} steps ({})\n  {:<28} {:>10} {:>10} {:>9}\n",
        v["refiner"].as_str().unwrap_or("?"),
        v["seeds"],
        v["steps"],
        v["trajectory"].as_str().unwrap_or("?"),
        "",
        "generated",
        "oracle",
        "ratio"
    );
    if let Some(w) = &short {
        s.insert_str(0, w);
    }
    s += &row("new area (m2)", "new_area_m2", "");
    s += &row("objects per 100 m2", "objects_per_100m2", bar("   (bar 0.5-1.5x)"));
    s += &row("median object footprint (m2)", "median_object_area_m2", bar("   (bar <= 2x)"));
    s += &row("p90 object footprint (m2)", "p90_object_area_m2", "");
    s += &row("object cover", "object_cover", "");
    s += &row("object saturation", "object_saturation", bar("   (bar >= 0.6x)"));
    s += &row("ground RMS (mm)", "ground_rms_mm", bar("   (bar <= 2x)"));
    s += &shape_rows(v);
    let sc = &v["scene"];
    s += &format!(
        "scene metrics ({} vs {} regions of {} m): JSD {:.4}  MMD {:.4}  COV {:.3}  MinDist {:.4}  1-NNA {:.3}\n",
        v["regions"]["generated"],
        v["regions"]["oracle"],
        v["regions"]["size_m"],
        sc["jsd"].as_f64().unwrap_or(f64::NAN),
        sc["mmd"].as_f64().unwrap_or(f64::NAN),
        sc["cov"].as_f64().unwrap_or(f64::NAN),
        sc["min_dist"].as_f64().unwrap_or(f64::NAN),
        sc["one_nna"].as_f64().unwrap_or(f64::NAN),
    );
    s += &format!(
        "loop back to the seed after {} steps: PSNR {:.2} dB, SSIM {:.3} against the seed frame\n",
        v["loop"]["steps"],
        v["loop"]["psnr"].as_f64().unwrap_or(f64::NAN),
        v["loop"]["ssim"].as_f64().unwrap_or(f64::NAN),
    );
    s += &format!(
        "KID (frozen synthetic-world encoder features, {} vs {} frames): {:.5}\nmedian step {:.1} ms; wall {:.0} s; worlds in {}\n",
        v["kid_frames"]["generated"],
        v["kid_frames"]["oracle"],
        v["kid"].as_f64().unwrap_or(f64::NAN),
        v["step_ms_median"].as_f64().unwrap_or(f64::NAN),
        v["wall_s"].as_f64().unwrap_or(f64::NAN),
        v["out"].as_str().unwrap_or("?"),
    );
    s
}

/// The object shape rows of [`summary_text`]: pooled over seeds (the compact share with its
/// ratio to the oracle's), then one line per seed; "-" where a world has no objects.
fn shape_rows(v: &serde_json::Value) -> String {
    let num = |x: &serde_json::Value, digits: usize| x.as_f64().map_or("-".into(), |x| format!("{x:.digits$}"));
    let mut s = String::new();
    for (name, key) in [
        ("median object solidity", "median_solidity"),
        ("median object elongation", "median_elongation"),
        ("compact object share", "compact_share"),
    ] {
        let (g, o) = (&v["generated"]["object_shape"][key], &v["oracle"]["object_shape"][key]);
        let ratio = match (key, g.as_f64(), o.as_f64()) {
            ("compact_share", Some(g), Some(o)) => format!(" {:>8.2}x", g / o),
            _ => String::new(),
        };
        s += &format!("  {name:<28} {:>10} {:>10}{ratio}\n", num(g, 3), num(o, 3));
    }
    let triple = |w: &serde_json::Value| {
        let sh = &w["object_shape"];
        format!(
            "{} / {} / {}",
            num(&sh["median_solidity"], 2),
            num(&sh["median_elongation"], 2),
            num(&sh["compact_share"], 2)
        )
    };
    s += "  per seed, solidity / elongation / compact share: generated | oracle\n";
    for p in v["per_seed"].as_array().into_iter().flatten() {
        let seed = format!("seed {}", p["seed_scene"]);
        s += &format!("    {seed:<26} {} | {}\n", triple(&p["generated"]), triple(&p["oracle"]));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn result(objects_per_100m2: f64, area: f64, regions: u64) -> serde_json::Value {
        let world = serde_json::json!({ "objects_per_100m2": objects_per_100m2, "new_area_m2": area });
        serde_json::json!({
            "generated": world, "oracle": world,
            "regions": { "generated": regions, "oracle": regions, "size_m": 5.0 },
        })
    }

    #[test]
    fn a_world_too_small_for_its_statistics_gets_a_warning_and_no_bar_verdicts() {
        // 2 objects in 100 m2, one region: the short run
        let short = result(2.0, 100.0, 1);
        let w = too_short(&short).expect("a 2-object world is too short");
        assert!(w.contains("2 generated and 2 true objects") && w.contains("1 regions"), "{w}");
        let text = summary_text(&short);
        assert!(text.starts_with("warning:") && !text.contains("(bar"), "{text}");
        // 40 objects over 400 m2 in 16 regions: judged, with bars
        let long = result(10.0, 400.0, 16);
        assert_eq!(too_short(&long), None);
        let text = summary_text(&long);
        assert!(!text.contains("warning") && text.contains("(bar 0.5-1.5x)"), "{text}");
        // enough objects but too few regions is still too short
        assert!(too_short(&result(10.0, 400.0, 3)).is_some());
    }
}
