//! LAS/LAZ ingest: reads a file into a recentred [`PointCloud`](crate::cloud::PointCloud),
//! and writes clouds back out (for tests and the generated sample scene).
//!
//! Every failure is an [`IngestError`] naming the file, never a panic, an abort or an
//! allocation larger than the file. The file is pre-parsed by hand before the `las` and `laz`
//! crates see it (header, VLRs, EVLRs, the LASzip VLR, the chunk table), because the crates
//! trust what it declares: they allocate declared record lengths, chunk counts and byte counts
//! before reading them, multiply counts by record lengths unchecked and assert that the
//! LASzip items match the record length. What they can still panic on is contained.
//!
//! LAZ is decoded on all cores (`laz-parallel`, rayon); LAS is a plain sequential read.
//!
//! - `preparse.rs`: the checks before the `las` crate sees the file, made by `header.rs` (the
//!   header block), `transforms.rs` (scales and offsets), `records.rs` (VLRs and EVLRs) and
//!   `laz_layout.rs` (the LASzip VLR, the chunk table, layered chunks), reading through
//!   `raw_file.rs` (bounded reads);
//! - `contain.rs`: a decoder panic turned into an error;
//! - `read.rs`: reading checked files batch by batch (LAZ on all cores), a dataset's files
//!   into one cloud;
//! - `chunk_starts.rs`: a preview sample without decompressing: the raw first point of
//!   every LAZ chunk, every k-th LAS record, of files here or objects by URL alike;
//! - `ranged.rs`: the one face a file's bytes are read through by range, a file here or an
//!   object by URL (`copc::bytes`), for the pre-parse, the header and the sample;
//! - `columns.rs`: the decoded points and the cloud made of them (origin, colors);
//! - `files.rs`: the files of a dataset, from files and folders (anywhere, or only inside a
//!   server's data roots), and `open_dataset_file`, the one open of a dataset's file;
//! - `info.rs`: what a file is, for `pointfarm info`: header facts, attributes, and a
//!   summary of its points streamed; `crs.rs`: the CRS its records declare;
//! - `source.rs`: a dataset's files as the level-of-detail builder's source, streamed;
//!   `objects.rs`: its files as objects by URL, checked by range and streamed in blocks;
//!   `store_update.rs`: a store updated from the files it gains, loses and keeps;
//! - `write.rs`: writing clouds as LAS or LAZ;
//! - `error.rs`: [`IngestError`].

mod chunk_starts;
mod columns;
mod contain;
mod crs;
#[cfg(test)]
mod dataset_tests;
mod error;
mod files;
mod header;
mod info;
mod laz_layout;
mod objects;
mod preparse;
mod ranged;
mod raw_file;
mod read;
mod records;
mod source;
mod store_update;
#[cfg(test)]
mod test_files;
mod transforms;
mod write;

pub use crate::cloud::MAX_COORDINATE;
pub(crate) use chunk_starts::sample_ranged;
pub use chunk_starts::{sample_chunk_starts, PreviewSample, LAS_PREVIEW_STRIDE};
pub(crate) use contain::contain_panics;
pub use crs::{Crs, GeoKeys, USER_DEFINED as GEOTIFF_USER_DEFINED};
pub use error::IngestError;
pub use files::{dataset_files, dataset_files_in, open_dataset_file, FileScope, Symlinks};
pub use info::{Attributes, FileInfo, PointSummary, RgbRange};
pub(crate) use laz_layout::layer_count;
pub(crate) use preparse::{check_file_with, ChunkChecks};
pub(crate) use ranged::RangedBytes;
pub(crate) use raw_file::ReadSeek;
pub use source::DatasetSource;
pub use store_update::{update_from_files, FilesChange};

/// The first four bytes of every LAS and LAZ file.
pub const LAS_SIGNATURE: &[u8; 4] = b"LASF";
pub use read::{dataset_point_count, deciding, load_dataset, load_point_cloud};
pub use write::{write_las, LasStreamWriter, LasWriteOptions, WriteLasError};
