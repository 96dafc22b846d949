//! `AllowedPrefixes`: the operator's list of URL prefixes a daemon may read datasets from.

use super::error::RemoteError;
use super::url::ObjectUrl;

/// The prefixes an operator allows; a URL is allowed when it lies under one of them, compared
/// by whole path segments so that `s3://bucket/team` does not allow `s3://bucket/team-other`.
#[derive(Clone, Debug, Default)]
pub struct AllowedPrefixes {
    prefixes: Vec<ObjectUrl>,
}

impl AllowedPrefixes {
    /// An allow-list of the given prefixes, each a URL validated like a dataset's.
    pub fn new<S: AsRef<str>>(prefixes: &[S]) -> Result<Self, RemoteError> {
        let prefixes = prefixes
            .iter()
            .map(|prefix| ObjectUrl::parse(prefix.as_ref()))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self { prefixes })
    }

    pub fn prefixes(&self) -> &[ObjectUrl] {
        &self.prefixes
    }

    /// Accepts a URL under an allowed prefix; refuses any other with an error naming the rule.
    pub fn check(&self, url: &ObjectUrl) -> Result<(), RemoteError> {
        match self.refusal(url) {
            None => Ok(()),
            Some(rule) => Err(RemoteError::NotAllowed {
                url: url.to_string(),
                rule,
            }),
        }
    }

    /// The rule that refuses `url`, or None where it lies under an allowed prefix.
    pub(crate) fn refusal(&self, url: &ObjectUrl) -> Option<String> {
        if self.prefixes.iter().any(|prefix| is_under(url, prefix)) {
            return None;
        }
        Some(if self.prefixes.is_empty() {
            "no remote prefix is allowed (the operator's allow-list is empty)".to_owned()
        } else {
            let listed: Vec<&str> = self.prefixes.iter().map(ObjectUrl::as_str).collect();
            format!("the operator allows only {}", listed.join(", "))
        })
    }
}

fn is_under(url: &ObjectUrl, prefix: &ObjectUrl) -> bool {
    let (url_origin, url_path) = url.origin_and_path();
    let (prefix_origin, prefix_path) = prefix.origin_and_path();
    if url_origin != prefix_origin {
        return false;
    }
    match url_path.strip_prefix(prefix_path) {
        Some(rest) => rest.is_empty() || prefix_path.ends_with('/') || rest.starts_with('/'),
        None => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn url(text: &str) -> ObjectUrl {
        ObjectUrl::parse(text).expect(text)
    }

    #[test]
    fn allows_by_whole_segments() {
        let allowed = AllowedPrefixes::new(&["s3://campaigns/team", "https://data.example/scans/"])
            .expect("rules");
        assert!(allowed
            .check(&url("s3://campaigns/team/site.copc.laz"))
            .is_ok());
        assert!(allowed.check(&url("s3://campaigns/team")).is_ok());
        assert!(allowed
            .check(&url("https://data.example/scans/a.laz"))
            .is_ok());
        for refused in [
            "s3://campaigns/team-other/a.laz",
            "s3://other/team/a.laz",
            "https://data.example:8443/scans/a.laz",
            "http://data.example/scans/a.laz",
        ] {
            let error = allowed.check(&url(refused)).expect_err(refused).to_string();
            assert!(error.contains("allows only s3://campaigns/team"), "{error}");
        }
    }

    #[test]
    fn an_empty_list_says_so() {
        let error = AllowedPrefixes::default()
            .check(&url("s3://campaigns/a.laz"))
            .expect_err("empty")
            .to_string();
        assert!(error.contains("allow-list is empty"), "{error}");
    }
}
