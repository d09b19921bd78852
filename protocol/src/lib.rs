//! The one home of brickcast's data layout, shared by server and client.
//!
//! * [`brick`], [`colour`]: the 8×8×8 brick (512-bit mask + compact RGB565 colours).
//! * [`map`]: the sparse three-level brick map, its edits, versions and memory accounting.
//! * [`palette`]: a brick's colours coded in fewer bits (one colour, a palette, or raw).
//! * [`trace`]: the CPU DDA tracer (the GPU shader's twin) and its flat reference.
//! * [`beam`]: the per-tile pre-pass that starts primary rays past the empty space they share.
//! * [`render`]: camera and the multi-threaded CPU renderer.
//! * [`shade`]: sky light, ambient occlusion, sun and shadows, tone mapping (the shader's twin).
//! * [`shadow`]: shadow rays that start from a per-frame table of the sun's voxel walk.
//! * [`wire`]: the websocket messages and their compact, compressed brick payloads.
//! * [`apply`]: what a wire edit op does to a brick map (shared by the server and log replay).
//! * [`demo`]: the built-in procedural demo scene.
//! * [`lod`]: levels of detail, a mip pyramid of the map kept current as edits land.
//! * [`journal`]: before-images of the bricks an edit changes (for undo), and brick diffs.
//! * [`replica`]: a client's copy of a scene, kept current by applying server messages.
//! * [`roster`]: a client's list of who else is present and what they look at.
//! * [`backoff`]: waits between retries, doubling, with jitter (every retry loop's rule).
//! * [`viewpoint`]: the first camera for a scene: one that shows the model, outside or in.

pub mod apply;
pub mod backoff;
pub mod beam;
mod block_edit;
pub mod blocks;
pub mod brick;
pub mod clipboard;
pub mod colour;
pub mod demo;
pub mod held;
pub mod journal;
pub mod lod;
pub mod map;
pub mod palette;
pub mod region;
pub mod render;
pub mod replica;
pub mod rewind;
pub mod roster;
pub mod shade;
pub mod shadow;
pub mod swatches;
pub mod trace;
pub mod viewpoint;
pub mod wire;
pub mod working_set;
pub mod world;

pub use brick::{BrickData, EMPTY, Mask};
pub use colour::Colour;
pub use map::{BrickMap, BrushMode, MemoryStats};
pub use render::{Camera, Frame, Lighting, Projection};
pub use trace::{Hit, Ray, trace};

// The README's Rust example is compiled and run as a doctest so it cannot drift from the API.
#[cfg(doctest)]
#[doc = include_str!("../../README.md")]
struct ReadmeDoctests;
