//! The viewer's lighting switches, one table for the window and the page.
//!
//! Why here: both viewers take keys by `KeyboardEvent.code` name, and a switch that only one of
//! them had would make the two disagree about what a scene looks like.

use brickcast_protocol::Lighting;

/// Keys that change the lighting, by `KeyboardEvent.code`, and what each does.
pub const SHADING_KEYS: [(&str, &str); 3] = [
    ("KeyO", "ambient occlusion on/off"),
    ("KeyL", "sun shadows on/off"),
    ("KeyH", "headlight on/off"),
];

/// How long the viewers show what a lighting key switched (on screen and in the status).
pub const NOTE_SECONDS: f64 = 3.0;

/// Headlight strength the H key turns on when the default has none.
pub const HEADLIGHT: f32 = 0.3;

/// Applies the switch bound to `code`, if any; returns a short line saying what is now on.
pub fn shading_key(lighting: &mut Lighting, code: &str) -> Option<String> {
    let default = Lighting::default();
    match code {
        "KeyO" => {
            lighting.ao = !lighting.ao;
            Some(format!("ambient occlusion {}", on_off(lighting.ao)))
        }
        "KeyL" => {
            lighting.shadows = !lighting.shadows;
            Some(format!("sun shadows {}", on_off(lighting.shadows)))
        }
        "KeyH" => {
            lighting.headlight = if lighting.headlight > 0.0 {
                0.0
            } else if default.headlight > 0.0 {
                default.headlight
            } else {
                HEADLIGHT
            };
            Some(format!("headlight {}", on_off(lighting.headlight > 0.0)))
        }
        _ => None,
    }
}

fn on_off(on: bool) -> &'static str {
    if on { "on" } else { "off" }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_listed_key_toggles_and_toggles_back() {
        for (code, _) in SHADING_KEYS {
            let mut lighting = Lighting::default();
            assert!(shading_key(&mut lighting, code).is_some(), "{code}");
            assert_ne!(lighting, Lighting::default(), "{code} changed nothing");
            shading_key(&mut lighting, code);
            assert_eq!(lighting, Lighting::default(), "{code} twice is a no-op");
        }
        assert_eq!(shading_key(&mut Lighting::default(), "KeyW"), None);
    }
}
