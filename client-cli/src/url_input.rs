//! Inputs given as URLs (`s3://bucket/scan.copc.laz`, `https://host/scan.copc.laz`), which
//! `render` and `info` read by range instead of as files here. Only a COPC file is read by
//! URL yet: a plain LAS/LAZ object or a prefix is refused, saying so. A `file://` URL is its
//! local path.

use std::path::PathBuf;

use anyhow::Result;
use pointfarm_render::copc::{self, CopcDataset, CopcError, CopcSummary};
use pointfarm_render::remote::{ObjectUrl, RemoteClient, RemoteSettings};

/// What only COPC files being read by URL means for an input that is not one.
const COPC_ONLY: &str = "only COPC files (.copc.laz) render by URL yet; a plain LAS/LAZ file \
                         or a prefix of them has to be copied here first";

/// The inputs of a command: files and folders here, or one object by URL.
pub enum Inputs {
    Paths(Vec<PathBuf>),
    Url(ObjectUrl),
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
    if url.is_prefix() {
        anyhow::bail!("{url}: names a prefix, not one file; {COPC_ONLY}");
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

/// The COPC file at `url`, opened for rendering.
pub fn open(client: &RemoteClient, url: &ObjectUrl) -> Result<CopcDataset> {
    copc::open_copc_url(client, url).map_err(refused)
}

/// The octree and header facts of the COPC file at `url`.
pub fn describe(client: &RemoteClient, url: &ObjectUrl) -> Result<CopcSummary> {
    copc::describe_url(client, url).map_err(refused)
}

/// An error opening a URL, saying what is read by URL where the object is no COPC file.
fn refused(error: CopcError) -> anyhow::Error {
    match error {
        CopcError::NotCopc { .. } => anyhow::anyhow!("{error}; {COPC_ONLY}"),
        other => other.into(),
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
    fn a_prefix_or_a_url_among_paths_is_refused_and_a_file_url_is_its_path() {
        let prefix = classify(&["s3://bucket/scans/".into()])
            .err()
            .expect("refused");
        assert!(prefix.to_string().contains("only COPC files"), "{prefix}");
        let mixed = classify(&["a.laz".into(), "https://host/b.copc.laz".into()]);
        assert!(mixed.is_err());
        match classify(&["file:///data/a.copc.laz".into()]).expect("a path") {
            Inputs::Paths(paths) => assert_eq!(paths, [PathBuf::from("/data/a.copc.laz")]),
            Inputs::Url(url) => panic!("{url} read as a URL"),
        }
    }
}
