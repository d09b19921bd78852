//! Tokens → roles, from the `--auth FILE`.
//!
//! File format: one `TOKEN ROLE [NAME]` line per token (`ROLE` is `admin`, `editor` or `viewer`:
//! an admin edits like an editor and may also use the admin API, `crate::admin`; `NAME`,
//! optional, is the user's display name, which then also pins their user id: see
//! `crate::identity`), `#` comments and blank lines ignored. Without a file every connection is an editor (a local, single-user
//! server). With one, a connection without a token is a viewer (hosting for remote viewers), and
//! an unknown token is refused outright so that a typo is loud rather than silently read-only.
//! Without a file the admin API answers only connections from this machine (loopback).

use std::collections::{HashMap, HashSet};
use std::path::Path;

use anyhow::{Context, bail};
use brickcast_protocol::wire::Role;

#[derive(Debug, Clone, Default)]
pub struct Auth {
    tokens: Option<HashMap<String, Grant>>,
    /// The names the file gives users, by [`crate::identity::name_key`]: nobody else may show
    /// them, or a name that looks like them.
    reserved: HashSet<String>,
}

/// What a token grants: a role, and the user it belongs to when the line names one.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Grant {
    pub role: Role,
    pub name: Option<String>,
    /// May use the admin API (an `admin` line; its role is [`Role::Editor`]).
    pub admin: bool,
}

/// The outcome of presenting a token.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Access {
    Granted(Grant),
    Refused,
}

impl Access {
    fn role(role: Role) -> Access {
        Access::Granted(Grant {
            role,
            name: None,
            admin: false,
        })
    }
}

impl Auth {
    /// Everyone is an editor.
    pub fn open() -> Auth {
        Auth::default()
    }

    /// Whether every connection is let in as an editor (no `--auth` file).
    pub fn is_open(&self) -> bool {
        self.tokens.is_none()
    }

    pub fn from_file(path: &Path) -> anyhow::Result<Auth> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading auth file {}", path.display()))?;
        Self::parse(&text).with_context(|| format!("in auth file {}", path.display()))
    }

    pub fn parse(text: &str) -> anyhow::Result<Auth> {
        let mut tokens = HashMap::new();
        for (n, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let mut parts = line.split_whitespace();
            let (Some(token), Some(role)) = (parts.next(), parts.next()) else {
                bail!("line {}: expected `TOKEN ROLE [NAME]`", n + 1);
            };
            let rest: Vec<&str> = parts.collect();
            let name = (!rest.is_empty()).then(|| rest.join(" "));
            if let Some(name) = &name
                && let Err(e) = brickcast_protocol::wire::check_display_name(name)
            {
                bail!("line {}: {e}", n + 1);
            }
            let (role, admin) = match role {
                "admin" => (Role::Editor, true),
                "editor" => (Role::Editor, false),
                "viewer" => (Role::Viewer, false),
                other => bail!(
                    "line {}: role must be `admin`, `editor` or `viewer`, not `{other}`",
                    n + 1
                ),
            };
            if tokens
                .insert(token.to_string(), Grant { role, name, admin })
                .is_some()
            {
                bail!("line {}: token listed twice", n + 1);
            }
        }
        let reserved = tokens
            .values()
            .filter_map(|g| g.name.as_deref())
            .map(crate::identity::name_key)
            .collect();
        Ok(Auth {
            tokens: Some(tokens),
            reserved,
        })
    }

    /// Whether `name` is (or looks like) a name the auth file gives a user.
    pub fn reserves(&self, name: &str) -> bool {
        !self.reserved.is_empty() && self.reserved.contains(&crate::identity::name_key(name))
    }

    /// Whether a request with `token` from `from` may use the admin API: an `admin` token, or
    /// (no auth file) any request from this machine. The error says why not.
    pub fn check_admin(&self, token: Option<&str>, from: std::net::IpAddr) -> Result<(), String> {
        match (&self.tokens, token) {
            (None, _) if from.is_loopback() => Ok(()),
            (None, _) => Err(format!(
                "the admin API of a server without --auth answers only this machine, not {from}: give the server an auth file with an `admin` line"
            )),
            (Some(_), None) => Err(
                "the admin API needs an admin token (`Authorization: Bearer TOKEN`; `--token` or BRICKCAST_TOKEN for `brickcast-server admin`)".into(),
            ),
            (Some(map), Some(t)) => match map.get(t) {
                Some(g) if g.admin => Ok(()),
                Some(_) => Err("that token is not an admin's (its line in the auth file gives another role)".into()),
                None => Err("unknown token".into()),
            },
        }
    }

    pub fn check(&self, token: Option<&str>) -> Access {
        match (&self.tokens, token) {
            (None, _) => Access::role(Role::Editor),
            (Some(_), None) => Access::role(Role::Viewer),
            (Some(map), Some(t)) => map
                .get(t)
                .map_or(Access::Refused, |g| Access::Granted(g.clone())),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roles_from_file() {
        let auth =
            Auth::parse("# team\nalice-secret editor Alice Liddell\nbob viewer  # read only\n\n")
                .unwrap();
        assert_eq!(
            auth.check(Some("alice-secret")),
            Access::Granted(Grant {
                role: Role::Editor,
                name: Some("Alice Liddell".into()),
                admin: false,
            })
        );
        assert_eq!(auth.check(Some("bob")), Access::role(Role::Viewer));
        assert_eq!(auth.check(None), Access::role(Role::Viewer));
        assert_eq!(auth.check(Some("mallory")), Access::Refused);
        assert_eq!(Auth::open().check(None), Access::role(Role::Editor));
        assert!(auth.reserves("Alice Liddell") && auth.reserves("AIice LiddeII"));
        assert!(!auth.reserves("Alice") && !Auth::open().reserves("Alice Liddell"));
        assert!(Auth::parse("x administrator").is_err());
        assert!(Auth::parse("x").is_err());
        assert!(Auth::parse("x editor\nx viewer").is_err());
    }

    #[test]
    fn admins_come_from_the_file_or_this_machine() {
        let here: std::net::IpAddr = "127.0.0.1".parse().unwrap();
        let away: std::net::IpAddr = "192.0.2.7".parse().unwrap();
        let auth = Auth::parse("root-secret admin Ops\nalice editor\n").unwrap();
        assert_eq!(
            auth.check(Some("root-secret")),
            Access::Granted(Grant {
                role: Role::Editor,
                name: Some("Ops".into()),
                admin: true,
            })
        );
        assert!(auth.check_admin(Some("root-secret"), away).is_ok());
        let not = auth.check_admin(Some("alice"), here).unwrap_err();
        assert!(not.contains("not an admin"), "{not}");
        assert!(
            auth.check_admin(None, here)
                .unwrap_err()
                .contains("needs an admin token")
        );
        assert!(auth.check_admin(Some("nope"), here).is_err());
        let open = Auth::open();
        assert!(open.check_admin(None, here).is_ok());
        assert!(open.check_admin(None, "::1".parse().unwrap()).is_ok());
        assert!(
            open.check_admin(None, away)
                .unwrap_err()
                .contains("only this machine")
        );
    }
}
