//! The brickcast thin client: a replica of a scene fed by the server, its GPU copy, the compute
//! tracer, the two front ends (`brickcast view` and `brickcast render`), and the load generator
//! (`brickcast load`).

pub mod headless;
pub mod identity;
pub mod light;
pub mod link;
pub mod live;
pub mod load;
pub mod replica;
pub mod viewer;

// The portable half (also compiled into the browser viewer), under the paths this crate has
// always used.
pub use brickcast_client_core::{
    Instant, camera, follow, gpu, overlay, present, session, shading, tools,
};
pub use light::LightArgs;
