//! What the scene list in `brickcast_scenes` says of a scene ([`SceneEntry`]), and the one
//! shape its size and log key take there, deleted scenes' entries included.

use serde::{Deserialize, Serialize};

/// What the scene list in `brickcast_scenes` says of a scene.
///
/// **The log key:** a scene's log stream, snapshots and lease are named by its log key, not
/// its name, so a scene can be renamed (the entry moves, the log stays) and a name can be
/// given to a new scene while the old one under it is kept deleted (its log keeps its key).
/// A scene's first log takes the scene's name as its key (entries written before log keys
/// existed have none, and mean that); a key already used by another entry, live or deleted,
/// gets a suffix `=<unix ms>` that no scene name can hold (`catalog::fresh_log_key`).
///
/// **Why the key sits inside `size`:** an entry whose key is its name is written as before
/// (`{"size": [x, y, z]}`); one with another key as `{"size": {"xyz": [x, y, z], "log":
/// KEY}}`, which a node from before log keys cannot read, so it refuses the scene (and never
/// purges a kept one) rather than use the log named after the scene — someone else's log.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "Sized", into = "Sized")]
pub struct SceneEntry {
    pub size: [u32; 3],
    pub log: Option<String>,
}

impl SceneEntry {
    /// Scene `name`'s entry, its log keyed `log` (kept `None` when that is the name).
    pub fn new(name: &str, size: [u32; 3], log: &str) -> SceneEntry {
        SceneEntry {
            size,
            log: (log != name).then(|| log.to_string()),
        }
    }

    /// The key the log, snapshots and lease of scene `name` (this entry's) go by.
    pub fn log_key<'a>(&'a self, name: &'a str) -> &'a str {
        self.log.as_deref().unwrap_or(name)
    }
}

/// A size, and a log key when it is not the scene's name (see [`SceneEntry`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Size {
    Plain([u32; 3]),
    Keyed { xyz: [u32; 3], log: String },
}

impl Size {
    /// `log` is `None` or differs from `name`: the shape a node from before log keys reads
    /// only when the key is the name.
    pub fn of(size: [u32; 3], log: Option<&str>, name: &str) -> Size {
        match log {
            Some(log) if log != name => Size::Keyed {
                xyz: size,
                log: log.to_string(),
            },
            _ => Size::Plain(size),
        }
    }

    /// The size and the log key (`None`: the name).
    pub fn parts(self) -> ([u32; 3], Option<String>) {
        match self {
            Size::Plain(size) => (size, None),
            Size::Keyed { xyz, log } => (xyz, Some(log)),
        }
    }
}

/// A scene entry as JSON holds it.
#[derive(Serialize, Deserialize)]
struct Sized {
    size: Size,
}

impl From<Sized> for SceneEntry {
    fn from(raw: Sized) -> SceneEntry {
        let (size, log) = raw.size.parts();
        SceneEntry { size, log }
    }
}

impl From<SceneEntry> for Sized {
    fn from(entry: SceneEntry) -> Sized {
        // The entry does not know its name: a key is written whenever there is one.
        let size = match entry.log {
            Some(log) => Size::Keyed {
                xyz: entry.size,
                log,
            },
            None => Size::Plain(entry.size),
        };
        Sized { size }
    }
}
