//! A dataset file's bytes read by range, through one face: a file here ([`LocalFile`]), or an
//! object by URL (`copc::bytes`), so that the pre-parse, the header and a preview's sampled
//! records are read, and checked, by the same code either way.

use std::io::SeekFrom;
use std::ops::Range;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use super::contain::contain_panics;
use super::files::{open_dataset_file, Symlinks};
use super::preparse::{check_file_with, ChunkChecks};
use super::raw_file::ReadSeek;
use super::read::DatasetFile;
use super::IngestError;

/// Bytes of a LAS/LAZ file, read as a stream (the pre-parse, the header) or by scattered
/// ranges (a preview's records).
pub(crate) trait RangedBytes: Sync {
    /// What a failed read is: a file's [`IngestError`], or an error that can also say why an
    /// object could not be fetched.
    type Error: From<IngestError> + Send;

    /// The path or URL that errors name.
    fn name(&self) -> &Path;

    /// Runs `read` over the bytes as a stream from their start, with their size.
    fn read_stream<T>(
        &self,
        read: impl FnOnce(&mut dyn ReadSeek, u64) -> Result<T, IngestError>,
    ) -> Result<T, Self::Error>;

    /// Small ranges scattered over the bytes, in the order asked, each checked by the caller to
    /// lie inside: an object's near ones are fetched as one request.
    fn read_sparse(&self, ranges: &[Range<u64>]) -> Result<Vec<Vec<u8>>, Self::Error>;
}

/// A file here, opened for each read as a dataset's files are (symbolic links followed), so
/// that a campaign of many tiles holds no file open between reads.
pub(crate) struct LocalFile {
    path: PathBuf,
}

impl LocalFile {
    pub fn new(path: &Path) -> Self {
        Self {
            path: path.to_owned(),
        }
    }

    fn io(&self, error: std::io::Error) -> IngestError {
        IngestError::Io {
            path: self.path.clone(),
            error,
        }
    }
}

impl RangedBytes for LocalFile {
    type Error = IngestError;

    fn name(&self) -> &Path {
        &self.path
    }

    fn read_stream<T>(
        &self,
        read: impl FnOnce(&mut dyn ReadSeek, u64) -> Result<T, IngestError>,
    ) -> Result<T, IngestError> {
        let mut file = open_dataset_file(&self.path, Symlinks::Follow).map_err(|e| self.io(e))?;
        let len = file.metadata().map_err(|e| self.io(e))?.len();
        read(&mut file, len)
    }

    fn read_sparse(&self, ranges: &[Range<u64>]) -> Result<Vec<Vec<u8>>, IngestError> {
        let file = open_dataset_file(&self.path, Symlinks::Follow).map_err(|e| self.io(e))?;
        ranges
            .iter()
            .map(|range| {
                let len = usize::try_from(range.end.saturating_sub(range.start))
                    .map_err(|_| self.io(std::io::Error::other("a range beyond memory")))?;
                let mut bytes = vec![0u8; len];
                file.read_exact_at(&mut bytes, range.start)
                    .map_err(|e| self.io(e))?;
                Ok(bytes)
            })
            .collect()
    }
}

/// Checks `bytes` as a load checks a file, looking as far into its LAZ chunks as `chunks`
/// says, and reads its header (every VLR and EVLR, each extent checked before).
pub(crate) fn check_ranged<B: RangedBytes>(
    bytes: &B,
    chunks: ChunkChecks,
) -> Result<(DatasetFile, las::Header), B::Error> {
    let name = bytes.name();
    bytes.read_stream(|stream, size| check_stream(name, stream, size, chunks))
}

/// Checks the `size` bytes of `stream`, named `name`, as a load checks a file, looking as far
/// into its LAZ chunks as `chunks` says, then reads its header from the start: the `las`
/// crate sees only bytes the pre-parse passed.
pub(super) fn check_stream(
    name: &Path,
    stream: &mut dyn ReadSeek,
    size: u64,
    chunks: ChunkChecks,
) -> Result<(DatasetFile, las::Header), IngestError> {
    let checked = check_file_with(name, stream, size, chunks)?;
    stream
        .seek(SeekFrom::Start(0))
        .map_err(|error| IngestError::Io {
            path: name.to_owned(),
            error,
        })?;
    let header = contain_panics(name, || {
        las::Header::new(&mut *stream).map_err(|error| IngestError::Malformed {
            path: name.to_owned(),
            error,
        })
    })?;
    Ok((DatasetFile::of_header(name, size, checked, &header), header))
}
