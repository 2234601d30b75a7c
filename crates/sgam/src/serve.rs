//! A small read-only HTTP/1.1 server on 127.0.0.1 for the viewer (`sgam view --serve`,
//! `sgam generate --view`): files of one run folder plus in-memory resources (the live page's
//! state and mesh). std::net only; one short-lived thread per connection, `Connection: close`.
//!
//! Only `GET`/`HEAD` of plain relative paths (`[A-Za-z0-9._-]` segments, none starting with a
//! dot) with a known extension are answered; nothing outside the folder is reachable.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{Ipv4Addr, SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use anyhow::{Context, Result};

/// A resource held in memory: content type and bytes.
type Resource = (&'static str, Arc<Vec<u8>>);

/// What the server answers from.
#[derive(Debug)]
struct Routes {
    /// Canonical run folder.
    root: PathBuf,
    /// Paths (without the leading `/`) answered from memory before the folder.
    memory: Mutex<HashMap<String, Resource>>,
}

/// The in-memory resources of a [`Server`], shareable between threads.
#[derive(Debug, Clone)]
pub struct Memory(Arc<Routes>);

impl Memory {
    /// Serves `bytes` at `/path` (replacing what was there), before any file.
    pub fn set(&self, path: &str, content_type: &'static str, bytes: Vec<u8>) {
        let mut m = self.0.memory.lock().unwrap_or_else(PoisonError::into_inner);
        m.insert(path.trim_start_matches('/').to_string(), (content_type, Arc::new(bytes)));
    }
}

/// A running server; [`Server::stop`] (or dropping it) closes the port and ends the thread.
#[derive(Debug)]
pub struct Server {
    addr: SocketAddr,
    routes: Arc<Routes>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

/// Content type of a served file by extension; other extensions are not served.
fn content_type(path: &str) -> Option<&'static str> {
    let ext = path.rsplit_once('.')?.1;
    Some(match ext {
        "html" => "text/html; charset=utf-8",
        "js" => "text/javascript; charset=utf-8",
        "json" => "application/json",
        "glb" => "model/gltf-binary",
        "png" => "image/png",
        "jpg" | "jpeg" => "image/jpeg",
        "gif" => "image/gif",
        "mp4" => "video/mp4",
        _ => return None,
    })
}

/// The served path of a request target (`/a/b.png?x` -> `a/b.png`; `/` -> `world.html`), or
/// `None` for anything but plain relative segments.
pub fn request_path(target: &str) -> Option<String> {
    let path = target.split(['?', '#']).next()?.strip_prefix('/')?;
    if path.is_empty() {
        return Some("world.html".into());
    }
    let ok_segment = |s: &str| {
        !s.is_empty() && !s.starts_with('.') && s.bytes().all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b))
    };
    path.split('/').all(ok_segment).then(|| path.to_string())
}

impl Server {
    /// Starts serving `root` on `127.0.0.1:port` (`0`: any free port). When `port` is taken, a
    /// free port is used instead (the address says which).
    pub fn start(root: &Path, port: u16) -> Result<Self> {
        let root = root.canonicalize().with_context(|| format!("{}: cannot serve this folder", root.display()))?;
        let listener = TcpListener::bind((Ipv4Addr::LOCALHOST, port))
            .or_else(|_| TcpListener::bind((Ipv4Addr::LOCALHOST, 0)))
            .context("cannot listen on 127.0.0.1")?;
        let addr = listener.local_addr()?;
        let routes = Arc::new(Routes { root, memory: Mutex::new(HashMap::new()) });
        let stop = Arc::new(AtomicBool::new(false));
        let (r, s) = (routes.clone(), stop.clone());
        let thread = std::thread::Builder::new().name("sgam-serve".into()).spawn(move || {
            for conn in listener.incoming() {
                if s.load(Ordering::SeqCst) {
                    break;
                }
                let Ok(conn) = conn else { continue };
                let r = r.clone();
                // a failed answer concerns one browser request only
                let _ = std::thread::Builder::new().name("sgam-serve-conn".into()).spawn(move || {
                    let _ = answer(&r, conn);
                });
            }
        })?;
        Ok(Self { addr, routes, stop, thread: Some(thread) })
    }

    /// `http://127.0.0.1:PORT/`.
    pub fn url(&self) -> String {
        format!("http://{}/", self.addr)
    }

    /// The bound address.
    #[cfg(test)]
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Serves `bytes` at `/path` from memory (replacing what was there), before any file.
    pub fn set(&self, path: &str, content_type: &'static str, bytes: Vec<u8>) {
        self.memory().set(path, content_type, bytes);
    }

    /// A handle to the in-memory resources that other threads can hold.
    pub fn memory(&self) -> Memory {
        Memory(self.routes.clone())
    }

    /// Closes the port and waits for the accept loop to end (answers in flight finish).
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // wake the blocking accept
        let _ = TcpStream::connect_timeout(&self.addr, Duration::from_secs(1));
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }

    /// Blocks until the process is ended (Ctrl-C).
    pub fn wait(mut self) {
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        if self.thread.is_some() {
            self.shutdown();
        }
    }
}

fn answer(routes: &Routes, conn: TcpStream) -> std::io::Result<()> {
    conn.set_read_timeout(Some(Duration::from_secs(10)))?;
    conn.set_write_timeout(Some(Duration::from_secs(60)))?;
    let mut reader = BufReader::new(conn.try_clone()?.take(16 * 1024));
    let mut line = String::new();
    reader.read_line(&mut line)?;
    // drain the headers (bounded by the take above)
    let mut header = String::new();
    while reader.read_line(&mut header)? > 2 {
        header.clear();
    }
    let mut out = conn;
    let mut parts = line.split_whitespace();
    let (method, target) = (parts.next().unwrap_or(""), parts.next().unwrap_or(""));
    if method != "GET" && method != "HEAD" {
        return respond(&mut out, "405 Method Not Allowed", "text/plain", b"GET or HEAD only\n", true);
    }
    let head = method == "HEAD";
    let Some(path) = request_path(target) else {
        return respond(&mut out, "400 Bad Request", "text/plain", b"bad path\n", !head);
    };
    let memory = routes.memory.lock().unwrap_or_else(PoisonError::into_inner).get(&path).cloned();
    if let Some((ty, bytes)) = memory {
        return respond(&mut out, "200 OK", ty, &bytes, !head);
    }
    let not_found = |out: &mut TcpStream| respond(out, "404 Not Found", "text/plain", b"not found\n", !head);
    let Some(ty) = content_type(&path) else { return not_found(&mut out) };
    let file = routes.root.join(&path);
    // the segments are plain names; a symbolic link must not lead out of the folder either
    let inside = file.canonicalize().is_ok_and(|f| f.starts_with(&routes.root) && f.is_file());
    let Some(mut f) = inside.then(|| std::fs::File::open(&file).ok()).flatten() else { return not_found(&mut out) };
    let len = f.metadata()?.len();
    write!(
        out,
        "HTTP/1.1 200 OK\r\nContent-Type: {ty}\r\nContent-Length: {len}\r\nCache-Control: no-store\r\nConnection: close\r\n\r\n"
    )?;
    if !head {
        std::io::copy(&mut f, &mut out)?;
    }
    out.flush()
}

fn respond(out: &mut TcpStream, status: &str, ty: &str, body: &[u8], with_body: bool) -> std::io::Result<()> {
    write!(
        out,
        "HTTP/1.1 {status}\r\nContent-Type: {ty}\r\nContent-Length: {}\r\nCache-Control: no-store\r\nConnection: close\r\n\r\n",
        body.len()
    )?;
    if with_body {
        out.write_all(body)?;
    }
    out.flush()
}

/// `GET http://addr/path` (a test helper): status code and body.
#[cfg(test)]
pub fn http_get(addr: SocketAddr, path: &str) -> std::io::Result<(u16, Vec<u8>)> {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(5))?;
    s.set_read_timeout(Some(Duration::from_secs(30)))?;
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n")?;
    let mut bytes = Vec::new();
    s.read_to_end(&mut bytes)?;
    let split =
        bytes.windows(4).position(|w| w == b"\r\n\r\n").ok_or_else(|| std::io::Error::other("no header end"))?;
    let head = String::from_utf8_lossy(&bytes[..split]).to_string();
    let code = head.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    Ok((code, bytes[split + 4..].to_vec()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn request_paths_are_plain_relative_names() {
        assert_eq!(request_path("/").as_deref(), Some("world.html"));
        assert_eq!(request_path("/rgb/00001.png?t=3").as_deref(), Some("rgb/00001.png"));
        for bad in ["/../etc/passwd", "/rgb/../../x.png", "/.sgam-lock", "//x.png", "/a%2e%2e/x", "x.png", "/a b.png"] {
            assert_eq!(request_path(bad), None, "{bad}");
        }
    }

    #[test]
    fn serves_files_and_memory_then_stops_when_asked() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("world.html"), "<p>hi</p>").unwrap();
        std::fs::create_dir(dir.path().join("rgb")).unwrap();
        std::fs::write(dir.path().join("rgb/00000.png"), [1u8, 2, 3]).unwrap();
        std::fs::write(dir.path().join("secret.txt"), "no").unwrap();
        let server = Server::start(dir.path(), 0).unwrap();
        let addr = server.addr();
        assert!(addr.ip().is_loopback());
        assert_eq!(http_get(addr, "/").unwrap(), (200, b"<p>hi</p>".to_vec()));
        assert_eq!(http_get(addr, "/rgb/00000.png").unwrap(), (200, vec![1, 2, 3]));
        assert_eq!(http_get(addr, "/secret.txt").unwrap().0, 404);
        assert_eq!(http_get(addr, "/../secret.txt").unwrap().0, 400);
        assert_eq!(http_get(addr, "/live.json").unwrap().0, 404);
        server.set("live.json", "application/json", b"{\"step\":3}".to_vec());
        assert_eq!(http_get(addr, "/live.json?t=1").unwrap(), (200, b"{\"step\":3}".to_vec()));
        server.stop();
        assert!(http_get(addr, "/").is_err(), "the port still answers after stop");
    }
}
