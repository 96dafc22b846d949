//! Datasets by URL: one COPC object in object storage or on an HTTP server, registered under
//! the operator's allow-list from a HEAD request and its header read by range, never read
//! whole. More `Daemon` methods.
//!
//! A `file://` URL is not one of them: it is a path on the server, resolved under the data
//! roots like any other ([`local_path`]), so that a URL never reads around them.

use std::path::PathBuf;

use pointfarm_render::remote::{AllowedPrefixes, ObjectUrl, RemoteClient, RemoteObject, UrlKind};

use crate::error::DaemonError;
use crate::limits::{check_length, MAX_NAME_BYTES};
use crate::model::{now_unix_ms, Dataset, RemoteSource};
use crate::service::{dataset_id, Daemon};

/// The bytes of a COPC file's head that tell it is one: the LAS 1.4 header (375 bytes) and the
/// header of the first VLR, which the COPC specification requires to be the `copc` info.
const COPC_HEAD_BYTES: u64 = COPC_INFO_OFFSET + 54;
const COPC_INFO_OFFSET: u64 = 375;

/// How a registration says that only COPC objects register by URL, and what to do instead.
const ONLY_COPC: &str = "only a single COPC object (.copc.laz) registers by URL yet; register \
                         other files by path under a data root, or upload them";

/// Checks one prefix of the operator's allow-list (`serve --allow-url-prefix`), with a
/// message that names it: an `s3://` or `http(s)://` URL without credentials or a query.
pub fn check_url_prefix(prefix: &str) -> Result<ObjectUrl, String> {
    let url = ObjectUrl::parse(prefix).map_err(|error| error.to_string())?;
    if matches!(url.kind(), UrlKind::File { .. }) {
        return Err(format!(
            "{url}: a file:// prefix is not needed: local files register under a data root \
             (--data-root)"
        ));
    }
    Ok(url)
}

/// The operator's allow-list from its prefixes, each checked by [`check_url_prefix`]; a
/// daemon refuses to start on a bad one, naming it.
pub fn url_prefixes<S: AsRef<str>>(prefixes: &[S]) -> Result<AllowedPrefixes, DaemonError> {
    for prefix in prefixes {
        check_url_prefix(prefix.as_ref())
            .map_err(|message| DaemonError::invalid("allowed URL prefix", message))?;
    }
    Ok(AllowedPrefixes::new(prefixes)?)
}

/// The scheme of `text` when it is written as a URL (`scheme://...`), lower-cased.
fn url_scheme(text: &str) -> Option<String> {
    let (scheme, _) = text.trim_start().split_once("://")?;
    let mut chars = scheme.chars();
    let starts_with_letter = chars.next().is_some_and(|c| c.is_ascii_alphabetic());
    let valid = chars.all(|c| c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.'));
    (starts_with_letter && valid).then(|| scheme.to_ascii_lowercase())
}

/// The local path a registration's `path` names: a `file://` URL's path, any other text as
/// it is. What a path then may reach is decided by the data roots alone.
pub fn local_path(path: &str) -> Result<String, DaemonError> {
    if url_scheme(path).as_deref() != Some("file") {
        return Ok(path.to_owned());
    }
    match ObjectUrl::parse(path)?.kind() {
        UrlKind::File { path } => Ok(path.display().to_string()),
        _ => Err(DaemonError::invalid(
            "path",
            format!("{path}: not a file:// URL"),
        )),
    }
}

/// The URL a registration's paths name, when they name an object by URL rather than files
/// on the server: one URL, alone, since a dataset by URL is one object.
pub fn requested_url(paths: &[String]) -> Result<Option<String>, DaemonError> {
    let is_remote = |path: &String| url_scheme(path).is_some_and(|scheme| scheme != "file");
    match paths {
        [one] if is_remote(one) => Ok(Some(one.trim().to_owned())),
        many if many.iter().any(is_remote) => Err(DaemonError::invalid(
            "paths",
            format!("a dataset by URL is one object: give its URL alone ({ONLY_COPC})"),
        )),
        _ => Ok(None),
    }
}

impl Daemon {
    /// Registers the COPC object at `url` as a dataset: refused unless the URL lies under the
    /// operator's allowed prefixes, before any request; then a HEAD gives its size and
    /// version, and its first bytes, read by range, must be a COPC header. Its id comes from
    /// the URL, the version and the size ([`RemoteSource::key`]), so registering the same
    /// version again answers the same dataset and a replaced object is another one.
    pub fn register_url(&self, url: &str, name: &str) -> Result<Dataset, DaemonError> {
        check_length("name", name, MAX_NAME_BYTES)?;
        let url = ObjectUrl::parse(url)?;
        if matches!(url.kind(), UrlKind::File { .. }) {
            return Err(DaemonError::invalid(
                "path",
                format!("{url}: a file:// URL is a path on the server"),
            ));
        }
        self.config.allowed_url_prefixes.check(&url).inspect_err(
            |error| tracing::warn!(%error, "a registration by URL is refused by the allow-list"),
        )?;
        if url.is_prefix() {
            return Err(DaemonError::invalid(
                "path",
                format!("{url}: names a prefix, not an object; {ONLY_COPC}"),
            ));
        }
        let client = self.remote_client()?;
        let object = client.open(&url)?;
        let version = object.version().map(str::to_owned).ok_or_else(|| {
            DaemonError::FailedPrecondition(format!(
                "{url}: the server gives no ETag or version id, so a changed object could not \
                 be told from the one registered"
            ))
        })?;
        check_copc_head(&object)?;
        let source = RemoteSource {
            url: url.to_string(),
            version,
        };
        let sha256 = source.key(object.size());
        let id = dataset_id(&sha256);
        if let Some(existing) = self.state.dataset(&id)? {
            return Ok(existing);
        }
        let name = match name {
            "" => object_name(&url),
            name => name.to_owned(),
        };
        let dataset = Dataset {
            id,
            name,
            size_bytes: object.size(),
            sha256,
            path: PathBuf::new(),
            files: Vec::new(),
            created_unix_ms: now_unix_ms(),
            remote: Some(source),
        };
        self.state.put_dataset(&dataset)?;
        tracing::info!(
            dataset = %dataset.id,
            url = %url,
            size_bytes = dataset.size_bytes,
            "dataset added by URL"
        );
        Ok(dataset)
    }

    /// The client that reads datasets by URL; none where the allow-list is empty, since
    /// every URL is then refused before a request.
    fn remote_client(&self) -> Result<&RemoteClient, DaemonError> {
        self.remote.as_ref().ok_or_else(|| {
            DaemonError::Internal("no remote client for an allowed URL prefix".into())
        })
    }
}

/// The object's first bytes, read by range, are a COPC file's: LAS 1.4 whose first VLR is
/// the `copc` info record.
fn check_copc_head(object: &RemoteObject) -> Result<(), DaemonError> {
    let url = object.url();
    let not_copc =
        |reason: &str| DaemonError::invalid("path", format!("{url}: {reason}; {ONLY_COPC}"));
    if object.size() < COPC_HEAD_BYTES {
        return Err(not_copc(&format!(
            "{} bytes, too small for a COPC file",
            object.size()
        )));
    }
    let head = object.read_range(0..COPC_HEAD_BYTES)?;
    if !head.starts_with(pointfarm_render::ingest::LAS_SIGNATURE) {
        return Err(not_copc(
            "not a LAS/LAZ file (it does not start with \"LASF\")",
        ));
    }
    let info = COPC_INFO_OFFSET as usize;
    let is_copc = head[24..26] == [1, 4]
        && u64::from(u16::from_le_bytes([head[94], head[95]])) == COPC_INFO_OFFSET
        && head[info + 2..info + 18] == *b"copc\0\0\0\0\0\0\0\0\0\0\0\0"
        && u16::from_le_bytes([head[info + 18], head[info + 19]]) == 1;
    if !is_copc {
        return Err(not_copc(
            "a LAS/LAZ file, but not COPC (its first record is not the COPC info)",
        ));
    }
    Ok(())
}

/// A dataset by URL is named by its object's last segment, as a file by its name.
fn object_name(url: &ObjectUrl) -> String {
    url.as_str()
        .rsplit('/')
        .find(|segment| !segment.is_empty())
        .unwrap_or(url.as_str())
        .to_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prefixes_are_checked_naming_the_bad_one() {
        let allowed = url_prefixes(&["s3://campaigns/team", "https://data.example/scans/"])
            .expect("good prefixes");
        assert_eq!(allowed.prefixes().len(), 2);
        assert!(url_prefixes::<&str>(&[])
            .expect("none")
            .prefixes()
            .is_empty());
        // Each refusal names the prefix, as far as it can be shown: never a credential or
        // a query, which may be a signature.
        for (bad, named, says) in [
            (
                "https://user:secret@data.example/",
                "data.example",
                "credentials",
            ),
            (
                "https://data.example/scans?X-Amz-Signature=1",
                "https://data.example/scans",
                "query",
            ),
            ("ftp://data.example/scans/", "ftp://data.example", "ftp://"),
            ("data.example/scans", "data.example/scans", "no scheme"),
            ("s3://Bad_Bucket/", "s3://Bad_Bucket", "bucket"),
            ("file:///srv/scans", "file:///srv/scans", "--data-root"),
        ] {
            let error = url_prefixes(&["s3://campaigns/team", bad])
                .expect_err(bad)
                .to_string();
            assert!(error.contains(says), "{bad}: {error}");
            assert!(error.contains(named), "{bad}: {error}");
            assert!(
                !error.contains("secret") && !error.contains("Signature"),
                "{error}"
            );
        }
    }

    #[test]
    fn a_request_names_a_url_alone_or_files() {
        let paths = |items: &[&str]| items.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        assert_eq!(
            requested_url(&paths(&["s3://b/a.copc.laz"])).expect("one URL"),
            Some("s3://b/a.copc.laz".to_owned())
        );
        assert_eq!(
            requested_url(&paths(&["HTTPS://h/a.copc.laz"])).expect("one URL"),
            Some("HTTPS://h/a.copc.laz".to_owned())
        );
        // Another scheme is still a URL, refused as one rather than looked for on disk.
        assert!(requested_url(&paths(&["gs://b/a.laz"]))
            .expect("a URL")
            .is_some());
        for local in [
            &["scans/a.laz"][..],
            &["/srv/a.laz", "b.laz"],
            &["file:///srv/a.laz"],
            &["a:b.laz"],
        ] {
            assert_eq!(requested_url(&paths(local)).expect("files"), None);
        }
        let mixed = requested_url(&paths(&["s3://b/a.copc.laz", "scans/b.laz"]))
            .expect_err("mixed")
            .to_string();
        assert!(mixed.contains("URL alone"), "{mixed}");
    }

    #[test]
    fn a_file_url_is_its_local_path() {
        assert_eq!(
            local_path("file:///srv/scans/a.laz").expect("path"),
            "/srv/scans/a.laz"
        );
        assert_eq!(local_path("scans/a.laz").expect("path"), "scans/a.laz");
        let error = local_path("file://host/a.laz").expect_err("a host");
        assert!(error.to_string().contains("not a host"), "{error}");
    }

    #[test]
    fn the_key_tells_versions_and_sizes_apart() {
        let source = |url: &str, version: &str| RemoteSource {
            url: url.to_owned(),
            version: version.to_owned(),
        };
        let key = source("s3://b/a.copc.laz", "\"e1\"").key(10);
        assert_eq!(key, source("s3://b/a.copc.laz", "\"e1\"").key(10));
        assert_ne!(key, source("s3://b/a.copc.laz", "\"e2\"").key(10));
        assert_ne!(key, source("s3://b/a.copc.laz", "\"e1\"").key(11));
        assert_ne!(key, source("s3://b/b.copc.laz", "\"e1\"").key(10));
        // The parts are length-prefixed: moving a byte from one to the other is another key.
        assert_ne!(source("ab", "c").key(1), source("a", "bc").key(1));
    }
}
