//! What can go wrong reading a dataset by URL, each error naming the URL it concerns.

use std::ops::Range;
use std::time::Duration;

/// The schemes a URL may have, as errors list them.
pub(crate) const SCHEMES: &str = "s3://, gs://, az://, http://, https:// or file://";

/// A failure of the remote storage layer; URLs never carry credentials (they are refused at
/// parse time), so every message can be logged as it is.
#[derive(Debug, thiserror::Error)]
pub enum RemoteError {
    #[error("{url}: not a dataset URL: {reason}")]
    InvalidUrl { url: String, reason: String },
    #[error("{url}: the scheme {scheme}:// is not supported (use {schemes})", schemes = SCHEMES)]
    UnsupportedScheme { url: String, scheme: String },
    #[error("{url}: not under an allowed prefix: {rule}")]
    NotAllowed { url: String, rule: String },
    #[error("{url}: a file:// URL is read as a local path, not through object storage")]
    LocalUrl { url: String },
    #[error("{url}: no such object")]
    NotFound { url: String },
    #[error("{url}: access denied ({reason})")]
    Denied { url: String, reason: String },
    #[error("{url}: the object changed while it was being read (it no longer matches version {version})")]
    ObjectChanged { url: String, version: String },
    #[error("{url}: no answer within {after:?}")]
    TimedOut { url: String, after: Duration },
    #[error("{url}: bytes {}..{} are outside the object's {size} bytes", range.start, range.end)]
    RangeOutOfBounds {
        url: String,
        range: Range<u64>,
        size: u64,
    },
    #[error("{url}: a read of {requested} bytes exceeds the limit of {limit} bytes per read")]
    ReadTooLarge {
        url: String,
        requested: u64,
        limit: u64,
    },
    #[error("{url}: asked for bytes {}..{}, the server answered {got} bytes", range.start, range.end)]
    ShortRead {
        url: String,
        range: Range<u64>,
        got: u64,
    },
    #[error("{url}: the server redirected to {target}, which is not followed: {reason}")]
    Redirected {
        url: String,
        target: String,
        reason: String,
    },
    #[error(
        "{url}: the server ignored the range request of bytes {}..{} and answered with the whole \
         object; pointfarm reads objects by range only, from servers that answer Range \
         requests with 206 Partial Content",
        range.start,
        range.end
    )]
    RangeIgnored { url: String, range: Range<u64> },
    #[error("{url}: listing failed: {reason}")]
    Listing { url: String, reason: String },
    #[error("{url}: more than {limit} objects under this prefix")]
    TooManyObjects { url: String, limit: usize },
    #[error("{url}: {message}")]
    Transport { url: String, message: String },
    #[error("{url}: the storage client could not be set up: {message}")]
    Client { url: String, message: String },
    #[error("the remote reader's runtime stopped: {message}")]
    Runtime { message: String },
}

impl RemoteError {
    /// Sorts an object_store error by what the caller can act on.
    pub(crate) fn from_store(url: &str, error: object_store::Error) -> Self {
        let url = url.to_owned();
        if let Some(refused) = refused_redirect(&error) {
            return RemoteError::Redirected {
                url,
                target: refused.target.clone(),
                reason: refused.reason.clone(),
            };
        }
        match error {
            object_store::Error::NotFound { .. } => RemoteError::NotFound { url },
            object_store::Error::PermissionDenied { .. } => {
                let reason = format!(
                    "the server refused these credentials (403); {}",
                    credential_sources(&url)
                );
                RemoteError::Denied { url, reason }
            }
            object_store::Error::Unauthenticated { .. } => {
                let reason = format!("no valid credentials (401); {}", credential_sources(&url));
                RemoteError::Denied { url, reason }
            }
            other => {
                if is_timeout(&other) {
                    RemoteError::Transport {
                        url,
                        message: format!("timed out, after retries: {other}"),
                    }
                } else {
                    RemoteError::Transport {
                        url,
                        message: other.to_string(),
                    }
                }
            }
        }
    }

    /// Sorts an error of a write: a missing bucket and a refusal by name, anything else on one
    /// line, since stores answer a failed write with the XML of their error.
    pub(crate) fn from_upload(url: &str, error: object_store::Error) -> Self {
        let text = one_line(&error);
        if names_missing_bucket(&text) {
            return RemoteError::Transport {
                url: url.to_owned(),
                message: missing_bucket(url).to_owned(),
            };
        }
        if text.contains("AccessDenied")
            || text.contains("403 Forbidden")
            || text.contains("AuthenticationFailed")
            || text.contains("AuthorizationFailure")
        {
            return Self::from_store(
                url,
                object_store::Error::PermissionDenied {
                    path: url.to_owned(),
                    source: text.into(),
                },
            );
        }
        match error {
            object_store::Error::Generic { .. } => RemoteError::Transport {
                url: url.to_owned(),
                message: format!("the write failed: {text}"),
            },
            other => Self::from_store(url, other),
        }
    }

    /// Whether this error is a stall, so callers can retry later rather than give up on the dataset.
    pub fn is_timeout(&self) -> bool {
        match self {
            RemoteError::TimedOut { .. } => true,
            RemoteError::Transport { message, .. } => message.starts_with("timed out"),
            _ => false,
        }
    }
}

/// Where the credentials of a URL's store come from, as object_store's builders read them,
/// naming the variables and never their values.
pub(crate) fn credential_sources(url: &str) -> &'static str {
    let scheme = url.split("://").next().unwrap_or_default();
    match scheme {
        "gs" => {
            "GCS reads them from the environment (GOOGLE_SERVICE_ACCOUNT, \
             GOOGLE_APPLICATION_CREDENTIALS, or the instance's metadata service)"
        }
        "az" | "azure" | "abfs" | "abfss" => {
            "Azure reads them from the environment (AZURE_STORAGE_ACCOUNT_NAME with \
             AZURE_STORAGE_ACCOUNT_KEY, AZURE_STORAGE_SAS_KEY or a managed identity)"
        }
        _ => {
            "object storage reads them from the environment (AWS_ACCESS_KEY_ID, \
             AWS_SECRET_ACCESS_KEY, ...)"
        }
    }
}

/// Whether a store's answer says the bucket or container does not exist: S3's and GCS's
/// `NoSuchBucket`, Azure's `ContainerNotFound`.
pub(crate) fn names_missing_bucket(text: &str) -> bool {
    text.contains("NoSuchBucket") || text.contains("ContainerNotFound")
}

/// How a missing bucket or container is said for a URL's store.
pub(crate) fn missing_bucket(url: &str) -> &'static str {
    if matches!(
        url.split("://").next(),
        Some("az" | "azure" | "abfs" | "abfss")
    ) {
        "no such container"
    } else {
        "no such bucket"
    }
}

/// An error and its causes on one line, the store's answer summarised by its `<Code>` and
/// `<Message>` where it sent XML.
fn one_line(error: &object_store::Error) -> String {
    let mut text = String::new();
    let mut source: Option<&(dyn std::error::Error + 'static)> = Some(error);
    while let Some(cause) = source {
        let shown = cause.to_string();
        if !text.contains(&shown) {
            if !text.is_empty() {
                text.push_str(": ");
            }
            text.push_str(&shown);
        }
        source = cause.source();
    }
    let tag = |name: &str| -> Option<String> {
        let open = format!("<{name}>");
        let start = text.find(&open)? + open.len();
        let end = text[start..].find("</")? + start;
        Some(text[start..end].to_owned())
    };
    let summary = match (tag("Code"), tag("Message")) {
        (Some(code), Some(message)) => Some(format!("{code}: {message}")),
        (Some(code), None) => Some(code),
        _ => None,
    };
    let head = text.split('<').next().unwrap_or_default().trim_end();
    let joined = match summary {
        Some(summary) => format!("{head} {summary}"),
        None => text.clone(),
    };
    joined.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// An error and its chain of causes, the error first.
pub(crate) fn causes<'a>(
    error: &'a (dyn std::error::Error + 'static),
) -> impl Iterator<Item = &'a (dyn std::error::Error + 'static)> {
    std::iter::successors(Some(error), |cause| cause.source())
}

/// Whether a timeout is somewhere in the error's chain of causes.
fn is_timeout(error: &object_store::Error) -> bool {
    causes(error).any(|cause| {
        let http = cause
            .downcast_ref::<object_store::client::HttpError>()
            .is_some_and(|http| {
                matches!(http.kind(), object_store::client::HttpErrorKind::Timeout)
            });
        let io = cause
            .downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.kind() == std::io::ErrorKind::TimedOut);
        http || io
    })
}

/// A redirect refused, as the request's error carries it to [`RemoteError`].
#[derive(Debug, thiserror::Error)]
#[error("the server redirected to {target}, which is not followed: {reason}")]
pub(crate) struct RedirectRefused {
    /// The target, without a query, fragment or credentials, so it can be logged.
    pub(crate) target: String,
    pub(crate) reason: String,
}

/// The refused redirect somewhere in an error's chain of causes.
pub(crate) fn refused_redirect<'a>(
    error: &'a (dyn std::error::Error + 'static),
) -> Option<&'a RedirectRefused> {
    causes(error).find_map(|cause| cause.downcast_ref::<RedirectRefused>())
}
