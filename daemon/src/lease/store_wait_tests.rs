//! Final frames wait for their store while it builds, against a real build held at a gate:
//! other jobs' frames go out meanwhile, and the build's end wakes the lease long poll.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use pointfarm_proto::v1 as pb;
use pointfarm_render::ingest::{write_las, LasWriteOptions};

use super::*;
use crate::model::JobSpec;
use crate::stores::{StoreAnswer, StoreBuildGate};
use crate::test_daemon;

/// Registers the file `name` under the test daemon's data root and submits a turntable of
/// `frames` frames on it, cut from levels of detail when `lod_error` is set.
fn submit_on(daemon: &Daemon, name: &str, frames: u32, lod_error: Option<f64>) -> Job {
    let dataset = daemon
        .register_dataset(&[name.to_owned()], name)
        .expect("register");
    let request = pb::SubmitJobRequest {
        dataset_id: dataset.id,
        camera_path: Some(pb::CameraPath::turntable(pb::Turntable::of_frames(frames))),
        width: 8,
        height: 6,
        render: Some(pb::RenderOptions {
            lod_error,
            ..Default::default()
        }),
        request_id: name.to_owned(),
        ..Default::default()
    };
    daemon
        .submit_job(JobSpec::try_from(&request).expect("spec"))
        .expect("submit")
}

/// A daemon in `dir` whose store builds wait at `gate`, with a LAS file of the sample scene
/// under its data root as `scene.las`.
fn gated_daemon(dir: &Path, gate: &StoreBuildGate) -> Arc<Daemon> {
    let daemon = test_daemon::open_with(dir, |config| {
        config.lease_timeout = Duration::from_secs(60);
        config.store_build_gate = Some(gate.clone());
    });
    let scene = pointfarm_render::sample::sample_scene(20_000, 3);
    let path = dir.join("roots").join("scene.las");
    write_las(&path, &scene, &LasWriteOptions::default()).expect("write");
    daemon
}

fn try_lease(daemon: &Daemon) -> Option<FrameTask> {
    daemon
        .lease_frame("w", false, &WorkerCapabilities::default())
        .expect("lease")
}

/// Leases as the gRPC long poll does: again each time the work signal is raised, until a
/// frame goes out or `limit` passes.
fn lease_when_woken(daemon: &Daemon, limit: Duration) -> Option<FrameTask> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_time()
        .build()
        .expect("runtime");
    let mut work = daemon.work.subscribe();
    runtime.block_on(async {
        let deadline = tokio::time::Instant::now() + limit;
        loop {
            work.borrow_and_update();
            if let Some(task) = try_lease(daemon) {
                return Some(task);
            }
            match tokio::time::timeout_at(deadline, work.changed()).await {
                Ok(Ok(())) => {}
                _ => return None,
            }
        }
    })
}

#[test]
fn a_final_frame_waits_while_its_store_builds_and_goes_out_when_it_is_ready() {
    let dir = tempfile::tempdir().expect("tempdir");
    let gate = StoreBuildGate::closed();
    let daemon = gated_daemon(dir.path(), &gate);
    let job = submit_on(&daemon, "scene.las", 2, Some(1.0));

    // Nothing builds yet: the frame goes out, and its worker's open starts the build.
    let first = try_lease(&daemon).expect("a frame before any build");
    assert_eq!(
        (first.lease.job_id.as_str(), first.lease.index),
        (job.id.as_str(), 0)
    );
    let opened = daemon
        .open_dataset_store(&first.dataset.id, true)
        .expect("open");
    assert!(matches!(opened, StoreAnswer::Building { .. }));
    daemon.release_frame(&first.lease.id).expect("release");
    assert!(
        try_lease(&daemon).is_none(),
        "a final frame whose store builds is held"
    );
    // A connected worker could take it: the job says it waits for its store.
    let _present = daemon.workers.poll_named(
        false,
        "w",
        WorkerCapabilities::default(),
        Duration::from_secs(60),
    );
    let held = daemon.state.job(&job.id).expect("state").expect("the job");
    assert_eq!(
        daemon.job_availability(&held).waiting.as_deref(),
        Some(crate::availability::STORE_BUILDING)
    );

    // Another job's frames still go out (a file rendered resident, no store).
    let other = submit_on(&daemon, "a.las", 1, None);
    let task = try_lease(&daemon).expect("the other job's frame");
    assert_eq!(task.lease.job_id, other.id);
    daemon.release_frame(&task.lease.id).expect("release");
    daemon.cancel_job(&other.id).expect("cancel");
    assert!(
        try_lease(&daemon).is_none(),
        "still held while the build waits"
    );

    // The build's end wakes the long poll, and the held frame goes out at once.
    gate.open();
    let task =
        lease_when_woken(&daemon, Duration::from_secs(60)).expect("woken by the ready store");
    assert_eq!(
        (task.lease.job_id.as_str(), task.lease.index),
        (job.id.as_str(), 0)
    );
    assert!(task.preview().is_none(), "leased for its final render");
    let opened = daemon
        .open_dataset_store(&task.dataset.id, true)
        .expect("open");
    assert!(
        matches!(opened, StoreAnswer::Ready(_)),
        "the frame went out only once its store was ready"
    );
}

/// A previewed job's frames are not held: each is offered for a preview while the store builds.
#[test]
fn a_previewed_job_is_offered_its_previews_while_its_store_builds() {
    let dir = tempfile::tempdir().expect("tempdir");
    let gate = StoreBuildGate::closed();
    let daemon = gated_daemon(dir.path(), &gate);
    let dataset = daemon
        .register_dataset(&["scene.las".to_owned()], "scene")
        .expect("register");
    let started = daemon.open_dataset_store(&dataset.id, true).expect("open");
    assert!(matches!(started, StoreAnswer::Building { .. }));
    let job = test_daemon::submit(&daemon, 2, |r| {
        r.preview = true;
        r.render = Some(pb::RenderOptions {
            lod_error: Some(1.0),
            ..Default::default()
        });
    });
    for index in 0..2 {
        let task = try_lease(&daemon).expect("a preview while the store builds");
        assert_eq!(
            (task.lease.job_id.as_str(), task.lease.index),
            (job.id.as_str(), index)
        );
        assert_eq!(task.preview(), Some(0));
    }
}
