//! Wrong tokens from one address, over real HTTP: slowed, then refused with 429 and
//! `Retry-After`, the right token too, until the window has passed; the daemon's log names
//! the address, never the token. A daemon without a client token opens its dashboard, but
//! not to other sites; over TLS the session cookie is `Secure`.

use std::process::Command;
use std::time::{Duration, Instant};

use pointfarm_daemon::access::Access;
use pointfarm_daemon::dashboard::LoginLimit;

use pointfarm_tests::tools::wait_until_listening;
use pointfarm_tests::{free_address, ServeProcess};

use super::farm::Farm;
use super::webdriver::{request, Answer};
use super::{serve, TOKEN, WORKER_TOKEN};

/// Posts `token` to the login form of the dashboard at `dashboard`, from its own page.
fn log_in_with(dashboard: &str, token: &str) -> Answer {
    let origin = format!("http://{dashboard}");
    let headers = [
        ("Origin", origin.as_str()),
        ("Content-Type", "application/x-www-form-urlencoded"),
    ];
    let body = format!("token={token}&next=%2F");
    request(dashboard, "POST", "/login", &headers, &body)
}

fn retry_after(answer: &Answer) -> u64 {
    answer.header("retry-after").parse().unwrap_or_else(|_| {
        panic!(
            "a Retry-After in seconds: {:?}",
            answer.header("retry-after")
        )
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_tokens_are_slowed_then_refused_until_the_window_has_passed() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let limit = LoginLimit {
        failures_before_slowing: 1,
        delay_per_failure: Duration::from_millis(400),
        failures_before_refusing: 3,
        window: Duration::from_secs(3),
        addresses: 100,
    };
    let access = Access::new(Some(TOKEN), Some(WORKER_TOKEN));
    let farm = Farm::start(scratch.path(), |_| {}, access, limit).await;
    let dashboard = farm.dashboard.clone();
    tokio::task::spawn_blocking(move || {
        // The worker token is no guess: it counts nothing.
        for _ in 0..limit.failures_before_refusing {
            assert_eq!(log_in_with(&dashboard, WORKER_TOKEN).status, 403);
        }
        let mut took = Vec::new();
        for _ in 0..limit.failures_before_refusing {
            let started = Instant::now();
            let refused = log_in_with(&dashboard, "guess");
            assert_eq!(refused.status, 401, "{}", refused.body);
            took.push(started.elapsed());
        }
        assert!(took[0] < limit.delay_per_failure, "{took:?}");
        assert!(took[1] >= limit.delay_per_failure, "slowed: {took:?}");
        assert!(
            took[2] >= limit.delay_per_failure * 2,
            "slowed more: {took:?}"
        );

        // Refused now, the right token too, by the form and as a bearer token.
        let refused = log_in_with(&dashboard, TOKEN);
        assert_eq!(refused.status, 429, "{}", refused.body);
        assert!(refused.header("set-cookie").is_empty());
        assert!(
            refused.body.contains("Too many wrong tokens"),
            "{}",
            refused.body
        );
        let seconds = retry_after(&refused);
        assert!((1..=limit.window.as_secs()).contains(&seconds), "{seconds}");
        let bearer = format!("Bearer {TOKEN}");
        let list_jobs = || {
            request(
                &dashboard,
                "GET",
                "/api/jobs",
                &[("Authorization", &bearer)],
                "",
            )
        };
        let api = list_jobs();
        assert_eq!(api.status, 429, "{}", api.body);
        assert!(retry_after(&api) >= 1);

        // After the window, the right token works.
        std::thread::sleep(Duration::from_secs(seconds));
        let admitted = log_in_with(&dashboard, TOKEN);
        assert_eq!(admitted.status, 303, "{}", admitted.body);
        assert!(!admitted.header("set-cookie").is_empty());
        let api = list_jobs();
        assert_eq!(api.status, 200, "{}", api.body);
    })
    .await
    .expect("the requests");
}

/// With `serve`'s own limit: wrong bearer tokens at once from one address lock it out, and
/// the log says so by address without the token.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_refuses_an_address_after_its_wrong_tokens_and_logs_no_token() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let (server, dashboard) = serve(&scratch.path().join("data"), &["--no-embedded-worker"]);
    let limit = LoginLimit::DEFAULT;
    let guess = "Bearer guessed-token-4f1d";
    std::thread::scope(|threads| {
        for _ in 0..limit.failures_before_refusing {
            threads.spawn(|| {
                let refused = request(
                    &dashboard,
                    "GET",
                    "/api/jobs",
                    &[("Authorization", guess)],
                    "",
                );
                assert_eq!(refused.status, 401, "{}", refused.body);
            });
        }
    });
    let refused = log_in_with(&dashboard, TOKEN);
    assert_eq!(refused.status, 429, "{}", refused.body);
    let seconds = retry_after(&refused);
    let window = limit.window.as_secs();
    assert!((window - 60..=window).contains(&seconds), "{seconds}");
    let log = server.log();
    let logged: Vec<&str> = log
        .lines()
        .filter(|line| line.contains("a wrong dashboard token"))
        .collect();
    assert_eq!(
        logged.len(),
        limit.failures_before_refusing as usize,
        "{log}"
    );
    assert!(
        logged.iter().all(|line| line.contains("127.0.0.1")),
        "{logged:?}"
    );
    assert!(!log.contains("guessed-token-4f1d"), "{log}");
}

/// A daemon without a client token (loopback development) opens its dashboard as it opens
/// its API, but still takes changes only from the dashboard's own origin.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_open_daemon_opens_its_dashboard_but_not_to_other_sites() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let dashboard = free_address();
    let _server = ServeProcess::start_with(
        &scratch.path().join("data"),
        &["--no-embedded-worker", "--dashboard-listen", &dashboard],
    );
    wait_until_listening(&dashboard, Duration::from_secs(30), "the dashboard");
    let page = request(&dashboard, "GET", "/", &[], "");
    assert_eq!(page.status, 200, "{}", page.body);
    let foreign = request(
        &dashboard,
        "POST",
        "/api/jobs/job-000000000001/cancel",
        &[("Origin", "http://evil.example")],
        "",
    );
    assert_eq!(foreign.status, 403, "{}", foreign.body);
}

/// Over TLS (the API's certificate) the session cookie is `Secure`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn over_tls_the_session_cookie_is_secure() {
    if Command::new("curl").arg("--version").output().is_err() {
        eprintln!("skipped: no curl to speak HTTPS with");
        return;
    }
    let scratch = tempfile::tempdir().expect("tempdir");
    let pki = pointfarm_tests::pki::TestPki::create(scratch.path());
    let cert = pki.cert.to_str().expect("a UTF-8 path");
    let key = pki.key.to_str().expect("a UTF-8 path");
    let args = ["--no-embedded-worker", "--tls-cert", cert, "--tls-key", key];
    let (_server, dashboard) = serve(&scratch.path().join("data"), &args);
    let origin = format!("Origin: https://{dashboard}");
    let output = Command::new("curl")
        .args(["-s", "-i", "--cacert"])
        .arg(&pki.ca)
        .args(["-H", &origin, "--data", &format!("token={TOKEN}")])
        .arg(format!("https://{dashboard}/login"))
        .output()
        .expect("curl");
    let answer = String::from_utf8_lossy(&output.stdout);
    assert!(answer.starts_with("HTTP/1.1 303"), "{answer}");
    let cookie = answer
        .lines()
        .find(|line| line.to_ascii_lowercase().starts_with("set-cookie:"))
        .unwrap_or_else(|| panic!("no cookie: {answer}"));
    for attribute in ["Secure", "HttpOnly", "SameSite=Strict"] {
        assert!(cookie.contains(attribute), "{cookie}");
    }
}
