//! Inputs given as URLs (`s3://bucket/scan.copc.laz`, `https://host/tiles/a.laz`,
//! `s3://bucket/campaign/`), which `render` and `info` read by range instead of as files here.
//! A COPC file renders node by node from its own hierarchy; plain LAS/LAZ tiles (one object,
//! or the `.las`/`.laz` objects under a prefix) are described, previewed from their chunk
//! starts, and built into a store here by streaming them, without being copied. A `file://`
//! URL is its local path.

use std::path::PathBuf;

use anyhow::Result;
use pointfarm_render::copc::{self, CopcDataset, CopcError, CopcSummary};
use pointfarm_render::remote::{ListedObject, ObjectUrl, RemoteClient, RemoteSettings};
use pointfarm_render::source::listed_tiles;

/// The inputs of a command: files and folders here, or one URL (an object or a prefix).
pub enum Inputs {
    Paths(Vec<PathBuf>),
    Url(ObjectUrl),
}

/// What a URL holds, once opened.
pub enum UrlDataset {
    /// A COPC file, rendered from its own hierarchy.
    Copc(Box<CopcDataset>),
    /// Plain LAS/LAZ tiles: the object, or those under the prefix, sorted, each with the
    /// version a store build holds it to.
    Tiles(Vec<ListedObject>),
}

/// Whether an input is written as a URL (`scheme://...`) rather than as a path.
pub fn looks_like_url(input: &std::path::Path) -> bool {
    input.to_str().is_some_and(|text| {
        text.split_once("://").is_some_and(|(scheme, _)| {
            !scheme.is_empty() && scheme.chars().all(|c| c.is_ascii_alphanumeric())
        })
    })
}

/// The URL `input` is written as, checked: an object's, or a `file://` URL's local path.
pub fn parse(input: &std::path::Path) -> Result<Inputs> {
    let url = ObjectUrl::parse(&input.to_string_lossy())?;
    if let Some(path) = url.local_path() {
        return Ok(Inputs::Paths(vec![path.to_owned()]));
    }
    Ok(Inputs::Url(url))
}

/// `inputs` as paths here, or as the one URL among them.
pub fn classify(inputs: &[PathBuf]) -> Result<Inputs> {
    match inputs {
        [one] if looks_like_url(one) => parse(one),
        many => {
            if let Some(url) = many.iter().find(|input| looks_like_url(input)) {
                anyhow::bail!(
                    "{}: a URL is rendered on its own, not with other inputs",
                    url.display()
                );
            }
            Ok(Inputs::Paths(many.to_vec()))
        }
    }
}

/// A client for reading by URL, credentials (for `s3://`) from the environment.
pub fn client() -> Result<RemoteClient> {
    Ok(RemoteClient::new(RemoteSettings::default())?)
}

/// What `url` holds: the tiles under a prefix (listed, within the client's bound on a
/// listing), or one object opened as a COPC file, else as one tile.
pub fn open(client: &RemoteClient, url: &ObjectUrl) -> Result<UrlDataset> {
    if url.is_prefix() {
        return Ok(UrlDataset::Tiles(tiles_under(client, url)?));
    }
    match copc::open_copc_url(client, url) {
        Ok(copc) => Ok(UrlDataset::Copc(Box::new(copc))),
        Err(CopcError::NotCopc { .. }) => Ok(UrlDataset::Tiles(listed_tiles(client, url)?)),
        Err(other) => Err(other.into()),
    }
}

/// The `.las` and `.laz` objects under `prefix` (in any case), sorted as a folder's files are.
pub fn tiles_under(client: &RemoteClient, prefix: &ObjectUrl) -> Result<Vec<ListedObject>> {
    let listed = listed_tiles(client, prefix)?;
    if listed.is_empty() {
        anyhow::bail!("{prefix}: no .las or .laz object under this prefix");
    }
    Ok(listed)
}

/// The octree and header facts of the object at `url`, when it is a COPC file; `None` for a
/// plain LAS/LAZ file.
pub fn describe_copc(client: &RemoteClient, url: &ObjectUrl) -> Result<Option<CopcSummary>> {
    match copc::describe_url(client, url) {
        Ok(summary) => Ok(Some(summary)),
        Err(CopcError::NotCopc { .. }) => Ok(None),
        Err(other) => Err(other.into()),
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;

    #[test]
    fn urls_are_told_from_paths() {
        assert!(looks_like_url(Path::new("https://host/a.copc.laz")));
        assert!(looks_like_url(Path::new("s3://bucket/a.copc.laz")));
        assert!(!looks_like_url(Path::new("scans/a.copc.laz")));
        assert!(!looks_like_url(Path::new("odd:/name")));
        assert!(!looks_like_url(Path::new("a b://c")));
    }

    #[test]
    fn a_url_among_paths_is_refused_and_a_file_url_is_its_path() {
        match classify(&["s3://bucket/scans/".into()]).expect("a prefix") {
            Inputs::Url(url) => assert!(url.is_prefix(), "{url}"),
            Inputs::Paths(paths) => panic!("{paths:?} read as paths"),
        }
        let mixed = classify(&["a.laz".into(), "https://host/b.copc.laz".into()]);
        assert!(mixed.is_err());
        match classify(&["file:///data/a.copc.laz".into()]).expect("a path") {
            Inputs::Paths(paths) => assert_eq!(paths, [PathBuf::from("/data/a.copc.laz")]),
            Inputs::Url(url) => panic!("{url} read as a URL"),
        }
    }
}
