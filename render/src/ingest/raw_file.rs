//! Bounded reads of a file being checked: every read names what it is reading, and a read
//! that would run past the end of the file is a [`IngestError::Corrupt`] before any buffer
//! is allocated for it.

use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use super::IngestError;

/// Where a record's data lies in the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct RecordSpan {
    pub offset: u64,
    pub len: u64,
}

/// Bytes that can be checked as a file: a local file, or an object by URL read through a
/// buffer of ranges (`copc::bytes`), so that both pass the one pre-parse.
pub(crate) trait ReadSeek: Read + Seek {}

impl<T: Read + Seek> ReadSeek for T {}

/// The file under inspection, its path (for errors) and its size (the bound of every read).
pub(super) struct RawFile<'a> {
    pub path: &'a Path,
    pub len: u64,
    file: &'a mut dyn ReadSeek,
}

impl<'a> RawFile<'a> {
    pub fn new(path: &'a Path, file: &'a mut dyn ReadSeek, len: u64) -> Self {
        Self { path, len, file }
    }

    pub fn corrupt(&self, what: impl Into<String>) -> IngestError {
        IngestError::Corrupt {
            path: self.path.to_owned(),
            what: what.into(),
        }
    }

    pub fn io(&self, error: std::io::Error) -> IngestError {
        IngestError::Io {
            path: self.path.to_owned(),
            error,
        }
    }

    /// Fails unless `len` bytes from `offset` lie inside the file.
    pub fn check_span(&self, offset: u64, len: u64, what: &str) -> Result<(), IngestError> {
        match offset.checked_add(len) {
            Some(end) if end <= self.len => Ok(()),
            _ => Err(self.corrupt(format!(
                "{what} ({len} bytes at offset {offset}) runs past the end of the file ({} bytes)",
                self.len
            ))),
        }
    }

    /// The `N` bytes at `offset`.
    pub fn array_at<const N: usize>(
        &mut self,
        offset: u64,
        what: &str,
    ) -> Result<[u8; N], IngestError> {
        let mut bytes = [0u8; N];
        self.read_into(offset, &mut bytes, what)?;
        Ok(bytes)
    }

    /// `len` bytes at `offset`, allocated only once they are known to be in the file.
    pub fn vec_at(&mut self, offset: u64, len: u64, what: &str) -> Result<Vec<u8>, IngestError> {
        self.check_span(offset, len, what)?;
        let mut bytes = vec![0u8; usize::try_from(len).map_err(|_| self.corrupt(what))?];
        self.read_into(offset, &mut bytes, what)?;
        Ok(bytes)
    }

    /// A record's data, already known to lie inside the file.
    pub fn vlr_at(&mut self, span: RecordSpan) -> Result<Vec<u8>, IngestError> {
        self.vec_at(span.offset, span.len, "the LASzip VLR")
    }

    pub fn u16_at(&mut self, offset: u64, what: &str) -> Result<u16, IngestError> {
        self.array_at(offset, what).map(u16::from_le_bytes)
    }

    pub fn u32_at(&mut self, offset: u64, what: &str) -> Result<u32, IngestError> {
        self.array_at(offset, what).map(u32::from_le_bytes)
    }

    pub fn u64_at(&mut self, offset: u64, what: &str) -> Result<u64, IngestError> {
        self.array_at(offset, what).map(u64::from_le_bytes)
    }

    /// The underlying file, positioned at `offset`, for a reader of the `laz` crate.
    pub fn file_at(&mut self, offset: u64) -> Result<&mut dyn ReadSeek, IngestError> {
        self.file
            .seek(SeekFrom::Start(offset))
            .map_err(|error| self.io(error))?;
        Ok(self.file)
    }

    /// Fills `buf` from `offset`, once the span is known to lie inside the file.
    pub fn read_into(
        &mut self,
        offset: u64,
        buf: &mut [u8],
        what: &str,
    ) -> Result<(), IngestError> {
        self.check_span(offset, buf.len() as u64, what)?;
        let path = self.path;
        let file = self.file_at(offset)?;
        file.read_exact(buf).map_err(|error| IngestError::Io {
            path: path.to_owned(),
            error,
        })
    }
}
