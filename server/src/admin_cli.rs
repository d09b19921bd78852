//! `brickcast-server admin …`: the admin API (`brickcast_server::admin`) from the command line,
//! against a running server.

use std::io::{BufRead, IsTerminal, Write};

use anyhow::{Context, bail};
use serde_json::{Value, json};

#[derive(clap::Args)]
pub struct Args {
    /// The server: its address (`127.0.0.1:7878`) or URL (`http://…`, `ws://…/scenes/x`).
    #[arg(long, default_value = "http://127.0.0.1:7878")]
    server: String,
    /// An admin token of the server's auth file (default: $BRICKCAST_TOKEN). A server without
    /// an auth file takes admin commands from its own machine without one.
    #[arg(long)]
    token: Option<String>,
    /// Print the server's JSON answer instead of lines for people.
    #[arg(long)]
    json: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(clap::Subcommand)]
enum Command {
    /// Scenes with their size and who is there, and the deleted scenes still kept.
    List,
    /// A new scene, served at once.
    Create {
        name: String,
        #[command(flatten)]
        spec: Spec,
    },
    /// Close a scene for everyone on it and delete it; it is kept for `--keep` so that
    /// `restore` can bring it back.
    Delete {
        name: String,
        /// Do not ask: the scene's name was checked.
        #[arg(long)]
        yes: bool,
        /// How long the deleted scene is kept (90s, 10m, 24h, 7d).
        #[arg(long, default_value = "24h")]
        keep: String,
    },
    /// Serve a deleted scene again (`list` shows the keys of those kept).
    Restore {
        key: String,
        /// Under this name (default: its name when it was deleted).
        #[arg(long = "as")]
        name: Option<String>,
    },
    /// Drop a deleted scene now, for good (its disk back; on a cluster, its name free again).
    Purge {
        key: String,
        /// Confirm: there is no undo.
        #[arg(long)]
        yes: bool,
    },
    /// Rename a scene (its users are told the new name).
    Rename { name: String, to: String },
    /// Make a scene anew (empty by default, at its size by default); the old one is kept like
    /// a deleted scene.
    Reset {
        name: String,
        #[command(flatten)]
        spec: Spec,
        /// Do not ask.
        #[arg(long)]
        yes: bool,
    },
    /// Save a scene as a file (its voxels as committed now; not its undo history).
    Backup {
        name: String,
        /// The file (default: NAME.scene).
        #[arg(long)]
        out: Option<std::path::PathBuf>,
    },
    /// Upload a backup (`backup`), a MagicaVoxel .vox model, or an .obj mesh (voxelized here,
    /// with its materials and textures, then uploaded) as scene NAME.
    Upload {
        name: String,
        file: std::path::PathBuf,
        /// Replace a scene of that name (the one before is kept like a deleted scene).
        #[arg(long)]
        replace: bool,
        /// Voxels along an .obj mesh's longest axis: a power of two, 8..=8192.
        #[arg(long)]
        resolution: Option<u32>,
        /// Voxelizing threads for an .obj mesh (default: one per core).
        #[arg(long, default_value_t = 0)]
        threads: usize,
        /// Let an .obj's MTL libraries and textures be read from outside its own folder.
        #[arg(long)]
        allow_outside_files: bool,
    },
    /// Disconnect a user and refuse them for a while.
    Kick {
        /// Their display name (look-alikes match too).
        #[arg(long, required_unless_present = "user")]
        name: Option<String>,
        /// Or their user id (`list` shows it).
        #[arg(long)]
        user: Option<u64>,
        /// Only from this scene (default: every scene).
        #[arg(long)]
        scene: Option<String>,
        /// How long they are refused after (0s: they may come back at once).
        #[arg(long = "for", default_value = "10m")]
        refuse_for: String,
    },
}

#[derive(clap::Args)]
struct Spec {
    /// What the scene holds: empty, terrain (a procedural world, any size) or demo.
    #[arg(long, default_value = "empty", value_parser = ["empty", "terrain", "demo"])]
    kind: String,
    /// Voxels along x, y (up) and z, e.g. 1024,256,1024.
    #[arg(long)]
    size: Option<String>,
    /// Terrain: another seed, another world.
    #[arg(long, default_value_t = 1)]
    seed: u32,
}

impl Spec {
    fn body(&self) -> anyhow::Result<Value> {
        let mut body = json!({ "kind": self.kind, "seed": self.seed });
        if let Some(size) = &self.size {
            body["size"] =
                json!(crate::generate_cli::parse_size(size).map_err(anyhow::Error::msg)?);
        }
        Ok(body)
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let base = base_url(&args.server)?;
    let token = args
        .token
        .clone()
        .or_else(|| std::env::var("BRICKCAST_TOKEN").ok());
    let api = Api { base, token };
    let answer = match &args.command {
        Command::List => api.call("GET", "/admin/scenes", None)?,
        Command::Create { name, spec } => {
            api.call("POST", &format!("/admin/scenes/{name}"), Some(spec.body()?))?
        }
        Command::Delete { name, yes, keep } => {
            confirm(*yes, name, "delete")?;
            let path = format!("/admin/scenes/{name}?confirm={name}&keep={keep}");
            api.call("DELETE", &path, None)?
        }
        Command::Restore { key, name } => {
            let body = name.as_ref().map_or(json!({}), |n| json!({ "as": n }));
            api.call("POST", &format!("/admin/deleted/{key}/restore"), Some(body))?
        }
        Command::Purge { key, yes } => {
            if !yes {
                bail!("purge drops {key} for good: add --yes to confirm");
            }
            api.call(
                "DELETE",
                &format!("/admin/deleted/{key}?confirm={key}"),
                None,
            )?
        }
        Command::Rename { name, to } => api.call(
            "POST",
            &format!("/admin/scenes/{name}/rename"),
            Some(json!({ "to": to })),
        )?,
        Command::Reset { name, spec, yes } => {
            confirm(*yes, name, "reset")?;
            let path = format!("/admin/scenes/{name}/reset");
            api.call("POST", &path, Some(spec.body()?))?
        }
        Command::Backup { name, out } => {
            let out = out
                .clone()
                .unwrap_or_else(|| std::path::PathBuf::from(format!("{name}.scene")));
            let bytes = api.download(&format!("/admin/scenes/{name}/backup"))?;
            std::fs::write(&out, &bytes).with_context(|| format!("writing {}", out.display()))?;
            json!({ "scene": name, "file": out.display().to_string(), "bytes": bytes.len() })
        }
        Command::Upload {
            name,
            file,
            replace,
            resolution,
            threads,
            allow_outside_files,
        } => {
            let path = format!("/admin/scenes/{name}?replace={replace}");
            let is_mesh = file
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("obj"));
            if is_mesh {
                // Voxelized here (the server takes scene files and .vox), then sent as a
                // scene file: the model's MTL and textures never have to reach the server.
                let options = brickcast_server::import::ImportOptions {
                    resolution: resolution
                        .unwrap_or(brickcast_server::import::ImportOptions::default().resolution),
                    threads: *threads,
                    allow_outside_files: *allow_outside_files,
                };
                let bars = crate::import_cli::Bars::new(!std::io::stderr().is_terminal());
                let imported = brickcast_server::import::import_file(file, &options, &bars)?;
                for warning in &imported.report.warnings {
                    eprintln!("warning: {warning}");
                }
                let bytes = brickcast_server::incoming::encode(name, &imported.map)
                    .map_err(|e| anyhow::anyhow!("encoding {}: {e}", file.display()))?;
                api.upload_bytes(&path, bytes)?
            } else {
                if resolution.is_some() {
                    eprintln!("warning: --resolution applies to .obj meshes; ignored");
                }
                api.upload(&path, file)?
            }
        }
        Command::Kick {
            name,
            user,
            scene,
            refuse_for,
        } => {
            let mut body = json!({ "for": refuse_for });
            if let Some(name) = name {
                body["name"] = json!(name);
            }
            if let Some(user) = user {
                body["user"] = json!(user);
            }
            if let Some(scene) = scene {
                body["scene"] = json!(scene);
            }
            api.call("POST", "/admin/kick", Some(body))?
        }
    };
    if args.json {
        println!("{answer}");
    } else {
        print!("{}", for_people(&args.command, &answer));
    }
    Ok(())
}

/// `http://HOST:PORT` from an address or a URL of the server.
fn base_url(server: &str) -> anyhow::Result<String> {
    let (scheme, rest) = match server.split_once("://") {
        Some(("http" | "ws", rest)) => ("http", rest),
        Some(("https" | "wss", rest)) => ("https", rest),
        Some((other, _)) => {
            bail!("--server {server:?}: {other}:// is not a server's URL (http, https, ws or wss)")
        }
        None => ("http", server),
    };
    let host = rest.split(['/', '#', '?']).next().unwrap_or("");
    if host.is_empty() {
        bail!("--server {server:?} names no host");
    }
    Ok(format!("{scheme}://{host}"))
}

/// Asks for the scene's name on a terminal; without one, `--yes` is needed.
fn confirm(yes: bool, name: &str, what: &str) -> anyhow::Result<()> {
    if yes {
        return Ok(());
    }
    if !std::io::stdin().is_terminal() {
        bail!("{what} closes scene {name} for everyone on it: add --yes to confirm");
    }
    eprint!("{what} closes scene {name} for everyone on it; type its name to go on: ");
    std::io::stderr().flush()?;
    let mut line = String::new();
    std::io::stdin().lock().read_line(&mut line)?;
    if line.trim() != name {
        bail!("not confirmed: nothing changed");
    }
    Ok(())
}

struct Api {
    base: String,
    token: Option<String>,
}

impl Api {
    fn agent() -> ureq::Agent {
        ureq::Agent::config_builder()
            .http_status_as_error(false)
            .build()
            .into()
    }

    fn auth(&self) -> Option<String> {
        self.token.as_ref().map(|t| format!("Bearer {t}"))
    }

    /// One request; the server's `{"error": …}` becomes this command's error.
    fn call(&self, method: &str, path: &str, body: Option<Value>) -> anyhow::Result<Value> {
        let url = format!("{}{path}", self.base);
        let (agent, auth) = (Self::agent(), self.auth());
        let response = match (method, body) {
            ("GET", _) => with_auth(agent.get(&url), &auth).call(),
            ("DELETE", _) => with_auth(agent.delete(&url), &auth).call(),
            (_, body) => with_auth(agent.post(&url), &auth)
                .header("content-type", "application/json")
                .send(body.unwrap_or(json!({})).to_string()),
        };
        let bytes = answer(method, &url, response)?;
        Ok(serde_json::from_slice(&bytes).unwrap_or(Value::Null))
    }

    /// The body of a GET.
    fn download(&self, path: &str) -> anyhow::Result<Vec<u8>> {
        let url = format!("{}{path}", self.base);
        let response = with_auth(Self::agent().get(&url), &self.auth()).call();
        answer("GET", &url, response)
    }

    /// PUTs a file, with a progress bar on a terminal.
    fn upload(&self, path: &str, file: &std::path::Path) -> anyhow::Result<Value> {
        let opened =
            std::fs::File::open(file).with_context(|| format!("opening {}", file.display()))?;
        let len = opened.metadata()?.len();
        self.upload_from(path, opened, len)
    }

    /// PUTs bytes made here (a voxelized mesh), with a progress bar on a terminal.
    fn upload_bytes(&self, path: &str, bytes: Vec<u8>) -> anyhow::Result<Value> {
        let len = bytes.len() as u64;
        self.upload_from(path, std::io::Cursor::new(bytes), len)
    }

    fn upload_from(
        &self,
        path: &str,
        source: impl std::io::Read + Send + Sync + 'static,
        len: u64,
    ) -> anyhow::Result<Value> {
        let url = format!("{}{path}", self.base);
        let bar = if std::io::stderr().is_terminal() {
            indicatif::ProgressBar::new(len)
        } else {
            indicatif::ProgressBar::hidden()
        };
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "uploading {bar:40} {bytes}/{total_bytes} ({eta} left)",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        let reader = bar.wrap_read(source);
        let response = with_auth(Self::agent().put(&url), &self.auth())
            .header("content-type", "application/octet-stream")
            .header("content-length", len.to_string())
            .send(ureq::SendBody::from_owned_reader(reader));
        bar.finish_and_clear();
        let bytes = answer("PUT", &url, response)?;
        Ok(serde_json::from_slice(&bytes).unwrap_or(Value::Null))
    }
}

/// The body of a successful answer; the server's `{"error": …}` (or the status) otherwise.
fn answer(
    method: &str,
    url: &str,
    response: Result<ureq::http::Response<ureq::Body>, ureq::Error>,
) -> anyhow::Result<Vec<u8>> {
    let mut response = response.map_err(|e| match &e {
        ureq::Error::Io(io) if io.kind() == std::io::ErrorKind::ConnectionRefused => {
            anyhow::anyhow!(
                "no server answers at {url}: is `brickcast-server serve` running there? (--server names another)"
            )
        }
        _ => anyhow::Error::new(e).context(format!("{method} {url}")),
    })?;
    let status = response.status();
    let bytes = response
        .body_mut()
        .with_config()
        .limit(u64::MAX)
        .read_to_vec()
        .with_context(|| format!("reading the answer to {method} {url}"))?;
    if status.is_success() {
        return Ok(bytes);
    }
    let value: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
    match value.get("error").and_then(Value::as_str) {
        Some(error) => bail!("{error}"),
        None if status.as_u16() == 404 => bail!(
            "{url}: 404: is this a brickcast server of this version (the admin API is under /admin/)?"
        ),
        None => bail!(
            "{method} {url}: {status}: {}",
            String::from_utf8_lossy(&bytes).trim()
        ),
    }
}

fn with_auth<B>(
    request: ureq::RequestBuilder<B>,
    auth: &Option<String>,
) -> ureq::RequestBuilder<B> {
    match auth {
        Some(value) => request.header("authorization", value),
        None => request,
    }
}

/// The answer as lines for people.
fn for_people(command: &Command, answer: &Value) -> String {
    let s = |v: &Value| v.as_str().unwrap_or("?").to_string();
    let size = |v: &Value| {
        let n: Vec<String> = v
            .as_array()
            .map(|a| a.iter().map(|n| n.to_string()).collect())
            .unwrap_or_default();
        n.join("x")
    };
    let when = |v: &Value| {
        v.as_u64()
            .map(|t| {
                humantime::format_rfc3339_seconds(
                    std::time::UNIX_EPOCH + std::time::Duration::from_secs(t),
                )
                .to_string()
            })
            .unwrap_or_default()
    };
    let mut out = String::new();
    match command {
        Command::List => {
            out += "scene	size	sequence	bricks	solid voxels	memory	who is here
";
            for scene in answer["scenes"].as_array().into_iter().flatten() {
                let users: Vec<String> = scene["users"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .map(|u| format!("{} (user {})", s(&u["name"]), u["user"]))
                    .collect();
                out += &format!(
                    "{}\t{}\tseq {}\t{} bricks\t{} voxels\t{:.1} MiB\t{}\n",
                    s(&scene["name"]),
                    size(&scene["size"]),
                    scene["seq"],
                    scene["bricks"],
                    scene["voxels"],
                    scene["gpu_bytes"].as_f64().unwrap_or(0.0) / f64::from(1 << 20),
                    if users.is_empty() {
                        "nobody here".to_string()
                    } else {
                        users.join(", ")
                    },
                );
            }
            for d in answer["deleted"].as_array().into_iter().flatten() {
                out += &format!(
                    "deleted: {} as {}\tkept until {}\n",
                    s(&d["name"]),
                    s(&d["key"]),
                    when(&d["kept_until"])
                );
            }
        }
        Command::Delete { name, .. } => {
            out += &format!(
                "deleted scene {name}; kept until {}: `brickcast-server admin restore {}` brings it back\n",
                when(&answer["kept_until"]),
                s(&answer["key"])
            );
        }
        Command::Purge { key, .. } => {
            out += &format!("dropped {key} ({}) for good\n", s(&answer["name"]));
        }
        Command::Kick { .. } => {
            for d in answer["disconnected"].as_array().into_iter().flatten() {
                out += &format!(
                    "disconnected {} (user {}) from {}\n",
                    s(&d["name"]),
                    d["user"],
                    s(&d["scene"])
                );
            }
            if answer["refused_for_s"].as_u64().unwrap_or(0) > 0 {
                out += &format!("refused for {} s\n", answer["refused_for_s"]);
            }
        }
        Command::Backup { name, .. } => {
            out += &format!(
                "scene {name} saved to {} ({} bytes): `brickcast-server admin upload NAME FILE` makes a scene of it\n",
                s(&answer["file"]),
                answer["bytes"]
            );
        }
        Command::Create { .. }
        | Command::Restore { .. }
        | Command::Rename { .. }
        | Command::Reset { .. }
        | Command::Upload { .. } => {
            out += &match answer.get("voxels") {
                Some(voxels) => format!(
                    "serving scene {}: {} voxels, {} bricks, {voxels} solid voxels, seq {}\n",
                    s(&answer["name"]),
                    size(&answer["size"]),
                    answer["bricks"],
                    answer["seq"]
                ),
                // A scene put back in a cluster's list: nodes open it when someone asks.
                None => format!(
                    "scene {} ({} voxels) is back in the cluster's list\n",
                    s(&answer["name"]),
                    size(&answer["size"])
                ),
            };
            if let Some(previous) = answer.get("previous") {
                out += &format!(
                    "the scene before is kept as {} until {}\n",
                    s(&previous["key"]),
                    when(&previous["kept_until"])
                );
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_server_is_named_by_address_or_url() {
        assert_eq!(base_url("127.0.0.1:7878").unwrap(), "http://127.0.0.1:7878");
        assert_eq!(
            base_url("ws://example.org:80/scenes/demo#token=x").unwrap(),
            "http://example.org:80"
        );
        assert_eq!(base_url("https://h/").unwrap(), "https://h");
        assert!(base_url("ftp://h").is_err());
        assert!(base_url("http://").is_err());
    }
}
