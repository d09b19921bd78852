//! Who the user is to the server: a display name and a user id kept across runs, so that undo
//! history follows the person rather than the connection.

use std::collections::hash_map::RandomState;
use std::hash::{BuildHasher, Hasher};
use std::path::PathBuf;

use brickcast_protocol::wire::{MAX_DISPLAY_NAME_BYTES, UserId};

/// The OS user's name, or "brickcast user".
pub fn default_name() -> String {
    let name = ["USER", "USERNAME", "LOGNAME"]
        .iter()
        .find_map(|v| std::env::var(v).ok().filter(|n| !n.trim().is_empty()))
        .unwrap_or_else(|| "brickcast user".into());
    let mut name = name.trim().to_string();
    while name.len() > MAX_DISPLAY_NAME_BYTES {
        name.pop();
    }
    name
}

/// Where the user id is kept: `$XDG_CONFIG_HOME/brickcast/user-id`, else
/// `~/.config/brickcast/user-id` (`%APPDATA%\brickcast\user-id` on Windows).
pub fn id_file() -> Option<PathBuf> {
    let base = std::env::var_os("XDG_CONFIG_HOME")
        .filter(|v| !v.is_empty())
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("APPDATA").map(PathBuf::from))
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".config")))?;
    Some(base.join("brickcast").join("user-id"))
}

/// A fresh random id (never 0, top bit clear: ids with it set are the server's).
pub fn random_id() -> UserId {
    let mut h = RandomState::new().build_hasher();
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos()),
    );
    h.write_u32(std::process::id());
    (h.finish() >> 1).max(1)
}

/// The user id kept in [`id_file`], created on first use. When the file cannot be read or
/// written the id is still returned (history then lasts as long as this run), with a warning.
pub fn user_id() -> UserId {
    let Some(path) = id_file() else {
        tracing::warn!("no config directory; undo history will not outlive this run");
        return random_id();
    };
    if let Ok(text) = std::fs::read_to_string(&path)
        && let Ok(id) = u64::from_str_radix(text.trim(), 16)
        && id != 0
    {
        return id;
    }
    let id = random_id();
    let written = path
        .parent()
        .map_or(Ok(()), std::fs::create_dir_all)
        .and_then(|_| std::fs::write(&path, format!("{id:016x}\n")));
    if let Err(e) = written {
        tracing::warn!(path = %path.display(), error = %e, "cannot keep the user id; undo history will not outlive this run");
    }
    id
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_are_random_nonzero_and_leave_the_top_bit_to_the_server() {
        let a = random_id();
        let b = random_id();
        assert_ne!(a, b);
        assert!(a != 0 && a >> 63 == 0);
        assert!(!default_name().is_empty());
    }
}
