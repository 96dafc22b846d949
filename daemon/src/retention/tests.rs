//! The retention rules against a real daemon on a temporary folder, with the clock moved by
//! the sweep's "now" rather than waited for.

use std::time::Duration;

use super::*;
use crate::model::JobState;
use crate::test_daemon::{self, png};

/// Renders every frame that can be leased now.
fn render_all(daemon: &Daemon) {
    while let Some(task) = test_daemon::lease(daemon) {
        test_daemon::render(daemon, &task);
    }
}

fn exists(daemon: &Daemon, job: &Job) -> bool {
    daemon.state.job(&job.id).expect("read").is_some()
}

#[test]
fn jobs_that_ended_longer_ago_than_the_retention_go_with_their_frames() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = test_daemon::open_with(dir.path(), |config| {
        config.job_retention = Some(Duration::from_secs(3600));
    });
    let ended = test_daemon::submit(&daemon, 2, |_| {});
    render_all(&daemon);
    let cancelled = test_daemon::submit(&daemon, 1, |_| {});
    daemon.cancel_job(&cancelled.id).expect("cancel");
    let unfinished = test_daemon::submit(&daemon, 1, |_| {});
    let ended_at = daemon.job(&cancelled.id).expect("job").updated_unix_ms;

    let within = daemon.sweep_retention(ended_at + 3_599_000).expect("sweep");
    assert_eq!(
        within,
        RetentionSweep::default(),
        "nothing is old enough yet"
    );
    let later = ended_at + 3_601_000;
    let swept = daemon.sweep_retention(later).expect("sweep");
    assert_eq!(swept.expired, vec![ended.id.clone(), cancelled.id.clone()]);
    assert!(!exists(&daemon, &ended) && !exists(&daemon, &cancelled));
    assert!(!daemon.config.frames_dir(&ended.id).exists());
    assert!(
        exists(&daemon, &unfinished),
        "an unfinished job is never removed"
    );
    let text = daemon.metrics_text().expect("metrics");
    assert!(
        text.contains(r#"pointfarm_jobs_removed_total{reason="retention"} 2"#),
        "{text}"
    );
}

#[test]
fn over_the_frame_quota_the_jobs_that_ended_first_go_first() {
    let dir = tempfile::tempdir().expect("tempdir");
    let frame_bytes = png(8, 6).len() as u64;
    // Room for three frames: of the two-frame jobs, only the last one stays.
    let daemon = test_daemon::open_with(dir.path(), |config| {
        config.frame_quota_bytes = Some(3 * frame_bytes);
    });
    let jobs: Vec<Job> = (0..3)
        .map(|_| {
            let job = test_daemon::submit(&daemon, 2, |_| {});
            render_all(&daemon);
            job
        })
        .collect();
    let unfinished = test_daemon::submit(&daemon, 1, |_| {});
    let swept = daemon.sweep_retention(now_unix_ms()).expect("sweep");
    assert_eq!(
        swept.over_quota,
        vec![jobs[0].id.clone(), jobs[1].id.clone()]
    );
    assert!(swept.expired.is_empty());
    assert_eq!(swept.frame_bytes, 2 * frame_bytes);
    assert!(exists(&daemon, &jobs[2]) && exists(&daemon, &unfinished));
    assert_eq!(
        daemon.job(&jobs[2].id).expect("job").state,
        JobState::Succeeded
    );
    let again = daemon.sweep_retention(now_unix_ms()).expect("sweep");
    assert!(
        again.over_quota.is_empty(),
        "within the quota: nothing more goes"
    );
}
