//! Job chains through real daemons: a job submitted after others renders only once they have
//! succeeded, fails along the chain when one is cancelled, keeps its chain across a restart,
//! and `pointfarm render --server --detach --after` builds such chains from a script.

use pointfarm_daemon::access::Access;
use pointfarm_proto::v1 as pb;
use pointfarm_tests::service::{
    cancel, clients, get_job, left_the_queue_at, queued_farm, submit, turntable_job, watch_to_end,
    watch_to_success, DetachedFarm, TestDaemon,
};
use pointfarm_tests::{pointfarm, stdout};

/// A turntable of `frames` frames that runs after `after`.
fn job_after(
    name: &str,
    dataset_id: &str,
    frames: u32,
    after: &[&pb::Job],
) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        after_job_ids: after.iter().map(|job| job.id.clone()).collect(),
        ..turntable_job(name, dataset_id, frames, 32, 24)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_after_another_renders_only_once_it_has_succeeded() {
    let daemon = TestDaemon::start(|_| {}, Access::default()).await;
    let (daemon, dataset, mut jobs) = daemon.with_sample(20_000, 3).await;
    let first = submit(&mut jobs, turntable_job("first", &dataset.id, 3, 32, 24)).await;
    // Of a higher priority: without its chain it would be leased first.
    let second_request = pb::SubmitJobRequest {
        priority: 10,
        ..job_after("second", &dataset.id, 2, &[&first])
    };
    let second = submit(&mut jobs, second_request).await;
    assert_eq!(second.after_job_ids, vec![first.id.clone()]);

    let (mut watcher, id) = (jobs.clone(), second.id.clone());
    let started = tokio::spawn(async move { left_the_queue_at(&mut watcher, &id).await });
    let (first_done, _) = watch_to_success(&mut jobs, &first.id, String::new).await;
    let started = started.await.expect("the watch of the second job");
    assert!(
        started >= first_done.updated_unix_ms,
        "the second job left the queue at {started}, before the first succeeded at {}",
        first_done.updated_unix_ms
    );
    let (second_done, frames) = watch_to_success(&mut jobs, &second.id, String::new).await;
    assert_eq!((second_done.frames_done, frames.len()), (2, 2));
    assert_eq!(second_done.after_job_ids, vec![first.id.clone()]);
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cancelled_job_fails_the_chain_after_it_and_unknown_jobs_are_refused() {
    // No worker: the jobs stay queued until the cancel.
    let (daemon, dataset, mut jobs) = queued_farm(|_| {}, 5_000, 4).await;
    let first = submit(&mut jobs, turntable_job("first", &dataset.id, 2, 32, 24)).await;
    let second = submit(&mut jobs, job_after("second", &dataset.id, 2, &[&first])).await;
    let third = submit(&mut jobs, job_after("third", &dataset.id, 2, &[&second])).await;
    let waiting = get_job(&mut jobs, &second.id).await;
    assert_eq!(
        waiting.waiting_reason,
        format!("waiting for job {} to succeed", first.id)
    );

    let unknown = pb::SubmitJobRequest {
        after_job_ids: vec![first.id.clone(), "job-000000009999".into()],
        ..turntable_job("unknown", &dataset.id, 2, 32, 24)
    };
    let refused = jobs.submit_job(unknown).await.expect_err("refused");
    assert_eq!(refused.code(), tonic::Code::NotFound);
    assert!(
        refused.message().contains("job job-000000009999"),
        "{}",
        refused.message()
    );

    cancel(&mut jobs, &first.id).await;
    let (second_end, _) = watch_to_end(&mut jobs, &second.id).await;
    assert_eq!(second_end.state, pb::JobState::Failed as i32);
    assert_eq!(second_end.error, format!("job {} was cancelled", first.id));
    let (third_end, _) = watch_to_end(&mut jobs, &third.id).await;
    assert_eq!(third_end.state, pb::JobState::Failed as i32);
    assert_eq!(third_end.error, format!("job {} failed", second.id));
    daemon.stop().await;
}

/// A detached render to `farm` with `more` arguments, which must succeed; its stdout.
fn render_detached(farm: &DetachedFarm, more: &[&str]) -> String {
    let output = farm.render(more);
    assert!(output.status.success(), "{output:?}");
    stdout(&output)
}

#[test]
fn detached_renders_chain_jobs_that_a_restart_keeps() {
    // No worker: a detached render must return while its job is still queued.
    let mut farm = DetachedFarm::start(5_000, 5);
    let address = farm.address.clone();

    let first = render_detached(&farm, &[]).trim().to_owned();
    assert!(first.starts_with("job-"), "only the job's id: {first:?}");
    let second = render_detached(&farm, &["--after", &first])
        .trim()
        .to_owned();
    assert!(second.starts_with("job-"), "only the job's id: {second:?}");
    let with_json = render_detached(&farm, &["--json", "--after", &second]);
    let third: serde_json::Value = serde_json::from_str(with_json.trim()).expect("one JSON line");
    assert_eq!(third["afterJobIds"], serde_json::json!([second]));
    let third = third["id"].as_str().expect("the job's id").to_owned();
    let fetched = std::fs::read_dir(&farm.out).map_or(0, |frames| frames.count());
    assert_eq!(fetched, 0, "a detached render fetches no frame");
    let shown = pointfarm(&["jobs", "show", &second, "--server", &address]);
    let shown = stdout(&shown);
    assert!(shown.contains(&format!("runs after: {first}")), "{shown}");
    assert!(
        shown.contains(&format!("waiting: waiting for job {first} to succeed")),
        "{shown}"
    );

    // Killed and started again, now with a worker: the chain holds and runs in order.
    farm.restart(&[]);
    let runtime = tokio::runtime::Runtime::new().expect("runtime");
    runtime.block_on(async {
        let (_, mut jobs) = clients(&address).await;
        let kept = get_job(&mut jobs, &third).await;
        assert_eq!(kept.after_job_ids, vec![second.clone()]);
        let mut ends = Vec::new();
        for id in [&first, &second, &third] {
            let (done, _) = watch_to_success(&mut jobs, id, || farm.server.log()).await;
            ends.push(done.updated_unix_ms);
        }
        assert!(
            ends.is_sorted(),
            "each job ends after the one before: {ends:?}"
        );
    });
}
