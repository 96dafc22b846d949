//! Prometheus metrics end to end: a real Prometheus server scrapes `pointfarm serve
//! --metrics-listen` and answers for the frames of a job through its HTTP API; and the
//! daemon's and a `pointfarm worker`'s `/metrics`, read directly after a job.

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use pointfarm_tests::service::{
    clients, scratch_sample, submit, turntable_job, upload_file, watch_to_success,
};
use pointfarm_tests::{pointfarm_bin, wait_for, ServeProcess, WorkerProcess};

const PROMETHEUS: &str = "/usr/bin/prometheus";

/// A free loopback address.
fn free_address() -> String {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|probe| probe.local_addr())
        .expect("a free loopback port")
        .port();
    format!("127.0.0.1:{port}")
}

/// `GET http://{address}{path}`: the status code and the body. HTTP/1.0, so that the answer
/// is the plain body up to the end of the connection.
fn http_get(address: &str, path: &str) -> std::io::Result<(u16, String)> {
    let mut stream = TcpStream::connect(address)?;
    stream.set_read_timeout(Some(Duration::from_secs(10)))?;
    write!(stream, "GET {path} HTTP/1.0\r\nHost: {address}\r\n\r\n")?;
    let mut answer = String::new();
    stream.read_to_string(&mut answer)?;
    let (head, body) = answer.split_once("\r\n\r\n").unwrap_or((&answer, ""));
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|code| code.parse().ok())
        .unwrap_or(0);
    Ok((status, body.to_owned()))
}

/// The metrics at `http://{address}/metrics`, by series (`name{labels}` as written).
fn scrape(address: &str) -> BTreeMap<String, f64> {
    let (status, body) = http_get(address, "/metrics").expect("GET /metrics");
    assert_eq!(status, 200, "{body}");
    assert!(body.ends_with("# EOF\n"), "{body}");
    body.lines()
        .filter(|line| !line.starts_with('#') && !line.is_empty())
        .map(|line| {
            let (series, value) = line.rsplit_once(' ').expect("series value");
            (series.to_owned(), value.parse().expect("a number"))
        })
        .collect()
}

fn value(metrics: &BTreeMap<String, f64>, series: &str) -> f64 {
    *metrics
        .get(series)
        .unwrap_or_else(|| panic!("no {series} in {metrics:#?}"))
}

/// A child process, killed when dropped.
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `pointfarm serve` with its embedded worker, told the metrics address in the environment
/// (`POINTFARM_METRICS_LISTEN`), which its embedded worker must not take for its own; once it
/// listens: the process, its gRPC address, and its log file.
fn serve_with_metrics_from_env(dir: &Path, metrics: &str) -> (Killed, String, std::path::PathBuf) {
    let address = free_address();
    let log = dir.join("serve.log");
    let child = Command::new(pointfarm_bin())
        .args(["serve", "--listen", &address, "--data-dir"])
        .arg(dir.join("data"))
        .env("POINTFARM_METRICS_LISTEN", metrics)
        .env("RUST_LOG", "warn,pointfarm=info")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).expect("serve log"))
        .spawn()
        .expect("start pointfarm serve");
    let server = Killed(child);
    wait_for(Duration::from_secs(30), "the daemon listening", || {
        TcpStream::connect(&address).ok()
    });
    (server, address, log)
}

/// A Prometheus server of Debian's package, scraping `target` every second; killed when
/// dropped.
struct Prometheus {
    address: String,
    child: Child,
    log: std::path::PathBuf,
}

impl Prometheus {
    fn start(dir: &Path, target: &str) -> Self {
        let config = dir.join("prometheus.yml");
        std::fs::write(
            &config,
            format!(
                "global:\n  scrape_interval: 1s\n  scrape_timeout: 1s\n\
                 scrape_configs:\n  - job_name: pointfarm\n    static_configs:\n      \
                 - targets: ['{target}']\n"
            ),
        )
        .expect("prometheus.yml");
        let address = free_address();
        let log = dir.join("prometheus.log");
        let child = Command::new(PROMETHEUS)
            .arg(format!("--config.file={}", config.display()))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.join("tsdb").display()
            ))
            .arg(format!("--web.listen-address={address}"))
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).expect("prometheus log"))
            .spawn()
            .expect("start prometheus");
        let prometheus = Self {
            address,
            child,
            log,
        };
        wait_for(Duration::from_secs(60), "a ready Prometheus", || {
            matches!(http_get(&prometheus.address, "/-/ready"), Ok((200, _))).then_some(())
        });
        prometheus
    }

    /// The value of the instant query `query`'s single series, if it has one.
    fn query(&self, query: &str) -> Option<f64> {
        let (status, body) = http_get(&self.address, &format!("/api/v1/query?query={query}"))
            .expect("query Prometheus");
        assert_eq!(status, 200, "{body}");
        let answer: serde_json::Value = serde_json::from_str(&body).expect("JSON");
        assert_eq!(answer["status"], "success", "{body}");
        let result = answer["data"]["result"].as_array().expect("a vector");
        match result.as_slice() {
            [] => None,
            [series] => series["value"][1].as_str()?.parse().ok(),
            more => panic!("{} series for {query}: {body}", more.len()),
        }
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for Prometheus {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Prometheus scrapes a daemon through a job rendered by its embedded worker; its API then
/// counts the job's frames.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn prometheus_scrapes_the_frames_a_job_completed() {
    if !Path::new(PROMETHEUS).is_file() {
        eprintln!(
            "skipped: {PROMETHEUS} is missing (Debian's `prometheus` package; deploy/test.sh \
             installs it)"
        );
        return;
    }
    let scratch = tempfile::tempdir().expect("tempdir");
    let metrics = free_address();
    let (_server, address, log) = serve_with_metrics_from_env(scratch.path(), &metrics);
    let prometheus = Prometheus::start(scratch.path(), &metrics);

    let (_sample_dir, file) = scratch_sample("s.las", 20_000, 4);
    let (mut datasets, mut jobs) = clients(&address).await;
    let dataset = upload_file(&mut datasets, "s.las", &file).await;
    let frames = 3;
    let job = submit(
        &mut jobs,
        turntable_job("scraped", &dataset.id, frames, 64, 48),
    )
    .await;
    watch_to_success(&mut jobs, &job.id, || {
        std::fs::read_to_string(&log).unwrap_or_default()
    })
    .await;

    let counted = wait_for(
        Duration::from_secs(60),
        "the job's frames in Prometheus",
        || {
            prometheus
                .query("pointfarm_frames_completed_total")
                .filter(|&completed| completed == f64::from(frames))
        },
    );
    assert_eq!(counted, f64::from(frames), "{}", prometheus.log());
    assert_eq!(prometheus.query(r#"up{job="pointfarm"}"#), Some(1.0));
    assert_eq!(
        prometheus.query(r#"sum(pointfarm_queue_frames{state="queued"})"#),
        Some(0.0)
    );
}

/// The daemon's and a worker's own `/metrics` after a job rendered by that worker.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_daemon_and_a_worker_serve_what_they_counted() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let daemon_metrics = free_address();
    let server = ServeProcess::start_with(
        &scratch.path().join("data"),
        &["--no-embedded-worker", "--metrics-listen", &daemon_metrics],
    );
    let before = scrape(&daemon_metrics);
    assert_eq!(value(&before, "pointfarm_frames_completed_total"), 0.0);
    assert_eq!(value(&before, "pointfarm_workers_connected"), 0.0);

    let worker_metrics = free_address();
    let worker = WorkerProcess::start_with(
        &format!("http://{}", server.address),
        &scratch.path().join("cache"),
        "scraped",
        &["--metrics-listen", &worker_metrics],
    );
    let (_sample_dir, file) = scratch_sample("s.las", 20_000, 5);
    let (mut datasets, mut jobs) = clients(&server.address).await;
    let dataset = upload_file(&mut datasets, "s.las", &file).await;
    let job = submit(&mut jobs, turntable_job("direct", &dataset.id, 2, 64, 48)).await;
    watch_to_success(&mut jobs, &job.id, || worker.log()).await;

    let daemon = scrape(&daemon_metrics);
    assert_eq!(value(&daemon, "pointfarm_frames_completed_total"), 2.0);
    assert_eq!(value(&daemon, "pointfarm_frames_failed_total"), 0.0);
    assert_eq!(value(&daemon, "pointfarm_workers_connected"), 1.0);
    assert_eq!(value(&daemon, "pointfarm_leases_held"), 0.0);
    assert_eq!(value(&daemon, "pointfarm_leases_expired_total"), 0.0);
    let size = std::fs::metadata(&file).expect("sample").len();
    assert_eq!(value(&daemon, "pointfarm_upload_bytes_total"), size as f64);
    // The worker decoded the dataset for the first frame and kept it for the second.
    assert_eq!(value(&daemon, "pointfarm_dataset_cache_misses_total"), 1.0);
    assert_eq!(value(&daemon, "pointfarm_dataset_cache_hits_total"), 0.0);
    assert_eq!(
        value(
            &daemon,
            r#"pointfarm_queue_frames{state="queued",priority="0"}"#
        ),
        0.0
    );
    assert_eq!(
        value(
            &daemon,
            r#"pointfarm_frame_stage_seconds_count{stage="load"}"#
        ),
        1.0
    );
    assert_eq!(
        value(
            &daemon,
            r#"pointfarm_frame_stage_seconds_count{stage="rasterize"}"#
        ),
        2.0
    );

    let own = scrape(&worker_metrics);
    assert_eq!(value(&own, "pointfarm_worker_frames_rendered_total"), 2.0);
    assert_eq!(value(&own, "pointfarm_worker_frames_failed_total"), 0.0);
    assert_eq!(
        value(&own, "pointfarm_worker_dataset_cache_misses_total"),
        1.0
    );
    assert_eq!(
        value(
            &own,
            r#"pointfarm_worker_frame_stage_seconds_count{stage="rasterize"}"#
        ),
        2.0
    );
    let (status, _) = http_get(&worker_metrics, "/elsewhere").expect("GET");
    assert_eq!(status, 404);
}
