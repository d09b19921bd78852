//! The half of the brickcast viewer that runs anywhere: natively (the `brickcast` binary) and in a
//! browser tab (`web/`, compiled to wasm32 with wgpu's WebGPU backend).
//!
//! Why a crate of its own: the browser viewer must not be a second implementation of the wire
//! format, the brick layout or the tracer. Everything here is shared by both shells; what is
//! left to a shell is its window, its socket and its clock. Nothing here may use threads, tokio,
//! winit or blocking waits (except behind `cfg(not(target_arch = "wasm32"))`).
//!
//! Data flow in both shells: server message → [`session::Session::apply`] (the replica) →
//! [`present::sync_scene`] (the GPU copy) → [`gpu::Tracer`] → [`present::Presenter`] (blit +
//! overlay).

pub mod backoff;
pub mod budget;
pub mod camera;
pub mod follow;
pub mod gpu;
pub mod history;
pub mod overlay;
pub mod paste;
pub mod present;
pub mod session;
pub mod shading;
pub mod swatch;
pub mod tools;

/// A clock that works on wasm32 too (`std::time::Instant` panics there).
#[cfg(not(target_arch = "wasm32"))]
pub use std::time::Instant;
#[cfg(target_arch = "wasm32")]
pub use web_time::Instant;
