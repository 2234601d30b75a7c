//! `sgam view`: (re)writes a run's browser viewer (`RUN/world.html`, built by
//! [`crate::viewer_page`]) and opens it, or serves the run folder on 127.0.0.1.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use sgam_core::Vec3;

use crate::serve::Server;

/// The vendored three.js bundle (three + OrbitControls + GLTFLoader; see assets/viewer/README.md).
pub const THREE_BUNDLE: &str = include_str!("../assets/viewer/three.bundle.min.js");
/// The page's own code.
pub const VIEWER_JS: &str = include_str!("../assets/viewer/viewer.js");
/// The page template (`{{TITLE}}`, `{{DATA}}`, `{{MESH}}`, `{{THREE}}`, `{{VIEWER}}`).
pub const VIEWER_HTML: &str = include_str!("../assets/viewer/viewer.html");

/// Meshes above this many bytes of GLB are not embedded (default of `--embed-limit-mb`).
pub const DEFAULT_EMBED_LIMIT_BYTES: u64 = 30_000_000;
/// Default port of `--serve` / `--view` (another free one when it is taken).
pub const DEFAULT_PORT: u16 = 7117;
/// Longest side of the embedded frame thumbnails, pixels.
pub const THUMB_SIDE: u32 = 160;
/// At most this many frustums are drawn along the path (plus the seed and the current frame).
pub const MAX_FRUSTUMS: usize = 60;

/// Arguments of `sgam view`.
#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  sgam view runs/world-001            # (re)write runs/world-001/world.html and open it\n  \
                  sgam view runs/big --serve          # serve it on 127.0.0.1 (meshes too large to embed)"
)]
pub struct ViewArgs {
    /// Run folder written by `sgam generate` (mesh.glb, transforms.json, rgb/).
    pub run: PathBuf,
    /// Serve the run folder on 127.0.0.1 until Ctrl-C (needed when the mesh is too large to
    /// embed: the page then loads mesh.glb from the server).
    #[arg(long)]
    pub serve: bool,
    /// Port of --serve (0: any free port; a taken port falls back to a free one).
    #[arg(long, default_value_t = DEFAULT_PORT)]
    pub port: u16,
    /// Embed meshes up to this size (MB of GLB) in the page; larger ones are loaded from the
    /// neighbouring mesh.glb.
    #[arg(long, default_value_t = DEFAULT_EMBED_LIMIT_BYTES as f64 / 1e6)]
    pub embed_limit_mb: f64,
    /// Do not open the page in a browser (by default it is opened with xdg-open when there is
    /// a display).
    #[arg(long)]
    pub no_open: bool,
    /// Also (re)write RUN/flythrough.mp4 from the run's frames (H.264; see the README on
    /// licensing).
    #[arg(long)]
    pub mp4: bool,
    /// Also write RUN/orbit.mp4: one turn around the world, rendered from RUN/map.bin.
    #[arg(long)]
    pub orbit_video: bool,
}

/// Runs `sgam view`.
pub fn run(args: ViewArgs) -> Result<()> {
    crate::guard::in_range("--embed-limit-mb", args.embed_limit_mb, 0.0..=4000.0)?;
    let page = write_world_html(&args.run, (args.embed_limit_mb * 1e6) as u64)?;
    println!("{}", page.path.display());
    eprintln!(
        "world.html: {:.1} MB, mesh {} ({:.1} MB, {} vertices), {} frames",
        page.bytes as f64 / 1e6,
        if page.mesh_embedded { "embedded" } else { "loaded from mesh.glb" },
        page.mesh_bytes as f64 / 1e6,
        page.vertices,
        page.frames
    );
    let (cams, _) = run_cameras(&args.run)?;
    let report = |name: &str, v: crate::video::VideoInfo| {
        let (path, mb) = (args.run.join(name), v.bytes as f64 / 1e6);
        eprintln!("{}: {} frames of {} x {} px, {mb:.1} MB", path.display(), v.frames, v.width, v.height);
    };
    if args.mp4 {
        report("flythrough.mp4", crate::video::write_flythrough_mp4(&args.run, cams.len())?);
    }
    if args.orbit_video {
        let up = cams.first().map(up_world).unwrap_or(Vec3::Z);
        report("orbit.mp4", crate::video::write_run_orbit_mp4(&args.run, up)?);
    }
    if args.serve {
        let server = Server::start(&args.run, args.port)?;
        println!("{}", server.url());
        eprintln!("serving {} on {} (Ctrl-C to stop)", args.run.display(), server.url());
        if !args.no_open {
            open_in_browser(&server.url());
        }
        server.wait();
        return Ok(());
    }
    if !page.mesh_embedded {
        eprintln!("the mesh is too large to embed: open the page with `sgam view {} --serve`", args.run.display());
    }
    if !args.no_open {
        open_in_browser(&page.path.display().to_string());
    }
    Ok(())
}

/// `target` as a browser opens it: URLs as they are, files as `file://` addresses.
fn browser_address(target: &str) -> String {
    if target.contains("://") {
        return target.to_string();
    }
    let path = std::path::Path::new(target);
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    format!("file://{}", absolute.display())
}

/// Opens `target` with `xdg-open` when there is a display, else says what to open; never fails
/// (no browser is fine).
pub fn open_in_browser(target: &str) {
    let display = ["DISPLAY", "WAYLAND_DISPLAY"].iter().any(|v| std::env::var_os(v).is_some_and(|s| !s.is_empty()));
    if !display {
        eprintln!("no display: open {} in a browser", browser_address(target));
        return;
    }
    let spawned = std::process::Command::new("xdg-open")
        .arg(target)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn();
    if spawned.is_err() {
        eprintln!("(xdg-open is not available: open {target} in a browser)");
    }
}

pub use crate::viewer_page::*;
