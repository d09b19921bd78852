//! The brickcast thin client: a replica of a scene fed by the server, its GPU copy, the compute
//! tracer, and the two front ends (`brickcast view` and `brickcast render`).

pub mod gpu;
pub mod headless;
pub mod link;
pub mod live;
pub mod replica;
pub mod viewer;
