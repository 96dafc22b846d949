//! The pointfarm daemon: datasets, jobs and their durable state (sled), frame tasks handed to
//! an embedded worker, and the `pointfarm.v1` gRPC API over all of it.
//!
//! Layers: `model` (domain types), `store` (sled), `service` (the domain operations),
//! `worker` (renders frame tasks with `pointfarm-worker`), `grpc` (converts and delegates;
//! the only module that knows protobuf), `server` (sockets, health, reflection, shutdown).

pub mod camera_path;
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
