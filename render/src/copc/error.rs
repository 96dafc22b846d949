//! `CopcError`: what can be wrong with a COPC file read node by node. Every message names
//! the file: its path, or the URL it was opened by.

use std::path::PathBuf;

use crate::ingest::IngestError;
use crate::lod::{LodError, NodeKey};
use crate::remote::RemoteError;

#[derive(Debug, thiserror::Error)]
pub enum CopcError {
    #[error("{}: {error}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        error: std::io::Error,
    },
    /// The checks every LAS/LAZ file passes before it is decoded (header, VLRs, EVLRs, the
    /// LASzip VLR and chunk table).
    #[error(transparent)]
    Ingest(#[from] IngestError),
    /// A COPC info VLR on a file that cannot be COPC (not LAZ, a point format COPC does not
    /// allow, no LASzip VLR).
    #[error("{}: not a valid COPC file: {reason}", path.display())]
    NotCopc { path: PathBuf, reason: String },
    #[error("{}: COPC info VLR: {reason}", path.display())]
    Info { path: PathBuf, reason: String },
    /// The hierarchy pages disagree with the file or with themselves: an entry beyond the
    /// file, a page visited twice, counts that do not add up.
    #[error("{}: COPC hierarchy is inconsistent: {reason}", path.display())]
    Hierarchy { path: PathBuf, reason: String },
    /// An object read by URL that could not be read: missing, refused, replaced since it was
    /// opened, cut short. The error names the URL.
    #[error(transparent)]
    Remote(#[from] RemoteError),
    /// A node's LAZ chunk that does not decode to what its entry says.
    #[error("{}: COPC node {key}: {reason}", path.display())]
    Node {
        path: PathBuf,
        key: NodeKey,
        reason: String,
    },
}

impl CopcError {
    pub(crate) fn io(path: &std::path::Path, error: std::io::Error) -> Self {
        Self::Io {
            path: path.to_owned(),
            error,
        }
    }

    pub(crate) fn hierarchy(path: &std::path::Path, reason: impl Into<String>) -> Self {
        Self::Hierarchy {
            path: path.to_owned(),
            reason: reason.into(),
        }
    }
}

impl From<CopcError> for LodError {
    fn from(error: CopcError) -> Self {
        LodError::RecordSource(Box::new(error))
    }
}
