//! Prometheus metrics end to end: a real Prometheus server scrapes `pointfarm serve
//! --metrics-listen` and answers for the frames of a job through its HTTP API; and the
//! daemon's and a `pointfarm worker`'s `/metrics`, read directly after a job.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use pointfarm_tests::prometheus::{http_get, prometheus_installed, scrape, Prometheus};
use pointfarm_tests::service::{
    clients, jobs_on_a_sample, scratch_sample, submit, turntable_job, upload_file, watch_to_success,
};
use pointfarm_tests::{free_address, wait_for, ServeProcess, WorkerProcess};

fn value(metrics: &BTreeMap<String, f64>, series: &str) -> f64 {
    *metrics
        .get(series)
        .unwrap_or_else(|| panic!("no {series} in {metrics:#?}"))
}

/// `pointfarm serve` with its embedded worker, told the metrics address in the environment
/// (`POINTFARM_METRICS_LISTEN`), which its embedded worker must not take for its own; once it
/// listens.
fn serve_with_metrics_from_env(dir: &Path, metrics: &str) -> ServeProcess {
    let environment = [("POINTFARM_METRICS_LISTEN", metrics.to_owned())];
    ServeProcess::start_in_environment(&environment, &dir.join("data"), &[])
}

/// `pointfarm serve` without a worker, its data in `scratch`, serving its metrics; once it
/// listens: the process and its metrics address.
fn serve_metered(scratch: &Path) -> (ServeProcess, String) {
    let metrics = free_address();
    let server = ServeProcess::start_with(
        &scratch.join("data"),
        &["--no-embedded-worker", "--metrics-listen", &metrics],
    );
    (server, metrics)
}

/// A `pointfarm worker` process named `name` for `server`, its cache in `scratch`, serving its
/// metrics: the process and its metrics address.
fn worker_metered(server: &ServeProcess, scratch: &Path, name: &str) -> (WorkerProcess, String) {
    let metrics = free_address();
    let worker = WorkerProcess::start_with(
        &format!("http://{}", server.address),
        &scratch.join("cache"),
        name,
        &["--metrics-listen", &metrics],
    );
    (worker, metrics)
}

/// Prometheus scrapes a daemon through a job rendered by its embedded worker; its API then
/// counts the job's frames.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn prometheus_scrapes_the_frames_a_job_completed() {
    if !prometheus_installed() {
        return;
    }
    let scratch = tempfile::tempdir().expect("tempdir");
    let metrics = free_address();
    let server = serve_with_metrics_from_env(scratch.path(), &metrics);
    let prometheus = Prometheus::start(scratch.path(), &[&metrics]);

    let (mut jobs, dataset) = jobs_on_a_sample(&server.address, 20_000, 4).await;
    let frames = 3;
    let job = submit(
        &mut jobs,
        turntable_job("scraped", &dataset.id, frames, 64, 48),
    )
    .await;
    watch_to_success(&mut jobs, &job.id, || server.log()).await;

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
    let (server, daemon_metrics) = serve_metered(scratch.path());
    let before = scrape(&daemon_metrics);
    assert_eq!(value(&before, "pointfarm_frames_completed_total"), 0.0);
    assert_eq!(value(&before, "pointfarm_workers_connected"), 0.0);

    let (worker, worker_metrics) = worker_metered(&server, scratch.path(), "scraped");
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

/// The Grafana dashboard `deploy/grafana/pointfarm.json`, parsed.
fn grafana_dashboard() -> serde_json::Value {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/grafana/pointfarm.json");
    let text = std::fs::read_to_string(&path).expect("the Grafana dashboard");
    serde_json::from_str(&text).expect("the dashboard is JSON")
}

/// The dashboard's panels that query (rows only group them), with their queries.
fn queried_panels(dashboard: &serde_json::Value) -> Vec<(&str, Vec<&str>)> {
    let panels = dashboard["panels"].as_array().expect("panels");
    panels
        .iter()
        .filter(|panel| panel["type"] != "row")
        .map(|panel| {
            let title = panel["title"].as_str().expect("a title");
            let targets = panel["targets"].as_array().expect("targets");
            let queries = targets
                .iter()
                .map(|t| t["expr"].as_str().expect("a query"))
                .collect();
            (title, queries)
        })
        .collect()
}

/// The dashboard is one Grafana imports as it is: a Prometheus data source chosen on import,
/// every panel on the 24-column grid without overlapping another, each with a query.
#[test]
fn the_grafana_dashboard_is_laid_out_for_grafana() {
    let dashboard = grafana_dashboard();
    assert_eq!(dashboard["uid"], "pointfarm-farm");
    assert!(
        dashboard["schemaVersion"].as_u64() >= Some(36),
        "{dashboard}"
    );
    let variables = dashboard["templating"]["list"]
        .as_array()
        .expect("variables");
    assert!(
        variables
            .iter()
            .any(|v| v["name"] == "datasource" && v["query"] == "prometheus"),
        "no Prometheus data source variable"
    );
    let panels = dashboard["panels"].as_array().expect("panels");
    let mut ids = std::collections::BTreeSet::new();
    let mut cells = std::collections::BTreeMap::new();
    for panel in panels {
        let title = panel["title"].as_str().expect("a title");
        assert!(!title.is_empty() && ids.insert(panel["id"].as_u64().expect("an id")));
        let place = &panel["gridPos"];
        let [x, y, w, h] = ["x", "y", "w", "h"].map(|k| place[k].as_u64().expect("gridPos"));
        assert!(w > 0 && h > 0 && x + w <= 24, "{title}: {place}");
        for cell in (x..x + w).flat_map(|x| (y..y + h).map(move |y| (x, y))) {
            if let Some(other) = cells.insert(cell, title) {
                panic!("{title} overlaps {other} at {cell:?}");
            }
        }
        if panel["type"] == "row" {
            continue;
        }
        assert_eq!(panel["datasource"]["uid"], "${datasource}", "{title}");
        let targets = panel["targets"].as_array().expect("targets");
        assert!(!targets.is_empty(), "{title} has no query");
        for target in targets {
            assert_eq!(target["datasource"]["uid"], "${datasource}", "{title}");
            assert!(target["expr"].as_str().is_some_and(|e| !e.is_empty()));
        }
    }
    assert!(queried_panels(&dashboard).len() >= 12);
}

/// Every query of the dashboard is valid PromQL that a real Prometheus, scraping a daemon and
/// a worker process through a job, answers with series: no panel of a working farm stays
/// empty for a misspelt metric or label.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_grafana_panel_shows_a_farm_that_rendered_a_job() {
    if !prometheus_installed() {
        return;
    }
    let scratch = tempfile::tempdir().expect("tempdir");
    let (server, daemon_metrics) = serve_metered(scratch.path());
    let (worker, worker_metrics) = worker_metered(&server, scratch.path(), "charted");
    let prometheus = Prometheus::start(scratch.path(), &[&daemon_metrics, &worker_metrics]);
    let (mut jobs, dataset) = jobs_on_a_sample(&server.address, 20_000, 6).await;
    let job = submit(&mut jobs, turntable_job("charted", &dataset.id, 2, 64, 48)).await;
    watch_to_success(&mut jobs, &job.id, || worker.log()).await;

    let dashboard = grafana_dashboard();
    let queries: Vec<(&str, String)> = queried_panels(&dashboard)
        .into_iter()
        .flat_map(|(title, queries)| {
            // Grafana's interval for rates: at least four scrapes; one minute here.
            queries
                .into_iter()
                .map(move |query| (title, query.replace("$__rate_interval", "1m")))
        })
        .collect();
    // Rates need two samples after the job's counts moved: scrapes come every second.
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    let empty = loop {
        let empty: Vec<String> = queries
            .iter()
            .filter_map(|(title, query)| match prometheus.query_series(query) {
                Ok(series) if !series.is_empty() => None,
                Ok(_) => Some(format!("{title}: {query}")),
                Err(error) => panic!("{title}: {query}: {error}"),
            })
            .collect();
        if empty.is_empty() || std::time::Instant::now() > deadline {
            break empty;
        }
        std::thread::sleep(Duration::from_millis(500));
    };
    assert!(
        empty.is_empty(),
        "panels without series:\n{}",
        empty.join("\n")
    );
}
