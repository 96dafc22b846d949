//! Everything that touches wgpu directly, apart from the passes themselves.

mod context;
mod readback;

pub use context::{AdapterChoice, GpuCapabilities, GpuContext, GpuError, ADAPTER_ENV};
pub(crate) use readback::{read_buffer, staging_buffer};
