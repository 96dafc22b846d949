//! The pointfarm daemon: datasets, jobs and their durable state (sled), frame tasks leased to
//! workers (the embedded worker process and `pointfarm worker` processes), and the
//! `pointfarm.v1` gRPC API over all of it.
//!
//! From the bottom up: `model` and `camera_path` (domain types, the camera of each frame), `error`
//! (the daemon's and the state database's errors), `limits` (the bounds on names and ids clients
//! send), `lease_record` (the stored lease), `manifest` (the counts recorded beside the database),
//! `capabilities` (what a worker can render, what a job requires of one), `state` (the sled state
//! database, `StateDb`), `stores` (the datasets' level-of-detail stores), `worker_presence` (which
//! workers can render, for health), `service` (the `Daemon` and its job operations), `datasets`
//! (datasets of one or more files: registered, uploaded, composed; more `Daemon` methods),
//! `remote_datasets` (datasets by URL: a COPC object, or LAS/LAZ tiles and s3:// prefixes of them,
//! under the operator's allowed prefixes; more `Daemon` methods),
//! `describe` (what a dataset's files hold, read with the render crate; more `Daemon` methods),
//! `chains` (jobs that run after others succeed, failed along the chain when one does not;
//! more `Daemon` methods), `job_control` (cancel, retry, pause, resume, priority, delete;
//! job names and labels; more `Daemon` methods), `retention` (ended jobs removed by age or
//! a quota of frames, on a sweep),
//! `lease` (frame leases: the one scheduling path, more `Daemon` methods), `grpc` (validates,
//! converts and delegates: one file per service, the conversions, the streaming of bytes; the
//! frame-task conversions are public for the worker's side of the wire), `supervisor` (runs the
//! embedded worker as a child process, a `pointfarm worker` whose code is the `pointfarm-worker`
//! crate's, never linked here), `access` (the client and worker roles and their tokens),
//! `server` (sockets, TLS, health, reflection, the lease sweep, shutdown), `dashboard` (the
//! farm in a browser: pages, a JSON API and live events over the same `Daemon` methods),
//! `metrics` (Prometheus
//! metrics of the daemon and the worker, and their HTTP endpoint), `webhooks` (job ends posted,
//! signed, to the operator's endpoints); `testing` (a small real disk to fill, for tests).
//! Only `grpc` and `server` (which mounts the services) know protobuf here; the worker crate's
//! lease loop is the other side of the wire.

pub mod access;
pub mod availability;
pub mod capabilities;
pub mod chains;
pub mod dashboard;
pub mod dataset_files;
pub mod datasets;
pub mod describe;
pub mod encode_record;
pub mod encodes;
pub mod error;
pub mod export;
pub mod farm_state;
pub mod grpc;
pub mod job_control;
pub mod lease;
pub mod lease_record;
pub mod limits;
pub mod manifest;
pub mod metrics;
pub mod model;
pub mod open_files;
pub mod output_queue;
pub mod outputs;
pub mod remote_datasets;
pub mod retention;
pub mod server;
pub mod service;
pub mod state;
pub mod stores;
pub mod supervisor;
#[cfg(test)]
mod test_daemon;
#[cfg(any(test, feature = "testing"))]
pub mod testing;
pub mod webhooks;
pub mod worker_presence;
