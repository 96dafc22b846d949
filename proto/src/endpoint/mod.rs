//! How pointfarm's processes reach each other: a daemon's URL, and for `https://` the
//! certificate authorities to trust (an `https://` server is only ever reached over TLS, and
//! a CA given for a plaintext URL is an error, not a silent downgrade); and the one set of
//! transport settings every server and client endpoint is made with: HTTP/2 windows,
//! keepalive, `TCP_NODELAY` on every socket, and the bounds on the connections a server
//! accepts ([`connections`]).

pub mod certificate;
pub mod connections;

use std::fmt;
use std::path::{Path, PathBuf};
use std::time::Duration;

use tonic::transport::{
    Certificate, Channel, ClientTlsConfig, Endpoint, Identity, Server, ServerTlsConfig,
};

/// HTTP/2 flow control: the bytes a peer may send on a stream, and on a whole connection,
/// before the receiver reads them. h2's defaults (64 KiB windows of 16 KiB frames) held a
/// worker's node fetches from the daemon to a fraction of the loopback's speed
/// (docs/perf/grpc-windows.md); a few MiB keep a fetch of node records moving while what may
/// wait unread stays small.
pub const HTTP2_STREAM_WINDOW_BYTES: u32 = 4 << 20;
pub const HTTP2_CONNECTION_WINDOW_BYTES: u32 = 16 << 20;
/// The largest HTTP/2 frame a peer may send: fewer frames for the same bytes.
pub const HTTP2_MAX_FRAME_BYTES: u32 = 1 << 20;

/// How often an HTTP/2 peer is pinged, and how long its answer may take before the
/// connection is dropped: a worker or client that vanished mid-call frees its connection and
/// its lease within a minute, not at TCP's retransmission timeout.
pub const HTTP2_KEEPALIVE_INTERVAL: Duration = Duration::from_secs(30);
pub const HTTP2_KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(20);

/// How long a client waits for a TCP (and TLS) connection to a daemon.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);

/// A tonic server made as every pointfarm server is: the HTTP/2 windows and frame size
/// clients get, for what they send (a dataset's files, the frames workers hand in),
/// keepalive pings, and the requests counted on their connections for the bounds of
/// [`connections`]. Serve it with `serve_with_incoming*` on a [`connections::Listener`].
pub fn server_builder(
) -> Server<tower_layer::Stack<connections::ConnectionLayer, tower_layer::Identity>> {
    Server::builder()
        .initial_stream_window_size(HTTP2_STREAM_WINDOW_BYTES)
        .initial_connection_window_size(HTTP2_CONNECTION_WINDOW_BYTES)
        .max_frame_size(HTTP2_MAX_FRAME_BYTES)
        .http2_keepalive_interval(Some(HTTP2_KEEPALIVE_INTERVAL))
        .http2_keepalive_timeout(Some(HTTP2_KEEPALIVE_TIMEOUT))
        .layer(connections::ConnectionLayer)
}

/// A server's TLS settings: its identity, and a handshake bounded as a connection's first
/// call is.
pub fn server_tls(cert_pem: &[u8], key_pem: &[u8]) -> ServerTlsConfig {
    ServerTlsConfig::new()
        .identity(Identity::from_pem(cert_pem, key_pem))
        .timeout(connections::ConnectionLimits::default().first_request_timeout)
}

/// A daemon's address with its TLS settings.
#[derive(Debug, Clone)]
pub struct ServerEndpoint {
    url: String,
    /// The CA certificates (PEM) trusted instead of the system's; `None` trusts the system's.
    ca_pem: Option<Vec<u8>>,
}

/// Why a server address cannot be used.
#[derive(Debug)]
pub enum EndpointError {
    /// Not a URL tonic can connect to.
    Address { server: String, reason: String },
    /// `--tls-ca` with an `http://` URL.
    CaForPlaintext { server: String },
    /// The CA file cannot be read, or holds no certificate.
    Ca { path: PathBuf, reason: String },
    /// No connection could be made.
    Connect { server: String, reason: String },
    /// The server presents a certificate marked as a certificate authority, which TLS
    /// refuses as a server's own.
    CaAsServerCertificate { server: String },
    /// The server's certificate is signed by no CA this client trusts.
    UntrustedCertificate {
        server: String,
        reason: String,
        ca_given: bool,
    },
}

impl fmt::Display for EndpointError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            EndpointError::Address { server, reason } => {
                write!(f, "'{server}' is not a server address: {reason}")
            }
            EndpointError::CaForPlaintext { server } => write!(
                f,
                "--tls-ca is for https:// servers, but '{server}' is plaintext http://"
            ),
            EndpointError::Ca { path, reason } => {
                write!(f, "the CA certificate {}: {reason}", path.display())
            }
            EndpointError::Connect { server, reason } => {
                write!(f, "cannot connect to {server}: {reason}")
            }
            EndpointError::CaAsServerCertificate { server } => write!(
                f,
                "cannot connect to {server}: its certificate is a CA certificate \
                 (basicConstraints CA:TRUE), which TLS refuses as a server's own; on the \
                 server, {}",
                certificate::SERVER_CERTIFICATE_HOWTO
            ),
            EndpointError::UntrustedCertificate {
                server,
                reason,
                ca_given,
            } => {
                write!(f, "cannot connect to {server}: {reason}: ")?;
                match ca_given {
                    true => write!(
                        f,
                        "its certificate is not signed by a CA of --tls-ca (nor is it that \
                         file's own, for a self-signed server)"
                    ),
                    false => write!(
                        f,
                        "its certificate is signed by no CA this system trusts; give the CA's \
                         certificate (a self-signed server's own) with --tls-ca FILE"
                    ),
                }
            }
        }
    }
}

impl std::error::Error for EndpointError {}

impl ServerEndpoint {
    /// `server` is `host:port` (plaintext, or TLS when a CA is given), `http://host:port` or
    /// `https://host:port`; `tls_ca` a PEM file of CA certificates to trust for TLS instead of
    /// the system's.
    pub fn new(server: &str, tls_ca: Option<&Path>) -> Result<Self, EndpointError> {
        let url = url_of(server, tls_ca.is_some())?;
        let ca_pem = tls_ca.map(read_ca).transpose()?;
        let endpoint = Self { url, ca_pem };
        // Checked here, so that a bad address or certificate is reported before any work.
        endpoint.endpoint()?;
        Ok(endpoint)
    }

    /// The URL, with its scheme.
    pub fn url(&self) -> &str {
        &self.url
    }

    pub fn is_tls(&self) -> bool {
        self.url.starts_with("https://")
    }

    /// The tonic endpoint, with TLS for `https://`.
    pub fn endpoint(&self) -> Result<Endpoint, EndpointError> {
        let invalid = |reason: String| EndpointError::Address {
            server: self.url.clone(),
            reason,
        };
        let endpoint = Endpoint::from_shared(self.url.clone())
            .map_err(|e| invalid(e.to_string()))?
            .connect_timeout(CONNECT_TIMEOUT)
            .tcp_nodelay(true)
            .tcp_keepalive(Some(connections::TCP_KEEPALIVE_IDLE))
            .http2_keep_alive_interval(HTTP2_KEEPALIVE_INTERVAL)
            .keep_alive_timeout(HTTP2_KEEPALIVE_TIMEOUT)
            .initial_stream_window_size(HTTP2_STREAM_WINDOW_BYTES)
            .initial_connection_window_size(HTTP2_CONNECTION_WINDOW_BYTES)
            .max_frame_size(HTTP2_MAX_FRAME_BYTES);
        if !self.is_tls() {
            return Ok(endpoint);
        }
        let tls = match &self.ca_pem {
            Some(pem) => ClientTlsConfig::new().ca_certificate(Certificate::from_pem(pem)),
            None => ClientTlsConfig::new().with_native_roots(),
        };
        endpoint.tls_config(tls).map_err(|e| invalid(e.to_string()))
    }

    /// A connection to the server, or why there is none in one sentence: each cause said
    /// once, and a server certificate that is a CA certificate named with its fix.
    pub async fn connect(&self) -> Result<Channel, EndpointError> {
        self.endpoint()?
            .connect()
            .await
            .map_err(|e| self.connect_error(&e))
    }

    /// What keeps a call from reaching the server, as [`ServerEndpoint::connect`] tells it.
    pub fn connect_error(&self, error: &(dyn std::error::Error + 'static)) -> EndpointError {
        let server = self.url.clone();
        if certificate::is_ca_used_as_server_certificate(error) {
            return EndpointError::CaAsServerCertificate { server };
        }
        if certificate::is_untrusted_server_certificate(error) {
            return EndpointError::UntrustedCertificate {
                server,
                reason: causes(error),
                ca_given: self.ca_pem.is_some(),
            };
        }
        EndpointError::Connect {
            server,
            reason: causes(error),
        }
    }
}

/// `error` and its causes joined with ": ", each said once: an error that shows its cause in
/// its own message is not followed by that cause again.
pub fn causes(error: &(dyn std::error::Error + 'static)) -> String {
    let mut said = error.to_string();
    let mut next = error.source();
    while let Some(cause) = next {
        let text = cause.to_string();
        if !text.is_empty() && !said.contains(&text) {
            said.push_str(": ");
            said.push_str(&text);
        }
        next = cause.source();
    }
    said
}

/// The URL of `server`: a bare `host:port` is plaintext, or TLS when a CA is given.
fn url_of(server: &str, has_ca: bool) -> Result<String, EndpointError> {
    match (server.split_once("://"), has_ca) {
        (None, false) => Ok(format!("http://{server}")),
        (None, true) => Ok(format!("https://{server}")),
        (Some(("http", _)), true) => Err(EndpointError::CaForPlaintext {
            server: server.into(),
        }),
        (Some(("http" | "https", _)), _) => Ok(server.to_string()),
        (Some((scheme, _)), _) => Err(EndpointError::Address {
            server: server.into(),
            reason: format!("unknown scheme '{scheme}' (http or https)"),
        }),
    }
}

fn read_ca(path: &Path) -> Result<Vec<u8>, EndpointError> {
    let error = |reason: String| EndpointError::Ca {
        path: path.to_owned(),
        reason,
    };
    let pem = std::fs::read(path).map_err(|e| error(e.to_string()))?;
    if !pem
        .windows(b"-----BEGIN CERTIFICATE-----".len())
        .any(|w| w == b"-----BEGIN CERTIFICATE-----")
    {
        return Err(error("holds no PEM certificate".into()));
    }
    Ok(pem)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_get_their_scheme_and_tls() {
        let plain = ServerEndpoint::new("127.0.0.1:50051", None).expect("plain");
        assert_eq!(plain.url(), "http://127.0.0.1:50051");
        assert!(!plain.is_tls());
        let https = ServerEndpoint::new("https://farm.example:443", None).expect("https");
        assert!(https.is_tls());
    }

    #[test]
    fn a_ca_makes_tls_and_never_goes_with_plaintext() {
        let dir = std::env::temp_dir().join(format!("pointfarm-ca-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let ca = dir.join("ca.pem");
        std::fs::write(
            &ca,
            "-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n",
        )
        .expect("write");
        assert_eq!(
            url_of("farm:50051", true).expect("bare"),
            "https://farm:50051"
        );
        let refused = ServerEndpoint::new("http://farm:50051", Some(&ca)).expect_err("http");
        assert!(matches!(refused, EndpointError::CaForPlaintext { .. }));
        let not_pem = dir.join("not.pem");
        std::fs::write(&not_pem, "hello").expect("write");
        let refused = ServerEndpoint::new("https://farm:1", Some(&not_pem)).expect_err("pem");
        assert!(
            refused.to_string().contains("no PEM certificate"),
            "{refused}"
        );
        let missing = ServerEndpoint::new("https://farm:1", Some(&dir.join("missing.pem")));
        assert!(matches!(missing, Err(EndpointError::Ca { .. })));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn unknown_schemes_are_refused() {
        let refused = ServerEndpoint::new("ftp://farm:1", None).expect_err("ftp");
        assert!(
            refused.to_string().contains("unknown scheme 'ftp'"),
            "{refused}"
        );
    }
}
