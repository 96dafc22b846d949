//! The pointfarm worker: leases frames from a daemon over the `pointfarm.v1` worker service,
//! renders them with `pointfarm-render` on its own GPU and hands the images back. It runs as
//! `pointfarm worker`, on another machine or as the daemon's embedded worker (a child process
//! the daemon supervises); both use the same leases, the same protocol and this same code.
//! The lease model and its wire conversions are the daemon's (`pointfarm-daemon`); the daemon
//! never links this crate.
//!
//! - `lease_loop`: the worker process's loop: lease a frame, render it while heartbeats renew
//!   the lease, hand the PNG in; retries, backoff and stopping.
//! - `render_state`: the worker's renderer, dataset cache and resident cloud, and the rendering
//!   of one leased frame into a PNG with its stage timings.
//! - `daemon_store`: the daemon's level-of-detail store, COPC hierarchy and preview sample as
//!   the worker reads them over gRPC.
//! - `opening_reads`: the node records a daemon's store's opening fetched, kept for its first
//!   frame.
//! - `url_dataset`: a dataset by URL, whose COPC object the worker reads itself by range.
//! - `published_store`: a store the daemon published to object storage, read from there.
//! - `range_cache`: the on-disk cache of ranges of objects by URL, by their version.
//! - `encode`: jobs' videos, made with ffmpeg under encode leases beside the frames.
//! - `lease_renewal`: keeping a frame's or a video's lease while its work runs.
//! - `stopping`: the waits between tries, which a stop cuts short.
//! - `backoff`: how long those waits are.
//! - `failure`: why a frame failed, and whether another attempt may succeed.
//! - `memory_limit`: the worker process's limit on its own memory.
//! - `supervised`: exiting when the supervising daemon is gone.
//! - `client`: the worker service's client with the worker's token.

mod backoff;
mod client;
pub mod daemon_store;
pub mod encode;
pub mod failure;
pub mod lease_loop;
mod lease_renewal;
pub mod memory_limit;
mod opening_reads;
pub mod published_store;
pub mod range_cache;
pub mod render_state;
mod stopping;
pub mod supervised;
pub mod url_dataset;
