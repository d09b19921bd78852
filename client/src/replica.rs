//! The client's copy of a scene lives in the protocol crate (`brickcast_protocol::replica`), so
//! the server's tests and every front end apply server messages through the same code; this
//! module keeps the client's paths.

pub use brickcast_protocol::replica::{Replica, ReplicaError};
