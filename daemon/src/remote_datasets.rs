//! Datasets by URL, registered under the operator's allow-list and never read whole: one COPC
//! object (a HEAD and its header read by range), or LAS/LAZ tiles, named one by one or as an
//! `s3://` prefix whose `.las`/`.laz` objects are listed as a folder's files are, each checked
//! by range as `ingest` checks a file and recorded with its size and version. A COPC object is
//! opened again only at that version ([`Daemon::open_registered_copc`]). More `Daemon`
//! methods.
//!
//! A `file://` URL is not one of them: it is a path on the server, resolved under the data
//! roots like any other ([`local_path`]), so that a URL never reads around them.

use std::path::PathBuf;

use pointfarm_render::remote::{
    AllowedPrefixes, ListedObject, ObjectUrl, RemoteClient, RemoteObject, UrlKind,
};
use pointfarm_render::source::{listed_tiles, open_tile_source};

use crate::error::DaemonError;
use crate::limits::{check_length, MAX_NAME_BYTES};
use crate::model::{now_unix_ms, tiles_key, Dataset, RemoteSource, RemoteTile};
use crate::service::{dataset_id, Daemon};

/// The bytes of a COPC file's head that tell it is one: the LAS 1.4 header (375 bytes) and the
/// header of the first VLR, which the COPC specification requires to be the `copc` info.
const COPC_HEAD_BYTES: u64 = COPC_INFO_OFFSET + 54;
const COPC_INFO_OFFSET: u64 = 375;

/// What registers by URL, said where a registration names something else.
const BY_URL: &str = "one COPC object, or LAS/LAZ objects and s3:// prefixes of them, register \
                      by URL";

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

/// The URLs a registration's paths name, when they name objects by URL rather than files on
/// the server: every path a URL, none mixed with files.
pub fn requested_urls(paths: &[String]) -> Result<Option<Vec<String>>, DaemonError> {
    let is_remote = |path: &String| url_scheme(path).is_some_and(|scheme| scheme != "file");
    if paths.is_empty() || !paths.iter().any(is_remote) {
        return Ok(None);
    }
    if !paths.iter().all(is_remote) {
        return Err(DaemonError::invalid(
            "paths",
            "a dataset by URL is read by URL alone: give URLs or files on the server, not both",
        ));
    }
    Ok(Some(
        paths.iter().map(|path| path.trim().to_owned()).collect(),
    ))
}

impl Daemon {
    /// Registers the objects at `urls` as a dataset: refused unless each URL lies under the
    /// operator's allowed prefixes, before any request. One object whose head is COPC's is a
    /// COPC dataset ([`Self::register_copc`]); anything else is LAS/LAZ tiles
    /// ([`Self::register_tiles`]).
    pub fn register_urls(&self, urls: &[String], name: &str) -> Result<Dataset, DaemonError> {
        check_length("name", name, MAX_NAME_BYTES)?;
        let mut parsed = Vec::with_capacity(urls.len());
        for url in urls {
            let url = ObjectUrl::parse(url)?;
            if matches!(url.kind(), UrlKind::File { .. }) {
                return Err(DaemonError::invalid(
                    "path",
                    format!("{url}: a file:// URL is a path on the server"),
                ));
            }
            self.check_allowed(&url)?;
            parsed.push(url);
        }
        let client = self.remote_client()?;
        if let [url] = parsed.as_slice() {
            if !url.is_prefix() {
                let object = client.open(url)?;
                if is_copc_head(&object)? {
                    return self.register_copc(object, name);
                }
            }
        }
        self.register_tiles(client, &parsed, name)
    }

    /// Refuses `url` unless it lies under the operator's allowed prefixes, naming the rule.
    fn check_allowed(&self, url: &ObjectUrl) -> Result<(), DaemonError> {
        Ok(self.config.allowed_url_prefixes.check(url).inspect_err(
            |error| tracing::warn!(%error, "a registration by URL is refused by the allow-list"),
        )?)
    }

    /// Registers a COPC object: its id comes from the URL, the version and the size
    /// ([`RemoteSource::key`]), so registering the same version again answers the same
    /// dataset and a replaced object is another one.
    fn register_copc(&self, object: RemoteObject, name: &str) -> Result<Dataset, DaemonError> {
        let url = object.url();
        let source = RemoteSource {
            url: url.to_string(),
            version: required_version(url, object.version())?,
        };
        let sha256 = source.key(object.size());
        self.put_url_dataset(Dataset {
            id: dataset_id(&sha256),
            name: default_name(name, url),
            size_bytes: object.size(),
            sha256,
            path: PathBuf::new(),
            files: Vec::new(),
            created_unix_ms: now_unix_ms(),
            remote: Some(source),
            tiles: Vec::new(),
        })
    }

    /// Registers the LAS/LAZ tiles `urls` name (objects, or prefixes listed), each opened at
    /// the version listed and checked by range as a file is, its URL, size and version
    /// recorded. Its id comes from those ([`tiles_key`]), so a replaced tile is another
    /// dataset.
    fn register_tiles(
        &self,
        client: &RemoteClient,
        urls: &[ObjectUrl],
        name: &str,
    ) -> Result<Dataset, DaemonError> {
        let mut listed: Vec<ListedObject> = Vec::new();
        for url in urls {
            let found = listed_tiles(client, url)?;
            if found.is_empty() {
                return Err(DaemonError::invalid(
                    "path",
                    format!("{url}: no .las or .laz objects under this prefix"),
                ));
            }
            listed.extend(found);
        }
        let mut tiles = Vec::with_capacity(listed.len());
        for tile in &mut listed {
            // A listing stays under its prefix; checked again so no object escapes the rule.
            self.check_allowed(&tile.url)?;
            // Some servers list no versions: a HEAD gives the one the reads are held to.
            if tile.version.is_none() {
                tile.version = client.open(&tile.url)?.version().map(str::to_owned);
            }
            tiles.push(RemoteTile {
                url: tile.url.to_string(),
                size_bytes: tile.size,
                version: required_version(&tile.url, tile.version.as_deref())?,
            });
        }
        open_tile_source(client, &listed)
            .map_err(|error| DaemonError::invalid("path", format!("{error}; {BY_URL}")))?;
        let sha256 = tiles_key(&tiles);
        self.put_url_dataset(Dataset {
            id: dataset_id(&sha256),
            name: default_name(name, &urls[0]),
            size_bytes: tiles.iter().map(|tile| tile.size_bytes).sum(),
            sha256,
            path: PathBuf::new(),
            files: Vec::new(),
            created_unix_ms: now_unix_ms(),
            remote: None,
            tiles,
        })
    }

    /// The COPC object of `dataset`, a COPC dataset by URL, opened with a HEAD and held to the
    /// version and size its registration recorded: every read of it is pinned to that version,
    /// and an object replaced since is refused, naming it, before anything of it is read.
    pub(crate) fn open_registered_copc(
        &self,
        dataset: &Dataset,
    ) -> Result<RemoteObject, DaemonError> {
        let source = dataset.remote.as_ref().ok_or_else(|| {
            DaemonError::Internal(format!(
                "dataset {} is not a COPC object by URL",
                dataset.id
            ))
        })?;
        let client = self.remote.as_ref().ok_or_else(|| {
            DaemonError::FailedPrecondition(format!(
                "dataset {} is read by URL ({}), which this daemon reads no more (no \
                 --allow-url-prefix)",
                dataset.id, source.url
            ))
        })?;
        let url = ObjectUrl::parse(&source.url)?;
        self.check_allowed(&url)?;
        let object = client.open(&url)?;
        let now = (object.version(), object.size());
        if now != (Some(source.version.as_str()), dataset.size_bytes) {
            return Err(DaemonError::FailedPrecondition(format!(
                "dataset {}: {url} was replaced after it was registered (version {}, {} bytes; \
                 now version {}, {} bytes): register it again to read it as it is now",
                dataset.id,
                source.version,
                dataset.size_bytes,
                now.0.unwrap_or("none"),
                now.1
            )));
        }
        Ok(object)
    }

    /// Stores a dataset by URL, or answers the one registered before with the same key.
    fn put_url_dataset(&self, dataset: Dataset) -> Result<Dataset, DaemonError> {
        if let Some(existing) = self.state.dataset(&dataset.id)? {
            return Ok(existing);
        }
        self.state.put_dataset(&dataset)?;
        tracing::info!(
            dataset = %dataset.id,
            name = %dataset.name,
            tiles = dataset.tiles.len(),
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

/// The version an object's reads are pinned to; refused without one, since a replaced
/// object could not then be told from the one registered.
fn required_version(url: &ObjectUrl, version: Option<&str>) -> Result<String, DaemonError> {
    version.map(str::to_owned).ok_or_else(|| {
        DaemonError::FailedPrecondition(format!(
            "{url}: the server gives no ETag or version id, so a changed object could not be \
             told from the one registered"
        ))
    })
}

/// Whether the object's first bytes, read by range, are a COPC file's: LAS 1.4 whose first
/// VLR is the `copc` info record. An object that is not LAS/LAZ at all is refused here.
fn is_copc_head(object: &RemoteObject) -> Result<bool, DaemonError> {
    let url = object.url();
    if object.size() < COPC_HEAD_BYTES {
        return Ok(false);
    }
    let head = object.read_range(0..COPC_HEAD_BYTES)?;
    if !head.starts_with(pointfarm_render::ingest::LAS_SIGNATURE) {
        return Err(DaemonError::invalid(
            "path",
            format!("{url}: not a LAS/LAZ file (it does not start with \"LASF\"); {BY_URL}"),
        ));
    }
    let info = COPC_INFO_OFFSET as usize;
    Ok(head[24..26] == [1, 4]
        && u64::from(u16::from_le_bytes([head[94], head[95]])) == COPC_INFO_OFFSET
        && head[info + 2..info + 18] == *b"copc\0\0\0\0\0\0\0\0\0\0\0\0"
        && u16::from_le_bytes([head[info + 18], head[info + 19]]) == 1)
}

/// The name given, or the URL's last segment, as a file is named by its name.
fn default_name(name: &str, url: &ObjectUrl) -> String {
    match name {
        "" => object_name(url.as_str()),
        name => name.to_owned(),
    }
}

/// An object by URL is named by its last segment, as a file by its name.
pub(crate) fn object_name(url: &str) -> String {
    url.rsplit('/')
        .find(|segment| !segment.is_empty())
        .unwrap_or(url)
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
    fn a_request_names_urls_or_files() {
        let paths = |items: &[&str]| items.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        assert_eq!(
            requested_urls(&paths(&["s3://b/a.copc.laz"])).expect("one URL"),
            Some(paths(&["s3://b/a.copc.laz"]))
        );
        assert_eq!(
            requested_urls(&paths(&["HTTPS://h/a.laz", " s3://b/tiles/"])).expect("URLs"),
            Some(paths(&["HTTPS://h/a.laz", "s3://b/tiles/"]))
        );
        // Another scheme is still a URL, refused as one rather than looked for on disk.
        assert!(requested_urls(&paths(&["gs://b/a.laz"]))
            .expect("a URL")
            .is_some());
        for local in [
            &["scans/a.laz"][..],
            &["/srv/a.laz", "b.laz"],
            &["file:///srv/a.laz"],
            &["a:b.laz"],
        ] {
            assert_eq!(requested_urls(&paths(local)).expect("files"), None);
        }
        let mixed = requested_urls(&paths(&["s3://b/a.copc.laz", "scans/b.laz"]))
            .expect_err("mixed")
            .to_string();
        assert!(mixed.contains("not both"), "{mixed}");
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

    #[test]
    fn the_tiles_key_tells_every_tile_apart() {
        let tile = |url: &str, size_bytes: u64, version: &str| RemoteTile {
            url: url.to_owned(),
            size_bytes,
            version: version.to_owned(),
        };
        let tiles = [
            tile("s3://b/t/a.laz", 10, "e1"),
            tile("s3://b/t/b.laz", 20, "e2"),
        ];
        let key = tiles_key(&tiles);
        assert_eq!(key, tiles_key(&tiles.clone()));
        let replaced = [tiles[0].clone(), tile("s3://b/t/b.laz", 20, "e3")];
        assert_ne!(key, tiles_key(&replaced));
        let resized = [tiles[0].clone(), tile("s3://b/t/b.laz", 21, "e2")];
        assert_ne!(key, tiles_key(&resized));
        assert_ne!(key, tiles_key(&tiles[..1]));
        // One tile's key is never the key of the same object registered as COPC.
        let copc = RemoteSource {
            url: "s3://b/t/a.laz".to_owned(),
            version: "e1".to_owned(),
        };
        assert_ne!(tiles_key(&tiles[..1]), copc.key(10));
    }
}
