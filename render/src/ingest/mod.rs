//! LAS/LAZ ingest: reads a file into a recentred [`PointCloud`](crate::cloud::PointCloud),
//! and writes clouds back out (for tests and the generated sample scene).
//!
//! Every failure is an [`IngestError`] naming the file, never a panic. The header is checked by
//! hand before the `las` crate sees it, because the crate trusts the declared point count: it
//! sizes its read buffer from it (an inflated count means a huge allocation), in LAS 1.4 files it
//! multiplies the 64-bit count by the record length unchecked, and its parallel LAZ decoder
//! panics when asked for more points than the file's chunks hold.
//!
//! LAZ is decoded on all cores (`laz-parallel`, rayon); LAS is a plain sequential read.
//!
//! - `header.rs`: the checks before the `las` crate sees the file;
//! - `read.rs`: reading a checked file batch by batch (LAZ on all cores);
//! - `columns.rs`: the decoded points and the cloud made of them (origin, colours);
//! - `write.rs`: writing clouds as LAS or LAZ;
//! - `error.rs`: [`IngestError`].

mod columns;
mod error;
mod header;
mod read;
#[cfg(test)]
mod test_files;
mod write;

pub use error::IngestError;

/// The first four bytes of every LAS and LAZ file.
pub const LAS_SIGNATURE: &[u8; 4] = b"LASF";
pub use read::load_point_cloud;
pub use write::{write_las, LasWriteOptions, WriteLasError};
