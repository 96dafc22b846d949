//! `CopcExportError`: what can stop an export, each naming what it was about.

use std::path::PathBuf;

use super::super::error::LodError;
use super::super::key::NodeKey;

#[derive(Debug, thiserror::Error)]
pub enum CopcExportError {
    /// Reading or checking the store's nodes failed.
    #[error("reading the store: {0}")]
    Store(#[from] LodError),
    /// The output could not be written (full disk, missing folder, permissions).
    #[error("writing {path}: {source}")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A dataset file's header could not be read for its scale and offset.
    #[error("reading the header of {path}: {reason}")]
    SourceHeader { path: PathBuf, reason: String },
    /// The coordinates do not fit LAS's 32-bit integers at the chosen scale.
    #[error("coordinates {min:?}..{max:?} do not fit 32-bit LAS integers at a scale of {scale:?}")]
    ScaleTooFine {
        min: [f64; 3],
        max: [f64; 3],
        scale: [f64; 3],
    },
    /// A node holds more than one LAZ chunk may describe.
    #[error("node {key} is too large for one COPC chunk ({what})")]
    NodeTooLarge { key: NodeKey, what: String },
    /// The LAZ compressor refused the data.
    #[error("compressing node {key}: {reason}")]
    Compress { key: NodeKey, reason: String },
    /// The files' extra bytes are more than one LAS record or VLR may hold beside the export's.
    #[error("the points' attributes take {record_bytes} bytes a record and {descriptor_bytes} bytes of descriptors, more than LAS allows (65,535)")]
    TooManyAttributes {
        record_bytes: usize,
        descriptor_bytes: usize,
    },
    /// The store holds no points: a COPC file needs at least its root.
    #[error("the store holds no points")]
    Empty,
}

impl CopcExportError {
    pub(crate) fn write(path: &std::path::Path, source: std::io::Error) -> Self {
        Self::Write {
            path: path.to_owned(),
            source,
        }
    }
}
