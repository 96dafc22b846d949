//! Which redirects an HTTP(S) server may send a reader to. A server that answers `302` to
//! another host would otherwise make the reader fetch an address nobody chose (an internal
//! host, a cloud metadata endpoint), around the operator's allow-list. So a redirect is
//! followed only within the origin (scheme, host and port) of the URL asked, where the server
//! could have answered the bytes itself, and, where an allow-list is given, only to a target
//! under one of its prefixes; a loop, too many hops or any other target fails the request,
//! naming the redirect and the rule, and is never retried.

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;

use object_store::client::{
    HttpClient, HttpConnector, HttpError, HttpErrorKind, HttpRequest, HttpResponse, HttpService,
};
use object_store::{ClientConfigKey, ClientOptions};
use url::Url;

use super::allow::AllowedPrefixes;
use super::error::RedirectRefused;
use super::settings::RemoteSettings;
use super::url::ObjectUrl;

/// Where a reader follows an HTTP redirect.
#[derive(Clone, Debug, Default)]
pub(crate) enum RedirectRule {
    /// To the origin of the URL asked only.
    #[default]
    SameOrigin,
    /// To the origin of the URL asked, and under one of these prefixes.
    WithinPrefixes(AllowedPrefixes),
}

impl RedirectRule {
    /// Whether the hop to `target`, after the URLs of `previous` (the first the one asked),
    /// may be followed.
    fn check(&self, previous: &[Url], target: &Url, max: usize) -> Result<(), RedirectRefused> {
        let refused = |reason: String| RedirectRefused {
            target: shown(target),
            reason,
        };
        let Some(asked) = previous.first() else {
            return Ok(());
        };
        if previous.iter().any(|hop| same_resource(hop, target)) {
            return Err(refused(format!(
                "the redirects loop back to {}",
                shown(target)
            )));
        }
        if previous.len() > max {
            return Err(refused(format!("more than {max} redirects")));
        }
        if target.origin() != asked.origin() {
            return Err(refused(format!(
                "pointfarm follows a redirect only within the origin asked ({}); give the \
                 URL it redirects to instead, where it is meant",
                asked.origin().ascii_serialization()
            )));
        }
        if let RedirectRule::WithinPrefixes(allowed) = self {
            let mut bare = target.clone();
            bare.set_query(None);
            bare.set_fragment(None);
            let rule = match ObjectUrl::parse(bare.as_str()) {
                Ok(url) => allowed.refusal(&url),
                Err(error) => Some(error.to_string()),
            };
            if let Some(rule) = rule {
                return Err(refused(format!("not under an allowed prefix: {rule}")));
            }
        }
        Ok(())
    }
}

/// Whether two URLs name the same resource, queries aside (a loop may count up a parameter).
fn same_resource(a: &Url, b: &Url) -> bool {
    a.origin() == b.origin() && a.path() == b.path()
}

/// A URL as it may be logged: no credentials, query or fragment (a signature hides there).
pub(crate) fn shown(url: &Url) -> String {
    let mut bare = url.clone();
    let had_query = bare.query().is_some();
    bare.set_query(None);
    bare.set_fragment(None);
    // Only URLs with a host carry credentials; setting them on others fails harmlessly.
    let _ = bare.set_username("");
    let _ = bare.set_password(None);
    let mut text = bare.to_string();
    if had_query {
        text.push_str("?…");
    }
    text
}

/// The HTTP client of an `http(s)://` store: what object_store's own builds (the settings'
/// timeouts, plain HTTP only where the builder allows it, the platform's TLS roots, no
/// transparent decompression, which would break sizes), with the redirect rule as its policy.
#[derive(Debug)]
pub(crate) struct RedirectingConnector {
    rule: Arc<RedirectRule>,
    settings: RemoteSettings,
}

impl RedirectingConnector {
    pub(crate) fn new(rule: Arc<RedirectRule>, settings: &RemoteSettings) -> Self {
        Self {
            rule,
            settings: settings.clone(),
        }
    }
}

impl HttpConnector for RedirectingConnector {
    fn connect(&self, options: &ClientOptions) -> object_store::Result<HttpClient> {
        let allow_http = options
            .get_config_value(&ClientConfigKey::AllowHttp)
            .is_some_and(|value| value.eq_ignore_ascii_case("true"));
        let rule = Arc::clone(&self.rule);
        let max = self.settings.max_redirects;
        let policy = reqwest::redirect::Policy::custom(move |attempt| {
            match rule.check(attempt.previous(), attempt.url(), max) {
                Ok(()) => attempt.follow(),
                Err(refused) => {
                    tracing::warn!(%refused, "a redirect is refused");
                    attempt.error(refused)
                }
            }
        });
        let client = reqwest::Client::builder()
            .user_agent(concat!("pointfarm/", env!("CARGO_PKG_VERSION")))
            .connect_timeout(self.settings.connect_timeout)
            .timeout(self.settings.request_timeout)
            .no_gzip()
            .no_brotli()
            .no_zstd()
            .no_deflate()
            .https_only(!allow_http)
            .redirect(policy)
            .build()
            .map_err(|error| object_store::Error::Generic {
                store: "HTTP",
                source: Box::new(error),
            })?;
        Ok(HttpClient::new(UnfollowedRedirects { client }))
    }
}

/// The reqwest client, turning a redirect it did not follow (one to a scheme it does not
/// speak, such as `file://`) into a refusal that names the target, as the policy's are.
#[derive(Debug)]
struct UnfollowedRedirects {
    client: reqwest::Client,
}

impl HttpService for UnfollowedRedirects {
    // What `#[async_trait]` makes of `async fn call`, written out to need no macro.
    fn call<'life0, 'async_trait>(
        &'life0 self,
        request: HttpRequest,
    ) -> Pin<Box<dyn Future<Output = Result<HttpResponse, HttpError>> + Send + 'async_trait>>
    where
        'life0: 'async_trait,
        Self: 'async_trait,
    {
        Box::pin(async move {
            let asked = request.uri().to_string();
            let response = HttpService::call(&self.client, request).await?;
            let status = response.status();
            let location = response
                .headers()
                .get("location")
                .and_then(|value| value.to_str().ok());
            match location {
                Some(location) if status.is_redirection() && status.as_u16() != 304 => {
                    let target = Url::parse(&asked).and_then(|base| base.join(location));
                    let refused = RedirectRefused {
                        target: target
                            .as_ref()
                            .map_or_else(|_| "an invalid URL".into(), shown),
                        reason: "pointfarm follows redirects to http:// and https:// URLs only"
                            .to_owned(),
                    };
                    tracing::warn!(%refused, "a redirect is refused");
                    Err(HttpError::new(HttpErrorKind::Unknown, refused))
                }
                _ => Ok(response),
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn url(text: &str) -> Url {
        Url::parse(text).expect(text)
    }

    fn check(rule: &RedirectRule, chain: &[&str], target: &str) -> Result<(), String> {
        let previous: Vec<Url> = chain.iter().map(|hop| url(hop)).collect();
        rule.check(&previous, &url(target), 5)
            .map_err(|refused| refused.to_string())
    }

    #[test]
    fn only_the_origin_asked_is_followed() {
        let rule = RedirectRule::SameOrigin;
        let asked = ["https://data.example/scans/a.laz"];
        assert!(check(&rule, &asked, "https://data.example/moved/a.laz?sig=1").is_ok());
        for other in [
            "https://cdn.example/scans/a.laz",
            "http://data.example/scans/a.laz",
            "https://data.example:8443/scans/a.laz",
            "http://169.254.169.254/latest/meta-data/",
            "file:///etc/passwd",
        ] {
            let error = check(&rule, &asked, other).expect_err(other);
            assert!(error.contains("only within the origin asked"), "{error}");
        }
    }

    #[test]
    fn the_allow_list_bounds_the_paths_too() {
        let allowed = AllowedPrefixes::new(&["http://data.example/scans/"]).expect("rule");
        let rule = RedirectRule::WithinPrefixes(allowed);
        let asked = ["http://data.example/scans/a.laz"];
        assert!(check(&rule, &asked, "http://data.example/scans/old/a.laz").is_ok());
        let error = check(&rule, &asked, "http://data.example/private/a.laz").expect_err("out");
        assert!(
            error.contains("allows only http://data.example/scans/"),
            "{error}"
        );
    }

    #[test]
    fn loops_and_long_chains_stop() {
        let rule = RedirectRule::SameOrigin;
        let chain = ["http://h/a", "http://h/b"];
        let error = check(&rule, &chain, "http://h/a?n=2").expect_err("loop");
        assert!(error.contains("loop back to http://h/a?…"), "{error}");
        let long: Vec<String> = (0..6).map(|n| format!("http://h/{n}")).collect();
        let long: Vec<&str> = long.iter().map(String::as_str).collect();
        let error = check(&rule, &long, "http://h/next").expect_err("long");
        assert!(error.contains("more than 5 redirects"), "{error}");
    }

    #[test]
    fn a_target_is_shown_without_secrets() {
        let shown = shown(&url(
            "https://user:pw@cdn.example/a.laz?X-Amz-Signature=s#f",
        ));
        assert_eq!(shown, "https://cdn.example/a.laz?…");
    }
}
