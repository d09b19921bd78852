//! A real browser for the browser viewer's tests: Debian's chromium with software WebGPU,
//! driven by `tests/browser/driver.mjs` (playwright-core) over a line of JSON each way.
//!
//! `scripts/test` installs chromium and the driver's one npm package when they are missing;
//! without them these tests fail with the command that installs them.

use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

use anyhow::{Context, Result, bail};
use serde_json::{Value, json};

/// Where the driver and its `node_modules` live.
fn driver_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("browser")
}

/// A frame traced by the page: RGBA pixels and the voxel each pixel hit.
pub struct PageFrame {
    pub pixels: Vec<[u8; 4]>,
    pub hits: Vec<Option<[u32; 3]>>,
}

/// One browser with one page.
pub struct Browser {
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
}

impl Browser {
    /// A browser with WebGPU (SwiftShader) and a `width`×`height` page.
    pub fn start(width: u32, height: u32) -> Result<Browser> {
        Self::launch(json!({"webgpu": true, "viewport": {"width": width, "height": height}}))
    }

    /// A browser without WebGPU.
    pub fn without_webgpu() -> Result<Browser> {
        Self::launch(json!({"webgpu": false}))
    }

    fn launch(options: Value) -> Result<Browser> {
        let dir = driver_dir();
        if !dir.join("node_modules/playwright-core").is_dir() {
            bail!(
                "the browser tests need playwright-core: run `npm ci --prefix {}` (scripts/test does)",
                dir.display()
            );
        }
        let chromium =
            std::env::var("BRICKCAST_CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
        if !std::path::Path::new(&chromium).exists() {
            bail!(
                "the browser tests need chromium: `apt-get install chromium` (scripts/test does)"
            );
        }
        let mut child = Command::new("node")
            .arg(dir.join("driver.mjs"))
            .arg(options.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .context("starting node (the browser tests need Node.js)")?;
        let stdin = child.stdin.take().context("driver stdin")?;
        let stdout = BufReader::new(child.stdout.take().context("driver stdout")?);
        let mut browser = Browser {
            child,
            stdin,
            stdout,
        };
        browser.answer().context("the browser did not start")?;
        Ok(browser)
    }

    fn answer(&mut self) -> Result<Value> {
        let mut line = String::new();
        if self.stdout.read_line(&mut line)? == 0 {
            bail!("the browser driver exited");
        }
        let reply: Value =
            serde_json::from_str(&line).with_context(|| format!("driver said {line:?}"))?;
        if reply["ok"] == json!(true) {
            Ok(reply["result"].clone())
        } else {
            bail!("{}", reply["error"].as_str().unwrap_or("the driver failed"))
        }
    }

    /// Sends one command and waits for its answer.
    pub fn call(&mut self, command: Value) -> Result<Value> {
        writeln!(self.stdin, "{command}")?;
        self.stdin.flush()?;
        self.answer()
            .with_context(|| format!("browser command {command}"))
    }

    pub fn goto(&mut self, url: &str) -> Result<()> {
        self.call(json!({"op": "goto", "url": url})).map(|_| ())
    }

    /// Evaluates `js` in the page and returns its (JSON) value.
    pub fn eval(&mut self, js: &str) -> Result<Value> {
        self.call(json!({"op": "eval", "js": js}))
    }

    /// Waits until `js` is truthy in the page (polled every 100 ms) and returns its value.
    pub fn wait(&mut self, js: &str, timeout_ms: u64) -> Result<Value> {
        self.call(json!({"op": "wait", "js": js, "timeout_ms": timeout_ms}))
    }

    /// The viewer's state (`Viewer::state`), or `None` before the viewer started.
    pub fn state(&mut self) -> Result<Option<Value>> {
        let text = self.eval("window.brickcast ? window.brickcast.state() : null")?;
        match text.as_str() {
            Some(t) => Ok(Some(serde_json::from_str(t)?)),
            None => Ok(None),
        }
    }

    /// Waits until the viewer's state satisfies `js_condition` (an expression over `s`).
    pub fn wait_state(&mut self, js_condition: &str, timeout_ms: u64) -> Result<Value> {
        let js = format!(
            "(() => {{ if (!window.brickcast) return false; const s = JSON.parse(window.brickcast.state()); return ({js_condition}) ? s : false; }})()"
        );
        self.wait(&js, timeout_ms)
    }

    /// A frame traced by the page at exactly `width`×`height` from `eye` towards `target`:
    /// RGBA pixels and the hit voxel of each pixel.
    pub fn trace(
        &mut self,
        width: u32,
        height: u32,
        eye: [f32; 3],
        target: [f32; 3],
        fov_y: f32,
    ) -> Result<PageFrame> {
        let js = format!(
            "window.brickcast.trace_exact({width}, {height}, new Float32Array({eye:?}), new Float32Array({target:?}), {fov_y}).then(f => ({{pixels: Array.from(f.pixels), hits: Array.from(f.hits)}}))"
        );
        let frame = self.eval(&js)?;
        let bytes: Vec<u8> = frame["pixels"]
            .as_array()
            .context("pixels")?
            .iter()
            .map(|v| v.as_u64().unwrap_or(0) as u8)
            .collect();
        let words: Vec<u32> = frame["hits"]
            .as_array()
            .context("hits")?
            .iter()
            .map(|v| v.as_u64().unwrap_or(0) as u32)
            .collect();
        let n = (width * height) as usize;
        if bytes.len() != n * 4 || words.len() != n * 3 {
            bail!(
                "the page returned {} pixel bytes and {} hit words",
                bytes.len(),
                words.len()
            );
        }
        let pixels = bytes
            .chunks_exact(4)
            .map(|p| [p[0], p[1], p[2], p[3]])
            .collect();
        let hits = words
            .chunks_exact(3)
            .map(|h| (h[0] != u32::MAX).then_some([h[0], h[1], h[2]]))
            .collect();
        Ok(PageFrame { pixels, hits })
    }

    pub fn click(&mut self, x: f64, y: f64, button: &str) -> Result<()> {
        self.call(json!({"op": "click", "x": x, "y": y, "button": button}))
            .map(|_| ())
    }

    /// A click with keys held (`"Alt"`, `"Control"`).
    pub fn click_with(&mut self, x: f64, y: f64, button: &str, modifiers: &[&str]) -> Result<()> {
        self.call(json!({"op": "click", "x": x, "y": y, "button": button, "modifiers": modifiers}))
            .map(|_| ())
    }

    /// Presses `button` at `from`, moves to `to` and releases it there.
    pub fn drag(&mut self, from: [f64; 2], to: [f64; 2], button: &str) -> Result<()> {
        self.call(json!({"op": "drag", "from": from, "to": to, "button": button}))
            .map(|_| ())
    }

    pub fn screenshot(&mut self, path: &std::path::Path) -> Result<()> {
        self.call(json!({"op": "screenshot", "path": path}))
            .map(|_| ())
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = writeln!(self.stdin, "{}", json!({"op": "close"}));
        let _ = self.stdin.flush();
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while std::time::Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
