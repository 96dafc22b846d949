//! The daemon's errors, by what the caller should do about them (the gRPC layer maps each
//! kind to one status code), and the state database's errors they wrap.

use pointfarm_render::remote::RemoteError;
use thiserror::Error;

/// The state database failed, or holds what it cannot read.
#[derive(Debug, Error)]
pub enum StateError {
    #[error("state database: {0}")]
    Db(#[from] sled::Error),
    #[error("state database holds a record it cannot read: {0}")]
    Corrupt(#[from] serde_json::Error),
    /// Another process (or a daemon not yet gone) holds the database.
    #[error("the state database {} is in use by another pointfarm daemon", .0.display())]
    Locked(std::path::PathBuf),
    /// Found when the database is opened: it lost or garbled records.
    #[error("{0}")]
    Damaged(String),
    #[error("state database: {0}")]
    Io(#[from] std::io::Error),
    /// The disk refused a write (full, over quota, failing); worth retrying once the daemon
    /// reports it takes writes again.
    #[error("{0}")]
    Unwritable(String),
}

#[derive(Debug, Error)]
pub enum DaemonError {
    /// A request field is invalid; `field` names it (e.g. `camera_path.turntable.frames`).
    #[error("{field}: {message}")]
    InvalidArgument { field: String, message: String },
    #[error("{0} not found")]
    NotFound(String),
    /// The request is valid but the state of things does not allow it.
    #[error("{0}")]
    FailedPrecondition(String),
    /// The caller's credentials do not allow this (e.g. another worker's lease).
    #[error("{0}")]
    PermissionDenied(String),
    /// A size limit was exceeded.
    #[error("{0}")]
    ResourceExhausted(String),
    /// Something the daemon depends on (an object store, an HTTP server) cannot be reached
    /// or gave no answer in time; the same request may succeed later.
    #[error("{0}")]
    Unavailable(String),
    #[error("internal error: {0}")]
    Internal(String),
}

impl DaemonError {
    pub fn invalid(field: impl Into<String>, message: impl Into<String>) -> Self {
        DaemonError::InvalidArgument {
            field: field.into(),
            message: message.into(),
        }
    }
}

impl From<StateError> for DaemonError {
    fn from(e: StateError) -> Self {
        match e {
            StateError::Damaged(message) => DaemonError::FailedPrecondition(message),
            // Not the request's fault, and it passes: the client should back off and retry.
            StateError::Unwritable(message) => DaemonError::ResourceExhausted(message),
            other => DaemonError::Internal(other.to_string()),
        }
    }
}

impl From<std::io::Error> for DaemonError {
    fn from(e: std::io::Error) -> Self {
        use std::io::ErrorKind;
        match e.kind() {
            // A full disk or quota (an upload's file, a frame's PNG) passes: the caller should
            // back off and retry.
            ErrorKind::StorageFull | ErrorKind::QuotaExceeded => {
                DaemonError::ResourceExhausted(disk_error_message(&e))
            }
            _ => DaemonError::Internal(e.to_string()),
        }
    }
}

/// How a refused write reads to a user: a full disk or quota by name, anything else as a
/// failed write.
pub fn disk_error_message(error: &std::io::Error) -> String {
    use std::io::ErrorKind;
    match error.kind() {
        ErrorKind::StorageFull => format!("the daemon's disk is full ({error})"),
        ErrorKind::QuotaExceeded => format!("the daemon's disk quota is used up ({error})"),
        _ => format!("the daemon's disk refused a write ({error})"),
    }
}

impl From<RemoteError> for DaemonError {
    /// Sorts a failure to read a dataset by URL by what the client can do about it; every
    /// message names the URL, and URLs never carry credentials.
    fn from(e: RemoteError) -> Self {
        let message = e.to_string();
        match e {
            RemoteError::InvalidUrl { .. }
            | RemoteError::UnsupportedScheme { .. }
            | RemoteError::LocalUrl { .. } => DaemonError::invalid("path", message),
            RemoteError::NotAllowed { .. } | RemoteError::Denied { .. } => {
                DaemonError::PermissionDenied(message)
            }
            RemoteError::NotFound { url } => DaemonError::NotFound(format!("object {url}")),
            RemoteError::ReadTooLarge { .. } | RemoteError::TooManyObjects { .. } => {
                DaemonError::ResourceExhausted(message)
            }
            // Asking again reads the object as it is then, or finds its server back.
            RemoteError::ObjectChanged { .. }
            | RemoteError::TimedOut { .. }
            | RemoteError::ShortRead { .. }
            | RemoteError::Transport { .. } => DaemonError::Unavailable(message),
            // The server's configuration answers the same until its operator changes it.
            RemoteError::RangeOutOfBounds { .. }
            | RemoteError::Redirected { .. }
            | RemoteError::RangeIgnored { .. }
            | RemoteError::Listing { .. }
            | RemoteError::Client { .. } => DaemonError::FailedPrecondition(message),
            RemoteError::Runtime { .. } => DaemonError::Internal(message),
        }
    }
}
