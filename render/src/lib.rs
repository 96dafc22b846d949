//! pointfarm's rendering library: reads LAS/LAZ into a recentred [`cloud::PointCloud`] and
//! renders it with a wgpu compute-shader rasterizer.
//!
//! This crate knows nothing of gRPC, the daemon or the CLI: it takes files, clouds, cameras
//! and render settings, and returns images with their stage timings.

pub mod cache;
pub mod camera;
pub mod classification;
pub mod cloud;
pub mod color;
pub mod copc;
pub mod cut;
pub mod encode;
pub mod extent;
pub mod extra_bytes;
pub mod filter;
pub mod gpu;
pub mod ingest;
pub mod legend;
pub mod lod;
pub mod raster;
pub mod reference;
pub mod remote;
pub mod request;
pub mod sample;
pub mod sled_open;
pub mod source;
pub mod spacing;
pub mod write_whole;

#[cfg(any(test, feature = "testing"))]
pub mod testing;
