//! What a server's certificate is, read with a real X.509 parse, and the one sentence that
//! tells a client why a TLS handshake refused it: TLS verifies a server's certificate as an
//! end entity, and a certificate marked as a certificate authority (basicConstraints
//! CA:TRUE, as a bare `openssl req -x509` makes one) is refused as such, by design.

use std::error::Error;

/// How to make a certificate a server can present: one of its own, marked as no CA and
/// naming the hosts clients reach it by.
pub const SERVER_CERTIFICATE_HOWTO: &str = "make a server certificate with `openssl req -x509 \
     -newkey rsa:2048 -nodes -keyout key.pem -out cert.pem -days 365 -subj /CN=localhost \
     -addext basicConstraints=critical,CA:FALSE \
     -addext subjectAltName=DNS:localhost,IP:127.0.0.1` (clients trust it with --tls-ca \
     cert.pem), or make a CA and sign a server certificate with it (clients trust the CA)";

/// Whether the first certificate of `cert_pem` (a server's own, the rest of a chain follows
/// it) is marked as a certificate authority; an error when it holds no certificate that
/// parses.
pub fn is_ca_certificate(cert_pem: &[u8]) -> Result<bool, String> {
    let pem = x509_parser::pem::Pem::iter_from_buffer(cert_pem)
        .map_while(Result::ok)
        .find(|pem| pem.label == "CERTIFICATE")
        .ok_or("holds no PEM certificate")?;
    let certificate = pem
        .parse_x509()
        .map_err(|e| format!("is no X.509 certificate ({e})"))?;
    let constraints = certificate
        .basic_constraints()
        .map_err(|e| format!("has a malformed basicConstraints extension ({e})"))?;
    Ok(constraints.is_some_and(|c| c.value.ca))
}

/// Why a server's certificate and key cannot make its TLS identity, in words: a key that is
/// not the certificate's named as such, anything else as its causes say it.
pub fn identity_error(error: &(dyn Error + 'static)) -> String {
    let mut next = Some(error);
    while let Some(error) = next {
        if let Some(rustls::Error::InconsistentKeys(_)) = error.downcast_ref::<rustls::Error>() {
            return "the key is not the certificate's: give the private key the certificate \
                    was made with"
                .into();
        }
        next = error.source();
    }
    super::causes(error)
}

/// Whether `error`, or an error it was caused by, is a TLS handshake's refusal of a server
/// certificate marked as a certificate authority.
pub fn is_ca_used_as_server_certificate(error: &(dyn Error + 'static)) -> bool {
    any_cause(error, refuses_ca_certificate)
}

/// Whether `error`, or an error it was caused by, is a TLS handshake's refusal of a server
/// certificate that no trusted CA signed: a self-signed or private one without `--tls-ca`,
/// or one that CA file does not vouch for.
pub fn is_untrusted_server_certificate(error: &(dyn Error + 'static)) -> bool {
    any_cause(error, |error| {
        matches!(
            error.downcast_ref::<rustls::Error>(),
            Some(rustls::Error::InvalidCertificate(
                rustls::CertificateError::UnknownIssuer | rustls::CertificateError::BadSignature
            ))
        )
    })
}

/// Whether `test` holds for `error` or an error it was caused by.
fn any_cause(error: &(dyn Error + 'static), test: impl Fn(&(dyn Error + 'static)) -> bool) -> bool {
    let mut next = Some(error);
    while let Some(error) = next {
        if test(error) {
            return true;
        }
        // An I/O error shows its inner error but gives that error's cause as its source.
        if let Some(inner) = error
            .downcast_ref::<std::io::Error>()
            .and_then(|io| io.get_ref())
        {
            if test(inner) {
                return true;
            }
        }
        next = error.source();
    }
    false
}

fn refuses_ca_certificate(error: &(dyn Error + 'static)) -> bool {
    match error.downcast_ref::<rustls::Error>() {
        Some(rustls::Error::InvalidCertificate(rustls::CertificateError::Other(other))) => {
            matches!(
                other.0.downcast_ref::<webpki::Error>(),
                Some(webpki::Error::CaUsedAsEndEntity)
            )
        }
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn a_ca_certificate_is_told_from_a_server_certificate() {
        use rcgen::{BasicConstraints, CertificateParams, IsCa, KeyPair};
        let key = KeyPair::generate().expect("key");
        let mut params = CertificateParams::new(vec!["localhost".into()]).expect("params");
        let leaf = params.self_signed(&key).expect("certificate").pem();
        assert!(!is_ca_certificate(leaf.as_bytes()).expect("parses"));
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        let ca = params.self_signed(&key).expect("certificate").pem();
        assert!(is_ca_certificate(ca.as_bytes()).expect("parses"));
        // The server's own certificate comes first; a CA after it is its chain.
        let chain = format!("{leaf}{ca}");
        assert!(!is_ca_certificate(chain.as_bytes()).expect("parses"));
        // A key before the certificate in the same file is passed over.
        let together = format!("{}{ca}", key.serialize_pem());
        assert!(is_ca_certificate(together.as_bytes()).expect("parses"));
    }

    #[test]
    fn bad_pem_is_an_error_not_a_panic() {
        assert!(is_ca_certificate(b"hello").is_err());
        let garbled = b"-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n";
        assert!(is_ca_certificate(garbled).is_err());
    }

    #[test]
    fn the_refusal_is_found_behind_io_errors() {
        let refusal = rustls::Error::InvalidCertificate(rustls::CertificateError::Other(
            rustls::OtherError(Arc::new(webpki::Error::CaUsedAsEndEntity)),
        ));
        let io = std::io::Error::new(std::io::ErrorKind::InvalidData, refusal);
        assert!(is_ca_used_as_server_certificate(&io));
        let unknown = rustls::Error::InvalidCertificate(rustls::CertificateError::UnknownIssuer);
        let io = std::io::Error::new(std::io::ErrorKind::InvalidData, unknown);
        assert!(!is_ca_used_as_server_certificate(&io));
        assert!(is_untrusted_server_certificate(&io));
        let expired = rustls::Error::InvalidCertificate(rustls::CertificateError::Expired);
        assert!(!is_untrusted_server_certificate(&expired));
    }
}
