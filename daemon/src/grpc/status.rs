//! The one map from the daemon's errors to gRPC status codes.

use tonic::Status;

use crate::error::DaemonError;

impl From<DaemonError> for Status {
    fn from(e: DaemonError) -> Self {
        match e {
            DaemonError::InvalidArgument { .. } => Status::invalid_argument(e.to_string()),
            DaemonError::NotFound(_) => Status::not_found(e.to_string()),
            DaemonError::FailedPrecondition(_) => Status::failed_precondition(e.to_string()),
            DaemonError::ResourceExhausted(_) => Status::resource_exhausted(e.to_string()),
            DaemonError::Internal(_) => Status::internal(e.to_string()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_daemon_error_has_its_status_code() {
        use tonic::Code;
        let cases = [
            (DaemonError::invalid("f", "m"), Code::InvalidArgument),
            (DaemonError::NotFound("x".into()), Code::NotFound),
            (
                DaemonError::FailedPrecondition("x".into()),
                Code::FailedPrecondition,
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
