//! `sgam generate --view`: the viewer served on 127.0.0.1 while the world grows. Every
//! `every` steps the map's mesh is extracted (the only work on the generator's thread; the
//! generator meshes with the same weight threshold, so nothing it computes changes) and handed
//! to a worker thread that encodes the GLB and publishes it with the poses so far. Extraction
//! waits until the time since the last one is at least 1/[`MAX_SHARE`] times what the last one
//! took, so it never costs more than that share of the run however large the world grows; a
//! step that comes earlier, or while the worker is busy, only updates the poses. Nothing is written into the run
//! folder and errors only end the live view, never the run.
//!
//! [`LiveView::off`] is the stand-in the generator holds when `--view` is not given: every call
//! returns at once.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{sync_channel, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use sgam_core::{Camera, TriMesh};
use sgam_map::TsdfMap;

use crate::serve::{Memory, Server};
use crate::view::{glb_counts, live_page_html, LiveState};

/// How often the live page asks for the state, milliseconds.
pub const POLL_MS: u32 = 1500;
/// Default steps between mesh updates.
pub const DEFAULT_EVERY: usize = 10;
/// Largest share of the run's time that mesh extraction for the live page may take.
pub const MAX_SHARE: f64 = 0.05;

/// The live view of a growing run, or its stand-in.
#[derive(Debug)]
pub struct LiveView {
    inner: Option<Live>,
}

#[derive(Debug)]
struct Live {
    server: Server,
    every: usize,
    last_step: usize,
    /// When the last mesh extraction started and how long it took.
    last_extract: Option<(Instant, Duration)>,
    version: u64,
    /// The mesh the page shows.
    shown: Arc<Mutex<Option<Shown>>>,
    busy: Arc<AtomicBool>,
    jobs: Option<SyncSender<Job>>,
    worker: Option<JoinHandle<()>>,
    /// Milliseconds the generator's thread spent in each mesh update (extraction).
    extract_ms: Vec<f64>,
}

/// A mesh published to the page: its version, GLB size (bytes), vertices and triangles.
#[derive(Debug, Clone, Copy)]
struct Shown {
    version: u64,
    bytes: u64,
    vertices: u64,
    triangles: u64,
}

#[derive(Debug)]
struct Job {
    version: u64,
    mesh: TriMesh,
    state: LiveState,
}

impl LiveView {
    /// The stand-in: no server, every call returns at once.
    pub fn off() -> Self {
        Self { inner: None }
    }

    /// Serves the live page of the run in `dir` on `127.0.0.1:port` (a free port when taken)
    /// when `on`, updating the mesh every `every` steps; prints the address.
    pub fn start_if(on: bool, dir: &std::path::Path, port: u16, every: usize) -> Result<Self> {
        if !on {
            return Ok(Self::off());
        }
        let server = Server::start(dir, port)?;
        let name = dir
            .canonicalize()
            .ok()
            .and_then(|d| d.file_name().map(|s| s.to_string_lossy().into_owned()))
            .unwrap_or_else(|| "world".into());
        let page = live_page_html(&format!("{name} (growing)"), POLL_MS)?;
        server.set("world.html", "text/html; charset=utf-8", page.into_bytes());
        server.set("live.json", "application/json", serde_json::to_vec(&LiveState::new(0, 0, &[]))?);
        let memory = server.memory();
        let shown = Arc::new(Mutex::new(None));
        let busy = Arc::new(AtomicBool::new(false));
        let (jobs, rx) = sync_channel::<Job>(1);
        let tmp = tempfile::tempdir().context("live view: cannot make a temporary folder")?;
        let (s, b) = (shown.clone(), busy.clone());
        let worker = std::thread::Builder::new().name("sgam-live".into()).spawn(move || {
            for job in rx {
                if let Err(e) = publish(&memory, tmp.path(), &s, job) {
                    eprintln!("live view: {e:#}");
                }
                b.store(false, Ordering::SeqCst);
            }
        })?;
        eprintln!("live view: {}  (the page follows the run and stops with it; afterwards open world.html, or serve it with `sgam view RUN --serve`)", server.url());
        crate::view::open_in_browser(&server.url());
        Ok(Self {
            inner: Some(Live {
                server,
                every: every.max(1),
                last_step: 0,
                last_extract: None,
                version: 0,
                shown,
                busy,
                jobs: Some(jobs),
                worker: Some(worker),
                extract_ms: Vec::new(),
            }),
        })
    }

    /// The address served (`None` for the stand-in).
    #[cfg(test)]
    pub fn url(&self) -> Option<String> {
        self.inner.as_ref().map(|l| l.server.url())
    }

    /// After generation step `step` of `total`: every `every` steps (and at the last one) the
    /// poses go to the page, and the mesh too when the worker is free and the time budget
    /// ([`MAX_SHARE`]) allows. Never fails the run: a failure ends the live view with a message.
    pub fn after_step(&mut self, step: usize, total: usize, map: &mut TsdfMap, cameras: &[Camera]) {
        let Some(live) = &mut self.inner else { return };
        let due = step >= live.last_step + live.every || step + 1 >= total || live.version == 0;
        if !due {
            return;
        }
        live.last_step = step;
        let mut state = LiveState::new(step, total, cameras);
        let in_budget =
            live.last_extract.is_none_or(|(at, took)| at.elapsed().as_secs_f64() * MAX_SHARE >= took.as_secs_f64());
        if !in_budget || live.busy.swap(true, Ordering::SeqCst) {
            // too soon, or the previous mesh is still being encoded: poses only, with the mesh
            // shown now
            state.mesh = mesh_ref(*live.shown.lock().unwrap_or_else(PoisonError::into_inner));
            match serde_json::to_vec(&state) {
                Ok(json) => live.server.set("live.json", "application/json", json),
                Err(e) => eprintln!("live view: {e}"),
            }
            return;
        }
        let t = Instant::now();
        let mesh = map.extract_mesh();
        live.last_extract = Some((t, t.elapsed()));
        live.extract_ms.push(t.elapsed().as_secs_f64() * 1000.0);
        live.version += 1;
        let job = Job { version: live.version, mesh, state };
        let sent = match &live.jobs {
            Some(tx) => tx.try_send(job),
            None => return,
        };
        if let Err(TrySendError::Disconnected(_)) = sent {
            eprintln!("live view: the worker stopped; the run goes on without it");
            live.jobs = None;
        }
    }

    /// Milliseconds the generator's thread spent per mesh update so far.
    #[cfg(test)]
    pub fn extract_ms(&self) -> &[f64] {
        self.inner.as_ref().map_or(&[], |l| &l.extract_ms)
    }

    /// The run's last state (marked finished) goes to the page, which stops polling; the server
    /// stays up for one more poll, then stops.
    pub fn finish(mut self, cameras: &[Camera]) {
        let Some(mut live) = self.inner.take() else { return };
        drop(live.jobs.take());
        if let Some(w) = live.worker.take() {
            let _ = w.join();
        }
        let total = cameras.len();
        let mut state = LiveState::new(total.saturating_sub(1), total, cameras);
        state.finished = true;
        state.mesh = mesh_ref(*live.shown.lock().unwrap_or_else(PoisonError::into_inner));
        if let Ok(json) = serde_json::to_vec(&state) {
            live.server.set("live.json", "application/json", json);
        }
        std::thread::sleep(Duration::from_millis(u64::from(POLL_MS) + 500));
        let n = live.extract_ms.len();
        if n > 0 {
            let mean = live.extract_ms.iter().sum::<f64>() / n as f64;
            eprintln!("live view: {n} mesh updates, {mean:.1} ms each on the generator's thread");
        }
        live.server.stop();
    }
}

fn mesh_ref(shown: Option<Shown>) -> Option<serde_json::Value> {
    shown.map(|m| {
        serde_json::json!({
            "embedded": false, "src": format!("live/mesh.glb?v={}", m.version), "version": m.version,
            "bytes": m.bytes, "vertices": m.vertices, "triangles": m.triangles
        })
    })
}

/// Encodes the job's mesh as GLB (through a temporary file: `sgam_io::write_glb` is the one GLB
/// writer) and publishes it, then the state that names it.
fn publish(memory: &Memory, tmp: &std::path::Path, shown: &Mutex<Option<Shown>>, job: Job) -> Result<()> {
    let path = tmp.join("mesh.glb");
    sgam_io::write_glb(&path, &job.mesh)?;
    let glb = std::fs::read(&path).with_context(|| format!("{}: cannot read back", path.display()))?;
    let (vertices, triangles) = glb_counts(&path, &glb)?;
    let now = Shown { version: job.version, bytes: glb.len() as u64, vertices, triangles };
    memory.set("live/mesh.glb", "model/gltf-binary", glb);
    *shown.lock().unwrap_or_else(PoisonError::into_inner) = Some(now);
    let mut state = job.state;
    state.mesh = mesh_ref(Some(now));
    memory.set("live.json", "application/json", serde_json::to_vec(&state)?);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::serve::http_get;
    use sgam_map::TsdfConfig;

    #[test]
    fn the_stand_in_does_nothing() {
        let mut live = LiveView::off();
        let mut map = TsdfMap::new(TsdfConfig::default());
        live.after_step(1, 10, &mut map, &[]);
        assert!(live.url().is_none() && live.extract_ms().is_empty());
        live.finish(&[]);
    }

    #[test]
    fn the_live_page_gets_the_mesh_and_poses_as_the_run_grows() {
        let dir = tempfile::tempdir().unwrap();
        let mut live = LiveView::start_if(true, dir.path(), 0, 2).unwrap();
        let addr: std::net::SocketAddr =
            live.url().unwrap().trim_start_matches("http://").trim_end_matches('/').parse().unwrap();
        let (code, page) = http_get(addr, "/").unwrap();
        assert_eq!(code, 200);
        let page = String::from_utf8(page).unwrap();
        assert!(page.contains("\"live\":{\"state\":\"live.json\""));
        // a tiny world: a plane seen by one camera, integrated into the map
        let cam = sgam_pipeline::synthetic_seed_camera(32);
        let renderer = sgam_synth::Renderer::new(&sgam_synth::Scene::generate(1, &Default::default()));
        let frame = renderer.render(&cam, &Default::default()).frame;
        let mut map = TsdfMap::new(TsdfConfig { voxel_size_m: 0.2, trunc_voxels: 4.0, ..TsdfConfig::default() });
        map.integrate(&frame, &cam);
        map.update_mesh();
        let cams = vec![cam; 3];
        live.after_step(1, 3, &mut map, &cams[..2]);
        // the worker publishes within a moment
        let mut state = serde_json::Value::Null;
        for _ in 0..100 {
            state = serde_json::from_slice(&http_get(addr, "/live.json").unwrap().1).unwrap();
            if state["mesh"].is_object() {
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        assert_eq!(state["poses"].as_array().unwrap().len(), 2);
        let vertices = state["mesh"]["vertices"].as_u64().unwrap();
        assert!(vertices > 100, "{vertices} vertices");
        // the page fetches the relative address from /
        let (code, glb) = http_get(addr, &format!("/{}", state["mesh"]["src"].as_str().unwrap())).unwrap();
        assert_eq!(code, 200);
        assert_eq!(glb_counts(std::path::Path::new("live.glb"), &glb).unwrap().0, vertices);
        assert_eq!(live.extract_ms().len(), 1);
        live.finish(&cams);
        assert!(http_get(addr, "/live.json").is_err(), "still serving after finish");
    }
}
