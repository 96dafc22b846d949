//! `ObjectUrl`: a dataset's address, checked once so that everything after it can trust it.

use std::fmt;
use std::path::PathBuf;

use object_store::path::Path as ObjectPath;
use url::Url;

use super::error::{RemoteError, SCHEMES};

/// Longest URL accepted, so that a client cannot make the daemon store or log arbitrary text.
pub const MAX_URL_LEN: usize = 2048;

/// Where an `ObjectUrl` points.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum UrlKind {
    /// An S3 or S3-compatible bucket; the endpoint and credentials come from the environment.
    S3 { bucket: String },
    /// A Google Cloud Storage bucket (`gs://`); credentials come from the environment.
    Gcs { bucket: String },
    /// An Azure Blob Storage container (`az://`, `azure://`, `abfs://`, `abfss://`); the
    /// account and credentials come from the environment.
    Azure { container: String },
    /// A plain HTTP(S) server that answers range requests.
    Http,
    /// A local file or folder, read by the local path rather than through object storage.
    File { path: PathBuf },
}

/// A validated `s3://bucket/key`, `gs://bucket/key`, `az://container/key`,
/// `http(s)://host/path` or `file:///path`. It never holds
/// credentials, a query or a fragment, so it can be shown and logged as it is.
#[derive(Clone, PartialEq, Eq)]
pub struct ObjectUrl {
    url: Url,
    kind: UrlKind,
}

impl ObjectUrl {
    /// Parses and validates a URL, with an error that says what is wrong with it.
    pub fn parse(text: &str) -> Result<Self, RemoteError> {
        let text = text.trim();
        let invalid = |reason: &str| RemoteError::InvalidUrl {
            url: shown(text),
            reason: reason.to_owned(),
        };
        if text.len() > MAX_URL_LEN {
            return Err(invalid(&format!("longer than {MAX_URL_LEN} bytes")));
        }
        let url = Url::parse(text).map_err(|error| match error {
            url::ParseError::RelativeUrlWithoutBase => {
                invalid(&format!("no scheme (use {SCHEMES})"))
            }
            other => invalid(&other.to_string()),
        })?;
        let azure_scheme = matches!(url.scheme(), "az" | "azure" | "abfs" | "abfss");
        if azure_scheme && !url.username().is_empty() && url.password().is_none() {
            return Err(invalid(
                "write the container as the host (az://container/path); the account comes \
                 from AZURE_STORAGE_ACCOUNT_NAME",
            ));
        }
        if !url.username().is_empty() || url.password().is_some() {
            return Err(invalid(
                "credentials in a URL are refused; give them through the environment",
            ));
        }
        if url.query().is_some() {
            return Err(invalid(
                "a query string is refused (it may carry a signature)",
            ));
        }
        if url.fragment().is_some() {
            return Err(invalid("a fragment is refused"));
        }
        // Checked on the text, since the parser would resolve them silently into another key.
        if text.split('/').skip(3).any(|segment| {
            let lowered = segment.to_ascii_lowercase();
            matches!(
                lowered.as_str(),
                "." | ".." | "%2e" | "%2e%2e" | ".%2e" | "%2e."
            )
        }) {
            return Err(invalid("a path with . or .. segments is refused"));
        }
        let kind = match url.scheme() {
            "s3" => {
                if url.port().is_some() {
                    return Err(invalid(
                        "an s3:// URL names a bucket, not a port; set AWS_ENDPOINT for another server",
                    ));
                }
                let bucket = url.host_str().unwrap_or_default();
                check_bucket(bucket).map_err(|reason| invalid(&reason))?;
                UrlKind::S3 {
                    bucket: bucket.to_owned(),
                }
            }
            "gs" => {
                let bucket = bucket_of(&url, "gs://bucket/prefix").map_err(|r| invalid(&r))?;
                check_gcs_bucket(bucket).map_err(|reason| invalid(&reason))?;
                UrlKind::Gcs {
                    bucket: bucket.to_owned(),
                }
            }
            "az" | "azure" | "abfs" | "abfss" => {
                let container =
                    bucket_of(&url, "az://container/prefix").map_err(|r| invalid(&r))?;
                check_azure_container(container).map_err(|reason| invalid(&reason))?;
                UrlKind::Azure {
                    container: container.to_owned(),
                }
            }
            "http" | "https" => {
                if url.host_str().is_none_or(str::is_empty) {
                    return Err(invalid("no host"));
                }
                UrlKind::Http
            }
            "file" => {
                if url
                    .host_str()
                    .is_some_and(|host| !host.is_empty() && host != "localhost")
                {
                    return Err(invalid("a file:// URL names a local path, not a host"));
                }
                let path = url
                    .to_file_path()
                    .map_err(|()| invalid("not an absolute local path"))?;
                UrlKind::File { path }
            }
            scheme => {
                return Err(RemoteError::UnsupportedScheme {
                    url: shown(text),
                    scheme: scheme.to_owned(),
                })
            }
        };
        Ok(Self { url, kind })
    }

    pub fn kind(&self) -> &UrlKind {
        &self.kind
    }

    pub fn as_str(&self) -> &str {
        self.url.as_str()
    }

    /// The local path of a `file://` URL.
    pub fn local_path(&self) -> Option<&std::path::Path> {
        match &self.kind {
            UrlKind::File { path } => Some(path),
            _ => None,
        }
    }

    /// Whether the URL is in object storage (S3, GCS or Azure): a bucket or container that
    /// can be listed and written, as an HTTP server or a local path cannot through it.
    pub fn is_object_storage(&self) -> bool {
        matches!(
            self.kind,
            UrlKind::S3 { .. } | UrlKind::Gcs { .. } | UrlKind::Azure { .. }
        )
    }

    /// Whether the URL names a prefix (a folder of objects) rather than one object.
    pub fn is_prefix(&self) -> bool {
        self.url.path().ends_with('/') || self.object_path().as_ref().is_empty()
    }

    /// The URL of the object `name` under this prefix, with a `/` between them.
    pub fn join(&self, name: &str) -> Result<Self, RemoteError> {
        let mut text = self.url.as_str().to_owned();
        if !text.ends_with('/') {
            text.push('/');
        }
        text.push_str(name);
        Self::parse(&text)
    }

    /// The key of the store this URL is read through: one per bucket or per origin, so that
    /// connections are shared.
    pub(crate) fn store_key(&self) -> String {
        match &self.kind {
            UrlKind::Http | UrlKind::File { .. } => self.url.origin().ascii_serialization(),
            _ => self.bucket_origin().unwrap_or_default(),
        }
    }

    /// The object's path within its store, percent-decoded.
    pub(crate) fn object_path(&self) -> ObjectPath {
        let path = self.url.path().trim_start_matches('/');
        ObjectPath::from_url_path(path).unwrap_or_else(|_| ObjectPath::from(path))
    }

    /// The scheme, host and port, and the path: what allow-list rules compare.
    pub(crate) fn origin_and_path(&self) -> (String, &str) {
        let origin = match &self.kind {
            UrlKind::Http => self.url.origin().ascii_serialization(),
            UrlKind::File { .. } => "file://".to_owned(),
            _ => self.bucket_origin().unwrap_or_default(),
        };
        (origin, self.url.path())
    }

    /// A bucket's or container's one spelling, `s3://b`, `gs://b` or `az://c`, whichever
    /// alias the URL was written with, so that `azure://c` and `az://c` share a store and
    /// an allow-list rule.
    fn bucket_origin(&self) -> Option<String> {
        match &self.kind {
            UrlKind::S3 { bucket } => Some(format!("s3://{bucket}")),
            UrlKind::Gcs { bucket } => Some(format!("gs://{bucket}")),
            UrlKind::Azure { container } => Some(format!("az://{container}")),
            UrlKind::Http | UrlKind::File { .. } => None,
        }
    }

    /// The URL of an object found by listing this URL's store.
    pub(crate) fn with_object_path(&self, location: &ObjectPath) -> Result<Self, RemoteError> {
        let mut url = self.url.clone();
        url.set_path(&format!("/{}", location.as_ref()));
        Self::parse(url.as_str())
    }
}

impl fmt::Display for ObjectUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.url.as_str())
    }
}

impl fmt::Debug for ObjectUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ObjectUrl({})", self.url.as_str())
    }
}

impl std::str::FromStr for ObjectUrl {
    type Err = RemoteError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        Self::parse(text)
    }
}

/// The host of a bucket URL, which names the bucket or container, refusing a port.
fn bucket_of<'a>(url: &'a Url, form: &str) -> Result<&'a str, String> {
    if url.port().is_some() {
        return Err(format!(
            "a {}:// URL names a bucket or container ({form}), not a port; \
             the endpoint comes from the environment",
            url.scheme()
        ));
    }
    Ok(url.host_str().unwrap_or_default())
}

/// Google Cloud Storage's bucket naming rules, bounded at 63 characters (longer names, with
/// dots, need a verified domain and are rare).
fn check_gcs_bucket(bucket: &str) -> Result<(), String> {
    check_name(bucket, "bucket", "gs://bucket/prefix", Punctuation::GCS)
}

/// Azure's container naming rules, whose names also have no two hyphens in a row.
fn check_azure_container(container: &str) -> Result<(), String> {
    check_name(
        container,
        "container",
        "az://container/prefix",
        Punctuation::AZURE,
    )?;
    if container.contains("--") {
        return Err(format!(
            "the container name {container:?} may not hold two hyphens in a row"
        ));
    }
    Ok(())
}

/// S3's bucket naming rules, checked here so that a typo is named before any request.
fn check_bucket(bucket: &str) -> Result<(), String> {
    check_name(bucket, "bucket", "s3://bucket/prefix", Punctuation::S3)
}

/// The characters besides lowercase letters and digits a provider allows in a bucket's name,
/// and how an error names them.
struct Punctuation {
    bytes: &'static [u8],
    named: &'static str,
}

impl Punctuation {
    const S3: Self = Self {
        bytes: b".-",
        named: "dots and hyphens",
    };
    const GCS: Self = Self {
        bytes: b".-_",
        named: "dots, hyphens and underscores",
    };
    const AZURE: Self = Self {
        bytes: b"-",
        named: "hyphens",
    };
}

/// A bucket or container name: 3 to 63 lowercase letters, digits and the provider's
/// punctuation, starting and ending with a letter or digit.
fn check_name(name: &str, what: &str, form: &str, punctuation: Punctuation) -> Result<(), String> {
    if name.is_empty() {
        return Err(format!("no {what} ({form})"));
    }
    if !(3..=63).contains(&name.len()) {
        return Err(format!(
            "the {what} name {name:?} is not 3 to 63 characters"
        ));
    }
    let valid = name.bytes().all(|byte| {
        byte.is_ascii_lowercase() || byte.is_ascii_digit() || punctuation.bytes.contains(&byte)
    });
    let ends_valid = name
        .bytes()
        .next()
        .zip(name.bytes().last())
        .is_some_and(|(first, last)| first.is_ascii_alphanumeric() && last.is_ascii_alphanumeric());
    if !valid || !ends_valid {
        return Err(format!(
            "the {what} name {name:?} may hold only lowercase letters, digits, {}, \
             starting and ending with a letter or digit",
            punctuation.named
        ));
    }
    Ok(())
}

/// A rejected URL as shown in its error: without anything after an `@` before the host, and cut
/// to a bound, so that a credential typed into a URL is not echoed.
fn shown(text: &str) -> String {
    let without_userinfo = match (text.find("://"), text.find('@')) {
        (Some(scheme_end), Some(at)) if at > scheme_end => {
            let host_start = scheme_end + 3;
            let path_start = text[host_start..]
                .find('/')
                .map_or(text.len(), |offset| host_start + offset);
            if at < path_start {
                format!("{}***@{}", &text[..host_start], &text[at + 1..])
            } else {
                text.to_owned()
            }
        }
        _ => text.to_owned(),
    };
    let without_query = match without_userinfo.find('?') {
        Some(query) => format!("{}?***", &without_userinfo[..query]),
        None => without_userinfo,
    };
    if without_query.len() > 200 {
        let mut end = 200;
        while !without_query.is_char_boundary(end) {
            end -= 1;
        }
        format!("{}...", &without_query[..end])
    } else {
        without_query
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_each_scheme() {
        let s3 = ObjectUrl::parse("s3://my-bucket/campaign/").expect("s3");
        assert_eq!(
            s3.kind(),
            &UrlKind::S3 {
                bucket: "my-bucket".to_owned()
            }
        );
        assert!(s3.is_prefix());
        assert_eq!(s3.object_path().as_ref(), "campaign");
        let http =
            ObjectUrl::parse("https://host.example:8443/scans/a%20b.copc.laz").expect("http");
        assert_eq!(http.kind(), &UrlKind::Http);
        assert!(!http.is_prefix());
        assert_eq!(http.object_path().as_ref(), "scans/a b.copc.laz");
        assert_eq!(http.store_key(), "https://host.example:8443");
        let gcs = ObjectUrl::parse("gs://scans_2024/site/a.copc.laz").expect("gs");
        assert_eq!(
            gcs.kind(),
            &UrlKind::Gcs {
                bucket: "scans_2024".to_owned()
            }
        );
        assert_eq!(gcs.store_key(), "gs://scans_2024");
        assert_eq!(gcs.object_path().as_ref(), "site/a.copc.laz");
        assert!(gcs.is_object_storage());
        for alias in ["az", "azure", "abfs", "abfss"] {
            let azure = ObjectUrl::parse(&format!("{alias}://scans/site/")).expect(alias);
            assert_eq!(
                azure.kind(),
                &UrlKind::Azure {
                    container: "scans".to_owned()
                }
            );
            assert_eq!(azure.store_key(), "az://scans", "{alias}");
            assert_eq!(azure.origin_and_path(), ("az://scans".to_owned(), "/site/"));
            assert!(azure.is_prefix());
        }
        assert!(!http.is_object_storage());
        let file = ObjectUrl::parse("file:///data/scan.laz").expect("file");
        assert_eq!(
            file.local_path(),
            Some(std::path::Path::new("/data/scan.laz"))
        );
    }

    #[test]
    fn refuses_with_a_reason() {
        let cases = [
            ("/data/scan.laz", "no scheme"),
            ("ftp://host/scan.laz", "ftp"),
            ("s3:///key", "no bucket"),
            ("s3://Bad_Bucket/key", "lowercase"),
            ("s3://bucket:9000/key", "port"),
            ("https://user:secret@host/scan.laz", "credentials"),
            ("https://host/scan.laz?X-Amz-Signature=abc", "query"),
            ("https://host/scan.laz#part", "fragment"),
            ("s3://bucket/a/../b", ".."),
            ("s3://bucket/a/%2E%2E/b", ".."),
            ("file://otherhost/data", "local path"),
            ("gs:///key", "no bucket"),
            ("gs://Scans/key", "lowercase"),
            ("gs://bucket:4443/key", "port"),
            ("az://under_score/key", "hyphens"),
            ("az://two--hyphens/key", "two hyphens"),
            ("azure://ab/key", "3 to 63"),
            (
                "abfs://data@account.dfs.core.windows.net/key",
                "AZURE_STORAGE_ACCOUNT_NAME",
            ),
        ];
        for (text, expected) in cases {
            let error = ObjectUrl::parse(text).expect_err(text).to_string();
            assert!(error.contains(expected), "{text}: {error}");
            assert!(!error.contains("secret"), "{error}");
            assert!(!error.contains("Signature=abc"), "{error}");
        }
    }
}
