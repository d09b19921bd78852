//! Helpers for the end-to-end tests: a real server in this process, the real `brickcast` binary,
//! and a virtual X display for the window.
//!
//! The server runs on a runtime of its own thread so that tests can drive blocking things (the
//! client binary, the viewer's network thread) without starving it, and can stop and restart it
//! on the same port and data directory as an operator would.

pub mod browser;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use brickcast_client::replica::Replica;
use brickcast_server::{Server, ServerConfig};

/// The demo scene size the tests serve: big enough for several regions, small to sync.
pub const TEST_SCENE: [u32; 3] = [128, 64, 128];

/// A server running on its own thread until [`TestServer::stop`] (or drop).
pub struct TestServer {
    pub addr: SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<Result<()>>>,
}

impl TestServer {
    /// Serves `data` on `addr` (port 0 picks a free one).
    pub fn start(data: &Path, addr: SocketAddr) -> Result<TestServer> {
        Self::start_with(data, addr, |_| {})
    }

    /// [`TestServer::start`] with the configuration adjusted first (auth tokens, limits, …).
    pub fn start_with(
        data: &Path,
        addr: SocketAddr,
        tweak: impl FnOnce(&mut ServerConfig),
    ) -> Result<TestServer> {
        let mut config = ServerConfig::new(addr, data.to_path_buf());
        config.demo_size = TEST_SCENE;
        tweak(&mut config);
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()?;
        let server = runtime.block_on(Server::bind(config))?;
        let addr = server.local_addr()?;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let thread = std::thread::Builder::new()
            .name("test-server".into())
            .spawn(move || {
                runtime.block_on(server.run(async move {
                    let _ = stopped.await;
                }))
            })?;
        Ok(TestServer {
            addr,
            stop: Some(stop),
            thread: Some(thread),
        })
    }

    /// The scene's address as a user would type it.
    pub fn url(&self, scene: &str) -> String {
        format!("ws://{}/scenes/{scene}", self.addr)
    }

    /// Graceful shutdown, waiting for the store to close.
    pub fn stop(mut self) -> Result<()> {
        self.shutdown()
    }

    fn shutdown(&mut self) -> Result<()> {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        match self.thread.take() {
            Some(t) => t
                .join()
                .map_err(|_| anyhow::anyhow!("server thread panicked"))?,
            None => Ok(()),
        }
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        let _ = self.shutdown();
    }
}

/// A fresh full copy of a scene, as a new client would get it.
pub fn fetch(url: &str) -> Result<Replica> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    Ok(runtime
        .block_on(brickcast_client::headless::fetch(
            url,
            None,
            brickcast_protocol::blocks::Quality::Exact,
            brickcast_client::headless::Within::default(),
        ))?
        .0)
}

/// The `brickcast` binary of this build. Cargo builds it before running any test of the
/// workspace (the client package's own tests need it); a test run of this crate alone does not.
pub fn brickcast_bin() -> PathBuf {
    let exe = std::env::current_exe().unwrap_or_default();
    // target/<profile>/deps/<test> → target/<profile>/brickcast
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .map(Path::to_path_buf)
        .unwrap_or_default();
    let bin = dir.join(format!("brickcast{}", std::env::consts::EXE_SUFFIX));
    assert!(
        bin.exists(),
        "{} is missing: build it first with `cargo build -p brickcast-client` (scripts/test does)",
        bin.display()
    );
    bin
}

/// `brickcast args` with `env` added, no stdin, and lavapipe's harmless warning silenced.
fn brickcast_command(args: &[&str], env: &[(&str, &str)]) -> Command {
    let mut cmd = Command::new(brickcast_bin());
    // The viewer keeps its user id under the config directory: not the tester's own.
    let config = std::env::temp_dir().join(format!("brickcast-tests-{}", std::process::id()));
    cmd.args(args)
        .env("XDG_CONFIG_HOME", config)
        .env("NODEVICE_SELECT", "1")
        .envs(env.iter().copied())
        .stdin(Stdio::null());
    cmd
}

/// Runs `brickcast` with `args` to completion within `timeout`, returning (status, stdout, stderr).
pub fn run_brickcast(
    args: &[&str],
    env: &[(&str, &str)],
    timeout: Duration,
) -> Result<(std::process::ExitStatus, String, String)> {
    run_brickcast_without(args, env, &[], timeout)
}

/// [`run_brickcast`] with the variables `unset` removed from its environment (this one's and
/// the tests' own, such as `NODEVICE_SELECT`).
pub fn run_brickcast_without(
    args: &[&str],
    env: &[(&str, &str)],
    unset: &[&str],
    timeout: Duration,
) -> Result<(std::process::ExitStatus, String, String)> {
    let mut command = brickcast_command(args, env);
    for name in unset {
        command.env_remove(name);
    }
    let child = command
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .context("starting brickcast")?;
    wait_with_timeout(child, timeout)
}

fn wait_with_timeout(
    mut child: Child,
    timeout: Duration,
) -> Result<(std::process::ExitStatus, String, String)> {
    use std::io::Read;
    let mut stdout = child.stdout.take().context("stdout")?;
    let mut stderr = child.stderr.take().context("stderr")?;
    let out = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stdout.read_to_string(&mut s);
        s
    });
    let err = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stderr.read_to_string(&mut s);
        s
    });
    let started = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait()? {
            break status;
        }
        if started.elapsed() > timeout {
            let _ = child.kill();
            let _ = child.wait();
            bail!(
                "brickcast did not finish within {timeout:?}; stderr:\n{}",
                err.join().unwrap_or_default()
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    Ok((
        status,
        out.join().unwrap_or_default(),
        err.join().unwrap_or_default(),
    ))
}

/// A virtual X display (`Xvfb`), killed on drop.
///
/// One at a time per test process: window tests trace on lavapipe, which takes every core, and
/// with three windows at once one of them sometimes did not open within a minute. The guard is
/// held until the display is dropped.
pub struct VirtualDisplay {
    pub display: String,
    child: Child,
    _turn: std::sync::MutexGuard<'static, ()>,
}

static DISPLAY_TURN: std::sync::Mutex<()> = std::sync::Mutex::new(());

impl VirtualDisplay {
    /// Starts Xvfb on a free display number. Errors (rather than skipping) when Xvfb is missing:
    /// scripts/test installs it.
    pub fn start() -> Result<VirtualDisplay> {
        // A test that failed while holding the turn poisons it; the display is still free.
        let turn = DISPLAY_TURN.lock().unwrap_or_else(|e| e.into_inner());
        // Tests in one process start displays at once: each takes its own numbers, so two
        // cannot both see a free number and then share the display the winner started.
        static TAKEN: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let base = 100 + (std::process::id() % 400) * 8;
        for _ in 0..50 {
            let number = base + TAKEN.fetch_add(1, std::sync::atomic::Ordering::Relaxed) % 4000;
            if Path::new(&format!("/tmp/.X11-unix/X{number}")).exists()
                || Path::new(&format!("/tmp/.X{number}-lock")).exists()
            {
                continue;
            }
            let mut child = Command::new("Xvfb")
                .args([
                    &format!(":{number}"),
                    "-screen",
                    "0",
                    "1024x768x24",
                    "-nolisten",
                    "tcp",
                    // X servers reset when their last client leaves, and a client connecting
                    // during the reset is refused ("Failed to open connection to X server"):
                    // the tests poll with short-lived xdotool clients while the viewer starts.
                    "-noreset",
                    // Key presses sent through XTEST on a loaded machine can be held long
                    // enough for X's auto-repeat (660 ms by default) to press them again.
                    "-ardelay",
                    "600000",
                ])
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .context("starting Xvfb (apt-get install xvfb; scripts/test does)")?;
            let socket = PathBuf::from(format!("/tmp/.X11-unix/X{number}"));
            let started = Instant::now();
            while started.elapsed() < Duration::from_secs(10) {
                // Ours only if our Xvfb is still running (a loser of a race exits) and answers
                // a client: the socket appears before the server is ready, and a server that
                // fails after creating it leaves it behind.
                if socket.exists() && child.try_wait()?.is_none() && answers(&format!(":{number}"))
                {
                    return Ok(VirtualDisplay {
                        display: format!(":{number}"),
                        child,
                        _turn: turn,
                    });
                }
                if child.try_wait()?.is_some() {
                    break; // lost a race for this number; try the next
                }
                std::thread::sleep(Duration::from_millis(50));
            }
            let _ = child.kill();
            let _ = child.wait();
        }
        bail!("could not start Xvfb on any display near :{base}")
    }
}

/// Whether an X client can connect to `display` (xdotool asks for the screen's size).
fn answers(display: &str) -> bool {
    Command::new("xdotool")
        .arg("getdisplaygeometry")
        .env("DISPLAY", display)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

impl Drop for VirtualDisplay {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Polls `check` until it returns true or `timeout` passes.
pub fn wait_until(timeout: Duration, mut check: impl FnMut() -> bool) -> bool {
    let started = Instant::now();
    while started.elapsed() < timeout {
        if check() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    check()
}

/// Reads a PNG as RGBA8 pixels.
pub fn read_png(path: &Path) -> Result<(u32, u32, Vec<[u8; 4]>)> {
    let image = image::open(path)
        .with_context(|| format!("reading {}", path.display()))?
        .to_rgba8();
    let (w, h) = image.dimensions();
    let pixels = image.pixels().map(|p| p.0).collect::<Vec<[u8; 4]>>();
    Ok((w, h, pixels))
}

/// A plain HTTP GET against the server: the body of a 200 answer.
pub fn http_get(addr: SocketAddr, path: &str) -> Result<String> {
    use std::io::{Read, Write};
    let mut stream = std::net::TcpStream::connect(addr)?;
    stream.set_read_timeout(Some(Duration::from_secs(10)))?;
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n"
    )?;
    let mut text = String::new();
    stream.read_to_string(&mut text)?;
    let (head, body) = text.split_once("\r\n\r\n").context("no HTTP header")?;
    if !head.starts_with("HTTP/1.1 200") {
        bail!("GET {path}: {}", head.lines().next().unwrap_or(""));
    }
    Ok(body.to_string())
}

/// One scene's entry in the server's `/scenes` list.
pub fn scene_info(addr: SocketAddr, scene: &str) -> Result<serde_json::Value> {
    let list: serde_json::Value = serde_json::from_str(&http_get(addr, "/scenes")?)?;
    list.as_array()
        .and_then(|l| l.iter().find(|s| s["name"] == scene))
        .cloned()
        .with_context(|| format!("scene {scene} not listed"))
}

/// Runs `xdotool` on `display` (it drives the window as a user would, through XTEST).
pub fn xdotool(display: &str, args: &[&str]) -> Result<String> {
    let out = Command::new("xdotool")
        .args(args)
        .env("DISPLAY", display)
        .stdin(Stdio::null())
        .output()
        .context("running xdotool (apt-get install xdotool; scripts/test does)")?;
    if !out.status.success() {
        bail!(
            "xdotool {args:?}: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    Ok(String::from_utf8_lossy(&out.stdout).trim().to_string())
}

/// Starts `brickcast` with `args` in the background (killed on drop). Its stderr goes to a
/// file that [`Background::describe`] reads, so a failing test can say why it died.
pub fn spawn_brickcast(args: &[&str], env: &[(&str, &str)]) -> Result<Background> {
    let log = tempfile::NamedTempFile::new().context("a file for the child's stderr")?;
    let child = brickcast_command(args, env)
        .stdout(Stdio::null())
        .stderr(log.reopen().context("reopening the stderr file")?)
        .spawn()
        .context("starting brickcast")?;
    Ok(Background(child, Some(log)))
}

/// A child process that is killed when the test ends, pass or fail, and where its stderr went.
pub struct Background(pub Child, pub Option<tempfile::NamedTempFile>);

impl Background {
    /// Whether it is still running (or how it ended) and the end of what it wrote to stderr.
    pub fn describe(&mut self) -> String {
        let state = match self.0.try_wait() {
            Ok(Some(status)) => format!("exited: {status}"),
            Ok(None) => "still running".to_string(),
            Err(e) => format!("unknown: {e}"),
        };
        let text = self
            .1
            .as_ref()
            .and_then(|f| std::fs::read_to_string(f.path()).ok())
            .unwrap_or_default();
        // The error comes first, a backtrace (with RUST_BACKTRACE) after it.
        let head: String = text.chars().take(2000).collect();
        format!("the viewer is {state}; its stderr begins:\n{head}")
    }

    /// Waits up to `timeout` for the process to exit by itself.
    pub fn wait_exit(&mut self, timeout: Duration) -> Result<Option<std::process::ExitStatus>> {
        let started = Instant::now();
        while started.elapsed() < timeout {
            if let Some(status) = self.0.try_wait()? {
                return Ok(Some(status));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        Ok(None)
    }
}

impl Drop for Background {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The colour the viewers paint in first is nobody's: a person drawn in it read as the
    /// paint colour (both were red).
    #[test]
    fn no_user_is_drawn_in_the_first_paint_colour() {
        let paint = brickcast_protocol::swatches::Swatches::default().get(0);
        for marker in brickcast_server::identity::marker_colours() {
            assert!(
                !brickcast_server::identity::looks_alike(marker, paint),
                "a user is drawn in {:?}, like the first paint colour",
                marker.to_rgb8()
            );
        }
    }

    /// A client connecting while others come and go is let in: without `-noreset` each last
    /// client's exit resets the server and about one connection in twelve was refused (the
    /// window tests' "Failed to open connection to X server").
    #[test]
    fn a_virtual_display_lets_clients_in_while_others_come_and_go() {
        let display = VirtualDisplay::start().expect("Xvfb");
        let stop = std::sync::atomic::AtomicBool::new(false);
        let refused = std::thread::scope(|s| {
            s.spawn(|| {
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    answers(&display.display);
                }
            });
            let refused = (0..150).filter(|_| !answers(&display.display)).count();
            stop.store(true, std::sync::atomic::Ordering::Relaxed);
            refused
        });
        assert_eq!(refused, 0, "{refused} of 150 connections refused");
    }
}
