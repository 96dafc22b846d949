//! The transport under load and attack, with real processes and sockets: TCP_NODELAY read
//! back from every connected socket of a daemon and its worker, a flood of idle connections
//! against a daemon held to 1,024 open files, and SIGTERM with a call stalled in flight.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::os::fd::OwnedFd;
use std::time::{Duration, Instant};

use pointfarm_proto::v1::dataset_service_client::DatasetServiceClient;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_tests::service::{
    clients, scratch_sample, submit, turntable_job, upload_file, upload_messages, watch_to_success,
};
use pointfarm_tests::{free_address, signal, wait_for, ServeProcess};
use tonic::transport::Channel;

/// The TCP sockets of process `pid` that have a peer, each with its local and peer address,
/// duplicated out of the process (`pidfd_getfd`) so that their options can be read.
fn connected_sockets(pid: u32) -> Vec<(SocketAddr, SocketAddr, OwnedFd)> {
    use rustix::process::{pidfd_getfd, pidfd_open, Pid, PidfdFlags, PidfdGetfdFlags};
    let pid = Pid::from_raw(pid as i32).expect("a process id");
    let pidfd = pidfd_open(pid, PidfdFlags::empty()).expect("pidfd_open");
    let mut sockets = Vec::new();
    let entries = std::fs::read_dir(format!("/proc/{pid}/fd", pid = pid.as_raw_pid()))
        .expect("the process's descriptors");
    for entry in entries.flatten() {
        let is_socket = std::fs::read_link(entry.path())
            .is_ok_and(|target| target.to_string_lossy().starts_with("socket:"));
        let Some(number) = entry.file_name().to_str().and_then(|n| n.parse().ok()) else {
            continue;
        };
        if !is_socket {
            continue;
        }
        // A descriptor closed since the listing is no longer there to read.
        let Ok(fd) = pidfd_getfd(&pidfd, number, PidfdGetfdFlags::empty()) else {
            continue;
        };
        let peer = rustix::net::getpeername(&fd).ok().flatten();
        let local = rustix::net::getsockname(&fd).ok();
        let (Some(peer), Some(local)) = (peer, local) else {
            continue;
        };
        if let (Ok(peer), Ok(local)) = (SocketAddr::try_from(peer), SocketAddr::try_from(local)) {
            sockets.push((local, peer, fd));
        }
    }
    sockets
}

fn port(address: &str) -> u16 {
    address
        .rsplit(':')
        .next()
        .and_then(|port| port.parse().ok())
        .expect("an address with a port")
}

/// An HTTP/1.1 GET of `/metrics` on `stream`, kept alive; the status line.
fn get_metrics(stream: &mut TcpStream) -> String {
    stream
        .write_all(b"GET /metrics HTTP/1.1\r\nHost: localhost\r\n\r\n")
        .expect("send the request");
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .expect("timeout");
    let mut answer = Vec::new();
    let mut buffer = [0u8; 65536];
    // Enough of the answer for its status line and a metric.
    while !answer.windows(16).any(|w| w == b"pointfarm_queue_") {
        let read = stream.read(&mut buffer).expect("read the answer");
        assert!(read > 0, "the metrics endpoint closed the connection");
        answer.extend_from_slice(&buffer[..read]);
    }
    String::from_utf8_lossy(&answer)
        .lines()
        .next()
        .unwrap_or_default()
        .to_string()
}

/// A two-frame job through `server`'s API, uploaded, rendered and watched to its end, then a
/// scrape of its metrics at `metrics`: every listener and the worker's sockets in use. The
/// client's gRPC channel and the scrape's connection are returned open.
async fn a_job_and_a_scrape(server: &ServeProcess, metrics: &str, seed: u64) -> OpenClient {
    let (_scratch, scene) = scratch_sample("scene.las", 20_000, seed);
    let (mut datasets, mut jobs) = clients(&server.address).await;
    let dataset = upload_file(&mut datasets, "scene.las", &scene).await;
    let job = submit(&mut jobs, turntable_job("two", &dataset.id, 2, 64, 48)).await;
    watch_to_success(&mut jobs, &job.id, || server.log()).await;
    let mut scrape = TcpStream::connect(metrics).expect("connect to the metrics");
    assert!(get_metrics(&mut scrape).contains("200"));
    OpenClient {
        _datasets: datasets,
        _jobs: jobs,
        _scrape: scrape,
    }
}

/// A client's connections to a daemon, open until dropped.
struct OpenClient {
    _datasets: DatasetServiceClient<Channel>,
    _jobs: JobServiceClient<Channel>,
    _scrape: TcpStream,
}

/// Every socket a daemon accepted (its API, its embedded worker's listener, its metrics) and
/// every socket its embedded worker opened answer TCP_NODELAY: a response in several
/// segments never waits for the peer's delayed ACK.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_connected_socket_of_a_daemon_and_its_worker_has_nodelay() {
    let dir = tempfile::tempdir().expect("tempdir");
    let metrics = free_address();
    let server =
        ServeProcess::start_with(&dir.path().join("data"), &["--metrics-listen", &metrics]);
    let worker_pid = server.embedded_worker_pid();

    // The worker has leased, fetched and handed in over its sockets.
    let _open = a_job_and_a_scrape(&server, &metrics, 3).await;

    let api = port(&server.address);
    let metrics_port = port(&metrics);
    let daemon = connected_sockets(server.pid());
    let worker = connected_sockets(worker_pid);
    let accepted_on = |port: u16| {
        daemon
            .iter()
            .filter(move |(local, _, _)| local.port() == port)
    };
    assert!(accepted_on(api).count() >= 1, "no accepted API socket");
    assert!(
        accepted_on(metrics_port).count() >= 1,
        "no accepted metrics socket"
    );
    // The worker's sockets to the daemon: opened by it, accepted by the embedded listener.
    let embedded: Vec<u16> = worker.iter().map(|(_, peer, _)| peer.port()).collect();
    assert!(
        !embedded.is_empty(),
        "the worker has no connection to the daemon"
    );
    assert!(
        daemon
            .iter()
            .any(|(local, _, _)| embedded.contains(&local.port())),
        "no socket accepted on the embedded worker's listener"
    );
    for (local, peer, fd) in daemon.iter().chain(&worker) {
        let nodelay = rustix::net::sockopt::tcp_nodelay(fd).expect("read TCP_NODELAY");
        assert!(nodelay, "{local} -> {peer} has no TCP_NODELAY");
    }
}

/// About 1,100 idle connections without a token, to the gRPC port and the metrics port of a
/// daemon held to 1,024 open files, starve nothing: an upload and a job go through while the
/// flood stays connected, the daemon never runs out of descriptors, and the silent
/// connections are closed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_idle_connections_starves_nothing_at_1024_open_files() {
    const FLOOD: usize = 1_100;
    // This test's own process holds both floods.
    let limit = rustix::process::getrlimit(rustix::process::Resource::Nofile);
    rustix::process::setrlimit(
        rustix::process::Resource::Nofile,
        rustix::process::Rlimit {
            current: limit.maximum,
            maximum: limit.maximum,
        },
    )
    .expect("raise this test's open-file limit");
    let dir = tempfile::tempdir().expect("tempdir");
    let metrics = free_address();
    let server = ServeProcess::start_with_open_file_limit(
        &dir.path().join("data"),
        1024,
        &["--metrics-listen", &metrics],
    );
    let limits = std::fs::read_to_string(format!("/proc/{}/limits", server.pid()))
        .expect("the daemon's limits");
    let open_files = limits
        .lines()
        .find(|line| line.starts_with("Max open files"))
        .expect("the open-file limit");
    assert!(
        open_files.split_whitespace().nth(3) == Some("1024"),
        "{open_files}"
    );

    let mut flood = Vec::new();
    for target in [&server.address, &metrics] {
        for _ in 0..FLOOD {
            match TcpStream::connect(target) {
                Ok(stream) => flood.push(stream),
                Err(error) => panic!("connecting the flood to {target}: {error}"),
            }
        }
    }

    let _open = a_job_and_a_scrape(&server, &metrics, 5).await;

    let descriptors = || {
        std::fs::read_dir(format!("/proc/{}/fd", server.pid()))
            .map(|entries| entries.count())
            .unwrap_or(usize::MAX)
    };
    assert!(descriptors() < 1000, "{} descriptors open", descriptors());
    // The silent connections are closed within the bound on a first call (10 s).
    wait_for(Duration::from_secs(30), "the flood closed", || {
        (descriptors() < 100).then_some(())
    });
    let log = server.log();
    assert!(!log.contains("Too many open files"), "{log}");
    drop(flood);
}

/// SIGTERM stops the daemon within its shutdown grace while an upload stalls mid-stream: a
/// call that never ends never holds the process.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_stops_the_daemon_within_its_grace_with_a_call_stalled() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut server = ServeProcess::start_with(
        &dir.path().join("data"),
        &["--no-embedded-worker", "--shutdown-grace", "2"],
    );
    let (mut datasets, _) = clients(&server.address).await;
    // The header and the first chunk, then nothing: the stream stays open.
    let (sender, receiver) = tokio::sync::mpsc::channel(4);
    let (_scratch, scene) = scratch_sample("scene.las", 100_000, 7);
    let messages = upload_messages("stalled.las", &std::fs::read(&scene).expect("the scene"));
    assert!(messages.len() > 2, "the scene takes several messages");
    for message in messages.into_iter().take(2) {
        sender.send(message).await.expect("queue a message");
    }
    let upload = tokio::spawn(async move {
        datasets
            .upload_dataset(tokio_stream::wrappers::ReceiverStream::new(receiver))
            .await
    });
    tokio::time::sleep(Duration::from_millis(500)).await;
    if upload.is_finished() {
        panic!("the upload ended: {:?}", upload.await);
    }

    let asked = Instant::now();
    signal(server.pid(), "TERM");
    let status = server
        .wait_for_exit(Duration::from_secs(15))
        .expect("the daemon exits");
    let took = asked.elapsed();
    assert!(status.success(), "{status:?}\n{}", server.log());
    assert!(took < Duration::from_secs(8), "took {took:?}");
    assert!(
        server.log().contains("stopping without them"),
        "{}",
        server.log()
    );
    drop(sender);
}
