//! `brickcast-server cluster repair --scene NAME`: the operator's way past a log message no
//! node can read.

/// What a node says when a scene's log cannot be followed: how to repair it.
pub fn hint(scene: &str) -> String {
    format!(
        "an operator can drop what cannot be read with `brickcast-server cluster repair --scene {scene}`"
    )
}
