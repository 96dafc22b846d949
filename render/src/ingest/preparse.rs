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

pub(crate) fn check_file(
    path: &Path,
    file: &mut dyn ReadSeek,
    file_len: u64,
) -> Result<CheckedFile, IngestError> {
    let facts = HeaderFacts::read(path, file, file_len)?;
    let mut raw = RawFile::new(path, file, file_len);
    let laszip = check_records(&mut raw, &facts)?;
    let (laz, chunks) = if facts.compressed {
        let (layout, chunks) = check_laz(&mut raw, &facts, laszip)?;
        (Some(layout), chunks)
    } else {
        (None, ChunkTable::default())
    };
    Ok(CheckedFile { facts, laz, chunks })
}
