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
            DaemonError::Unavailable(_) => Code::Unavailable,
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
            (DaemonError::Unavailable("x".into()), Code::Unavailable),
            (DaemonError::Internal("x".into()), Code::Internal),
        ];
        for (error, code) in cases {
            assert_eq!(Status::from(error).code(), code);
        }
    }

    #[test]
    fn remote_errors_have_the_status_a_client_can_act_on() {
        use pointfarm_render::remote::RemoteError;
        let url = || "https://data.example/scans/a.copc.laz".to_owned();
        let cases = [
            (
                RemoteError::InvalidUrl {
                    url: url(),
                    reason: "r".into(),
                },
                Code::InvalidArgument,
            ),
            (
                RemoteError::NotAllowed {
                    url: url(),
                    rule: "the operator allows only s3://b".into(),
                },
                Code::PermissionDenied,
            ),
            (RemoteError::NotFound { url: url() }, Code::NotFound),
            (
                RemoteError::Transport {
                    url: url(),
                    message: "connection refused".into(),
                },
                Code::Unavailable,
            ),
            (
                RemoteError::TimedOut {
                    url: url(),
                    after: std::time::Duration::from_secs(1),
                },
                Code::Unavailable,
            ),
        ];
        for (error, code) in cases {
            let status = Status::from(DaemonError::from(error));
            assert_eq!(status.code(), code, "{status:?}");
            assert!(status.message().contains(&url()), "{status:?}");
        }
    }
}
