//! The metrics' text after real leases against a real state database, read back as
//! Prometheus would.

use std::collections::BTreeMap;
use std::time::Duration;

use super::*;
use crate::capabilities::WorkerCapabilities;
use crate::lease::{FailureKind, FrameOutcome};
use crate::model::Job;
use crate::service::Daemon;
use crate::test_daemon;

fn submit(daemon: &Daemon, frames: u32, priority: i32) -> Job {
    test_daemon::submit(daemon, frames, |request| {
        request.priority = priority;
        request.request_id = format!("r-{frames}-{priority}");
    })
}

/// The `pointfarm_queue_frames` series of the frames in `state` of jobs of `priority`.
fn queue_frames(state: &str, priority: i32) -> String {
    format!(r#"pointfarm_queue_frames{{state="{state}",priority="{priority}"}}"#)
}

/// What `daemon` serves as its metrics now, as Prometheus reads it.
fn scrape(daemon: &Daemon) -> Scrape {
    parse(&daemon.metrics_text().expect("text"))
}

fn timing(stage: &str, ms: f64) -> StageTiming {
    StageTiming {
        stage: stage.into(),
        ms,
        gpu_clock: false,
    }
}

/// The metrics' text as Prometheus reads it: the type of each family, and the value of each
/// series (`name{labels}` as written).
#[derive(Debug)]
struct Scrape {
    types: BTreeMap<String, String>,
    samples: BTreeMap<String, f64>,
}

fn parse(text: &str) -> Scrape {
    let mut types = BTreeMap::new();
    let mut samples = BTreeMap::new();
    assert!(text.ends_with("# EOF\n"), "ends with its marker: {text}");
    for line in text.lines() {
        if let Some(declared) = line.strip_prefix("# TYPE ") {
            let (name, kind) = declared.split_once(' ').expect("# TYPE name kind");
            types.insert(name.to_owned(), kind.to_owned());
        } else if !line.starts_with('#') {
            let (series, value) = line.rsplit_once(' ').expect("series value");
            let value: f64 = value.parse().expect("a number");
            assert!(
                samples.insert(series.to_owned(), value).is_none(),
                "{series} twice"
            );
        }
    }
    Scrape { types, samples }
}

impl Scrape {
    fn value(&self, series: &str) -> f64 {
        *self
            .samples
            .get(series)
            .unwrap_or_else(|| panic!("no {series} in {:#?}", self.samples))
    }

    /// Checks each series' value, naming every one that differs.
    fn assert_values(&self, expected: &[(&str, f64)]) {
        let differing: Vec<String> = expected
            .iter()
            .filter(|(series, value)| self.value(series) != *value)
            .map(|(series, value)| format!("{series}: {} not {value}", self.value(series)))
            .collect();
        assert!(differing.is_empty(), "{differing:#?}");
    }
}

#[test]
fn after_a_job_every_family_is_there_with_what_happened() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = test_daemon::open(dir.path(), Duration::from_secs(60));
    let job = submit(&daemon, 3, 0);
    let urgent = submit(&daemon, 2, 5);

    // Highest priority first: both frames of the urgent job, then the first of the other.
    let first = daemon
        .lease_frame("w1", false, &WorkerCapabilities::default())
        .expect("lease")
        .expect("task");
    let second = daemon
        .lease_frame("w2", false, &WorkerCapabilities::default())
        .expect("lease")
        .expect("task");
    let timeout = daemon.config.lease_timeout;
    drop(
        daemon
            .workers
            .poll_named(false, "w1", Default::default(), timeout),
    );
    drop(
        daemon
            .workers
            .poll_named(false, "w2", Default::default(), timeout),
    );
    assert_eq!(first.lease.job_id, urgent.id);
    let state = daemon.farm_state().expect("state");
    assert_eq!(state.leases_held, 2);
    assert_eq!(state.workers_connected, 2);
    assert_eq!(
        state.queue,
        BTreeMap::from([
            (
                0,
                QueueDepth {
                    queued: 3,
                    ..QueueDepth::default()
                }
            ),
            (
                5,
                QueueDepth {
                    leased: 2,
                    ..QueueDepth::default()
                }
            ),
        ])
    );
    let during = scrape(&daemon);
    assert_eq!(during.value(&queue_frames("leased", 5)), 2.0);
    assert_eq!(during.value(&queue_frames("queued", 0)), 3.0);

    let outcome = |hit| FrameOutcome {
        timings: vec![timing("load", 250.0), timing("rasterize", 2.0)],
        dataset_cache_hit: Some(hit),
        cut: None,
        preview: None,
    };
    daemon
        .complete_frame(&first.lease.id, &test_daemon::png(8, 6), outcome(false))
        .expect("complete");
    daemon
        .fail_frame(&second.lease.id, "GPU lost", FailureKind::Transient)
        .expect("fail");
    // The failed frame again, then the other job.
    let mut frames = 1;
    while let Some(task) = daemon
        .lease_frame("w1", false, &WorkerCapabilities::default())
        .expect("lease")
    {
        daemon
            .complete_frame(&task.lease.id, &test_daemon::png(8, 6), outcome(true))
            .expect("complete");
        frames += 1;
    }
    assert_eq!(frames, 5);
    assert_eq!(
        daemon.job(&job.id).expect("job").state,
        crate::model::JobState::Succeeded
    );
    daemon.metrics.uploaded(1234);

    let text = daemon.metrics_text().expect("text");
    let after = parse(&text);
    for (family, kind) in [
        ("pointfarm_queue_frames", "gauge"),
        ("pointfarm_frames_completed", "counter"),
        ("pointfarm_frames_failed", "counter"),
        ("pointfarm_frame_stage_seconds", "histogram"),
        ("pointfarm_leases_held", "gauge"),
        ("pointfarm_leases_expired", "counter"),
        ("pointfarm_workers_connected", "gauge"),
        ("pointfarm_dataset_cache_hits", "counter"),
        ("pointfarm_dataset_cache_misses", "counter"),
        ("pointfarm_upload_bytes", "counter"),
    ] {
        assert_eq!(
            after.types.get(family).map(String::as_str),
            Some(kind),
            "{family} in {text}"
        );
    }
    after.assert_values(&[
        ("pointfarm_frames_completed_total", 5.0),
        ("pointfarm_frames_failed_total", 1.0),
        ("pointfarm_leases_expired_total", 0.0),
        ("pointfarm_leases_held", 0.0),
        ("pointfarm_dataset_cache_hits_total", 4.0),
        ("pointfarm_dataset_cache_misses_total", 1.0),
        ("pointfarm_upload_bytes_total", 1234.0),
        (r#"pointfarm_frame_stage_seconds_count{stage="load"}"#, 5.0),
        (r#"pointfarm_frame_stage_seconds_sum{stage="load"}"#, 1.25),
        // Buckets double from half a millisecond: 2 ms is within the 4 ms one, 250 ms is
        // not within the 128 ms one.
        (
            r#"pointfarm_frame_stage_seconds_bucket{le="0.004",stage="rasterize"}"#,
            5.0,
        ),
        (
            r#"pointfarm_frame_stage_seconds_bucket{le="0.128",stage="load"}"#,
            0.0,
        ),
        // Nothing left: the default priority's series read 0, the finished job's are gone.
        (&queue_frames("queued", 0), 0.0),
    ]);
    assert!(!text.contains(r#"priority="5""#), "{text}");
}

#[test]
fn an_expired_lease_counts_an_expiry_and_a_failed_attempt() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = test_daemon::open(dir.path(), Duration::from_millis(50));
    submit(&daemon, 1, 0);
    daemon
        .lease_frame("lost", false, &WorkerCapabilities::default())
        .expect("lease")
        .expect("task");
    std::thread::sleep(Duration::from_millis(150));
    assert_eq!(daemon.expire_leases().expect("expire"), 1);
    scrape(&daemon).assert_values(&[
        ("pointfarm_leases_expired_total", 1.0),
        ("pointfarm_frames_failed_total", 1.0),
        (&queue_frames("queued", 0), 1.0),
        ("pointfarm_workers_connected", 0.0),
    ]);
}

#[test]
fn stage_names_from_workers_are_bounded() {
    let stages = StageSeconds::new();
    let many: Vec<StageTiming> = (0..100)
        .map(|i| timing(&format!("stage_{i}"), 1.0))
        .chain([timing("Not A Label", 1.0), timing("nan", f64::NAN)])
        .collect();
    stages.observe(&many);
    let mut registry = Registry::default();
    registry.register("stage", "", stages.family.clone());
    let text = encode(&registry);
    assert_eq!(
        text.matches("stage_count{").count(),
        MAX_STAGES + 1,
        "and one for the others"
    );
    assert_eq!(
        parse(&text).value(r#"stage_count{stage="other"}"#),
        (100 - MAX_STAGES + 1) as f64
    );
}

#[test]
fn a_worker_counts_its_frames_and_caches() {
    let metrics = WorkerMetrics::new();
    metrics.frame_rendered(&FrameOutcome {
        timings: vec![timing("build", 1500.0), timing("shade", 1.0)],
        dataset_cache_hit: None,
        cut: Some(crate::model::FrameCut {
            gpu_hits: 5,
            gpu_uploaded: 3,
            host_hits: 2,
            nodes_read: 1,
            ..Default::default()
        }),
        preview: None,
    });
    metrics.frame_rendered(&FrameOutcome {
        timings: vec![timing("load", 10.0)],
        dataset_cache_hit: Some(true),
        cut: None,
        preview: None,
    });
    metrics.frame_failed();
    let scrape = parse(&metrics.text());
    scrape.assert_values(&[
        ("pointfarm_worker_frames_rendered_total", 2.0),
        ("pointfarm_worker_frames_failed_total", 1.0),
        ("pointfarm_worker_dataset_cache_hits_total", 1.0),
        ("pointfarm_worker_dataset_cache_misses_total", 0.0),
        (
            r#"pointfarm_worker_node_cache_hits_total{cache="gpu"}"#,
            5.0,
        ),
        (
            r#"pointfarm_worker_node_cache_misses_total{cache="host"}"#,
            1.0,
        ),
        (
            r#"pointfarm_worker_frame_stage_seconds_sum{stage="build"}"#,
            1.5,
        ),
    ]);
}

#[test]
fn a_paused_jobs_frames_are_paused_not_queued() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = test_daemon::open(dir.path(), Duration::from_secs(30));
    let held = submit(&daemon, 3, 0);
    submit(&daemon, 2, 0);
    daemon.pause_job(&held.id).expect("pause");
    scrape(&daemon).assert_values(&[
        (&queue_frames("paused", 0), 3.0),
        (&queue_frames("queued", 0), 2.0),
        (&queue_frames("leased", 0), 0.0),
    ]);
    daemon.resume_job(&held.id).expect("resume");
    scrape(&daemon).assert_values(&[
        (&queue_frames("paused", 0), 0.0),
        (&queue_frames("queued", 0), 5.0),
    ]);
}
