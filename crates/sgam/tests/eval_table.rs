//! `sgam eval table`: the baselines table and the trajectory table.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

#[test]
fn eval_table_refuses_unknown_repeated_and_file_trajectories_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("table");
    for (list, needle) in [
        ("zigzag,loop", "invalid value 'loop' for '--trajectories"),
        ("file", "invalid value 'file' for '--trajectories"),
        ("line,circle,line", "--trajectories lists line twice"),
        ("", "--trajectories"),
    ] {
        let o = common::sgam(&["eval", "table", "--trajectories", list, "--out", out.to_str().unwrap()]);
        assert!(!o.status.success(), "--trajectories {list:?} succeeded");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(needle), "--trajectories {list:?}: {err}");
        assert!(!out.exists(), "--trajectories {list:?} started work in {}", out.display());
    }
    // a missing model file, and too few steps, are named before any world is grown
    let missing = dir.path().join("absent.safetensors");
    for (extra, needle) in
        [(vec!["--model", missing.to_str().unwrap()], "absent.safetensors"), (vec!["--steps", "3"], "--steps 3")]
    {
        let mut args = vec!["eval", "table", "--out", out.to_str().unwrap()];
        args.extend(extra);
        let o = common::sgam(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(needle), "{args:?}: {err}");
        assert!(!out.exists(), "{args:?} started work in {}", out.display());
    }
}

#[test]
fn a_table_along_two_trajectories_has_one_marked_row_for_each_and_labelled_overviews() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("table");
    let o = common::sgam(&[
        "eval",
        "table",
        "--seeds",
        "1",
        "--steps",
        "10",
        "--one-step-scenes",
        "1",
        "--trajectories",
        "zigzag,line",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // table.md: the baselines table, then one row per trajectory, in the listed order, each
    // figure with a bar marked met or missed
    let md = std::fs::read_to_string(out.join("table.md")).unwrap();
    let (_, second) = md.split_once("| trajectory |").expect(&md);
    let rows: Vec<&str> = second.lines().filter(|l| l.starts_with("| ")).collect();
    assert_eq!(rows.len(), 2, "{second}");
    assert!(rows[0].starts_with("| zigzag | ") && rows[1].starts_with("| line | "), "{second}");
    for row in &rows {
        assert_eq!(row.matches(" | ").count(), 8, "{row}");
        assert!(row.contains('✓') || row.contains('✗') || row.contains('?'), "no marks: {row}");
    }
    assert!(second.contains("Bars: zigzag: "), "{second}");
    // table.json: the zig-zag row is the first baseline row's evaluation; the line's worlds are
    // grown along the line under trajectory-line, sharing the zig-zag's loop-consistency run
    let j: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("table.json")).unwrap()).unwrap();
    let t = j["trajectories"].as_array().unwrap();
    assert_eq!(t.len(), 2);
    assert_eq!(t[0]["trajectory"], "zigzag");
    assert_eq!(t[0]["world"], j["rows"][0]["world"]);
    assert_eq!(t[1]["trajectory"], "line");
    assert_eq!(t[1]["world"]["trajectory"], "line");
    assert_eq!(t[1]["world"]["refiner"], j["rows"][0]["world"]["refiner"]);
    assert_ne!(t[1]["world"]["oracle"], t[0]["world"]["oracle"], "the line's oracle is its own");
    assert!(t[1]["figures"]["objects_per_100m2"]["bar"].is_string(), "{}", t[1]["figures"]);
    let line_seed = out.join("trajectory-line").join("seed-1000000");
    assert!(line_seed.join("oracle").join("mesh.ply").exists(), "{}", line_seed.display());
    let grown: Vec<String> =
        std::fs::read_dir(&line_seed).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    assert!(!grown.iter().any(|n| n.ends_with("-loop")), "{grown:?}");
    assert_eq!(t[1]["world"]["loop"], t[0]["world"]["loop"]);
    // overviews.png: six panels, three per line, each with a light caption band whose text
    // is near-black
    let pic = image::open(out.join("overviews.png")).unwrap().to_rgb8();
    assert_eq!(pic.width(), 3 * 480);
    let panel_h = pic.height() / 2;
    assert!(panel_h > 300, "no caption band: {}x{}", pic.width(), pic.height());
    for panel in 0..6u32 {
        let (x0, y0) = ((panel % 3) * 480, (panel / 3) * panel_h + 300);
        let band: Vec<_> = (y0..y0 + panel_h - 300).flat_map(|y| (x0..x0 + 480).map(move |x| (x, y))).collect();
        let ink = band.iter().filter(|(x, y)| pic.get_pixel(*x, *y).0.iter().all(|c| *c < 60)).count();
        assert!(ink > 100, "panel {panel} has no label ({ink} dark pixels)");
    }
    // Each panel's picture (480 x 300, a world's 1280 x 800 overview scaled by 3/8): the world's
    // mesh, framed inside 95 % of the view (see the overview test in cli.rs), so bands of 10
    // columns on each side and 6 rows at the top and bottom are white background (12 and 7.5
    // scaled, less a pixel for the filter), and the mesh covers at least a quarter of it
    // (measured: 38-41 % on the six panels).
    let mut pictures = Vec::new();
    for panel in 0..6u32 {
        let (x0, y0) = ((panel % 3) * 480, (panel / 3) * panel_h);
        let mut mesh = 0usize;
        let mut picture = Vec::with_capacity(480 * 300);
        for y in 0..300 {
            for x in 0..480 {
                let p = pic.get_pixel(x0 + x, y0 + y).0;
                let border = !(10..470).contains(&x) || !(6..294).contains(&y);
                assert!(!border || p == [255; 3], "panel {panel}: ({x}, {y}) = {p:?} outside the framed mesh");
                mesh += usize::from(p != [255; 3]);
                picture.push(p);
            }
        }
        assert!(mesh >= 480 * 300 / 4, "panel {panel} shows a mesh in {mesh} pixels only");
        pictures.push(picture);
    }
    // six worlds grown six ways: no two pictures alike
    for i in 0..6 {
        for j in 0..i {
            assert!(pictures[i] != pictures[j], "panels {j} and {i} show the same picture");
        }
    }
}
