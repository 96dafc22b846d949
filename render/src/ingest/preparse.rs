//! The raw pre-parse of a file, before the `las` and `laz` crates see it: the header, every
//! VLR and EVLR header, the LASzip VLR and the chunk table. Each size, count and offset read
//! from the file is checked against the file's size (and the fields it must agree with)
//! before anything is allocated from it, so what the crates then allocate is bounded by the
//! data actually present.

use std::path::Path;

use laz::laszip::ChunkTable;

use super::header::HeaderFacts;
use super::laz_layout::{check_laz, LazLayout};
use super::raw_file::{RawFile, ReadSeek};
use super::records::check_records;
use super::IngestError;

/// A file that passed the pre-parse: its header facts and, for LAZ, how it is compressed and
/// its chunk table (every entry inside the compressed data).
pub(crate) struct CheckedFile {
    pub facts: HeaderFacts,
    pub laz: Option<LazLayout>,
    pub chunks: ChunkTable,
}

/// How far into a LAZ file's chunks the pre-parse looks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ChunkChecks {
    /// The chunk table and every chunk's layer table: a file about to be decoded whole.
    Layers,
    /// The chunk table alone: a COPC file, whose reader checks a chunk's layer table before
    /// it decodes the chunk, and which may be read by URL, where a read of every chunk's
    /// table would be a request per chunk at open.
    Table,
}

pub(crate) fn check_file(
    path: &Path,
    file: &mut dyn ReadSeek,
    file_len: u64,
) -> Result<CheckedFile, IngestError> {
    check_file_with(path, file, file_len, ChunkChecks::Layers)
}

/// [`check_file`], looking as far into the chunks as `chunks` says.
pub(crate) fn check_file_with(
    path: &Path,
    file: &mut dyn ReadSeek,
    file_len: u64,
    chunks: ChunkChecks,
) -> Result<CheckedFile, IngestError> {
    let facts = HeaderFacts::read(path, file, file_len)?;
    let mut raw = RawFile::new(path, file, file_len);
    let laszip = check_records(&mut raw, &facts)?;
    let (laz, chunks) = if facts.compressed {
        let layers = chunks == ChunkChecks::Layers;
        let (layout, chunks) = check_laz(&mut raw, &facts, laszip, layers)?;
        (Some(layout), chunks)
    } else {
        (None, ChunkTable::default())
    };
    Ok(CheckedFile { facts, laz, chunks })
}
