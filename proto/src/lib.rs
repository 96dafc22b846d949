//! The `pointfarm.v1` gRPC API: messages, clients and service traits generated from
//! `pointfarm/v1/pointfarm.proto` at build time.

/// Generated code for package `pointfarm.v1`.
pub mod v1 {
    // Generated code: its doc comments come from the .proto file.
    #![allow(clippy::all, missing_docs)]
    tonic::include_proto!("pointfarm.v1");

    /// The encoded file descriptor set, for gRPC server reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        include_bytes!(concat!(env!("OUT_DIR"), "/pointfarm_descriptor.bin"));

    impl CameraPath {
        /// The turntable `turntable` through the default lens.
        pub fn turntable(turntable: Turntable) -> Self {
            Self {
                path: Some(camera_path::Path::Turntable(turntable)),
                lens: None,
            }
        }
    }

    impl Turntable {
        /// `frames` frames around the automatic centre, radius and height.
        pub fn of_frames(frames: u32) -> Self {
            Self {
                frames,
                ..Default::default()
            }
        }
    }
}

pub mod endpoint;

use tonic::metadata::{Ascii, MetadataValue};
use tonic::{Request, Status};

/// A client interceptor that sends `authorization: Bearer <token>` with every call, when there
/// is a token (the daemon's `--token`). Shared by the CLI and worker processes.
#[derive(Debug, Clone, Default)]
pub struct BearerToken(Option<MetadataValue<Ascii>>);

/// A token with characters that cannot travel in a gRPC header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct InvalidToken;

impl std::fmt::Display for InvalidToken {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("the token has characters that cannot be sent")
    }
}

impl std::error::Error for InvalidToken {}

impl BearerToken {
    /// No header when `token` is `None`.
    pub fn new(token: Option<&str>) -> Result<Self, InvalidToken> {
        token
            .map(|t| format!("Bearer {t}").parse().map_err(|_| InvalidToken))
            .transpose()
            .map(Self)
    }
}

impl tonic::service::Interceptor for BearerToken {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(value) = &self.0 {
            request
                .metadata_mut()
                .insert("authorization", value.clone());
        }
        Ok(request)
    }
}

/// A gRPC status code as the words users read (`not found`, `permission denied`), not its Rust
/// name. Shared by the CLI and worker processes.
pub fn code_words(code: tonic::Code) -> &'static str {
    match code {
        tonic::Code::Ok => "ok",
        tonic::Code::Cancelled => "cancelled",
        tonic::Code::Unknown => "unknown error",
        tonic::Code::InvalidArgument => "invalid argument",
        tonic::Code::DeadlineExceeded => "deadline exceeded",
        tonic::Code::NotFound => "not found",
        tonic::Code::AlreadyExists => "already exists",
        tonic::Code::PermissionDenied => "permission denied",
        tonic::Code::ResourceExhausted => "resource exhausted",
        tonic::Code::FailedPrecondition => "failed precondition",
        tonic::Code::Aborted => "aborted",
        tonic::Code::OutOfRange => "out of range",
        tonic::Code::Unimplemented => "unimplemented",
        tonic::Code::Internal => "internal error",
        tonic::Code::Unavailable => "unavailable",
        tonic::Code::DataLoss => "data loss",
        tonic::Code::Unauthenticated => "unauthenticated",
    }
}

#[cfg(test)]
mod tests {
    use tonic::service::Interceptor;

    use super::*;

    #[test]
    fn bearer_token_sets_the_authorization_header_only_when_there_is_a_token() {
        let mut with = BearerToken::new(Some("s3cret")).expect("valid token");
        let request = with.call(Request::new(())).expect("passes");
        assert_eq!(
            request
                .metadata()
                .get("authorization")
                .map(|v| v.to_str().ok()),
            Some(Some("Bearer s3cret"))
        );
        let mut without = BearerToken::new(None).expect("no token");
        let request = without.call(Request::new(())).expect("passes");
        assert!(request.metadata().get("authorization").is_none());
        assert_eq!(
            BearerToken::new(Some("line\nbreak")).err(),
            Some(InvalidToken)
        );
    }
}
