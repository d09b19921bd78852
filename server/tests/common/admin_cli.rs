//! `brickcast-server admin …` as a user runs it, for the admin tests.

use std::net::SocketAddr;
use std::process::Output;

use serde_json::Value;

/// Runs `brickcast-server admin --server ADDR --json ARGS…` with `token` in BRICKCAST_TOKEN
/// (blocking, so off the async workers).
pub async fn admin(addr: SocketAddr, args: &[&str], token: Option<&str>) -> Output {
    let mut all = vec![
        "admin".to_string(),
        "--server".into(),
        addr.to_string(),
        "--json".into(),
    ];
    all.extend(args.iter().map(|s| s.to_string()));
    let token = token.map(String::from);
    tokio::task::spawn_blocking(move || {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_brickcast-server"));
        cmd.args(&all)
            .env("RUST_LOG", "warn")
            .env_remove("BRICKCAST_TOKEN")
            .stdin(std::process::Stdio::null());
        if let Some(token) = token {
            cmd.env("BRICKCAST_TOKEN", token);
        }
        cmd.output().expect("the CLI runs")
    })
    .await
    .unwrap()
}

/// The command's JSON answer (it must have succeeded).
pub fn ok(out: &Output) -> Value {
    assert!(
        out.status.success(),
        "admin failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("one JSON answer")
}

/// The command's error for people (it must have failed, cleanly).
pub fn refused(out: &Output) -> String {
    assert!(!out.status.success(), "expected a refusal");
    let text = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        text.starts_with("Error: ") && !text.contains("panicked"),
        "{text}"
    );
    text
}
