//! The webhook endpoints an operator configures: a URL, the secret that signs what is sent
//! there, and the job ends it is told of. Everything is checked when the daemon starts, so a
//! mistake refuses the start instead of losing events later.

use std::fmt;
use std::path::PathBuf;

use reqwest::Url;
use serde::Deserialize;

/// How a job ended, as the events and the `events` setting name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobEnd {
    Succeeded,
    Failed,
    Cancelled,
}

impl JobEnd {
    pub const ALL: [JobEnd; 3] = [JobEnd::Succeeded, JobEnd::Failed, JobEnd::Cancelled];

    /// The event's name in `X-Pointfarm-Event` and the body's `event`.
    pub fn event(self) -> &'static str {
        match self {
            JobEnd::Succeeded => "job.succeeded",
            JobEnd::Failed => "job.failed",
            JobEnd::Cancelled => "job.cancelled",
        }
    }
}

/// Where an endpoint's secret is read from at start: never the command line, whose
/// arguments any user of the host can list.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SecretSource {
    /// A file, whose surrounding whitespace (its final newline) is not part of the secret.
    File(PathBuf),
    /// An environment variable of the daemon.
    Env(String),
}

/// One endpoint as configured, before it is checked; the `[[serve.webhook]]` table's keys.
#[derive(Clone, Debug, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WebhookSpec {
    pub url: String,
    #[serde(default)]
    pub secret_file: Option<PathBuf>,
    #[serde(default)]
    pub secret_env: Option<String>,
    /// The job ends sent there; all of them when not given.
    #[serde(default)]
    pub events: Option<Vec<JobEnd>>,
}

impl WebhookSpec {
    /// An endpoint told of every job end, its secret read from `secret`.
    pub fn new(url: &str, secret: Option<SecretSource>) -> Self {
        let (secret_file, secret_env) = match secret {
            Some(SecretSource::File(path)) => (Some(path), None),
            Some(SecretSource::Env(name)) => (None, Some(name)),
            None => (None, None),
        };
        Self {
            url: url.to_owned(),
            secret_file,
            secret_env,
            events: None,
        }
    }
}

/// The key that signs deliveries; its `Debug` shows nothing of it, so that it cannot reach a
/// log through the configuration.
#[derive(Clone, PartialEq, Eq)]
pub struct WebhookSecret(Vec<u8>);

impl WebhookSecret {
    /// The secret in `bytes` without surrounding whitespace; none when nothing is left.
    pub fn from_bytes(bytes: &[u8]) -> Option<Self> {
        let trimmed = bytes.trim_ascii();
        (!trimmed.is_empty()).then(|| Self(trimmed.to_vec()))
    }

    pub(crate) fn bytes(&self) -> &[u8] {
        &self.0
    }
}

impl fmt::Debug for WebhookSecret {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("WebhookSecret(redacted)")
    }
}

/// A checked endpoint: an http(s) URL, its secret, the job ends it wants.
#[derive(Clone)]
pub struct WebhookEndpoint {
    url: Url,
    secret: WebhookSecret,
    events: Vec<JobEnd>,
}

/// Shows the URL as logs do ([`shown_url`]) and nothing of the secret: the daemon's
/// configuration, which holds the endpoints, may be printed whole.
impl fmt::Debug for WebhookEndpoint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("WebhookEndpoint")
            .field("url", &self.shown_url())
            .field("secret", &self.secret)
            .field("events", &self.events)
            .finish()
    }
}

/// Why an endpoint was refused; each names the endpoint by [`shown_url`] and never holds the
/// secret.
#[derive(Debug, thiserror::Error)]
pub enum WebhookConfigError {
    #[error("webhook `{url}`: not a URL ({reason})")]
    NotAUrl { url: String, reason: String },
    #[error("webhook {url}: the URL must be http:// or https://, not {scheme}://")]
    Scheme { url: String, scheme: String },
    #[error("webhook {url}: no secret to sign its deliveries (secret_file or secret_env)")]
    NoSecret { url: String },
    #[error("webhook {url}: give its secret once, by secret_file or by secret_env")]
    TwoSecrets { url: String },
    #[error("webhook {url}: its secret file {path} cannot be read: {reason}")]
    SecretFile {
        url: String,
        path: String,
        reason: String,
    },
    #[error("webhook {url}: its secret file {path} is empty")]
    EmptySecretFile { url: String, path: String },
    #[error("webhook {url}: its secret variable {name} is not set")]
    NoSecretVariable { url: String, name: String },
    #[error("webhook {url}: its secret variable {name} is empty")]
    EmptySecretVariable { url: String, name: String },
    #[error("webhook {url}: `events` lists no event; leave it out for all of them")]
    NoEvents { url: String },
}

impl WebhookEndpoint {
    /// Checks `spec` and reads its secret, from the file or the environment variable it names.
    pub fn load(spec: &WebhookSpec) -> Result<Self, WebhookConfigError> {
        Self::load_with_env(spec, |name| std::env::var_os(name))
    }

    /// [`WebhookEndpoint::load`], the environment read through `env`.
    pub(crate) fn load_with_env(
        spec: &WebhookSpec,
        env: impl FnOnce(&str) -> Option<std::ffi::OsString>,
    ) -> Result<Self, WebhookConfigError> {
        let url = Url::parse(spec.url.trim()).map_err(|e| WebhookConfigError::NotAUrl {
            url: shown_text(&spec.url),
            reason: e.to_string(),
        })?;
        let shown = shown_url(&url);
        if !matches!(url.scheme(), "http" | "https") {
            return Err(WebhookConfigError::Scheme {
                scheme: url.scheme().to_owned(),
                url: shown,
            });
        }
        if !url.has_host() {
            return Err(WebhookConfigError::NotAUrl {
                url: shown,
                reason: "no host".into(),
            });
        }
        let secret = match (&spec.secret_file, &spec.secret_env) {
            (Some(_), Some(_)) => return Err(WebhookConfigError::TwoSecrets { url: shown }),
            (None, None) => return Err(WebhookConfigError::NoSecret { url: shown }),
            (Some(path), None) => {
                let bytes = std::fs::read(path).map_err(|e| WebhookConfigError::SecretFile {
                    url: shown.clone(),
                    path: path.display().to_string(),
                    reason: e.to_string(),
                })?;
                WebhookSecret::from_bytes(&bytes).ok_or_else(|| {
                    WebhookConfigError::EmptySecretFile {
                        url: shown.clone(),
                        path: path.display().to_string(),
                    }
                })?
            }
            (None, Some(name)) => {
                let value = env(name).ok_or_else(|| WebhookConfigError::NoSecretVariable {
                    url: shown.clone(),
                    name: name.clone(),
                })?;
                WebhookSecret::from_bytes(value.as_encoded_bytes()).ok_or_else(|| {
                    WebhookConfigError::EmptySecretVariable {
                        url: shown.clone(),
                        name: name.clone(),
                    }
                })?
            }
        };
        let mut events = spec.events.clone().unwrap_or_else(|| JobEnd::ALL.to_vec());
        events.dedup();
        if events.is_empty() {
            return Err(WebhookConfigError::NoEvents { url: shown });
        }
        Ok(Self {
            url,
            secret,
            events,
        })
    }

    pub fn url(&self) -> &Url {
        &self.url
    }

    /// The URL as logs show it ([`shown_url`]).
    pub fn shown_url(&self) -> String {
        shown_url(&self.url)
    }

    pub(crate) fn secret(&self) -> &WebhookSecret {
        &self.secret
    }

    pub fn wants(&self, end: JobEnd) -> bool {
        self.events.contains(&end)
    }
}

/// `url` without its user, password, query and fragment: what a log or an error may show of
/// an endpoint, since a URL can carry credentials there.
pub fn shown_url(url: &Url) -> String {
    let mut shown = url.clone();
    let _ = shown.set_username("");
    let _ = shown.set_password(None);
    shown.set_query(None);
    shown.set_fragment(None);
    shown.to_string()
}

/// [`shown_url`] of text that is no URL: without what could be a user and password (up to an
/// `@`) or a query.
fn shown_text(text: &str) -> String {
    let text = text.trim();
    let text = text.split(['?', '#']).next().unwrap_or_default();
    match (text.find("://"), text.rfind('@')) {
        (Some(scheme_end), Some(at)) if at > scheme_end => {
            format!("{}{}", &text[..scheme_end + 3], &text[at + 1..])
        }
        (None, Some(at)) => text[at + 1..].to_owned(),
        _ => text.to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn secret_file(contents: &[u8]) -> (tempfile::TempDir, PathBuf) {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("secret");
        std::fs::write(&path, contents).expect("write the secret");
        (dir, path)
    }

    fn load(spec: &WebhookSpec) -> Result<WebhookEndpoint, String> {
        WebhookEndpoint::load_with_env(spec, |name| {
            (name == "HOOK_SECRET").then(|| "from-env\n".into())
        })
        .map_err(|e| e.to_string())
    }

    /// The endpoint at `url` whose secret file holds `secret`, which must be accepted.
    fn accepted_with_secret_file(url: &str, secret: &[u8]) -> WebhookEndpoint {
        let (_dir, path) = secret_file(secret);
        load(&WebhookSpec::new(url, Some(SecretSource::File(path)))).expect("accepted")
    }

    #[test]
    fn a_good_endpoint_reads_its_secret_without_the_final_newline() {
        let endpoint = accepted_with_secret_file("https://ci.example/hook", b"s3cret\n");
        assert_eq!(endpoint.secret().bytes(), b"s3cret");
        assert!(JobEnd::ALL.iter().all(|end| endpoint.wants(*end)));
        let from_env = load(&WebhookSpec::new(
            "http://127.0.0.1:8080/",
            Some(SecretSource::Env("HOOK_SECRET".into())),
        ))
        .expect("accepted");
        assert_eq!(from_env.secret().bytes(), b"from-env");
    }

    #[test]
    fn a_bad_endpoint_is_refused_naming_it_and_why() {
        let (_dir, path) = secret_file(b"s3cret");
        let (_empty_dir, empty) = secret_file(b" \n");
        let file = || Some(SecretSource::File(path.clone()));
        let cases = [
            (
                WebhookSpec::new("ftp://ci.example/hook", file()),
                "must be http:// or https://",
            ),
            (WebhookSpec::new("ci.example/hook", file()), "not a URL"),
            (
                WebhookSpec::new("https://ci.example/hook", None),
                "no secret",
            ),
            (
                WebhookSpec::new(
                    "https://ci.example/hook",
                    Some(SecretSource::File("/nonexistent/pointfarm-secret".into())),
                ),
                "/nonexistent/pointfarm-secret cannot be read",
            ),
            (
                WebhookSpec::new("https://ci.example/hook", Some(SecretSource::File(empty))),
                "is empty",
            ),
            (
                WebhookSpec::new(
                    "https://ci.example/hook",
                    Some(SecretSource::Env("UNSET_SECRET".into())),
                ),
                "UNSET_SECRET is not set",
            ),
            (
                WebhookSpec {
                    secret_env: Some("HOOK_SECRET".into()),
                    ..WebhookSpec::new("https://ci.example/hook", file())
                },
                "give its secret once",
            ),
            (
                WebhookSpec {
                    events: Some(Vec::new()),
                    ..WebhookSpec::new("https://ci.example/hook", file())
                },
                "lists no event",
            ),
        ];
        for (spec, reason) in cases {
            let refused = load(&spec).expect_err(&spec.url);
            assert!(refused.starts_with("webhook "), "{refused}");
            assert!(refused.contains(reason), "{refused}");
            if spec.url.contains("ci.example") {
                assert!(refused.contains("ci.example/hook"), "{refused}");
            }
        }
    }

    /// Credentials in a URL stay out of what logs and errors show, and so does the secret.
    #[test]
    fn neither_the_secret_nor_the_urls_credentials_are_shown() {
        let endpoint =
            accepted_with_secret_file("https://user:pass@ci.example/hook?token=abc#x", b"s3cret");
        assert_eq!(endpoint.shown_url(), "https://ci.example/hook");
        let debug = format!("{endpoint:?}");
        assert!(debug.contains("https://ci.example/hook"), "{debug}");
        for hidden in ["s3cret", "pass", "abc"] {
            assert!(!debug.contains(hidden), "{debug}");
        }
        for url in [
            "ftp://user:pass@ci.example/x?token=abc",
            "https://user:pass@[ci.example/x?token=abc",
        ] {
            let refused = load(&WebhookSpec::new(url, None)).expect_err("refused");
            assert!(refused.contains("ci.example/x"), "{refused}");
            assert!(
                !refused.contains("pass") && !refused.contains("abc"),
                "{refused}"
            );
        }
    }

    #[test]
    fn events_are_parsed_by_name_and_unknown_keys_refused() {
        let spec: WebhookSpec =
            serde_json::from_str(r#"{"url": "https://x.example/", "events": ["failed"]}"#)
                .expect("parses");
        assert_eq!(spec.events, Some(vec![JobEnd::Failed]));
        let unknown = serde_json::from_str::<WebhookSpec>(r#"{"url": "u", "secret": "s"}"#)
            .expect_err("refused");
        assert!(
            unknown.to_string().contains("unknown field `secret`"),
            "{unknown}"
        );
        let event = serde_json::from_str::<WebhookSpec>(r#"{"url": "u", "events": ["done"]}"#)
            .expect_err("refused");
        assert!(
            event.to_string().contains("unknown variant `done`"),
            "{event}"
        );
    }
}
