//! Who a connection is: the user id its history is kept under, the name and colour others see.
//!
//! **Why ids come from the client.** History must survive reconnecting and restarts, so a
//! user needs an id that outlives a connection; the viewer keeps a random one in a file under
//! the user's config directory and sends it in `Hello`. Without `--auth` nothing stops a client
//! from claiming someone else's id (and everyone may edit anyway): the server is trusted by
//! people who trust each other. With `--auth`, a token line that names a user pins the id:
//! token-pinned ids have the top bit set and ids a client sends have it cleared, so no client
//! can claim a token's user by choosing its id.

use brickcast_protocol::Colour;
use brickcast_protocol::wire::{UserId, clean_display_name};

/// Who a connection is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Identity {
    pub user: UserId,
    pub name: String,
    pub colour: Colour,
    /// False for a connection that sent no id: its history is dropped when it leaves.
    pub stable: bool,
    /// The name (and id) come from the auth file: the user cannot rename themself.
    pub pinned: bool,
}

/// The bit set in the ids of users an auth file names (and cleared in ids clients choose).
pub const PINNED: u64 = 1 << 63;

/// Colours far apart from each other, one per user by id; no greens, which the terrain of
/// most scenes is, and no red: the viewers paint in red first, and a person drawn in it read
/// as the paint colour (issue #32).
const PALETTE: [(u8, u8, u8); 12] = [
    (140, 140, 140),
    (30, 110, 240),
    (250, 230, 30),
    (150, 60, 210),
    (20, 200, 220),
    (255, 130, 0),
    (240, 70, 200),
    (255, 255, 255),
    (90, 50, 20),
    (255, 180, 200),
    (0, 130, 130),
    (20, 30, 110),
];

fn mix(mut x: u64) -> u64 {
    x ^= x >> 33;
    x = x.wrapping_mul(0xff51_afd7_ed55_8ccd);
    x ^= x >> 33;
    x = x.wrapping_mul(0xc4ce_b9fe_1a85_ec53);
    x ^ (x >> 33)
}

/// FNV-1a, then mixed: stable across runs and builds (ids are stored).
fn hash_name(name: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in name.bytes() {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    mix(h)
}

/// The colour a user is drawn in, unless someone else present has it (see [`colour_among`]).
pub fn colour_of(user: UserId) -> Colour {
    palette_colour((mix(user) % PALETTE.len() as u64) as usize)
}

/// Every colour a user may be drawn in.
pub fn marker_colours() -> Vec<Colour> {
    (0..PALETTE.len()).map(palette_colour).collect()
}

fn palette_colour(i: usize) -> Colour {
    let (r, g, b) = PALETTE[i % PALETTE.len()];
    Colour::from_rgb8(r, g, b)
}

/// Squared RGB distance under which two markers read as the same colour (90 steps; every two
/// palette colours are farther apart).
const ALIKE: i32 = 90 * 90;

fn distance(a: Colour, b: Colour) -> i32 {
    let (a, b) = (a.to_rgb8(), b.to_rgb8());
    (0..3)
        .map(|i| (i32::from(a[i]) - i32::from(b[i])).pow(2))
        .sum()
}

/// Whether two markers would read as the same colour.
pub fn looks_alike(a: Colour, b: Colour) -> bool {
    distance(a, b) < ALIKE
}

/// The user's own colour, unless it looks like one another user present shows: then the
/// palette colour farthest from every colour shown. People in one scene can tell each other
/// apart (up to twelve of them), and a user among few keeps the same colour every time.
pub fn colour_among(user: UserId, taken: &[Colour]) -> Colour {
    let nearest = |c: Colour| {
        taken
            .iter()
            .map(|&t| distance(c, t))
            .min()
            .unwrap_or(i32::MAX)
    };
    let own = colour_of(user);
    if nearest(own) >= ALIKE {
        return own;
    }
    (0..PALETTE.len())
        .map(palette_colour)
        .max_by_key(|&c| nearest(c))
        .filter(|&c| nearest(c) > nearest(own))
        .unwrap_or(own)
}

/// A name fit to show: the client's made fit (`clean_display_name`: no control or format
/// characters, no stacked marks), else `guest-N`.
fn display_name(asked: &str, session: u64) -> String {
    let name = clean_display_name(asked);
    if name.is_empty() {
        format!("guest-{session}")
    } else {
        name
    }
}

/// What two names that look alike share: their UTS #39 skeleton, compared without case. The
/// skeleton is case-sensitive (it maps capital `I` and `1` to `l`) and lowercasing makes an `i`
/// of what was an `I`, so the key is the skeleton of the lowercased skeleton with `i` read as
/// `l`: `Alice`, `AIice`, `ALICE`, `A1ice` and a Cyrillic `Аlice` meet, and `rn` meets `m`.
/// It errs towards "alike" (`Allce` meets `Alice` too): a name is only refused for it.
/// Two people whose names have one key cannot both be shown under them.
pub fn name_key(name: &str) -> String {
    let once: String = unicode_security::skeleton(name).collect();
    unicode_security::skeleton(&once.to_lowercase())
        .map(|c| if c == 'i' { 'l' } else { c })
        .collect()
}

/// Whether `user` is pinned by a token's line (its id cannot be chosen by a client).
pub fn is_pinned(user: UserId) -> bool {
    user & PINNED != 0
}

/// Decides a connection's identity from its `Hello` (`asked_user`, `asked_name`) and, with
/// `--auth`, the name its token's line gives (`token_name`). `open` is whether the server runs
/// without `--auth`; `reserved` whether a name is another's (the auth file's names and those
/// that look like them): a client asking for one is shown as `guest-N`.
pub fn identify(
    open: bool,
    token_name: Option<&str>,
    asked_user: UserId,
    asked_name: &str,
    session: u64,
    reserved: impl Fn(&str) -> bool,
) -> Identity {
    let (user, name, stable) = match token_name {
        Some(name) => (hash_name(name) | PINNED, name.to_string(), true),
        None => {
            let asked = if open {
                asked_user
            } else {
                asked_user & !PINNED
            };
            let mut name = display_name(asked_name, session);
            if reserved(&name) {
                name = format!("guest-{session}");
            }
            if asked == 0 {
                // Any id unlikely to meet another: it lives as long as the connection.
                let user = mix(session ^ 0x9e37_79b9_7f4a_7c15 ^ nanos()) & !PINNED;
                (user.max(1), name, false)
            } else {
                (asked, name, true)
            }
        }
    };
    Identity {
        user,
        name,
        colour: colour_of(user),
        stable,
        pinned: token_name.is_some(),
    }
}

fn nanos() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn none(_: &str) -> bool {
        false
    }

    #[test]
    fn names_that_look_alike_share_a_key() {
        let alice = name_key("Alice");
        // Capital I for l, Cyrillic А, Greek ο, case, a digit one, fullwidth letters.
        for alike in ["AIice", "\u{410}lice", "ALICE", "A1ice", "Ａｌｉｃｅ"] {
            assert_eq!(name_key(alike), alice, "{alike:?}");
        }
        assert_eq!(name_key("Bοb"), name_key("Bob"));
        assert_eq!(name_key("rnary"), name_key("mary"));
        for other in ["Alicia", "Al ice", "Bob", "alice2"] {
            assert_ne!(name_key(other), alice, "{other:?}");
        }
        // A client asking for a reserved name is shown as a guest.
        let reserved = |n: &str| name_key(n) == alice;
        assert_eq!(
            identify(false, None, 5, "A\u{200B}lice", 7, reserved).name,
            "guest-7"
        );
        assert_eq!(identify(false, None, 5, "Bob", 7, reserved).name, "Bob");
        // The token's own user keeps it.
        assert_eq!(
            identify(false, Some("Alice"), 5, "x", 7, reserved).name,
            "Alice"
        );
        assert!(is_pinned(
            identify(false, Some("Alice"), 5, "x", 7, reserved).user
        ));
    }

    #[test]
    fn tokens_pin_ids_and_clients_cannot_claim_them() {
        let alice = identify(false, Some("alice"), 5, "x", 1, none);
        assert_eq!(alice.name, "alice");
        assert!(alice.stable);
        assert_eq!(alice, identify(false, Some("alice"), 77, "y", 2, none));
        let claim = identify(false, None, alice.user, "mallory", 3, none);
        assert_ne!(claim.user, alice.user);
        // Without --auth an id is taken as sent.
        assert_eq!(
            identify(true, None, alice.user, "m", 3, none).user,
            alice.user
        );
        let anon = identify(true, None, 0, "", 9, none);
        assert!(!anon.stable && anon.user != 0);
        assert_eq!(anon.name, "guest-9");
        assert_eq!(
            identify(true, None, 4, " bad\u{7}name ", 9, none).name,
            "badname"
        );
        assert_eq!(identify(true, None, 4, "bob", 9, none).colour, colour_of(4));
        // Someone present already shows user 4's colour: the next free one instead.
        let mine = colour_of(4);
        let other = colour_among(4, &[mine]);
        assert_ne!(other, mine);
        assert_eq!(colour_among(4, &[]), mine);
        let all: Vec<Colour> = (0..PALETTE.len()).map(palette_colour).collect();
        assert_eq!(colour_among(4, &all), mine, "twelve taken: keep one's own");
        // Every pair of palette colours is told apart by the rule.
        for (i, a) in all.iter().enumerate() {
            for b in &all[i + 1..] {
                let d: i32 = (0..3)
                    .map(|k| (i32::from(a.to_rgb8()[k]) - i32::from(b.to_rgb8()[k])).pow(2))
                    .sum();
                assert!(d >= 90 * 90, "{a:?} and {b:?} look alike");
            }
        }
    }
}
