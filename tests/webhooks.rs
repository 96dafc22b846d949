//! Webhooks end to end: `pointfarm serve` posts job ends to real HTTP servers on loopback
//! sockets, which record what they are sent and answer as each test scripts them: signed
//! events whose signature a receiver's own HMAC checks, each end for the endpoints that want
//! it, retries after 503s, an endpoint that never answers holding up nobody else, and a bad
//! configuration refusing the start.

use std::collections::{BTreeMap, VecDeque};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use hmac::{Hmac, Mac};
use pointfarm_proto::v1 as pb;
use pointfarm_tests::prometheus::scrape;
use pointfarm_tests::service::{
    cancel, jobs_on_a_sample, run_job, still_clipped_outside_the_sample, submit, turntable_job,
    watch_to_success,
};
use pointfarm_tests::{free_address, own_stderr_lines, pointfarm, wait_for, ServeProcess};
use sha2::Sha256;

const SECRET: &str = "hook-secret-7c1e";

/// One request as the server read it.
#[derive(Clone, Debug)]
struct Received {
    path: String,
    /// Header names in lower case.
    headers: BTreeMap<String, String>,
    body: Vec<u8>,
}

impl Received {
    fn header(&self, name: &str) -> &str {
        self.headers
            .get(name)
            .map(String::as_str)
            .unwrap_or_else(|| panic!("no {name} header in {:?}", self.headers))
    }

    fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body).expect("a JSON body")
    }
}

/// How the server answers: each request takes the next scripted status (200 once they run
/// out), or none at all for an endpoint that accepts and stalls.
#[derive(Clone, Copy, PartialEq)]
enum Answers {
    Scripted,
    Never,
}

#[derive(Default)]
struct Recorded {
    requests: Vec<Received>,
    statuses: VecDeque<u16>,
    /// Connections that stalled requests hold open, and whether each is still open.
    stalled_open: Vec<bool>,
}

/// A small HTTP/1.1 server on a loopback port, a thread per connection, keeping every request
/// it reads.
struct HookServer {
    url: String,
    recorded: Arc<Mutex<Recorded>>,
}

impl HookServer {
    fn start(answers: Answers, statuses: &[u16]) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").expect("a loopback port");
        let url = format!(
            "http://{}/hooks/pointfarm",
            listener.local_addr().expect("its address")
        );
        let recorded = Arc::new(Mutex::new(Recorded {
            statuses: statuses.iter().copied().collect(),
            ..Recorded::default()
        }));
        let shared = Arc::clone(&recorded);
        std::thread::spawn(move || {
            for stream in listener.incoming().flatten() {
                let recorded = Arc::clone(&shared);
                std::thread::spawn(move || serve_connection(stream, answers, &recorded));
            }
        });
        Self { url, recorded }
    }

    fn requests(&self) -> Vec<Received> {
        self.recorded.lock().expect("lock").requests.clone()
    }

    /// Waits (generously) until `count` requests have come, and returns them.
    fn wait_for_requests(&self, count: usize) -> Vec<Received> {
        wait_for(
            Duration::from_secs(120),
            &format!("{count} requests at {}", self.url),
            || {
                let requests = self.requests();
                (requests.len() >= count).then_some(requests)
            },
        )
    }
}

fn serve_connection(stream: TcpStream, answers: Answers, recorded: &Mutex<Recorded>) {
    let mut reader = BufReader::new(stream.try_clone().expect("clone the stream"));
    let mut writer = stream;
    // Keep-alive: requests follow one another on the connection until the client closes it.
    while let Some(request) = read_request(&mut reader) {
        let status = {
            let mut state = recorded.lock().expect("lock");
            state.requests.push(request);
            match answers {
                Answers::Scripted => state.statuses.pop_front().unwrap_or(200),
                Answers::Never => {
                    state.stalled_open.push(true);
                    let index = state.stalled_open.len() - 1;
                    drop(state);
                    // Never answer; note when the client gives up and closes.
                    let mut rest = Vec::new();
                    let _ = reader.read_to_end(&mut rest);
                    recorded.lock().expect("lock").stalled_open[index] = false;
                    return;
                }
            }
        };
        let answer = format!("HTTP/1.1 {status} Scripted\r\nContent-Length: 0\r\n\r\n");
        if writer.write_all(answer.as_bytes()).is_err() {
            return;
        }
    }
}

/// One request, or none when the client closed the connection.
fn read_request(reader: &mut impl BufRead) -> Option<Received> {
    let mut line = String::new();
    if reader.read_line(&mut line).ok()? == 0 {
        return None;
    }
    let path = line.split_whitespace().nth(1)?.to_owned();
    let mut headers = BTreeMap::new();
    loop {
        line.clear();
        reader.read_line(&mut line).ok()?;
        let header = line.trim_end();
        if header.is_empty() {
            break;
        }
        let (name, value) = header.split_once(':')?;
        headers.insert(name.trim().to_ascii_lowercase(), value.trim().to_owned());
    }
    let length: usize = headers
        .get("content-length")
        .map_or(Some(0), |n| n.parse().ok())?;
    let mut body = vec![0; length];
    reader.read_exact(&mut body).ok()?;
    Some(Received {
        path,
        headers,
        body,
    })
}

/// What a receiver does: HMAC-SHA256 of the raw body with the shared secret, compared in
/// constant time with `X-Pointfarm-Signature`.
fn assert_signed(request: &Received, secret: &str) {
    let signature = request.header("x-pointfarm-signature");
    let hex = signature
        .strip_prefix("sha256=")
        .unwrap_or_else(|| panic!("not a sha256= signature: {signature}"));
    let bytes: Vec<u8> = (0..hex.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).expect("hex"))
        .collect();
    let mut mac = Hmac::<Sha256>::new_from_slice(secret.as_bytes()).expect("a key");
    mac.update(&request.body);
    mac.verify_slice(&bytes)
        .expect("the signature is the HMAC of the body with the secret");
    let mut tampered = Hmac::<Sha256>::new_from_slice(secret.as_bytes()).expect("a key");
    tampered.update(&[request.body.as_slice(), b" "].concat());
    assert!(tampered.verify_slice(&bytes).is_err());
}

fn secret_file(dir: &Path) -> PathBuf {
    let path = dir.join("webhook-secret");
    std::fs::write(&path, format!("{SECRET}\n")).expect("write the secret");
    path
}

/// `serve` with `more` arguments and data in `scratch`, posting its jobs' ends to `hook` signed
/// with the secret it reads from a file there.
fn serve_posting_to(scratch: &Path, hook: &HookServer, more: &[&str]) -> ServeProcess {
    let secret = secret_file(scratch);
    let mut args = more.to_vec();
    args.extend([
        "--webhook",
        &hook.url,
        "--webhook-secret-file",
        secret.to_str().expect("a UTF-8 path"),
    ]);
    ServeProcess::start_with(&scratch.join("data"), &args)
}

/// `serve` with `more` arguments and data in `scratch`, reading `config` from a configuration
/// file it writes there.
fn serve_configured(scratch: &Path, config: &str, more: &[&str]) -> ServeProcess {
    let path = scratch.join("pointfarm.toml");
    std::fs::write(&path, config).expect("write the configuration");
    let mut args = more.to_vec();
    args.extend(["--config", path.to_str().expect("a UTF-8 path")]);
    ServeProcess::start_with(&scratch.join("data"), &args)
}

/// A job that succeeds is posted once to the webhook as `job.succeeded`, signed, with its
/// counts; the secret never reaches the daemon's log.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_that_succeeds_posts_one_signed_event() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let hook = HookServer::start(Answers::Scripted, &[]);
    let server = serve_posting_to(scratch.path(), &hook, &[]);
    let (mut jobs, dataset) = jobs_on_a_sample(&server.address, 5_000, 7).await;
    let job = submit(&mut jobs, turntable_job("hooked", &dataset.id, 2, 32, 24)).await;
    watch_to_success(&mut jobs, &job.id, || server.log()).await;

    let requests = hook.wait_for_requests(1);
    assert_eq!(requests.len(), 1, "{requests:?}");
    let request = &requests[0];
    assert_eq!(request.path, "/hooks/pointfarm");
    assert_eq!(request.header("content-type"), "application/json");
    assert_eq!(request.header("x-pointfarm-event"), "job.succeeded");
    assert_eq!(request.header("x-pointfarm-delivery").len(), 32);
    assert_signed(request, SECRET);
    let body = request.json();
    assert_eq!(body["event"], "job.succeeded");
    assert_eq!(body["job"]["id"], job.id.as_str());
    assert_eq!(body["job"]["requestId"], "hooked");
    assert_eq!(body["job"]["datasetId"], dataset.id.as_str());
    assert_eq!(body["job"]["state"], "JOB_STATE_SUCCEEDED");
    assert_eq!(body["job"]["framesDone"], 2);
    assert_eq!(body["job"]["framesTotal"], 2);
    assert_eq!(body["job"]["failedAttempts"], "0");
    let created: i64 = body["job"]["createdUnixMs"]
        .as_str()
        .and_then(|ms| ms.parse().ok())
        .expect("createdUnixMs");
    let ended: i64 = body["job"]["endedUnixMs"]
        .as_str()
        .and_then(|ms| ms.parse().ok())
        .expect("endedUnixMs");
    assert!(created > 0 && ended >= created, "{body}");
    assert!(!server.log().contains(SECRET));
    assert_the_guides_python_verifies(request, SECRET);
}

/// The Python function of the service guide's "Webhooks" section, run on a delivery as
/// received: it accepts the daemon's signature and refuses another.
fn assert_the_guides_python_verifies(request: &Received, secret: &str) {
    let guide = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/guide/service.md"),
    )
    .expect("the service guide");
    let section = guide
        .split("\n## Webhooks\n")
        .nth(1)
        .expect("a Webhooks section");
    let function = section
        .split("```python\n")
        .nth(1)
        .and_then(|rest| rest.split("```").next())
        .expect("a Python block in the Webhooks section");
    let script = format!(
        "{function}\nimport sys\n\
         print(is_from_the_farm(sys.argv[1].encode(), sys.stdin.buffer.read(), sys.argv[2]))\n"
    );
    let verdict = |signature: &str| {
        let mut python = std::process::Command::new("python3")
            .args(["-c", &script, secret, signature])
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .expect("python3 runs");
        python
            .stdin
            .take()
            .expect("its stdin")
            .write_all(&request.body)
            .expect("the body written");
        let output = python.wait_with_output().expect("python3 ends");
        assert!(output.status.success(), "{output:?}");
        String::from_utf8_lossy(&output.stdout).trim().to_owned()
    };
    assert_eq!(verdict(request.header("x-pointfarm-signature")), "True");
    assert_eq!(verdict(&format!("sha256={}", "0".repeat(64))), "False");
}

/// A cancelled job is posted as `job.cancelled`; an endpoint that answers 503 twice gets it
/// on the third try, the same delivery and signature each time, and the metrics count one
/// delivered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cancelled_job_is_posted_again_after_503s() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let hook = HookServer::start(Answers::Scripted, &[503, 503]);
    let metrics = free_address();
    let server = serve_posting_to(
        scratch.path(),
        &hook,
        &["--no-embedded-worker", "--metrics-listen", &metrics],
    );
    let (mut jobs, dataset) = jobs_on_a_sample(&server.address, 2_000, 8).await;
    let job = submit(&mut jobs, turntable_job("unwanted", &dataset.id, 4, 32, 24)).await;
    cancel(&mut jobs, &job.id).await;

    let requests = hook.wait_for_requests(3);
    assert_eq!(requests.len(), 3, "{requests:?}");
    for request in &requests {
        assert_eq!(request.header("x-pointfarm-event"), "job.cancelled");
        assert_eq!(
            request.header("x-pointfarm-delivery"),
            requests[0].header("x-pointfarm-delivery")
        );
        assert_eq!(request.body, requests[0].body);
        assert_signed(request, SECRET);
    }
    let body = requests[2].json();
    assert_eq!(body["event"], "job.cancelled");
    assert_eq!(body["job"]["id"], job.id.as_str());
    assert_eq!(body["job"]["state"], "JOB_STATE_CANCELLED");
    let counted = wait_for(Duration::from_secs(30), "the delivery counted", || {
        let series = scrape(&metrics);
        let delivered = series.get("pointfarm_webhook_deliveries_total{outcome=\"delivered\"}");
        (delivered == Some(&1.0)).then_some(series)
    });
    assert_eq!(
        counted.get("pointfarm_webhook_deliveries_total{outcome=\"failed\"}"),
        Some(&0.0)
    );
    let log = server.log();
    assert_eq!(
        log.matches("webhook delivery failed; trying again").count(),
        2,
        "{log}"
    );
    assert!(log.contains(&hook.url), "{log}");
}

/// A job that fails is posted as `job.failed` with its error and failed attempts, to the
/// endpoint that wants every end and to the one that wants failures only; a cancellation goes
/// to the first alone.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_job_reaches_the_endpoints_that_want_failures() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let every_end = HookServer::start(Answers::Scripted, &[]);
    let failures_only = HookServer::start(Answers::Scripted, &[]);
    let secret = secret_file(scratch.path());
    let config = format!(
        "[serve]\nwebhook_secret_file = {}\n\n[[serve.webhook]]\nurl = \"{}\"\n\n\
         [[serve.webhook]]\nurl = \"{}\"\nevents = [\"failed\"]\n",
        toml_string(&secret),
        every_end.url,
        failures_only.url,
    );
    let server = serve_configured(scratch.path(), &config, &[]);
    let (mut jobs, dataset) = jobs_on_a_sample(&server.address, 5_000, 4).await;
    // Far more frames than render before the cancel arrives.
    let cancelled = submit(&mut jobs, turntable_job("long", &dataset.id, 500, 64, 48)).await;
    cancel(&mut jobs, &cancelled.id).await;
    let failed = run_job(
        &mut jobs,
        &dataset.id,
        "outside",
        still_clipped_outside_the_sample(),
    )
    .await;
    assert_eq!(failed.state, pb::JobState::Failed as i32, "{failed:?}");

    let failure = &failures_only.wait_for_requests(1)[0];
    let every = every_end.wait_for_requests(2);
    assert_eq!(failures_only.requests().len(), 1);
    let events: Vec<&str> = every
        .iter()
        .map(|request| request.header("x-pointfarm-event"))
        .collect();
    assert!(
        events.contains(&"job.cancelled") && events.contains(&"job.failed"),
        "{events:?}"
    );
    assert_eq!(failure.header("x-pointfarm-event"), "job.failed");
    assert_signed(failure, SECRET);
    let body = failure.json();
    assert_eq!(body["job"]["id"], failed.id.as_str());
    assert_eq!(body["job"]["state"], "JOB_STATE_FAILED");
    assert_eq!(body["job"]["error"], failed.error.as_str());
    let attempts: u64 = body["job"]["failedAttempts"]
        .as_str()
        .and_then(|n| n.parse().ok())
        .expect("failedAttempts");
    assert!(attempts >= 1, "{body}");
}

/// An endpoint that accepts connections and never answers holds up neither the jobs' ends
/// nor the other endpoint: every event reaches the other one while the stalled endpoint's
/// first requests are still waiting for an answer, well within one try's timeout. Both come
/// from `[[serve.webhook]]` tables of the configuration file, each with its own secret.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_endpoint_that_never_answers_delays_nothing_else() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let stalled = HookServer::start(Answers::Never, &[]);
    let answering = HookServer::start(Answers::Scripted, &[]);
    let secret = secret_file(scratch.path());
    let other_secret = scratch.path().join("other-secret");
    std::fs::write(&other_secret, "another-secret").expect("write the secret");
    let config = format!(
        "[serve]\n\n[[serve.webhook]]\nurl = \"{}\"\nsecret_file = {}\n\n\
         [[serve.webhook]]\nurl = \"{}\"\nsecret_file = {}\nevents = [\"cancelled\"]\n",
        stalled.url,
        toml_string(&other_secret),
        answering.url,
        toml_string(&secret)
    );
    let server = serve_configured(scratch.path(), &config, &["--no-embedded-worker"]);
    let (mut jobs, dataset) = jobs_on_a_sample(&server.address, 2_000, 9).await;
    let mut ids = Vec::new();
    for n in 0..3 {
        let job = submit(
            &mut jobs,
            turntable_job(&format!("job-{n}"), &dataset.id, 4, 32, 24),
        )
        .await;
        cancel(&mut jobs, &job.id).await;
        ids.push(job.id);
    }

    let delivered = answering.wait_for_requests(3);
    let mut posted: Vec<String> = delivered
        .iter()
        .map(|request| {
            assert_signed(request, SECRET);
            request.json()["job"]["id"]
                .as_str()
                .expect("a job id")
                .to_owned()
        })
        .collect();
    posted.sort();
    ids.sort();
    assert_eq!(posted, ids);
    let held = stalled.recorded.lock().expect("lock").stalled_open.clone();
    assert!(!held.is_empty(), "the stalled endpoint was never tried");
    assert!(
        held.iter().all(|open| *open),
        "a stalled request timed out before the other endpoint had every event: {held:?}"
    );
    assert_signed(&stalled.requests()[0], "another-secret");
}

/// A bad webhook refuses the start with one line that names it and says why.
#[test]
fn a_bad_webhook_refuses_the_start_naming_it() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let data = scratch.path().join("data");
    let data = data.to_str().expect("a UTF-8 path");
    let secret = secret_file(scratch.path());
    let secret = secret.to_str().expect("a UTF-8 path");
    let missing = scratch.path().join("missing-secret");
    let missing = missing.to_str().expect("a UTF-8 path");
    let address = free_address();
    let cases = [
        (
            vec![
                "--webhook",
                "ftp://ci.example/hook",
                "--webhook-secret-file",
                secret,
            ],
            "webhook ftp://ci.example/hook: the URL must be http:// or https://",
        ),
        (
            vec![
                "--webhook",
                "https://ci.example/hook",
                "--webhook-secret-file",
                missing,
            ],
            "webhook https://ci.example/hook: its secret file",
        ),
        (
            vec!["--webhook", "https://ci.example/hook"],
            "webhook https://ci.example/hook: no secret",
        ),
    ];
    for (flags, reason) in cases {
        let mut args = vec!["serve", "--listen", &address, "--data-dir", data];
        args.extend(flags);
        let output = pointfarm(&args);
        assert!(!output.status.success(), "{args:?} started");
        let lines = own_stderr_lines(&output);
        assert_eq!(lines.len(), 1, "{lines:?}");
        assert!(lines[0].starts_with("error: "), "{lines:?}");
        assert!(lines[0].contains(reason), "{lines:?}");
        assert!(!lines[0].contains(SECRET), "{lines:?}");
    }
}

fn toml_string(path: &Path) -> String {
    format!("{:?}", path.to_str().expect("a UTF-8 path"))
}
