//! The one map from the daemon's errors to gRPC status codes.

use tonic::{Code, Status};

use crate::error::DaemonError;
use crate::limits::{truncated, MAX_MESSAGE_BYTES};

impl From<DaemonError> for Status {
    fn from(e: DaemonError) -> Self {
        // Whatever a message quotes, it stays small enough for a header.
        let message = truncated(&e.to_string(), MAX_MESSAGE_BYTES);
        let code = match e {
            DaemonError::InvalidArgument { .. } => Code::InvalidArgument,
            DaemonError::NotFound(_) => Code::NotFound,
            DaemonError::FailedPrecondition(_) => Code::FailedPrecondition,
            DaemonError::PermissionDenied(_) => Code::PermissionDenied,
            DaemonError::ResourceExhausted(_) => Code::ResourceExhausted,
            DaemonError::Internal(_) => Code::Internal,
        };
        Status::new(code, message)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_are_bounded() {
        let status = Status::from(DaemonError::NotFound("x".repeat(1 << 20)));
        assert!(status.message().len() <= MAX_MESSAGE_BYTES);
    }

    #[test]
    fn every_daemon_error_has_its_status_code() {
        let cases = [
            (DaemonError::invalid("f", "m"), Code::InvalidArgument),
            (DaemonError::NotFound("x".into()), Code::NotFound),
            (
                DaemonError::FailedPrecondition("x".into()),
                Code::FailedPrecondition,
            ),
            (
                DaemonError::PermissionDenied("x".into()),
                Code::PermissionDenied,
            ),
            (
                DaemonError::ResourceExhausted("x".into()),
                Code::ResourceExhausted,
            ),
            (DaemonError::Internal("x".into()), Code::Internal),
        ];
        for (error, code) in cases {
            assert_eq!(Status::from(error).code(), code);
        }
    }
}
