//! `LodError`: everything that can go wrong while building or reading a level-of-detail store.

use std::path::PathBuf;

use super::key::NodeKey;

#[derive(Debug, thiserror::Error)]
pub enum LodError {
    #[error("level-of-detail options: {0}")]
    InvalidOptions(String),
    #[error("point source: {0}")]
    Source(String),
    #[error("point source: batch has {positions} positions but {field} has {len} values")]
    BatchLengths {
        positions: usize,
        field: &'static str,
        len: usize,
    },
    #[error("point source: point {index} is not finite ({position:?})")]
    NonFinitePoint { index: u64, position: [f64; 3] },
    #[error("point source: point {index} at {position:?} lies outside the declared bounds {min:?}..{max:?}")]
    PointOutsideBounds {
        index: u64,
        position: [f64; 3],
        min: [f64; 3],
        max: [f64; 3],
    },
    #[error("point source: a point at {position:?} is not on the coordinate grid (scale and offset) its files declare")]
    PointOffGrid { position: [f64; 3] },
    #[error("point source: bounds {min:?}..{max:?} are not finite, inverted or beyond the coordinate limit")]
    InvalidBounds { min: [f64; 3], max: [f64; 3] },
    #[error("point source: it declared {declared} points but gave {read} on pass {pass}")]
    CountMismatch {
        declared: u64,
        read: u64,
        pass: &'static str,
    },
    #[error("point source: the second pass differs from the first ({0}); the points must be read in the same order each time")]
    SourceChanged(String),
    #[error("the memory budget of {budget} bytes cannot hold {needed} bytes for {what}")]
    BudgetTooSmall {
        budget: u64,
        needed: u64,
        what: &'static str,
    },
    #[error("{count} points lie within node {key} at the deepest level; they cannot be split to fit the memory budget")]
    TooDense { key: NodeKey, count: u64 },
    #[error("spill file {}: {error}", path.display())]
    Spill {
        path: PathBuf,
        #[source]
        error: std::io::Error,
    },
    #[error("level-of-detail store: {0}")]
    Db(#[from] sled::Error),
    #[error("level-of-detail payload file {}: {error}", path.display())]
    Payload {
        path: PathBuf,
        #[source]
        error: std::io::Error,
    },
    #[error("level-of-detail store holds no hierarchy (never built, or the build did not finish)")]
    MissingHierarchy,
    #[error("level-of-detail hierarchy is damaged: {0}")]
    CorruptHierarchy(String),
    #[error("level-of-detail node {key} is not in the hierarchy")]
    UnknownNode { key: NodeKey },
    #[error("level-of-detail node {key} is damaged: {reason}")]
    CorruptNode { key: NodeKey, reason: String },
    /// The layers below a store's payload file (`layers.rs`) are not those its list records:
    /// the store is built again.
    #[error("level-of-detail payload layers are damaged: {0}")]
    CorruptLayers(String),
    /// A store that cannot take this change in place (`update.rs`): it is built again.
    #[error("level-of-detail store cannot be updated: {0}")]
    CannotUpdate(String),
    /// The node records could not be had from where they are kept (a daemon that did not
    /// answer); worth another attempt, unlike a damaged node.
    #[error("level-of-detail nodes: {0}")]
    Records(String),
    /// A record source's own failure, kept whole (a COPC file's chunk unreadable or not what
    /// its entry says): sources depend on the store's types, not the other way round.
    #[error(transparent)]
    RecordSource(Box<dyn std::error::Error + Send + Sync>),
}

impl LodError {
    /// Whether this says the store's own bytes failed their checks (a node record's checksum
    /// or layout, a payload file cut short, a damaged hierarchy): a store so damaged is a
    /// cache to build again from its dataset's files, unlike a read that failed.
    pub fn is_damage(&self) -> bool {
        matches!(
            self,
            Self::CorruptNode { .. }
                | Self::CorruptHierarchy(_)
                | Self::CorruptLayers(_)
                | Self::MissingHierarchy
        )
    }

    pub(crate) fn spill(path: impl Into<PathBuf>, error: std::io::Error) -> Self {
        Self::Spill {
            path: path.into(),
            error,
        }
    }

    pub(crate) fn payload(path: impl Into<PathBuf>, error: std::io::Error) -> Self {
        Self::Payload {
            path: path.into(),
            error,
        }
    }
}
