//! The brickcast thin client: a replica of a scene fed by the server, its GPU copy, the compute
//! tracer, the two front ends (`brickcast view` and `brickcast render`), and the load generator
//! (`brickcast load`).

pub mod follow;
pub mod gpu;
pub mod headless;
pub mod identity;
pub mod link;
pub mod live;
pub mod load;
pub mod overlay;
pub mod replica;
pub mod viewer;
