//! Job control against a real daemon on a temporary folder: retry, pause and resume,
//! priority, delete and cancel, what each refuses, what a restart keeps; and the checks of
//! names, labels and priorities.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use super::*;
use crate::lease::FailureKind;
use crate::model::FrameState;
use crate::test_daemon::{self, lease as next_lease, render};

fn open(dir: &Path) -> Arc<Daemon> {
    test_daemon::open(dir, Duration::from_secs(60))
}

/// The message of a FailedPrecondition error.
fn refusal(result: Result<Job, DaemonError>) -> String {
    match result {
        Err(DaemonError::FailedPrecondition(message)) => message,
        other => panic!("expected FailedPrecondition, got {other:?}"),
    }
}

#[test]
fn retry_queues_the_failed_frames_again_with_their_attempts_reset() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = test_daemon::open_with(dir.path(), |config| config.max_frame_attempts = 2);
    let job = test_daemon::submit(&daemon, 2, |_| {});
    let first = next_lease(&daemon).expect("frame 0");
    render(&daemon, &first);
    for _ in 0..2 {
        let task = next_lease(&daemon).expect("frame 1");
        daemon
            .fail_frame(&task.lease.id, "no GPU", FailureKind::Transient)
            .expect("fail");
    }
    let failed = daemon.job(&job.id).expect("job");
    assert_eq!(failed.state, JobState::Failed);
    assert_eq!(failed.blocklist.len(), 0, "two failures blocklist no one");

    let retried = daemon.retry_job(&job.id).expect("retry");
    assert_eq!(
        (retried.state, retried.error.clone()),
        (JobState::Running, None)
    );
    assert_eq!(retried.frames_done, 1, "the finished frame stays finished");
    assert_eq!(
        daemon.state.frame(&job.id, 1).expect("frame"),
        Some(FrameState::Pending { attempts: 0 })
    );
    // Attempts start from zero: two more failures are allowed before the job fails again.
    let task = next_lease(&daemon).expect("frame 1 again");
    assert_eq!(
        (task.lease.job_id.as_str(), task.lease.index),
        (job.id.as_str(), 1)
    );
    assert_eq!(task.failed_attempts, 0);
    daemon
        .fail_frame(&task.lease.id, "no GPU", FailureKind::Transient)
        .expect("fail");
    assert_eq!(daemon.job(&job.id).expect("job").state, JobState::Running);
    let task = next_lease(&daemon).expect("frame 1 once more");
    assert_eq!(render(&daemon, &task).state, JobState::Succeeded);

    let message = refusal(daemon.retry_job(&job.id));
    assert_eq!(
        message,
        format!(
            "job {} is succeeded; only a failed job can be retried",
            job.id
        )
    );
    let cancelled = test_daemon::submit(&daemon, 1, |_| {});
    daemon.cancel_job(&cancelled.id).expect("cancel");
    assert_eq!(
        refusal(daemon.retry_job(&cancelled.id)),
        format!(
            "job {} was cancelled; only a failed job can be retried",
            cancelled.id
        )
    );
}

#[test]
fn a_job_failed_along_its_chain_is_retried_only_after_the_job_before_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = open(dir.path());
    let first = test_daemon::submit(&daemon, 1, |_| {});
    let second = test_daemon::submit(&daemon, 1, |r| r.after_job_ids = vec![first.id.clone()]);
    let task = next_lease(&daemon).expect("the first job's frame");
    daemon
        .fail_frame(&task.lease.id, "unreadable", FailureKind::Permanent)
        .expect("fail");
    assert_eq!(daemon.job(&second.id).expect("job").state, JobState::Failed);
    let message = refusal(daemon.retry_job(&second.id));
    assert!(
        message.contains(&format!("job {} failed; retry that job first", first.id)),
        "{message}"
    );
    daemon.retry_job(&first.id).expect("retry the first");
    daemon.retry_job(&second.id).expect("then the second");
    let task = next_lease(&daemon).expect("the first job's frame again");
    assert_eq!(task.lease.job_id, first.id);
    render(&daemon, &task);
    let task = next_lease(&daemon).expect("the second's");
    assert_eq!(render(&daemon, &task).state, JobState::Succeeded);
}

#[test]
fn a_paused_job_is_leased_nothing_while_its_frames_in_flight_finish() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = open(dir.path());
    let job = test_daemon::submit(&daemon, 2, |_| {});
    let in_flight = next_lease(&daemon).expect("frame 0");
    assert_eq!(
        daemon.pause_job(&job.id).expect("pause").state,
        JobState::Paused
    );
    assert!(
        next_lease(&daemon).is_none(),
        "a paused job is leased nothing"
    );
    assert_eq!(
        daemon
            .job_availability(&daemon.job(&job.id).expect("job"))
            .waiting,
        Some("paused: no frame of it is leased until it is resumed".into())
    );
    let finished = render(&daemon, &in_flight);
    assert_eq!(
        (finished.state, finished.frames_done),
        (JobState::Paused, 1)
    );
    let again = daemon.pause_job(&job.id).expect("pause twice");
    assert_eq!(again, finished, "pausing a paused job changes nothing");

    assert_eq!(
        daemon.resume_job(&job.id).expect("resume").state,
        JobState::Queued
    );
    let resumed = daemon.job(&job.id).expect("job");
    assert_eq!(daemon.resume_job(&job.id).expect("resume twice"), resumed);
    let task = next_lease(&daemon).expect("frame 1, once resumed");
    assert_eq!(render(&daemon, &task).state, JobState::Succeeded);
    assert_eq!(
        refusal(daemon.pause_job(&job.id)),
        format!(
            "job {} already succeeded; only a queued or running job can be paused",
            job.id
        )
    );
    assert!(refusal(daemon.resume_job(&job.id)).contains("already succeeded"));
}

#[test]
fn a_higher_priority_leases_a_younger_job_first() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = open(dir.path());
    let older = test_daemon::submit(&daemon, 2, |_| {});
    let younger = test_daemon::submit(&daemon, 2, |_| {});
    let raised = daemon.set_job_priority(&younger.id, 50).expect("priority");
    assert_eq!(raised.spec.priority, 50);
    let order: Vec<String> = std::iter::from_fn(|| next_lease(&daemon))
        .map(|task| task.lease.job_id)
        .collect();
    assert_eq!(
        order,
        [&younger.id, &younger.id, &older.id, &older.id].map(String::clone),
        "the higher priority first, then the older job"
    );
    assert!(matches!(
        daemon.set_job_priority(&older.id, 101),
        Err(DaemonError::InvalidArgument { .. })
    ));
}

#[test]
fn deleting_removes_the_job_its_frames_and_fails_the_jobs_after_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = open(dir.path());
    let done = test_daemon::submit(&daemon, 1, |r| r.request_id = "the-request".into());
    let task = next_lease(&daemon).expect("frame");
    render(&daemon, &task);
    let frames = daemon.config.frames_dir(&done.id);
    assert!(frames.join("frame_00000.png").exists());
    let waiting_on = test_daemon::submit(&daemon, 1, |_| {});
    daemon.pause_job(&waiting_on.id).expect("pause");
    let after = test_daemon::submit(&daemon, 1, |r| {
        r.after_job_ids = vec![done.id.clone(), waiting_on.id.clone()]
    });

    let deleted = daemon.delete_job(&done.id, false).expect("delete");
    assert_eq!(deleted.state, JobState::Succeeded);
    assert!(matches!(
        daemon.job(&done.id),
        Err(DaemonError::NotFound(_))
    ));
    assert!(!frames.exists(), "its frames are gone");
    let failed = daemon.job(&after.id).expect("job");
    assert_eq!(
        (failed.state, failed.error),
        (
            JobState::Failed,
            Some(format!("job {} it runs after was deleted", done.id))
        )
    );
    // The request id is free again: the same submission makes a new job.
    let again = test_daemon::submit(&daemon, 1, |r| r.request_id = "the-request".into());
    assert_ne!(again.id, done.id);

    let message = refusal(daemon.delete_job(&waiting_on.id, false));
    assert!(message.contains("is paused; cancel it first"), "{message}");
    let forced = daemon.delete_job(&waiting_on.id, true).expect("force");
    assert_eq!(forced.state, JobState::Cancelled);
    assert!(matches!(
        daemon.job(&waiting_on.id),
        Err(DaemonError::NotFound(_))
    ));
    // A restart finds no folder of frames without its job.
    drop(daemon);
    let daemon = open(dir.path());
    assert!(matches!(
        daemon.job(&done.id),
        Err(DaemonError::NotFound(_))
    ));
}

#[test]
fn cancelling_a_cancelled_job_returns_it_unchanged() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = open(dir.path());
    let job = test_daemon::submit(&daemon, 1, |_| {});
    let cancelled = daemon.cancel_job(&job.id).expect("cancel");
    assert_eq!(cancelled.state, JobState::Cancelled);
    assert_eq!(daemon.cancel_job(&job.id).expect("again"), cancelled);
    let task_job = test_daemon::submit(&daemon, 1, |_| {});
    let task = next_lease(&daemon).expect("frame");
    render(&daemon, &task);
    assert_eq!(
        refusal(daemon.cancel_job(&task_job.id)),
        format!("job {} already succeeded; nothing to cancel", task_job.id)
    );
}

#[test]
fn a_restart_keeps_names_labels_priorities_and_pauses() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = open(dir.path());
    let job = test_daemon::submit(&daemon, 1, |r| {
        r.name = "hall, east wing".into();
        r.labels = [("shot".to_string(), "010".to_string())].into();
    });
    daemon.set_job_priority(&job.id, -7).expect("priority");
    daemon.pause_job(&job.id).expect("pause");
    drop(daemon);

    let daemon = open(dir.path());
    let kept = daemon.job(&job.id).expect("job");
    assert_eq!(kept.spec.name, "hall, east wing");
    assert_eq!(
        kept.spec.labels.get("shot").map(String::as_str),
        Some("010")
    );
    assert_eq!((kept.spec.priority, kept.state), (-7, JobState::Paused));
    assert!(next_lease(&daemon).is_none(), "still paused");
    let filter = JobFilter {
        state: None,
        labels: [("shot".to_string(), "010".to_string())].into(),
    };
    let found = daemon.find_jobs(&filter, 10, "").expect("find").items;
    assert_eq!(found.len(), 1);
    let other = JobFilter {
        labels: [("shot".to_string(), "020".to_string())].into(),
        ..filter
    };
    assert!(daemon
        .find_jobs(&other, 10, "")
        .expect("find")
        .items
        .is_empty());
}

#[test]
fn names_labels_and_priorities_are_checked() {
    assert!(check_name("name", "turntable of the hall").is_ok());
    assert!(check_name("name", &"é".repeat(MAX_NAME_CHARS)).is_ok());
    assert!(check_name("name", &"a".repeat(MAX_NAME_CHARS + 1)).is_err());
    assert!(check_name("name", "two\nlines").is_err());

    let labels = |pairs: &[(&str, &str)]| -> BTreeMap<String, String> {
        pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect()
    };
    assert!(check_labels("labels", &labels(&[("shot", "010"), ("team.a_b-c", "")])).is_ok());
    for bad_key in ["", "Shot", "shot name", "shot/1", &"k".repeat(64)] {
        let result = check_labels("labels", &labels(&[(bad_key, "v")]));
        assert!(result.is_err(), "{bad_key:?} accepted");
    }
    let long_value = "v".repeat(MAX_LABEL_VALUE_BYTES + 1);
    match check_labels("labels", &labels(&[("shot", &long_value)])) {
        Err(DaemonError::InvalidArgument { field, .. }) => assert_eq!(field, "labels[shot]"),
        other => panic!("{other:?}"),
    }
    let many: BTreeMap<String, String> = (0..=MAX_LABELS)
        .map(|i| (format!("k{i}"), String::new()))
        .collect();
    assert!(check_labels("labels", &many).is_err());

    assert!(check_priority("priority", 100).is_ok());
    assert!(check_priority("priority", -100).is_ok());
    assert!(check_priority("priority", -101).is_err());
}

/// An HTTP endpoint on loopback that answers every POST with 200 and keeps the `event` of
/// each body, in the order they came.
fn webhook_receiver() -> (String, Arc<std::sync::Mutex<Vec<String>>>) {
    use std::io::{BufRead, BufReader, Read, Write};
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let url = format!("http://{}/hook", listener.local_addr().expect("address"));
    let events = Arc::new(std::sync::Mutex::new(Vec::new()));
    let received = Arc::clone(&events);
    std::thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            let mut reader = BufReader::new(stream);
            let mut length = 0;
            loop {
                let mut line = String::new();
                if reader.read_line(&mut line).unwrap_or(0) == 0 || line == "\r\n" {
                    break;
                }
                if let Some((name, value)) = line.split_once(':') {
                    if name.eq_ignore_ascii_case("content-length") {
                        length = value.trim().parse().unwrap_or(0);
                    }
                }
            }
            let mut body = vec![0; length];
            if reader.read_exact(&mut body).is_err() {
                continue;
            }
            let body: serde_json::Value = serde_json::from_slice(&body).unwrap_or_default();
            let event = body["event"].as_str().unwrap_or_default().to_owned();
            received.lock().expect("events").push(event);
            let _ = reader
                .get_mut()
                .write_all(b"HTTP/1.1 200 OK\r\ncontent-length: 0\r\nconnection: close\r\n\r\n");
        }
    });
    (url, events)
}

#[test]
fn only_ends_reach_the_webhooks_and_a_forced_delete_is_a_cancellation() {
    use crate::webhooks::{SecretSource, WebhookEndpoint, WebhookSpec};
    let (url, events) = webhook_receiver();
    let spec = WebhookSpec::new(&url, Some(SecretSource::Env("HOOK_SECRET".into())));
    let endpoint =
        WebhookEndpoint::load_with_env(&spec, |_| Some("s3cret".into())).expect("endpoint");
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = test_daemon::open_with(dir.path(), |config| config.webhooks = vec![endpoint]);

    let retried = test_daemon::submit(&daemon, 1, |_| {});
    daemon.pause_job(&retried.id).expect("pause");
    daemon.resume_job(&retried.id).expect("resume");
    daemon.set_job_priority(&retried.id, 9).expect("priority");
    let task = next_lease(&daemon).expect("frame");
    daemon
        .fail_frame(&task.lease.id, "unreadable", FailureKind::Permanent)
        .expect("fail");
    daemon.retry_job(&retried.id).expect("retry");
    let task = next_lease(&daemon).expect("frame again");
    render(&daemon, &task);
    let deleted = test_daemon::submit(&daemon, 1, |_| {});
    daemon.pause_job(&deleted.id).expect("pause");
    daemon.delete_job(&deleted.id, true).expect("delete");
    daemon
        .delete_job(&retried.id, false)
        .expect("delete an ended job");

    let expected = ["job.failed", "job.succeeded", "job.cancelled"];
    let waited = std::time::Instant::now();
    while events.lock().expect("events").len() < expected.len()
        && waited.elapsed() < Duration::from_secs(20)
    {
        std::thread::sleep(Duration::from_millis(20));
    }
    // Anything spurious would have come by now, after the ends it followed.
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(*events.lock().expect("events"), expected);
}
