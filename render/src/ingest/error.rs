//! Why a file could not be loaded: [`IngestError`], whose every variant names the file.

use std::io;
use std::path::PathBuf;

/// Why a file could not be loaded. Every variant names the file, and every message is complete
/// on its own (the underlying cause is part of it), so it reads well in logs and the CLI.
#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    /// Opening, reading or seeking failed (missing file, permissions, device errors).
    #[error("{}: {error}", path.display())]
    Io { path: PathBuf, error: io::Error },

    /// The file does not start with the `LASF` signature.
    #[error("{}: not a LAS/LAZ file (starts with {found:?}, expected \"LASF\")", path.display())]
    NotLas { path: PathBuf, found: String },

    /// The file ends before its header (and VLRs) do.
    #[error("{}: truncated: the file ends inside the LAS header ({file_len} bytes)", path.display())]
    TruncatedHeader { path: PathBuf, file_len: u64 },

    /// The point data holds fewer points than the header declares.
    #[error(
        "{}: truncated: header says {declared} points but data ends after {available}",
        path.display()
    )]
    Truncated {
        path: PathBuf,
        declared: u64,
        available: u64,
    },

    /// The declared count times the record length overflows 64 bits: no file holds that many.
    #[error("{}: corrupt header: it declares {declared} points", path.display())]
    ImpossiblePointCount { path: PathBuf, declared: u64 },

    /// The LAZ chunk table accounts for fewer points than the header declares. With fixed-size
    /// chunks (the usual case) the last chunk's count is not recorded, so this is an upper bound.
    #[error(
        "{}: truncated: header says {declared} points but the LAZ chunks hold at most {chunk_capacity}",
        path.display()
    )]
    TruncatedLaz {
        path: PathBuf,
        declared: u64,
        chunk_capacity: u64,
    },

    /// The LAZ chunk table, written after the points, is missing or unreadable: usually a file
    /// that was cut short or whose writer never finished.
    #[error("{}: truncated or unfinished LAZ: cannot read the chunk table: {error}", path.display())]
    LazChunkTable {
        path: PathBuf,
        error: laz::LasZipError,
    },

    #[error("{}: unsupported LAS version {major}.{minor} (1.0 to 1.4 are supported)", path.display())]
    UnsupportedVersion { path: PathBuf, major: u8, minor: u8 },

    #[error("{}: unsupported point format {format} (0 to 10 are supported)", path.display())]
    UnsupportedPointFormat { path: PathBuf, format: u8 },

    #[error("a dataset needs at least one LAS/LAZ file")]
    NoFiles,

    #[error("{}: the folder holds no .las or .laz file", path.display())]
    NoFilesInFolder { path: PathBuf },

    /// A symbolic link that leads outside the folders a dataset's files may come from (a
    /// server's data roots); where it leads is not said.
    #[error("{}: a symbolic link that leads outside the data roots", path.display())]
    OutsideRoots { path: PathBuf },

    /// A `.las`/`.laz` name that is a FIFO, a socket, a device: never opened.
    #[error("{}: not a regular file ({kind})", path.display())]
    NotRegularFile { path: PathBuf, kind: &'static str },

    /// A point beyond the bounds its file's header declares, found by a level-of-detail
    /// build, which builds within the headers' bounds.
    #[error(
        "{}: its point at {} lies outside the bounds its header declares ({} .. {}): levels \
         of detail are built within the headers' bounds, so the header must be corrected \
         (for example with LAStools' `lasinfo -repair_bb`); below 20M points the dataset \
         also renders without --lod-error",
        path.display(), xyz(position), xyz(min), xyz(max)
    )]
    PointOutsideHeaderBounds {
        path: PathBuf,
        position: [f64; 3],
        min: [f64; 3],
        max: [f64; 3],
    },

    /// A dataset of one file, which declares no point.
    #[error("{}: the file contains no points", path.display())]
    NoPoints { path: PathBuf },

    /// A dataset of several files, none of which declares a point.
    #[error("none of the dataset's {files} files contains a point")]
    NoPointsInFiles { files: usize },

    /// A size, count or offset read from the file points outside it or contradicts another
    /// field; `what` names the field and says why.
    #[error("{}: corrupt file: {what}", path.display())]
    Corrupt { path: PathBuf, what: String },

    /// An object by URL could not be opened or read; the error names its URL.
    #[error(transparent)]
    Remote(#[from] crate::remote::RemoteError),

    /// A scale factor that is not a finite, normal, non-zero number, or an offset that is not
    /// finite: points cannot be placed (`x scale factor is NaN`).
    #[error("{}: corrupt header: {field} is {problem}", path.display())]
    BadTransform {
        path: PathBuf,
        field: &'static str,
        problem: &'static str,
    },

    /// The scale factors and offsets put points where no survey is: beyond
    /// [`MAX_COORDINATE`](super::MAX_COORDINATE) or past what f64 holds.
    #[error(
        "{}: corrupt header: scale factors and offsets put points at {extreme:e}, beyond ±1e12",
        path.display()
    )]
    ImplausibleCoordinates { path: PathBuf, extreme: f64 },

    /// The `las`/`laz` decoder panicked on data that passed every check made beforehand; the
    /// panic was contained and its message is kept.
    #[error("{}: malformed LAS/LAZ data: the decoder failed: {message}", path.display())]
    DecoderPanicked { path: PathBuf, message: String },

    /// Anything else the `las` crate rejects: malformed VLRs, corrupt LAZ chunks, ...
    #[error("{}: malformed LAS/LAZ data: {error}", path.display())]
    Malformed { path: PathBuf, error: las::Error },
}

/// A position as a message says it: millimetres, the file's usual precision.
fn xyz(p: &[f64; 3]) -> String {
    format!("{:.3}, {:.3}, {:.3}", p[0], p[1], p[2])
}
