//! Who may call what: the two roles of the API and the credentials that give them.
//!
//! - A **client** (`--token`) uses `DatasetService` and `JobService`; a **worker**
//!   (`--worker-token`) uses `WorkerService`. Each token is refused with PERMISSION_DENIED on
//!   the other role's services, so a client cannot fail or hand in frames.
//! - A role without a token is open to every caller, except that a daemon with a client token
//!   but no worker token serves no remote workers at all: a client token is never enough to
//!   render.
//! - The embedded worker is not a caller here: it speaks to a listener of its own on loopback
//!   with a token made for each start (`server.rs`).
//! - Tokens are compared in constant time, through their SHA-256 digests, so neither their
//!   content nor their length leaks through timing.
//! - A daemon reachable beyond loopback must have a client token and TLS, or be started with
//!   `--insecure` ([`Access::check_exposure`]).

use std::net::SocketAddr;
use std::sync::Arc;

use sha2::{Digest, Sha256};
use tonic::{Request, Status};

/// The credentials a daemon accepts.
#[derive(Clone, Default)]
pub struct Access {
    client_token: Option<Secret>,
    worker_token: Option<Secret>,
}

/// What the daemon serves, as far as its exposure is concerned.
#[derive(Debug, Clone, Copy)]
pub struct Exposure {
    pub address: SocketAddr,
    pub tls: bool,
    /// Serve beyond loopback without a token or without TLS, knowingly.
    pub insecure: bool,
}

/// A token, kept only as its digest.
#[derive(Clone)]
struct Secret(Arc<[u8; 32]>);

impl Secret {
    fn new(token: &str) -> Self {
        Self(Arc::new(Sha256::digest(token.as_bytes()).into()))
    }

    /// Whether `given` is this token, in time that depends on neither.
    fn matches(&self, given: &str) -> bool {
        let given: [u8; 32] = Sha256::digest(given.as_bytes()).into();
        let difference = self
            .0
            .iter()
            .zip(given)
            .fold(0u8, |acc, (a, b)| acc | (a ^ b));
        std::hint::black_box(difference) == 0
    }
}

/// The role a service belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    Client,
    Worker,
}

impl Role {
    fn flag(self) -> &'static str {
        match self {
            Role::Client => "--token",
            Role::Worker => "--worker-token",
        }
    }
}

impl Access {
    /// Tokens of each role; `None` leaves a role open (see the module's rules).
    pub fn new(client_token: Option<&str>, worker_token: Option<&str>) -> Self {
        Self {
            client_token: client_token.map(Secret::new),
            worker_token: worker_token.map(Secret::new),
        }
    }

    /// The gate for the services of `role`.
    pub fn gate(&self, role: Role) -> Gate {
        Gate {
            role,
            access: self.clone(),
        }
    }

    /// Refuses to serve beyond loopback without a client token or without TLS, unless
    /// `insecure`: anyone who can reach the port could otherwise read and change every job.
    pub fn check_exposure(&self, exposure: Exposure) -> Result<(), String> {
        if exposure.insecure || exposure.address.ip().is_loopback() {
            return Ok(());
        }
        let mut missing = Vec::new();
        if self.client_token.is_none() {
            missing.push("a client token (--token)");
        }
        if !exposure.tls {
            missing.push("TLS (--tls-cert and --tls-key)");
        }
        if missing.is_empty() {
            return Ok(());
        }
        Err(format!(
            "refusing to listen on {} without {}: anyone who reaches it could read, submit and \
             cancel jobs{}. Listen on 127.0.0.1, add them, or pass --insecure",
            exposure.address,
            missing.join(" and "),
            if exposure.tls {
                ""
            } else {
                " and read tokens and frames on the wire"
            }
        ))
    }

    fn token_of(&self, role: Role) -> Option<&Secret> {
        match role {
            Role::Client => self.client_token.as_ref(),
            Role::Worker => self.worker_token.as_ref(),
        }
    }

    /// Whether a call of `role` with the bearer token `given` may go on.
    fn admit(&self, role: Role, given: Option<&str>) -> Result<(), Status> {
        let other = match role {
            Role::Client => Role::Worker,
            Role::Worker => Role::Client,
        };
        let Some(expected) = self.token_of(role) else {
            if role == Role::Worker && self.client_token.is_some() {
                return Err(Status::permission_denied(
                    "this daemon serves no remote workers: start it with --worker-token",
                ));
            }
            return Ok(());
        };
        match given {
            Some(token) if expected.matches(token) => Ok(()),
            Some(token) if self.token_of(other).is_some_and(|t| t.matches(token)) => {
                Err(Status::permission_denied(format!(
                    "this token ({}) does not give access to the {} API",
                    other.flag(),
                    match role {
                        Role::Client => "client",
                        Role::Worker => "worker",
                    }
                )))
            }
            Some(_) => Err(Status::unauthenticated("invalid bearer token")),
            None => Err(Status::unauthenticated(
                "missing 'authorization: Bearer <token>' header",
            )),
        }
    }
}

/// The server interceptor of one role's services.
#[derive(Clone)]
pub struct Gate {
    role: Role,
    access: Access,
}

/// The bearer token of a call, if it has one.
pub fn bearer_token<T>(request: &Request<T>) -> Option<&str> {
    request
        .metadata()
        .get("authorization")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "))
}

impl tonic::service::Interceptor for Gate {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        self.access.admit(self.role, bearer_token(&request))?;
        pointfarm_proto::endpoint::connections::admit_connection(&request);
        Ok(request)
    }
}

#[cfg(test)]
mod tests {
    use tonic::Code;

    use super::*;

    /// Checks each `(role, token given, expected code)` against `access`; `None` admits.
    fn assert_admits(access: &Access, cases: &[(Role, Option<&str>, Option<Code>)]) {
        for &(role, given, expected) in cases {
            let code = access.admit(role, given).err().map(|status| status.code());
            assert_eq!(code, expected, "{role:?} with {given:?}");
        }
    }

    #[test]
    fn each_token_opens_only_its_role() {
        let access = Access::new(Some("client-secret"), Some("worker-secret"));
        assert_admits(
            &access,
            &[
                (Role::Client, Some("client-secret"), None),
                (Role::Worker, Some("worker-secret"), None),
                (
                    Role::Worker,
                    Some("client-secret"),
                    Some(Code::PermissionDenied),
                ),
                (
                    Role::Client,
                    Some("worker-secret"),
                    Some(Code::PermissionDenied),
                ),
                (
                    Role::Client,
                    Some("client-secret2"),
                    Some(Code::Unauthenticated),
                ),
                (Role::Worker, None, Some(Code::Unauthenticated)),
            ],
        );
    }

    #[test]
    fn a_client_token_alone_serves_no_remote_workers() {
        let client_only = Access::new(Some("client-secret"), None);
        assert_admits(
            &client_only,
            &[
                (
                    Role::Worker,
                    Some("client-secret"),
                    Some(Code::PermissionDenied),
                ),
                (Role::Worker, None, Some(Code::PermissionDenied)),
            ],
        );
        assert_admits(
            &Access::default(),
            &[
                (Role::Worker, None, None),
                (Role::Client, Some("anything"), None),
            ],
        );
        assert_admits(
            &Access::new(None, Some("worker-secret")),
            &[
                (Role::Client, None, None),
                (Role::Worker, None, Some(Code::Unauthenticated)),
            ],
        );
    }

    #[test]
    fn tokens_match_only_themselves() {
        let secret = Secret::new("s3cret");
        assert!(secret.matches("s3cret"));
        for other in ["", "s3cre", "s3cret ", "S3cret", "s3cret\0"] {
            assert!(!secret.matches(other), "{other:?}");
        }
    }

    #[test]
    fn exposure_beyond_loopback_needs_a_token_and_tls_or_insecure() {
        let exposure = |address: &str, tls: bool, insecure: bool| Exposure {
            address: address.parse().expect("address"),
            tls,
            insecure,
        };
        let open = Access::default();
        let tokened = Access::new(Some("t"), None);
        // (access, address, TLS, --insecure, allowed)
        let cases = [
            (&open, "127.0.0.1:1", false, false, true),
            (&open, "[::1]:1", false, false, true),
            (&open, "0.0.0.0:1", false, false, false),
            (&tokened, "10.0.0.1:1", false, false, false),
            (&open, "0.0.0.0:1", true, false, false),
            (&tokened, "0.0.0.0:1", true, false, true),
            (&open, "0.0.0.0:1", false, true, true),
        ];
        for (access, address, tls, insecure, allowed) in cases {
            let result = access.check_exposure(exposure(address, tls, insecure));
            assert_eq!(
                result.is_ok(),
                allowed,
                "{address} tls {tls} insecure {insecure}"
            );
        }
        // The refusal names what is missing.
        let refused = open
            .check_exposure(exposure("0.0.0.0:1", false, false))
            .expect_err("open and plaintext");
        assert!(
            refused.contains("--token") && refused.contains("--tls-cert"),
            "{refused}"
        );
        let refused = tokened
            .check_exposure(exposure("10.0.0.1:1", false, false))
            .expect_err("plaintext");
        assert!(
            !refused.contains("--token)") && refused.contains("TLS"),
            "{refused}"
        );
    }
}
