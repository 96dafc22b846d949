//! The scheduling index: order, what leaves it, and its rebuilding in an older database.

use std::collections::HashSet;

use pointfarm_render::request::{CameraPath, Lens, RenderOptions, RenderRequest, Turntable};

use super::*;

fn spec(request_id: &str, frames: u32, priority: i32) -> JobSpec {
    JobSpec {
        request_id: request_id.into(),
        dataset_id: "ds-1".into(),
        request: RenderRequest {
            width: 8,
            height: 8,
            camera_path: CameraPath::Turntable(Turntable::around_the_cloud(frames)),
            lens: Lens::default(),
            render: RenderOptions::default(),
        },
        priority,
    }
}

fn open(path: &std::path::Path) -> Store {
    Store::open(path, false).expect("open").0
}

/// The order in which frames are handed out while none is given back.
fn schedule(store: &Store) -> Vec<(String, u32)> {
    let (mut order, mut leased) = (Vec::new(), HashSet::new());
    while let Some((job, index)) = store.next_task(&leased).expect("next") {
        leased.insert((job.id.clone(), index));
        order.push((job.id, index));
    }
    order
}

#[test]
fn frames_are_scheduled_by_priority_then_age_then_index() {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = open(&dir.path().join("state.sled"));
    let (low, _) = store.submit_job(spec("low", 2, -5)).expect("submit");
    let (old, _) = store.submit_job(spec("old", 2, 0)).expect("submit");
    let (high, _) = store.submit_job(spec("high", 1, 7)).expect("submit");
    let (new, _) = store.submit_job(spec("new", 1, 0)).expect("submit");
    assert_eq!(
        schedule(&store),
        [
            (high.id, 0),
            (old.id.clone(), 0),
            (old.id, 1),
            (new.id, 0),
            (low.id.clone(), 0),
            (low.id, 1)
        ]
    );
}

#[test]
fn done_frames_and_ended_jobs_leave_the_schedule() {
    let dir = tempfile::tempdir().expect("tempdir");
    let store = open(&dir.path().join("state.sled"));
    let (first, _) = store.submit_job(spec("a", 3, 0)).expect("submit");
    let (second, _) = store.submit_job(spec("b", 2, 0)).expect("submit");
    let report = FrameReport {
        index: 0,
        timings: Vec::new(),
        dataset_cache_hit: None,
        failed_attempts: 0,
    };
    store
        .set_frame(&first.id, 0, &FrameState::Done(report))
        .expect("done");
    store
        .update_job(&second.id, |j| j.state = JobState::Cancelled)
        .expect("cancel");
    assert_eq!(
        schedule(&store),
        [(first.id.clone(), 1), (first.id.clone(), 2)]
    );
    // A failed attempt keeps the frame pending.
    store
        .set_frame(&first.id, 1, &FrameState::Pending { attempts: 1 })
        .expect("retry");
    assert_eq!(schedule(&store), [(first.id.clone(), 1), (first.id, 2)]);
}

#[test]
fn a_database_without_the_index_gets_it_when_opened() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("state.sled");
    let scheduled = {
        let store = open(&path);
        store.submit_job(spec("a", 2, 0)).expect("submit");
        store.submit_job(spec("b", 1, 3)).expect("submit");
        let scheduled = schedule(&store);
        // As a database written before the index existed.
        for tree in [&store.trees.queue, &store.trees.pending, &store.trees.meta] {
            tree.clear().expect("clear");
        }
        store.flush().expect("flush");
        assert!(schedule(&store).is_empty());
        scheduled
    };
    assert_eq!(schedule(&open(&path)), scheduled);
}
