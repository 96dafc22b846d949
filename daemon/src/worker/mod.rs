//! Workers: what leases frames from the daemon and renders them, all through the same leases
//! (`crate::lease`) and the same gRPC worker protocol.
//!
//! - `remote`: the `pointfarm worker` process, a gRPC client with its own GPU and cache.
//! - `supervisor`: runs a worker process as the daemon's embedded worker: restarts it when it
//!   exits, counts the attempts of the frames it held, stops it on shutdown.
//! - `render_state`: a worker's renderer, dataset cache and resident cloud, and the rendering
//!   of one leased frame into a PNG with its stage timings.
//! - `failure`: why a frame failed, and whether another attempt may succeed.
//! - `memory_limit`: the worker process's limit on its own memory.

mod client;
pub mod daemon_store;
pub mod failure;
pub mod memory_limit;
pub mod remote;
pub mod render_state;
pub mod supervisor;
