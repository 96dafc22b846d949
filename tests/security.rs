//! Transport and roles, with real processes and sockets: TLS with a certificate made for the
//! test (clients and workers through it, plaintext and unknown CAs refused; a CA certificate
//! served named at start and by the client; a certificate that cannot serve refused before
//! the daemon says it serves), the refusal to listen beyond loopback without a token and TLS,
//! reflection in both versions (behind the client token where one is set), and leases that
//! only their holder can use.

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use pointfarm_daemon::access::Access;
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_proto::v1::worker_service_client::WorkerServiceClient;
use pointfarm_tests::pki::TestPki;
use pointfarm_tests::service::{
    list_leases, scratch_sample, submit, turntable_job, upload_file, TestDaemon,
};
use pointfarm_tests::{
    own_stderr_lines, path_arg, pointfarm, pointfarm_bin, wait_for, ServeProcess, WorkerProcess,
};
use tokio_stream::StreamExt;
use tonic::Code;

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

fn assert_fails_saying(output: &Output, needle: &str) {
    assert!(
        !output.status.success(),
        "expected a failure saying {needle}"
    );
    assert!(stderr(output).contains(needle), "{}", stderr(output));
}

fn port_of(server: &ServeProcess) -> &str {
    server
        .address
        .rsplit(':')
        .next()
        .expect("the address has a port")
}

/// A daemon without an embedded worker, its data in `dir`, serving TLS with `pki`'s
/// certificate and requiring the client token in `client_token`, with more `args`.
fn tls_daemon(dir: &Path, pki: &TestPki, client_token: &Path, args: &[&str]) -> ServeProcess {
    let mut all = vec![
        "--no-embedded-worker",
        "--tls-cert",
        path_arg(&pki.cert),
        "--tls-key",
        path_arg(&pki.key),
        "--token-file",
        path_arg(client_token),
    ];
    all.extend_from_slice(args);
    ServeProcess::start_with(&dir.join("data"), &all)
}

#[test]
fn tls_carries_clients_and_workers_and_plaintext_is_refused() {
    let (scratch, scene) = scratch_sample("scene.las", 20_000, 5);
    let dir = scratch.path();
    let pki = TestPki::create(dir);
    let (client_token, worker_token) = (dir.join("client.token"), dir.join("worker.token"));
    std::fs::write(&client_token, "client-Secret-4f1c\n").expect("token");
    std::fs::write(&worker_token, "worker-Secret-9a2e\n").expect("token");
    let server = tls_daemon(
        dir,
        &pki,
        &client_token,
        &["--worker-token-file", path_arg(&worker_token)],
    );
    let https = format!("https://localhost:{}", port_of(&server));
    let worker = WorkerProcess::start_with(
        &https,
        &dir.join("cache"),
        "tls-worker",
        &[
            "--tls-ca",
            path_arg(&pki.ca),
            "--worker-token-file",
            path_arg(&worker_token),
        ],
    );
    // A bare address with a CA means TLS.
    let frames = dir.join("frames");
    let bare = format!("localhost:{}", port_of(&server));
    let rendered = pointfarm(&[
        "render",
        path_arg(&scene),
        "--server",
        &bare,
        "--tls-ca",
        path_arg(&pki.ca),
        "--token-file",
        path_arg(&client_token),
        "--turntable=2",
        "--size=64x48",
        "--out",
        path_arg(&frames),
    ]);
    assert!(
        rendered.status.success(),
        "{}\n{}\n{}",
        stderr(&rendered),
        worker.log(),
        server.log()
    );
    for i in 0..2 {
        assert!(frames.join(format!("frame_{i:05}.png")).is_file());
    }
    let listed = pointfarm(&[
        "dataset",
        "list",
        "--server",
        &https,
        "--tls-ca",
        path_arg(&pki.ca),
        "--token-file",
        path_arg(&client_token),
    ]);
    assert!(listed.status.success(), "{}", stderr(&listed));

    // A CA the system does not know, plaintext to the TLS port, and a CA with a plaintext URL
    // all fail; none falls back.
    let client = |server: &str, extra: &[&str]| {
        let mut args = vec!["dataset", "list", "--server", server, "--token-file"];
        args.push(path_arg(&client_token));
        args.extend_from_slice(extra);
        pointfarm(&args)
    };
    assert_fails_saying(
        &client(&https, &[]),
        "its certificate is signed by no CA this system trusts; give the CA's certificate",
    );
    let plaintext = format!("http://localhost:{}", port_of(&server));
    assert!(!client(&plaintext, &[]).status.success());
    assert_fails_saying(
        &client(&plaintext, &["--tls-ca", path_arg(&pki.ca)]),
        "--tls-ca is for https://",
    );
    assert_fails_saying(
        &client(&https, &["--tls-ca", path_arg(&pki.ca), "--token", "x"]),
        "give the token once",
    );
    // The client token is no worker token.
    let refused = pointfarm(&[
        "worker",
        "--server",
        &https,
        "--tls-ca",
        path_arg(&pki.ca),
        "--worker-token-file",
        path_arg(&client_token),
        "--cache-dir",
        path_arg(&dir.join("cache-refused")),
    ]);
    assert_fails_saying(&refused, "permission denied");
    // A certificate signed by a CA is a server's own: nothing to warn of.
    assert!(!server.log().contains("CA certificate"), "{}", server.log());
    // Tokens never reach the logs.
    for log in [server.log(), worker.log()] {
        assert!(!log.contains("Secret-"), "a token in a log:\n{log}");
    }
}

/// A certificate made the quickest way, `openssl req -x509` without extensions, is marked as
/// a CA: `serve` says so at start with how to make a server certificate, and a client that
/// trusts it fails in one sentence naming the cause and the fix, never the TLS library's
/// words, and says it once.
#[test]
fn a_ca_certificate_served_is_named_at_start_and_by_the_client() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let dir = scratch.path();
    let (cert, key) = (dir.join("c.pem"), dir.join("k.pem"));
    let made = Command::new("openssl")
        .args(["req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout"])
        .arg(&key)
        .arg("-out")
        .arg(&cert)
        .args(["-days", "30", "-subj", "/CN=localhost"])
        .output();
    let Ok(made) = made else {
        eprintln!("skipped: openssl is not installed");
        return;
    };
    assert!(made.status.success(), "{}", stderr(&made));
    let server = ServeProcess::start_with(
        &dir.join("data"),
        &[
            "--no-embedded-worker",
            "--tls-cert",
            path_arg(&cert),
            "--tls-key",
            path_arg(&key),
        ],
    );
    let log = wait_for(Duration::from_secs(10), "the certificate warning", || {
        let log = server.log();
        log.contains("is a CA certificate").then_some(log)
    });
    assert!(log.contains("WARN"), "{log}");
    assert!(
        log.contains("-addext basicConstraints=critical,CA:FALSE")
            && log.contains("-addext subjectAltName=DNS:localhost,IP:127.0.0.1"),
        "{log}"
    );

    let https = format!("https://localhost:{}", port_of(&server));
    let refused = pointfarm(&[
        "dataset",
        "list",
        "--server",
        &https,
        "--tls-ca",
        path_arg(&cert),
    ]);
    assert_fails_saying(&refused, "is a CA certificate (basicConstraints CA:TRUE)");
    let message = stderr(&refused);
    for needle in [
        "basicConstraints CA:TRUE",
        "-addext basicConstraints=critical,CA:FALSE",
    ] {
        assert_eq!(message.matches(needle).count(), 1, "{message}");
    }
    for words in [
        "CaUsedAsEndEntity",
        "invalid peer certificate",
        "error: error:",
    ] {
        assert!(!message.contains(words), "{message}");
    }
    let lines = own_stderr_lines(&refused);
    assert_eq!(lines.len(), 1, "one line: {message}");
    assert!(lines[0].starts_with("error: cannot connect to https://localhost:"));

    // A worker stops with the same sentence rather than retrying what cannot succeed.
    let mut worker = WorkerProcess::start_with(
        &https,
        &dir.join("worker"),
        "w",
        &["--tls-ca", path_arg(&cert)],
    );
    let log = wait_for(Duration::from_secs(60), "the worker's refusal", || {
        let log = worker.log();
        log.contains("is a CA certificate").then_some(log)
    });
    assert_eq!(log.matches("basicConstraints CA:TRUE").count(), 1, "{log}");
    assert!(!log.contains("CaUsedAsEndEntity"), "{log}");
    let status = worker.terminate(Duration::from_secs(10)).expect("an exit");
    assert_eq!(status.code(), Some(1), "{log}");
}

/// Runs `pointfarm serve` with `args`; its output if it exits within 30 s (it is killed and
/// the test fails otherwise).
fn serve_exits(data_dir: &Path, args: &[&str]) -> Output {
    let mut child = Command::new(pointfarm_bin())
        .arg("serve")
        .args(["--data-dir", path_arg(data_dir), "--no-embedded-worker"])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start pointfarm serve");
    let deadline = Instant::now() + Duration::from_secs(30);
    while child.try_wait().expect("poll").is_none() {
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("pointfarm serve {args:?} did not refuse to start");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().expect("output")
}

/// A certificate that cannot be read, a file that holds no certificate and a key that is not
/// the certificate's each stop `pointfarm serve` with one line that names the fault, before it
/// says anything of what it would serve.
#[test]
fn a_refused_certificate_stops_serve_before_it_says_it_serves() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let dir = scratch.path();
    let pki = TestPki::create(dir);
    let other = dir.join("other");
    std::fs::create_dir(&other).expect("a folder");
    let other_key = TestPki::create(&other).key;
    let missing = dir.join("missing.pem");
    let refusals = [
        (&missing, &pki.key, "reading "),
        (
            &pki.key,
            &pki.key,
            "the TLS certificate (--tls-cert) holds no PEM certificate",
        ),
        (&pki.cert, &other_key, "the key is not the certificate's"),
    ];
    for (index, (cert, key, needle)) in refusals.into_iter().enumerate() {
        let data_dir = dir.join(format!("data-{index}"));
        let refused = serve_exits(
            &data_dir,
            &[
                "--listen",
                "127.0.0.1:0",
                "--tls-cert",
                path_arg(cert),
                "--tls-key",
                path_arg(key),
            ],
        );
        assert_fails_saying(&refused, needle);
        let lines = own_stderr_lines(&refused);
        assert_eq!(lines.len(), 1, "one line: {lines:#?}");
        assert!(lines[0].starts_with("error: "), "{}", lines[0]);
        let said = String::from_utf8_lossy(&refused.stdout);
        assert!(said.is_empty(), "it said before refusing: {said}");
        assert!(
            !data_dir.exists(),
            "the state was opened before the certificate was checked"
        );
    }
}

#[test]
fn listening_beyond_loopback_needs_a_token_and_tls_or_insecure() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let dir = scratch.path();
    let pki = TestPki::create(dir);
    let refused = serve_exits(&dir.join("d1"), &["--listen", "0.0.0.0:0"]);
    assert_fails_saying(&refused, "refusing to listen on 0.0.0.0");
    assert_fails_saying(&refused, "--insecure");
    let refused = serve_exits(
        &dir.join("d2"),
        &["--listen", "0.0.0.0:0", "--token", "client-token"],
    );
    assert_fails_saying(&refused, "TLS (--tls-cert and --tls-key)");
    let same = serve_exits(
        &dir.join("d3"),
        &["--token", "same-token", "--worker-token", "same-token"],
    );
    assert_fails_saying(&same, "give clients and workers different tokens");

    let port = || {
        std::net::TcpListener::bind("0.0.0.0:0")
            .and_then(|probe| probe.local_addr())
            .expect("a free port")
            .port()
    };
    let tls = [
        "--no-embedded-worker",
        "--token",
        "client-token",
        "--tls-cert",
        path_arg(&pki.cert),
        "--tls-key",
        path_arg(&pki.key),
    ];
    let mut secured =
        ServeProcess::start_with_args(&format!("0.0.0.0:{}", port()), &dir.join("d4"), &tls);
    assert!(secured.is_running(), "{}", secured.log());
    let mut insecure = ServeProcess::start_with_args(
        &format!("0.0.0.0:{}", port()),
        &dir.join("d5"),
        &["--no-embedded-worker", "--insecure"],
    );
    assert!(insecure.is_running(), "{}", insecure.log());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reflection_answers_in_v1_and_v1alpha() {
    use tonic_reflection::pb::{v1, v1alpha};
    let daemon = TestDaemon::start_without_worker(|_| {}, Access::default()).await;
    let channel = daemon.channel().await;

    let request = v1alpha::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(
            v1alpha::server_reflection_request::MessageRequest::ListServices(String::new()),
        ),
    };
    let mut answers =
        v1alpha::server_reflection_client::ServerReflectionClient::new(channel.clone())
            .server_reflection_info(tokio_stream::iter([request]))
            .await
            .expect("v1alpha reflection")
            .into_inner();
    let answer = answers.next().await.expect("an answer").expect("ok");
    let Some(v1alpha::server_reflection_response::MessageResponse::ListServicesResponse(list)) =
        answer.message_response
    else {
        panic!("not a service list: {answer:?}");
    };
    let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
    assert!(
        names.iter().any(|n| n == "pointfarm.v1.JobService"),
        "{names:?}"
    );

    let answer = list_services_v1(channel, None)
        .await
        .expect("v1 reflection");
    assert!(matches!(
        answer.message_response,
        Some(v1::server_reflection_response::MessageResponse::ListServicesResponse(_))
    ));
    daemon.stop().await;
}

/// The first answer of v1 reflection to a ListServices request on `channel`, with the bearer
/// `token` if given.
async fn list_services_v1(
    channel: tonic::transport::Channel,
    token: Option<&str>,
) -> Result<tonic_reflection::pb::v1::ServerReflectionResponse, tonic::Status> {
    use tonic_reflection::pb::v1;
    let list = v1::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(v1::server_reflection_request::MessageRequest::ListServices(
            String::new(),
        )),
    };
    let mut request = tonic::Request::new(tokio_stream::iter([list]));
    if let Some(token) = token {
        let value = format!("Bearer {token}").parse().expect("a header value");
        request.metadata_mut().insert("authorization", value);
    }
    let mut answers = v1::server_reflection_client::ServerReflectionClient::new(channel)
        .server_reflection_info(request)
        .await?
        .into_inner();
    answers.next().await.expect("an answer")
}

/// Reflection maps the whole API: where a client token is set, it needs one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reflection_needs_the_client_token_where_one_is_set() {
    let daemon = TestDaemon::start_without_worker(|_| {}, Access::new(Some("client"), None)).await;
    let refused = list_services_v1(daemon.channel().await, None)
        .await
        .expect_err("reflection without the token");
    assert_eq!(refused.code(), Code::Unauthenticated, "{refused}");
    let refused = list_services_v1(daemon.channel().await, Some("wrong"))
        .await
        .expect_err("reflection with another token");
    assert_eq!(refused.code(), Code::Unauthenticated, "{refused}");
    list_services_v1(daemon.channel().await, Some("client"))
        .await
        .expect("reflection with the token");
    daemon.stop().await;
}

/// The embedded worker's lease, taken from the client's listing, cannot be renewed or failed
/// through the public worker service; lease ids are 128 random bits.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lease_is_usable_only_by_its_holder() {
    let daemon = TestDaemon::start(|_| {}, Access::default()).await;
    let (_scratch, scene) = scratch_sample("scene.las", 200_000, 9);
    let mut datasets = daemon.datasets().await;
    let dataset = upload_file(&mut datasets, "scene.las", &scene).await;
    let mut jobs = daemon.jobs().await;
    let job = submit(
        &mut jobs,
        turntable_job("bound", &dataset.id, 400, 320, 240),
    )
    .await;
    let mut workers = WorkerServiceClient::new(daemon.channel().await);
    let mut lister = JobServiceClient::new(daemon.channel().await);

    let deadline = Instant::now() + Duration::from_secs(120);
    let mut seen = std::collections::HashSet::new();
    let denied = loop {
        assert!(
            Instant::now() < deadline,
            "no embedded lease could be tried"
        );
        let leases = list_leases(&mut lister).await;
        let Some(lease) = leases.into_iter().find(|l| l.embedded) else {
            tokio::time::sleep(Duration::from_millis(5)).await;
            continue;
        };
        let hex = lease
            .lease_id
            .strip_prefix("lease-")
            .expect("lease- prefix");
        assert!(
            hex.len() == 32 && hex.bytes().all(|b| b.is_ascii_hexdigit()),
            "{}",
            lease.lease_id
        );
        seen.insert(lease.lease_id.clone());
        let heartbeat = workers
            .heartbeat(pb::HeartbeatRequest {
                lease_id: lease.lease_id.clone(),
            })
            .await;
        match heartbeat {
            Err(status) => break (status, lease.lease_id),
            // Handed in between the listing and the call: try the next one.
            Ok(answer) => assert_eq!(answer.into_inner().action, pb::LeaseAction::Stop as i32),
        }
    };
    let (status, lease_id) = denied;
    assert_eq!(
        status.code(),
        Code::PermissionDenied,
        "{}",
        status.message()
    );
    assert!(
        status.message().contains("embedded worker"),
        "{}",
        status.message()
    );
    let failed = workers
        .fail_frame(pb::FailFrameRequest {
            lease_id,
            reason: "forged".into(),
            kind: pb::FailureKind::Permanent as i32,
        })
        .await;
    // Denied, or the lease is gone already; never a failed job.
    if let Err(status) = &failed {
        assert!(
            matches!(
                status.code(),
                Code::PermissionDenied | Code::FailedPrecondition
            ),
            "{status:?}"
        );
    }
    let now = jobs
        .cancel_job(pb::CancelJobRequest { id: job.id })
        .await
        .expect("cancel")
        .into_inner();
    assert!(
        now.error.is_empty(),
        "the forged failure reached the job: {}",
        now.error
    );
    daemon.stop().await;
}

/// `serve --health-listen`: beside a TLS port with tokens, the health service alone in
/// plaintext, for probes that cannot speak TLS (Kubernetes' gRPC probes); the API is not
/// there.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_checks_answer_in_plaintext_on_a_port_of_their_own() {
    use pointfarm_tests::health::{health, JOB_SERVICE};
    use tonic_health::pb::health_check_response::ServingStatus;

    let scratch = tempfile::tempdir().expect("tempdir");
    let dir = scratch.path();
    let pki = TestPki::create(dir);
    let token = dir.join("client.token");
    std::fs::write(&token, "client-Secret-77d0\n").expect("token");
    let health_address = pointfarm_tests::free_address();
    let _server = tls_daemon(dir, &pki, &token, &["--health-listen", &health_address]);
    let channel = wait_for_channel(&health_address).await;
    let status = |service| health(&health_address, service);
    assert_eq!(
        status("pointfarm.v1.WorkerService").await,
        ServingStatus::Serving as i32
    );
    // No worker can render yet: the jobs' service says so here as on the main port.
    assert_eq!(status(JOB_SERVICE).await, ServingStatus::NotServing as i32);
    let api = JobServiceClient::new(channel)
        .list_jobs(pb::ListJobsRequest::default())
        .await
        .expect_err("no API on the health port");
    assert_eq!(api.code(), Code::Unimplemented, "{api}");
}

/// A plaintext channel to `address` once it accepts connections (within 30 s).
async fn wait_for_channel(address: &str) -> tonic::transport::Channel {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        match tonic::transport::Channel::from_shared(format!("http://{address}"))
            .expect("an address")
            .connect()
            .await
        {
            Ok(channel) => return channel,
            Err(e) if Instant::now() > deadline => panic!("no health port at {address}: {e}"),
            Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    }
}
