//! The browser viewer (`sgam view`, RUN/world.html) through the real binary, on a tiny world:
//! what the page holds, that poses drawn the way the page draws them lie over the mesh, the
//! served endpoints, and (when a Chromium is installed, and always under CI=true) the page
//! opened in headless Chromium.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

mod common;
use common::{ok, sgam};

use sgam_core::Vec3;

/// The vendored bundle and the page's code, as the binary embeds them.
const THREE_BUNDLE: &str = include_str!("../assets/viewer/three.bundle.min.js");
const VIEWER_JS: &str = include_str!("../assets/viewer/viewer.js");

/// A tiny finished run (null refiner, 32 x 32 px, 6 steps) in `tmp/run`.
fn tiny_run(tmp: &Path) -> PathBuf {
    let run = tmp.join("run");
    ok(&["generate", "--out", run.to_str().unwrap(), "--res", "32", "--steps", "6", "--refiner", "null", "--no-video"]);
    run
}

/// `sgam view RUN --no-open [extra]`: the page's text.
fn view(run: &Path, extra: &[&str]) -> String {
    let mut args = vec!["view", run.to_str().unwrap(), "--no-open"];
    args.extend_from_slice(extra);
    let out = sgam(&args);
    assert!(out.status.success(), "sgam view failed:\n{}", String::from_utf8_lossy(&out.stderr));
    let printed = String::from_utf8(out.stdout).unwrap();
    assert_eq!(Path::new(printed.trim()), run.join("world.html"), "sgam view prints the page's path");
    std::fs::read_to_string(run.join("world.html")).unwrap()
}

/// The text of `<script id="ID" ...>` in the page.
fn script<'a>(html: &'a str, id: &str) -> &'a str {
    let open = format!("<script id=\"{id}\"");
    let start = html.find(&open).unwrap_or_else(|| panic!("no {open}"));
    let body = start + html[start..].find('>').unwrap() + 1;
    &html[body..body + html[body..].find("</script>").unwrap()]
}

fn base64_decode(text: &str) -> Vec<u8> {
    let value = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {c}"),
    };
    let bytes: Vec<u8> = text.bytes().filter(|c| !c.is_ascii_whitespace()).collect();
    assert_eq!(bytes.len() % 4, 0, "base64 length");
    let mut out = Vec::with_capacity(bytes.len() / 4 * 3);
    for quad in bytes.chunks(4) {
        let pad = quad.iter().filter(|&&c| c == b'=').count();
        let n =
            quad.iter().take(4 - pad).enumerate().fold(0u32, |n, (k, &c)| n | (u32::from(value(c)) << (18 - 6 * k)));
        out.extend_from_slice(&n.to_be_bytes()[1..4 - pad]);
    }
    out
}

/// The POSITION accessor's vertices of a GLB (glTF axes), read through its JSON.
fn glb_positions(glb: &[u8]) -> Vec<Vec3> {
    let u32_at = |o: usize| u32::from_le_bytes(glb[o..o + 4].try_into().unwrap()) as usize;
    assert_eq!(&glb[0..4], b"glTF");
    assert_eq!(u32_at(8), glb.len(), "GLB length field");
    let json_len = u32_at(12);
    let json: serde_json::Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    let bin = &glb[20 + json_len + 8..];
    let prim = &json["meshes"][0]["primitives"][0];
    let acc = &json["accessors"][prim["attributes"]["POSITION"].as_u64().unwrap() as usize];
    assert_eq!(acc["componentType"], 5126);
    let view = &json["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
    let off = view["byteOffset"].as_u64().unwrap_or(0) as usize;
    let f = |i: usize| f32::from_le_bytes(bin[off + 4 * i..off + 4 * i + 4].try_into().unwrap());
    (0..acc["count"].as_u64().unwrap() as usize).map(|v| Vec3::new(f(3 * v), f(3 * v + 1), f(3 * v + 2))).collect()
}

fn ply_vertex_count(path: &Path) -> usize {
    let bytes = std::fs::read(path).unwrap();
    let header = String::from_utf8_lossy(&bytes[..bytes.len().min(1024)]).into_owned();
    let line = header.lines().find(|l| l.starts_with("element vertex ")).unwrap();
    line["element vertex ".len()..].trim().parse().unwrap()
}

#[test]
fn world_html_holds_the_bundle_and_a_mesh_that_decodes_to_the_runs_vertex_count() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tiny_run(tmp.path());
    let html = view(&run, &[]);
    assert!(html.contains(THREE_BUNDLE), "the page lacks the three.js bundle");
    assert!(html.contains(VIEWER_JS), "the page lacks viewer.js");
    assert!(!html.contains("{{"), "a template key was left unfilled");
    // nothing from the network: no address in the page but the XHTML namespace (a name three.js
    // creates elements in, never fetched)
    let rest = html.replace("http://www.w3.org/1999/xhtml", "");
    assert!(!rest.contains("http://") && !rest.contains("https://"), "the page names a network address");
    let data: serde_json::Value = serde_json::from_str(script(&html, "sgam-data")).unwrap();
    let glb = base64_decode(script(&html, "sgam-mesh"));
    assert_eq!(glb, std::fs::read(run.join("mesh.glb")).unwrap(), "the embedded mesh is not mesh.glb");
    let run_json: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("run.json")).unwrap()).unwrap();
    let vertices = run_json["map"]["vertices"].as_u64().unwrap() as usize;
    assert!(vertices > 100, "tiny world has {vertices} vertices");
    assert_eq!(glb_positions(&glb).len(), vertices);
    assert_eq!(ply_vertex_count(&run.join("mesh.ply")), vertices);
    assert_eq!(data["mesh"]["vertices"].as_u64().unwrap() as usize, vertices);
    assert_eq!(data["mesh"]["embedded"], true);
    // one pose, frame path and thumbnail per frame (seed + 6 steps); thumbnails are JPEGs
    assert_eq!(data["poses"].as_array().unwrap().len(), 7);
    assert_eq!(data["frames"][6], "rgb/00006.png");
    let thumbs = data["thumbs"]["rgb"].as_array().unwrap();
    assert_eq!(thumbs.len(), 7);
    let jpeg = base64_decode(thumbs[3].as_str().unwrap().strip_prefix("data:image/jpeg;base64,").unwrap());
    let img = image::load_from_memory_with_format(&jpeg, image::ImageFormat::Jpeg).unwrap();
    assert_eq!((img.width(), img.height()), (32, 32));
    assert!(data["thumbs"]["guidance"].is_null(), "this run kept no guidance frames");
}

/// Row-major 3x3 numbers as a function on vectors.
fn rotation(rows: &[f32]) -> impl Fn(Vec3) -> Vec3 + '_ {
    move |v| {
        Vec3::new(
            rows[0] * v.x + rows[1] * v.y + rows[2] * v.z,
            rows[3] * v.x + rows[4] * v.y + rows[5] * v.z,
            rows[6] * v.x + rows[7] * v.y + rows[8] * v.z,
        )
    }
}

/// Whether every camera centre (world, z up), taken to the page's axes by `three_from_world`,
/// lies above the mesh's ground (5th percentile of the heights of `mesh` along `up`) and over
/// the mesh's horizontal extent (its 2nd..98th percentile box, grown by 10 %). Returns the
/// first failure.
fn poses_over_mesh(
    centres_world: &[Vec3],
    three_from_world: &dyn Fn(Vec3) -> Vec3,
    up: Vec3,
    mesh: &[Vec3],
) -> Result<(), String> {
    let up = up.normalize();
    let e1 = if up.x.abs() < 0.9 { Vec3::X } else { Vec3::Y }.cross(up).normalize();
    let e2 = up.cross(e1);
    let quantile = |mut v: Vec<f32>, q: f32| {
        v.sort_by(f32::total_cmp);
        v[((v.len() - 1) as f32 * q) as usize]
    };
    let heights: Vec<f32> = mesh.iter().map(|p| p.dot(up)).collect();
    let ground = quantile(heights, 0.05);
    let range = |e: Vec3| {
        let v: Vec<f32> = mesh.iter().map(|p| p.dot(e)).collect();
        let (lo, hi) = (quantile(v.clone(), 0.02), quantile(v, 0.98));
        let m = 0.1 * (hi - lo);
        (lo - m, hi + m)
    };
    let (r1, r2) = (range(e1), range(e2));
    for (i, c) in centres_world.iter().enumerate() {
        let p = three_from_world(*c);
        if p.dot(up) <= ground + 0.5 {
            return Err(format!("camera {i} at height {} is not above the ground at {ground}", p.dot(up)));
        }
        let (a, b) = (p.dot(e1), p.dot(e2));
        if !(r1.0..=r1.1).contains(&a) || !(r2.0..=r2.1).contains(&b) {
            return Err(format!("camera {i} at ({a}, {b}) is beside the mesh ({r1:?}, {r2:?})"));
        }
    }
    Ok(())
}

#[test]
fn poses_drawn_the_way_the_page_draws_them_lie_over_the_mesh() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tiny_run(tmp.path());
    let html = view(&run, &[]);
    let data: serde_json::Value = serde_json::from_str(script(&html, "sgam-data")).unwrap();
    let mesh = glb_positions(&base64_decode(script(&html, "sgam-mesh")));
    let nums =
        |v: &serde_json::Value| v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect::<Vec<_>>();
    // what viewer.js does: position = three_from_world * t, up = three_from_world * up_world
    let m = nums(&data["three_from_world"]);
    let up_world = nums(&data["up_world"]);
    let centres: Vec<Vec3> = data["poses"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| {
            let p = nums(p);
            Vec3::new(p[3], p[7], p[11])
        })
        .collect();
    // the poses are those of transforms.json
    let t = sgam_io::read_nerf_transforms(&run.join("transforms.json")).unwrap();
    for (c, f) in centres.iter().zip(&t.frames) {
        assert!((*c - f.world_from_camera.translation).length() < 1e-4);
    }
    let three_from_world = rotation(&m);
    let up = three_from_world(Vec3::new(up_world[0], up_world[1], up_world[2]));
    poses_over_mesh(&centres, &three_from_world, up, &mesh).unwrap();
    // the check has teeth: poses left in world axes (z up) over the y-up mesh are under it, and
    // a mirrored axis change puts them beside it
    let as_is = |v: Vec3| v;
    assert!(poses_over_mesh(&centres, &as_is, Vec3::Y, &mesh).is_err());
    let mirrored = |v: Vec3| Vec3::new(v.x, v.z, v.y);
    assert!(poses_over_mesh(&centres, &mirrored, Vec3::Y, &mesh).is_err());
}

#[test]
fn a_mesh_above_the_embed_limit_is_loaded_from_the_neighbouring_file() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tiny_run(tmp.path());
    let embedded = view(&run, &[]).len();
    let html = view(&run, &["--embed-limit-mb", "0.001"]);
    let data: serde_json::Value = serde_json::from_str(script(&html, "sgam-data")).unwrap();
    assert_eq!(data["mesh"]["embedded"], false);
    assert_eq!(data["mesh"]["src"], "mesh.glb");
    assert!(script(&html, "sgam-mesh").trim().is_empty());
    let glb = std::fs::metadata(run.join("mesh.glb")).unwrap().len() as usize;
    assert!(html.len() + glb < embedded, "page without the mesh: {} bytes, with: {embedded}", html.len());
}

#[test]
fn kept_guidance_and_missing_masks_go_on_the_timeline() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tiny_run(tmp.path());
    for kind in ["guidance", "missing"] {
        std::fs::create_dir(run.join(kind)).unwrap();
        for i in 0..7 {
            image::RgbImage::from_pixel(32, 32, image::Rgb([i * 30, 0, 0]))
                .save(run.join(format!("{kind}/{i:05}.png")))
                .unwrap();
        }
    }
    // a missing mask lacking for one frame: none are shown (a timeline with holes would mislead)
    std::fs::remove_file(run.join("missing/00004.png")).unwrap();
    let html = view(&run, &[]);
    let data: serde_json::Value = serde_json::from_str(script(&html, "sgam-data")).unwrap();
    let guidance = data["thumbs"]["guidance"].as_array().unwrap();
    assert_eq!(guidance.len(), 7);
    let jpeg = base64_decode(guidance[5].as_str().unwrap().strip_prefix("data:image/jpeg;base64,").unwrap());
    let px = image::load_from_memory(&jpeg).unwrap().to_rgb8().get_pixel(16, 16).0;
    assert!(px[0].abs_diff(150) <= 8 && px[1] <= 8, "guidance thumbnail of frame 5 is {px:?}, not its picture");
    assert!(data["thumbs"]["missing"].is_null());
}

#[test]
fn view_refuses_a_folder_that_is_not_a_run() {
    let tmp = tempfile::tempdir().unwrap();
    let out = sgam(&["view", tmp.path().to_str().unwrap(), "--no-open"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("transforms.json") && err.contains(tmp.path().to_str().unwrap()), "{err}");
    assert!(!tmp.path().join("world.html").exists());
}

/// `GET path` on `addr`: status code and body.
fn get(addr: SocketAddr, path: &str) -> std::io::Result<(u16, Vec<u8>)> {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(5))?;
    s.set_read_timeout(Some(Duration::from_secs(30)))?;
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n")?;
    let mut bytes = Vec::new();
    s.read_to_end(&mut bytes)?;
    let split = bytes.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
    let code = String::from_utf8_lossy(&bytes[..split]).split_whitespace().nth(1).unwrap().parse().unwrap();
    Ok((code, bytes[split + 4..].to_vec()))
}

#[test]
fn view_serve_answers_on_loopback_until_stopped() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tiny_run(tmp.path());
    let mut child = Command::new(env!("CARGO_BIN_EXE_sgam"))
        .args(["view", run.to_str().unwrap(), "--serve", "--port", "0", "--no-open"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // stdout: the page's path, then the address
    let mut stdout = child.stdout.take().unwrap();
    let mut printed = String::new();
    let mut buf = [0u8; 256];
    while printed.lines().count() < 2 {
        let n = stdout.read(&mut buf).unwrap();
        assert!(n > 0, "sgam view --serve ended early: {printed}");
        printed.push_str(&String::from_utf8_lossy(&buf[..n]));
    }
    let url = printed.lines().nth(1).unwrap().trim().to_string();
    let addr: SocketAddr = url.trim_start_matches("http://").trim_end_matches('/').parse().unwrap();
    assert!(addr.ip().is_loopback(), "{url}");
    let result = std::panic::catch_unwind(|| {
        assert_eq!(get(addr, "/").unwrap(), (200, std::fs::read(run.join("world.html")).unwrap()));
        assert_eq!(get(addr, "/mesh.glb").unwrap(), (200, std::fs::read(run.join("mesh.glb")).unwrap()));
        assert_eq!(get(addr, "/rgb/00003.png").unwrap().0, 200);
        assert_eq!(get(addr, "/snapshot.bin").unwrap().0, 404);
        assert_eq!(get(addr, "/../run.json").unwrap().0, 400);
    });
    child.kill().unwrap();
    child.wait().unwrap();
    result.unwrap();
    assert!(get(addr, "/").is_err(), "the port still answers after the server ended");
}

// ---- the page in a real browser --------------------------------------------------------------

/// A Chromium binary: $SGAM_CHROMIUM, else chromium / chromium-browser / google-chrome on PATH.
fn find_chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("SGAM_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    let path = std::env::var_os("PATH")?;
    ["chromium", "chromium-browser", "google-chrome", "google-chrome-stable"]
        .iter()
        .flat_map(|name| std::env::split_paths(&path).map(move |dir| dir.join(name)))
        .find(|p| p.is_file())
}

/// Runs headless Chromium (software WebGL) on `url`, killing it after `limit`.
fn chromium(bin: &Path, url: &str, extra: &[String], limit: Duration) -> Output {
    let profile = tempfile::tempdir().unwrap();
    let mut child = Command::new(bin)
        .args([
            "--headless",
            "--no-sandbox", // needed as root (CI); the page is our own local file
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--hide-scrollbars",
            "--window-size=960,640",
            "--virtual-time-budget=30000",
            "--enable-logging=stderr",
            "--v=0",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .args(extra)
        .arg(url)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > limit {
            child.kill().unwrap();
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    child.wait_with_output().unwrap()
}

#[test]
fn the_page_opens_in_headless_chromium_with_the_mesh_on_screen() {
    let Some(bin) = find_chromium() else {
        if std::env::var("CI").is_ok_and(|v| v == "true") {
            panic!("CI=true but no chromium on PATH: .ci/run installs it (apt-get install chromium)");
        }
        eprintln!("skipping the_page_opens_in_headless_chromium: no chromium found (set SGAM_CHROMIUM or install it)");
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let run = tiny_run(tmp.path());
    view(&run, &[]);
    let page = run.join("world.html").canonicalize().unwrap();
    let shot = tmp.path().join("shot.png");
    let out = chromium(
        &bin,
        &format!("file://{}#selftest", page.display()),
        &[format!("--screenshot={}", shot.display())],
        Duration::from_secs(180),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    let console: Vec<&str> = stderr.lines().filter(|l| l.contains(":CONSOLE")).collect();
    eprintln!("console:\n{}", console.join("\n"));
    // the ready line: mesh on screen, no errors counted by the page, every camera over the mesh
    let ready = console.iter().find(|l| l.contains("sgam-ready")).unwrap_or_else(|| panic!("never ready:\n{stderr}"));
    let run_json: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("run.json")).unwrap()).unwrap();
    let vertices = run_json["map"]["vertices"].as_u64().unwrap();
    assert!(ready.contains(&format!("vertices={vertices} ")), "{ready}");
    assert!(ready.contains("errors=0 "), "{ready}");
    assert!(ready.contains("selftest down=7/7 up=0/7"), "a camera is not over the mesh: {ready}");
    // Chromium logs every console message at one level: errors are told by their words
    let is_error = |l: &str| {
        let l = l.to_ascii_lowercase();
        ["error", "uncaught", "exception", "failed", "gl_"].iter().any(|w| l.contains(w))
    };
    let errors: Vec<&str> = console.iter().copied().filter(|l| !l.contains("sgam-ready") && is_error(l)).collect();
    assert!(errors.is_empty(), "console errors:\n{}", errors.join("\n"));
    // the screenshot: the middle of the window (clear of the panels) is mostly mesh, not the
    // page's background, in many colours
    let img = image::open(&shot).unwrap_or_else(|e| panic!("no screenshot ({e}):\n{stderr}")).to_rgb8();
    assert_eq!(img.dimensions(), (960, 640));
    let background = [0xe8u8, 0xee, 0xf3];
    let (mut mesh_px, mut total) = (0usize, 0usize);
    let mut colours = std::collections::HashSet::new();
    for y in 160..480 {
        for x in 200..700 {
            let p = img.get_pixel(x, y).0;
            total += 1;
            let diff: i32 = (0..3).map(|c| (i32::from(p[c]) - i32::from(background[c])).abs()).sum();
            if diff > 30 {
                mesh_px += 1;
                colours.insert(p.map(|v| v >> 3));
            }
        }
    }
    let covered = mesh_px as f64 / total as f64;
    eprintln!("mesh covers {:.0} % of the middle, {} colours", 100.0 * covered, colours.len());
    assert!(covered > 0.2, "the mesh covers only {:.1} % of the middle of the window", 100.0 * covered);
    assert!(colours.len() > 30, "a flat picture ({} colours)", colours.len());
}

#[test]
fn a_tiled_world_opens_coarse_and_served_loads_full_detail_near_the_view() {
    let Some(bin) = find_chromium() else {
        if std::env::var("CI").is_ok_and(|v| v == "true") {
            panic!("CI=true but no chromium on PATH: .ci/run installs it (apt-get install chromium)");
        }
        eprintln!("skipping a_tiled_world_opens_coarse: no chromium found (set SGAM_CHROMIUM or install it)");
        return;
    };
    // a world whose map outgrew --max-map-mb (2 cm voxels along 33 m rows), so it is in tiles
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("run");
    #[rustfmt::skip]
    ok(&["generate", "--out", run.to_str().unwrap(), "--refiner", "null", "--res", "32", "--voxel-size", "0.02",
         "--depth-max", "15", "--trajectory", "boustrophedon", "--grid", "82", "--steps", "100",
         "--max-map-mb", "16", "--snapshot-every", "1000", "--no-video"]);
    let html = view(&run, &[]);
    let data: serde_json::Value = serde_json::from_str(script(&html, "sgam-data")).unwrap();
    assert_eq!(data["mesh"]["src"], "mesh-tiles/coarse.glb");
    let cells = data["tiles"]["cells"].as_array().unwrap();
    assert!(cells.len() > 4, "{} cells", cells.len());
    let coarse = data["mesh"]["vertices"].as_u64().unwrap();
    assert!(coarse > 1000, "{coarse} vertices in the coarse world");
    let mut child = Command::new(env!("CARGO_BIN_EXE_sgam"))
        .args(["view", run.to_str().unwrap(), "--serve", "--port", "0", "--no-open"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut stdout = child.stdout.take().unwrap();
    let mut printed = String::new();
    let mut buf = [0u8; 256];
    while printed.lines().count() < 2 {
        let n = stdout.read(&mut buf).unwrap();
        assert!(n > 0, "sgam view --serve ended early: {printed}");
        printed.push_str(&String::from_utf8_lossy(&buf[..n]));
    }
    let url = format!("{}world.html", printed.lines().nth(1).unwrap().trim());
    let out = chromium(&bin, &url, &[], Duration::from_secs(180));
    child.kill().unwrap();
    child.wait().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    let console: Vec<&str> = stderr.lines().filter(|l| l.contains(":CONSOLE")).collect();
    eprintln!("console:\n{}", console.join("\n"));
    // the whole world at once, coarse; then the cells near the view in full detail
    let ready = console.iter().find(|l| l.contains("sgam-ready")).unwrap_or_else(|| panic!("never ready:\n{stderr}"));
    assert!(ready.contains(&format!("vertices={coarse} ")) && ready.contains("errors=0\""), "{ready}");
    let fine = console.iter().filter(|l| l.contains("sgam-fine cells=")).count();
    assert!(fine >= 1, "no cell was loaded in full detail");
    let is_error = |l: &str| {
        let l = l.to_ascii_lowercase();
        ["error", "uncaught", "exception", "failed", "gl_", "could not be loaded"].iter().any(|w| l.contains(w))
    };
    let errors: Vec<&str> = console.iter().copied().filter(|l| !l.contains("sgam-ready") && is_error(l)).collect();
    assert!(errors.is_empty(), "console errors:\n{}", errors.join("\n"));
}
