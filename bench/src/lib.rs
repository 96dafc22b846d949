//! The benchmark harness behind `pointfarm bench`: workloads, and a runner that renders each
//! with every method on the same resident buffers, the same camera and the same image size.
//!
//! Methods: the fixed-function `PointList` baseline
//! ([`PointListBaseline`](pointfarm_render::raster::PointListBaseline)), the compute
//! rasterizer's basic mode ([`Renderer`](pointfarm_render::raster::Renderer)) and its other
//! modes ([`ComputeMode`]: high quality, the 32-bit path, fill with EDL or Pintus shading).
//! A frame's time is the GPU work that produces its image: every pass of the frame (clear,
//! point passes, resolve, shading). Upload, readback and other host-side stages are reported
//! per stage but left out of the frame time, since they do not depend on the method. Every
//! figure is the median over measured frames, after warm-up rounds. Each round renders frames
//! with every method in turn, so that slow drifts of the machine's speed reach every method
//! alike; each method's measured frame follows at least [`WARM_IN_A_ROW`] of its own
//! unmeasured frames ([`SETTLE_AFTER_BASELINE`] for the first compute method after the
//! baseline on a software adapter), as in a job's run of frames. Each compute method has a
//! renderer of its own, so that no method starts its frame from the state another left
//! (`rounds::Methods`).
//!
//! Series: uniform cubes of 1M to 30M points (frame time against points in view, with a
//! least-squares line per method) and the k-plane cuboid (against overdraw); `huge` adds a
//! 100M-point cube generated and uploaded segment by segment, with the host's peak memory.
//!
//! The crate's modules, one job each: [`workloads`] (the scenes and their views) from the
//! generated [`clouds`]; `rounds` (warming and measuring the methods) and `huge` (the cloud
//! uploaded segment by segment); [`ingest`] (decoding and the dataset cache); [`campaign`] (building
//! the level-of-detail store of a campaign of many files, no GPU); [`scheduler`] (leasing a
//! frame against the daemon's job history, no GPU); [`service_load`] (real daemon processes
//! under many clients' submissions, and leasing as a worker, through gRPC); [`cuts`] (rendering level-of-detail stores
//! cut by cut: a cold turntable, frame time against points, fidelity, resident against cut);
//! [`copc`] (a COPC file's first frame node by node against decoding it whole);
//! [`object_storage`] (a COPC file from an S3 server against the local disk, and workers
//! reading a published store with the daemon out of the data path); `memory` (the
//! process's resident memory);
//! [`report`] (what was measured), written as [`markdown`], [`json`] and a [`plot`];
//! [`frame_figures`] (how much of a rendered frame its subject fills and lights, for the
//! gallery's default-render figures).
//!
//! The `PointList` baseline is compiled into the renderer only here: this crate enables the
//! render crate's `pointlist-baseline` feature.

pub mod campaign;
pub mod cli;
pub mod clouds;
pub mod copc;
pub mod cuts;
pub mod daemon_log;
mod error;
pub mod flight;
pub mod frame_figures;
mod huge;
pub mod ingest;
pub mod json;
pub mod markdown;
mod memory;
pub mod object_storage;
mod options;
pub mod plot;
pub mod report;
mod rounds;
mod run;
pub mod scheduler;
mod scratch;
pub mod serve;
pub mod service_load;
mod stats;
mod store;
pub mod workloads;

pub use error::BenchError;
pub use ingest::{generated_workload, IngestResult};
pub use options::{BenchOptions, ComputeMode, FrameRounds};
pub use report::{
    in_uniform_series, AdapterReport, BatchCounts, BenchReport, IngestMemory, MethodResult,
    ModeResult, ScalingFit, SkippedWorkload, StageMedian, WorkloadResult,
};
pub use rounds::{
    image_agreement, settle_after_baseline, MAX_WARM_FRAMES, SETTLE_AFTER_BASELINE, WARM_IN_A_ROW,
};
pub use run::run;
pub use workloads::{
    uniform_workload, CUBOID_PLANES, HEADLINE_WORKLOAD, HUGE_POINTS, REAL_SCANS, UNIFORM_POINTS,
    UNIFORM_SERIES,
};
