//! Building object_store clients for a URL: one per bucket or origin, with the settings'
//! timeouts and retries, and credentials only from the environment.

use std::sync::{Arc, Once};

use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey};
use object_store::azure::{AzureConfigKey, MicrosoftAzureBuilder};
use object_store::gcp::{GoogleCloudStorageBuilder, GoogleConfigKey};
use object_store::http::HttpBuilder;
use object_store::{ClientConfigKey, ObjectStore};

use super::error::RemoteError;
use super::redirect::{RedirectRule, RedirectingConnector};
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

/// A client for the bucket or origin of `url`; an `http(s)://` one follows redirects by
/// `redirects` alone (object storage endpoints are the operator's, from the environment).
pub(crate) fn build_store(
    url: &ObjectUrl,
    settings: &RemoteSettings,
    redirects: &Arc<RedirectRule>,
) -> Result<Arc<dyn ObjectStore>, RemoteError> {
    install_tls_provider();
    let client_error = |error: object_store::Error| RemoteError::Client {
        url: url.to_string(),
        message: error.to_string(),
    };
    let client = settings.client_config();
    let store: Arc<dyn ObjectStore> = match url.kind() {
        // Each builder's `from_env` reads its credentials and endpoint from the environment
        // and never shows them: AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_ENDPOINT, ...;
        // GOOGLE_SERVICE_ACCOUNT (a file whose `gcs_base_url` and `disable_oauth` point it at
        // an emulator), GOOGLE_APPLICATION_CREDENTIALS, ..., else the metadata server;
        // AZURE_STORAGE_ACCOUNT_NAME, AZURE_STORAGE_ACCOUNT_KEY, AZURE_STORAGE_SAS_KEY, ...,
        // else a managed identity, and AZURE_STORAGE_USE_EMULATOR for Azurite.
        UrlKind::S3 { bucket } => Arc::new(
            with_client(
                AmazonS3Builder::from_env().with_bucket_name(bucket),
                client,
                |builder, key, value| builder.with_config(AmazonS3ConfigKey::Client(key), value),
            )
            .with_retry(settings.retry_config())
            .build()
            .map_err(client_error)?,
        ),
        UrlKind::Gcs { bucket } => Arc::new(
            with_client(
                GoogleCloudStorageBuilder::from_env().with_bucket_name(bucket),
                client,
                |builder, key, value| builder.with_config(GoogleConfigKey::Client(key), value),
            )
            .with_retry(settings.retry_config())
            .build()
            .map_err(client_error)?,
        ),
        UrlKind::Azure { container } => Arc::new(
            with_client(
                MicrosoftAzureBuilder::from_env().with_container_name(container),
                client,
                |builder, key, value| builder.with_config(AzureConfigKey::Client(key), value),
            )
            .with_retry(settings.retry_config())
            .build()
            .map_err(client_error)?,
        ),
        UrlKind::Http => {
            let allow_http = if url.as_str().starts_with("http://") {
                "true"
            } else {
                "false"
            };
            let builder = HttpBuilder::new()
                .with_url(url.store_key())
                .with_config(object_store::ClientConfigKey::AllowHttp, allow_http)
                .with_http_connector(RedirectingConnector::new(Arc::clone(redirects), settings));
            Arc::new(
                with_client(builder, client, HttpBuilder::with_config)
                    .with_retry(settings.retry_config())
                    .build()
                    .map_err(client_error)?,
            )
        }
        UrlKind::File { .. } => {
            return Err(RemoteError::LocalUrl {
                url: url.to_string(),
            })
        }
    };
    Ok(store)
}

/// A builder given the HTTP client's settings through its own configuration keys, so that
/// they add to what it read from the environment instead of replacing it.
fn with_client<B>(
    builder: B,
    client: Vec<(ClientConfigKey, String)>,
    set: impl Fn(B, ClientConfigKey, String) -> B,
) -> B {
    client
        .into_iter()
        .fold(builder, |builder, (key, value)| set(builder, key, value))
}
