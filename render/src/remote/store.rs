//! Building object_store clients for a URL: one per bucket or origin, with the settings'
//! timeouts and retries, and credentials only from the environment.

use std::sync::{Arc, Once};

use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey};
use object_store::http::HttpBuilder;
use object_store::ObjectStore;

use super::error::RemoteError;
use super::settings::RemoteSettings;
use super::url::{ObjectUrl, UrlKind};

/// Makes ring rustls' process-wide provider once; reqwest asks for it, and ring is the provider
/// tonic's TLS already uses, so both agree whichever comes first.
fn install_tls_provider() {
    static INSTALL: Once = Once::new();
    INSTALL.call_once(|| {
        // An error means another part of the process installed one first; that one serves.
        let _ = rustls::crypto::ring::default_provider().install_default();
    });
}

/// A client for the bucket or origin of `url`.
pub(crate) fn build_store(
    url: &ObjectUrl,
    settings: &RemoteSettings,
) -> Result<Arc<dyn ObjectStore>, RemoteError> {
    install_tls_provider();
    let client_error = |error: object_store::Error| RemoteError::Client {
        url: url.to_string(),
        message: error.to_string(),
    };
    match url.kind() {
        UrlKind::S3 { bucket } => {
            // `from_env` reads AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_ENDPOINT,
            // AWS_ALLOW_HTTP and the rest; the builder never shows them.
            let mut builder = AmazonS3Builder::from_env()
                .with_bucket_name(bucket)
                .with_retry(settings.retry_config());
            for (key, value) in settings.client_config() {
                builder = builder.with_config(AmazonS3ConfigKey::Client(key), value);
            }
            Ok(Arc::new(builder.build().map_err(client_error)?))
        }
        UrlKind::Http => {
            let mut builder = HttpBuilder::new()
                .with_url(url.store_key())
                .with_retry(settings.retry_config())
                .with_config(
                    object_store::ClientConfigKey::AllowHttp,
                    if url.as_str().starts_with("http://") {
                        "true"
                    } else {
                        "false"
                    },
                );
            for (key, value) in settings.client_config() {
                builder = builder.with_config(key, value);
            }
            Ok(Arc::new(builder.build().map_err(client_error)?))
        }
        UrlKind::File { .. } => Err(RemoteError::LocalUrl {
            url: url.to_string(),
        }),
    }
}
