//! Builds the browser viewer (`web/`, compiled to wasm32) and leaves it in `OUT_DIR/web` for
//! `src/web.rs` to embed, so `cargo run -p brickcast-server -- serve` serves the page with no
//! other step.
//!
//! The bundle is rebuilt whenever anything it is made of changes (the web crate, the client
//! core, the protocol crate, the shaders, the lockfile), so it is never stale. When it cannot be
//! built, the server still builds, with a warning saying why and the one command that fixes it;
//! the page then says the same thing instead of a viewer.
//!
//! How: a nested `cargo build --target wasm32-unknown-unknown -p brickcast-web` in its own target
//! directory (a shared one would wait forever on the lock this build holds), then the bindings
//! generator as a library (`wasm-bindgen-cli-support`, pinned to the `wasm-bindgen` version the
//! web crate uses), then gzip, so the server can send the compressed bundle as it is.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;

const WASM_TARGET: &str = "wasm32-unknown-unknown";
/// How an error that must fail the build starts (the others leave the server without a viewer).
const FAILED: &str = "the browser viewer failed to build";

fn main() {
    let manifest = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("set by cargo"));
    let root = manifest
        .parent()
        .expect("the server is in the workspace")
        .to_path_buf();
    let out = PathBuf::from(std::env::var_os("OUT_DIR").expect("set by cargo")).join("web");
    std::fs::create_dir_all(&out).expect("OUT_DIR is writable");
    for input in [
        "web/src",
        "web/Cargo.toml",
        "client/core",
        "protocol/src",
        "protocol/Cargo.toml",
        "shaders",
        "Cargo.lock",
    ] {
        println!("cargo:rerun-if-changed={}", root.join(input).display());
    }
    println!("cargo:rerun-if-env-changed=BRICKCAST_WEB");
    let status = match build(&root, &out) {
        Ok(()) => String::new(),
        // A bug in the viewer is the build's failure, not a missing viewer.
        Err(why) if why.starts_with(FAILED) => {
            eprintln!("{why}");
            std::process::exit(1);
        }
        Err(why) => {
            println!("cargo:warning=the browser viewer was not built: {why}");
            for file in ["brickcast_web.js", "brickcast_web_bg.wasm"] {
                let _ = std::fs::write(out.join(file), b"");
                let _ = std::fs::write(out.join(format!("{file}.gz")), b"");
            }
            why
        }
    };
    std::fs::write(out.join("status.txt"), status).expect("OUT_DIR is writable");
}

fn build(root: &Path, out: &Path) -> Result<(), String> {
    if std::env::var("BRICKCAST_WEB").as_deref() == Ok("skip") {
        return Err("this server was built with BRICKCAST_WEB=skip".into());
    }
    let rustc = std::env::var("RUSTC").unwrap_or_else(|_| "rustc".into());
    let sysroot = Command::new(&rustc)
        .args(["--print", "sysroot"])
        .output()
        .map_err(|e| format!("cannot run {rustc}: {e}"))?;
    let sysroot = PathBuf::from(String::from_utf8_lossy(&sysroot.stdout).trim());
    let std_lib = sysroot.join("lib/rustlib").join(WASM_TARGET);
    // A missing path counts as changed: once the target is added, the next build picks it up.
    println!("cargo:rerun-if-changed={}", std_lib.display());
    if !std_lib.is_dir() {
        return Err(format!(
            "Rust's {WASM_TARGET} target is not installed; add it with `rustup target add {WASM_TARGET}` and build again"
        ));
    }

    let target_dir = target_dir(out).join("web");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let mut cmd = Command::new(cargo);
    cmd.current_dir(root)
        .args([
            "build",
            "--release",
            "--locked",
            "-p",
            "brickcast-web",
            "--target",
            WASM_TARGET,
        ])
        .arg("--target-dir")
        .arg(&target_dir)
        // Small and fast enough: the heavy work runs on the GPU.
        .env("CARGO_PROFILE_RELEASE_DEBUG", "false")
        .env("CARGO_PROFILE_RELEASE_OPT_LEVEL", "s")
        .env("CARGO_PROFILE_RELEASE_CODEGEN_UNITS", "16");
    // What the outer build was told applies to the server, not to the wasm bundle.
    for var in [
        "RUSTFLAGS",
        "CARGO_ENCODED_RUSTFLAGS",
        "RUSTC_WRAPPER",
        "RUSTC_WORKSPACE_WRAPPER",
        "CARGO_BUILD_TARGET",
        "CARGO_TARGET_DIR",
        "CARGO_BUILD_RUSTFLAGS",
    ] {
        cmd.env_remove(var);
    }
    let output = cmd
        .output()
        .map_err(|e| format!("cannot run cargo for the wasm build: {e}"))?;
    if !output.status.success() {
        let stderr = String::from_utf8_lossy(&output.stderr);
        let tail: Vec<&str> = stderr.lines().rev().take(30).collect();
        let tail: Vec<&str> = tail.into_iter().rev().collect();
        return Err(format!("{FAILED}:\n{}", tail.join("\n")));
    }
    let wasm = target_dir
        .join(WASM_TARGET)
        .join("release")
        .join("brickcast_web.wasm");
    wasm_bindgen_cli_support::Bindgen::new()
        .input_path(&wasm)
        .web(true)
        .map_err(|e| format!("{FAILED}: wasm-bindgen: {e}"))?
        .typescript(false)
        .generate(out)
        .map_err(|e| format!("{FAILED}: wasm-bindgen: {e:#}"))?;
    for file in ["brickcast_web.js", "brickcast_web_bg.wasm"] {
        let bytes = std::fs::read(out.join(file)).map_err(|e| format!("{file}: {e}"))?;
        let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
        gz.write_all(&bytes)
            .and_then(|()| gz.finish())
            .and_then(|z| std::fs::write(out.join(format!("{file}.gz")), z))
            .map_err(|e| format!("compressing {file}: {e}"))?;
    }
    Ok(())
}

/// The target directory this build runs in (the one holding cargo's `CACHEDIR.TAG`).
fn target_dir(out: &Path) -> PathBuf {
    out.ancestors()
        .find(|p| p.join("CACHEDIR.TAG").is_file())
        .map(Path::to_path_buf)
        .unwrap_or_else(|| out.to_path_buf())
}
