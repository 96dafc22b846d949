//! The pointfarm daemon: datasets, jobs and their durable state (sled), frame tasks leased to
//! workers (embedded threads and `pointfarm worker` processes), and the `pointfarm.v1` gRPC API
//! over all of it.
//!
//! Layers: `model` (domain types), `store` (sled), `service` (the domain operations), `lease`
//! (frame leases: the one scheduling path), `frame_render` (renders one task with
//! `pointfarm-worker`, shared by both kinds of worker), `worker` (the embedded worker thread),
//! `remote_worker` (the worker process, a gRPC client), `grpc` (converts and delegates; with
//! `remote_worker` the only modules that know protobuf), `server` (sockets, health,
//! reflection, the lease sweep, shutdown).

pub mod error;
pub mod frame_render;
pub mod grpc;
pub mod lease;
pub mod model;
pub mod remote_worker;
pub mod server;
pub mod service;
pub mod store;
pub mod worker;
