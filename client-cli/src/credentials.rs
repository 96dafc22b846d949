//! Credentials on the command line: bearer tokens given as a flag, an environment variable
//! or a file (so they stay out of `ps` and shell history), and the CA a client trusts for an
//! `https://` server.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use pointfarm_proto::endpoint::ServerEndpoint;

/// How a client command authenticates to a server.
#[derive(Args, Clone, Debug, Default)]
pub struct ClientCredentials {
    /// Bearer token for the server (its --token).
    #[arg(long, env = "POINTFARM_TOKEN", hide_env_values = true, global = true)]
    token: Option<String>,
    /// Read the bearer token from this file instead.
    #[arg(long, value_name = "FILE", env = "POINTFARM_TOKEN_FILE", global = true)]
    token_file: Option<PathBuf>,
    /// Trust the CA certificates in this PEM file for the server's TLS, instead of the
    /// system's (a bare HOST:PORT then means https://).
    #[arg(long, value_name = "FILE", env = "POINTFARM_TLS_CA", global = true)]
    tls_ca: Option<PathBuf>,
}

impl ClientCredentials {
    pub fn token(&self) -> Result<Option<String>> {
        secret(self.token.as_deref(), self.token_file.as_deref(), "--token")
    }

    /// Where `server` is, with this trust.
    pub fn endpoint(&self, server: &str) -> Result<ServerEndpoint> {
        Ok(ServerEndpoint::new(server, self.tls_ca.as_deref())?)
    }
}

/// A token given as `flag` (or its environment variable) or in the file given as
/// `{flag}-file`; at most one of them. A file's trailing line break is not part of it.
pub fn secret(value: Option<&str>, file: Option<&Path>, flag: &str) -> Result<Option<String>> {
    let token = match (value, file) {
        (None, None) => return Ok(None),
        (Some(_), Some(_)) => bail!(
            "{flag} and {flag}-file are both given (as flags or in the environment): give the \
             token once"
        ),
        (Some(value), None) => value.to_owned(),
        (None, Some(path)) => std::fs::read_to_string(path)
            .with_context(|| format!("reading the {flag}-file {}", path.display()))?
            .trim_end_matches(['\n', '\r'])
            .to_owned(),
    };
    if token.is_empty() {
        bail!("the {flag} is empty");
    }
    // What travels in an `authorization` header; no character a terminal or log could mangle.
    if !token.bytes().all(|b| b.is_ascii_graphic()) {
        bail!("the {flag} may hold only printable ASCII characters without spaces");
    }
    Ok(Some(token))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_token_comes_from_the_flag_or_the_file_never_both() {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = dir.path().join("token");
        std::fs::write(&file, "s3cret-from-file\n").expect("write");
        assert_eq!(
            secret(None, Some(&file), "--token")
                .expect("file")
                .as_deref(),
            Some("s3cret-from-file")
        );
        assert_eq!(
            secret(Some("s3cret"), None, "--token")
                .expect("flag")
                .as_deref(),
            Some("s3cret")
        );
        assert_eq!(secret(None, None, "--token").expect("none"), None);
        let both = secret(Some("a"), Some(&file), "--token").expect_err("both");
        assert!(both.to_string().contains("give the token once"), "{both}");
        for bad in ["", "two words", "tab\there", "caf\u{e9}"] {
            assert!(secret(Some(bad), None, "--token").is_err(), "{bad:?}");
        }
        let missing = secret(None, Some(&dir.path().join("missing")), "--worker-token")
            .expect_err("missing file");
        assert!(
            format!("{missing:#}").contains("--worker-token-file"),
            "{missing:#}"
        );
    }
}
