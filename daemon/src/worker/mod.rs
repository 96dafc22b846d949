//! Workers: what leases frames from the daemon and renders them. Both kinds go through the
//! same leases (`crate::lease`) and render with the same [`render_state::WorkerRenderState`].
//!
//! - `embedded`: a thread of the daemon that leases in-process and reads the daemon's files.
//! - `remote`: the `pointfarm worker` process, a gRPC client with its own GPU and cache.
//! - `render_state`: a worker's renderer, dataset cache and resident cloud, and the rendering
//!   of one leased frame into a PNG with its stage timings.

pub mod embedded;
pub mod remote;
pub mod render_state;
