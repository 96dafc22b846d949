//! Delivering events: a thread of its own runs a small tokio runtime with one task per
//! endpoint, fed by a bounded queue, so that the scheduler only ever hands an event over and a
//! slow or dead endpoint holds up nothing but its own deliveries. Each delivery is a signed
//! POST, tried again with exponential backoff and jitter (or the endpoint's `Retry-After`) on
//! connection errors, timeouts, 5xx and 429, and given up after [`ATTEMPTS`].

use std::sync::{Arc, Once};
use std::time::Duration;

use hmac::{Hmac, Mac};
use reqwest::header::{HeaderMap, HeaderValue, CONTENT_TYPE, RETRY_AFTER};
use reqwest::StatusCode;
use sha2::Sha256;
use tokio::sync::{mpsc, Semaphore};

use super::config::{JobEnd, WebhookEndpoint, WebhookSecret};
use crate::metrics::WebhookCounters;

/// Tries of one delivery, the first included: about a minute of backoff with the waits below.
const ATTEMPTS: u32 = 6;
/// The wait before the first retry; each later one doubles it, up to [`LONGEST_WAIT`].
const FIRST_WAIT: Duration = Duration::from_secs(1);
const LONGEST_WAIT: Duration = Duration::from_secs(30);
/// The longest one try may take, connecting and the answer's head included: an endpoint that
/// accepts and never answers costs a delivery this much per try, and nobody else anything.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(10);
const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// Deliveries to one endpoint under way at once; more wait in its queue.
const IN_FLIGHT_PER_ENDPOINT: usize = 4;
/// Events waiting for one endpoint; past it, new ones are dropped (and counted).
const QUEUE_PER_ENDPOINT: usize = 256;

/// A job's end as sent: the same body to every endpoint, signed with each one's secret.
#[derive(Debug)]
pub(crate) struct Event {
    pub(crate) end: JobEnd,
    pub(crate) job_id: String,
    pub(crate) body: Vec<u8>,
}

/// The scheduler's side of one endpoint's queue.
pub(crate) struct Queue {
    pub(crate) endpoint: Arc<WebhookEndpoint>,
    pub(crate) events: mpsc::Sender<Arc<Event>>,
}

/// Starts the delivery thread for `endpoints`; it ends once every queue is dropped and their
/// deliveries are done.
pub(crate) fn start(
    endpoints: &[WebhookEndpoint],
    counters: WebhookCounters,
) -> Result<Vec<Queue>, String> {
    install_tls_provider();
    let client = reqwest::Client::builder()
        .timeout(REQUEST_TIMEOUT)
        .connect_timeout(CONNECT_TIMEOUT)
        // A redirect would resend the signed body elsewhere; a moved endpoint is the
        // operator's to reconfigure.
        .redirect(reqwest::redirect::Policy::none())
        .user_agent(concat!("pointfarm/", env!("CARGO_PKG_VERSION")))
        .build()
        .map_err(|e| format!("the webhooks' HTTP client: {}", describe(&e)))?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| format!("the webhooks' runtime: {e}"))?;
    let mut queues = Vec::new();
    let mut receivers = Vec::new();
    for endpoint in endpoints {
        let endpoint = Arc::new(endpoint.clone());
        let (events, received) = mpsc::channel(QUEUE_PER_ENDPOINT);
        queues.push(Queue {
            endpoint: Arc::clone(&endpoint),
            events,
        });
        receivers.push((endpoint, received));
    }
    std::thread::Builder::new()
        .name("webhooks".into())
        .spawn(move || {
            runtime.block_on(async move {
                let tasks: Vec<_> = receivers
                    .into_iter()
                    .map(|(endpoint, received)| {
                        tokio::spawn(serve_endpoint(
                            client.clone(),
                            endpoint,
                            received,
                            counters.clone(),
                        ))
                    })
                    .collect();
                for task in tasks {
                    let _ = task.await;
                }
            });
        })
        .map_err(|e| format!("the webhooks' thread: {e}"))?;
    Ok(queues)
}

/// Ring as rustls' process-wide provider, once: reqwest asks for one, and ring is the provider
/// tonic's TLS and the reads of datasets by URL use, so all agree whichever comes first.
fn install_tls_provider() {
    static INSTALL: Once = Once::new();
    INSTALL.call_once(|| {
        // An error means another part of the process installed one first; that one serves.
        let _ = rustls::crypto::ring::default_provider().install_default();
    });
}

/// Delivers the events of one endpoint's queue, a few at a time, until the queue closes.
async fn serve_endpoint(
    client: reqwest::Client,
    endpoint: Arc<WebhookEndpoint>,
    mut received: mpsc::Receiver<Arc<Event>>,
    counters: WebhookCounters,
) {
    let in_flight = Arc::new(Semaphore::new(IN_FLIGHT_PER_ENDPOINT));
    while let Some(event) = received.recv().await {
        let Ok(permit) = Arc::clone(&in_flight).acquire_owned().await else {
            return;
        };
        let (client, endpoint, counters) =
            (client.clone(), Arc::clone(&endpoint), counters.clone());
        tokio::spawn(async move {
            deliver(&client, &endpoint, &event, &counters).await;
            drop(permit);
        });
    }
    // The deliveries under way finish before the thread ends.
    let _ = in_flight.acquire_many(IN_FLIGHT_PER_ENDPOINT as u32).await;
}

/// What one try came to.
enum Try {
    Delivered,
    /// Worth trying again: no connection, no answer in time, 5xx or 429; not before `after`
    /// when the answer's `Retry-After` asks for it.
    Retry {
        reason: String,
        after: Option<Duration>,
    },
    /// The endpoint refused the delivery itself (another 4xx, a redirect).
    Refused(String),
}

/// Delivers `event` to `endpoint`, retrying as [`backoff`] says; every failed try is logged
/// with the endpoint's shown URL, and the outcome counted.
async fn deliver(
    client: &reqwest::Client,
    endpoint: &WebhookEndpoint,
    event: &Event,
    counters: &WebhookCounters,
) {
    let delivery = delivery_id();
    let signature = signature(endpoint.secret(), &event.body);
    let webhook = endpoint.shown_url();
    let name = event.end.event();
    for attempt in 1..=ATTEMPTS {
        let (reason, after) = match try_once(client, endpoint, event, &delivery, &signature).await {
            Try::Delivered => {
                tracing::debug!(
                    %webhook, event = name, job = %event.job_id, %delivery, attempt,
                    "webhook delivered"
                );
                counters.delivered();
                return;
            }
            Try::Retry { reason, after } if attempt < ATTEMPTS => (reason, after),
            Try::Retry { reason, .. } | Try::Refused(reason) => {
                tracing::warn!(
                    %webhook, event = name, job = %event.job_id, %delivery, attempt, %reason,
                    "webhook delivery failed; giving up"
                );
                counters.failed();
                return;
            }
        };
        // An endpoint's own Retry-After is heeded, within the longest wait.
        let wait =
            backoff(attempt, rand::random()).max(after.unwrap_or_default().min(LONGEST_WAIT));
        tracing::warn!(
            %webhook, event = name, job = %event.job_id, %delivery, attempt, %reason,
            retry_in_s = wait.as_secs_f64(), "webhook delivery failed; trying again"
        );
        tokio::time::sleep(wait).await;
    }
}

async fn try_once(
    client: &reqwest::Client,
    endpoint: &WebhookEndpoint,
    event: &Event,
    delivery: &str,
    signature: &str,
) -> Try {
    let sent = client
        .post(endpoint.url().clone())
        .header(CONTENT_TYPE, HeaderValue::from_static("application/json"))
        .header("X-Pointfarm-Event", event.end.event())
        .header("X-Pointfarm-Delivery", delivery)
        .header("X-Pointfarm-Signature", signature)
        .body(event.body.clone())
        .send()
        .await;
    match sent {
        Ok(response) => judge(response.status(), retry_after(response.headers())),
        Err(error) if error.is_builder() => Try::Refused(describe(&error)),
        Err(error) => Try::Retry {
            reason: describe(&error),
            after: None,
        },
    }
}

/// Whether an answer delivered the event, is worth another try (not before `after`), or
/// refused it.
fn judge(status: StatusCode, after: Option<Duration>) -> Try {
    if status.is_success() {
        Try::Delivered
    } else if status.is_server_error() || status == StatusCode::TOO_MANY_REQUESTS {
        Try::Retry {
            reason: format!("answered {status}"),
            after,
        }
    } else {
        Try::Refused(format!("answered {status}"))
    }
}

/// The seconds a `Retry-After` header asks to wait (its HTTP-date form is not read).
fn retry_after(headers: &HeaderMap) -> Option<Duration> {
    let seconds = headers
        .get(RETRY_AFTER)?
        .to_str()
        .ok()?
        .trim()
        .parse()
        .ok()?;
    Some(Duration::from_secs(seconds))
}

/// The wait after failed try `attempt` (1 for the first): [`FIRST_WAIT`] doubled at each
/// try up to [`LONGEST_WAIT`], of which `jitter` (in 0..1) keeps between half and all, so
/// that deliveries failed together do not all come back at once.
pub(crate) fn backoff(attempt: u32, jitter: f64) -> Duration {
    let doublings = attempt.saturating_sub(1).min(16);
    let full = FIRST_WAIT.saturating_mul(1 << doublings).min(LONGEST_WAIT);
    full.mul_f64(0.5 + 0.5 * jitter.clamp(0.0, 1.0))
}

/// `X-Pointfarm-Signature`: `sha256=` and the hex HMAC-SHA256 of the body keyed by the secret,
/// which a receiver computes again to know the delivery is the daemon's and whole.
pub(crate) fn signature(secret: &WebhookSecret, body: &[u8]) -> String {
    // HMAC takes a key of any length: longer ones are hashed, shorter ones padded.
    let Ok(mut mac) = Hmac::<Sha256>::new_from_slice(secret.bytes()) else {
        unreachable!("HMAC-SHA256 accepts keys of every length")
    };
    mac.update(body);
    format!("sha256={}", crate::model::hex(&mac.finalize().into_bytes()))
}

/// `X-Pointfarm-Delivery`: 128 random bits, the same on every try of one delivery, so that a
/// receiver can tell a retry of something it already has.
fn delivery_id() -> String {
    format!("{:032x}", rand::random::<u128>())
}

/// An HTTP client's error with its causes but without its URL, which may carry credentials:
/// "cannot connect: client error (Connect): tcp connect error: Connection refused".
fn describe(error: &reqwest::Error) -> String {
    let mut text = String::from(if error.is_timeout() {
        "no answer in time"
    } else if error.is_connect() {
        "cannot connect"
    } else {
        "the request failed"
    });
    let mut source = std::error::Error::source(error);
    while let Some(cause) = source {
        text.push_str(": ");
        text.push_str(&cause.to_string());
        source = cause.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    /// RFC 4231, test case 2: the signature is HMAC-SHA256 of the raw body.
    #[test]
    fn the_signature_is_the_hmac_sha256_of_the_body() {
        let secret = WebhookSecret::from_bytes(b"Jefe").expect("a secret");
        assert_eq!(
            signature(&secret, b"what do ya want for nothing?"),
            "sha256=5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
        let other = WebhookSecret::from_bytes(b"Jeff").expect("a secret");
        assert_ne!(
            signature(&other, b"what do ya want for nothing?"),
            signature(&secret, b"what do ya want for nothing?")
        );
    }

    /// Waits double from a second up to half a minute; jitter keeps between half and all of
    /// each, and all the waits of one delivery add up to about a minute at most.
    #[test]
    fn the_backoff_doubles_up_to_a_bound_with_jitter_in_its_upper_half() {
        let longest: Vec<f64> = (1..ATTEMPTS)
            .map(|a| backoff(a, 1.0).as_secs_f64())
            .collect();
        assert_eq!(longest, [1.0, 2.0, 4.0, 8.0, 16.0]);
        let shortest: Vec<f64> = (1..ATTEMPTS)
            .map(|a| backoff(a, 0.0).as_secs_f64())
            .collect();
        assert_eq!(shortest, [0.5, 1.0, 2.0, 4.0, 8.0]);
        assert_eq!(backoff(7, 1.0), LONGEST_WAIT);
        assert_eq!(backoff(u32::MAX, 1.0), LONGEST_WAIT);
        assert_eq!(backoff(3, 7.0), backoff(3, 1.0));
        let total: f64 = longest.iter().sum();
        assert!((30.0..=60.0).contains(&total), "{total}");
    }

    #[test]
    fn only_server_errors_and_too_many_requests_are_tried_again() {
        let status = |code: u16| StatusCode::from_u16(code).expect("a status");
        let retried = |code: u16| matches!(judge(status(code), None), Try::Retry { .. });
        for code in [500, 502, 503, 504, 429] {
            assert!(retried(code), "{code}");
        }
        for code in [400, 401, 403, 404, 410, 301, 302] {
            assert!(!retried(code), "{code}");
            assert!(matches!(judge(status(code), None), Try::Refused(_)));
        }
        assert!(matches!(
            judge(StatusCode::NO_CONTENT, None),
            Try::Delivered
        ));
        let later = Some(Duration::from_secs(7));
        assert!(matches!(
            judge(StatusCode::TOO_MANY_REQUESTS, later),
            Try::Retry { after, .. } if after == later
        ));
    }

    #[test]
    fn retry_after_is_read_in_seconds() {
        let mut headers = HeaderMap::new();
        assert_eq!(retry_after(&headers), None);
        headers.insert(RETRY_AFTER, HeaderValue::from_static("120"));
        assert_eq!(retry_after(&headers), Some(Duration::from_secs(120)));
        headers.insert(
            RETRY_AFTER,
            HeaderValue::from_static("Wed, 21 Oct 2026 07:28:00 GMT"),
        );
        assert_eq!(retry_after(&headers), None);
    }

    #[test]
    fn delivery_ids_differ() {
        let ids: std::collections::HashSet<String> = (0..100).map(|_| delivery_id()).collect();
        assert_eq!(ids.len(), 100);
        assert!(ids.iter().all(|id| id.len() == 32));
    }
}
