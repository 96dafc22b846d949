//! The scheduling index: order, what leaves it, and its rebuilding in an older database; a
//! database on a real disk that fills up and empties again.

use std::collections::HashSet;

use pointfarm_render::request::RenderRequest;

use super::*;

fn spec(request_id: &str, frames: u32, priority: i32) -> JobSpec {
    let request = RenderRequest::turntable(8, 8, frames);
    JobSpec {
        priority,
        ..JobSpec::new(request_id.into(), "ds-1".into(), request)
    }
}

/// Submits a job of `frames` frames that renders previews to `state`.
fn submit_preview_job(state: &StateDb, frames: u32) -> Job {
    let spec = JobSpec {
        preview: true,
        ..spec("a", frames, 0)
    };
    state.submit_job(spec).expect("submit").0
}

/// The state database `state.sled` in `dir`.
fn open(dir: &std::path::Path) -> StateDb {
    StateDb::open(&dir.join("state.sled"), false)
        .expect("open")
        .0
}

/// The order in which frames are handed out while none is given back.
fn schedule(state: &StateDb) -> Vec<(String, u32)> {
    let (mut order, mut leased) = (Vec::new(), HashSet::new());
    while let Some((job, index)) = state
        .next_task(&leased, &|_| true, &|_, _| Some(0))
        .expect("next")
    {
        leased.insert((job.id.clone(), index));
        order.push((job.id, index));
    }
    order
}

#[test]
fn frames_are_scheduled_by_priority_then_age_then_index() {
    let dir = tempfile::tempdir().expect("tempdir");
    let state = open(dir.path());
    let (low, _) = state.submit_job(spec("low", 2, -5)).expect("submit");
    let (old, _) = state.submit_job(spec("old", 2, 0)).expect("submit");
    let (high, _) = state.submit_job(spec("high", 1, 7)).expect("submit");
    let (new, _) = state.submit_job(spec("new", 1, 0)).expect("submit");
    assert_eq!(
        schedule(&state),
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
    let state = open(dir.path());
    let (first, _) = state.submit_job(spec("a", 3, 0)).expect("submit");
    let (second, _) = state.submit_job(spec("b", 2, 0)).expect("submit");
    let report = FrameReport::default();
    state
        .set_frame(&first.id, 0, &FrameState::Done(report))
        .expect("done");
    state
        .update_job(&second.id, |j| j.state = JobState::Cancelled)
        .expect("cancel");
    assert_eq!(
        schedule(&state),
        [(first.id.clone(), 1), (first.id.clone(), 2)]
    );
    // A failed attempt keeps the frame pending.
    state
        .set_frame(&first.id, 1, &FrameState::Pending { attempts: 1 })
        .expect("retry");
    assert_eq!(schedule(&state), [(first.id.clone(), 1), (first.id, 2)]);
}

#[test]
fn a_database_without_the_index_gets_it_when_opened() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scheduled = {
        let state = open(dir.path());
        state.submit_job(spec("a", 2, 0)).expect("submit");
        state.submit_job(spec("b", 1, 3)).expect("submit");
        let scheduled = schedule(&state);
        // As a database written before the index existed.
        state
            .with(|records| {
                let trees = &records.trees;
                for tree in [&trees.queue, &trees.pending, &trees.meta] {
                    tree.clear()?;
                }
                Ok(())
            })
            .expect("clear");
        state.flush().expect("flush");
        assert!(schedule(&state).is_empty());
        scheduled
    };
    assert_eq!(schedule(&open(dir.path())), scheduled);
}

/// A state database on a small tmpfs that holds one job, the disk then filled: where the
/// full-disk tests start.
struct FullDisk {
    state: StateDb,
    /// The job submitted while there was room.
    before: Job,
    /// The file that fills the disk; removing it makes room again.
    filler: std::path::PathBuf,
    disk: crate::testing::SmallDisk,
}

impl FullDisk {
    /// The job has `frames` frames; None where no tmpfs can be mounted.
    fn after_a_job_of(frames: u32) -> Option<Self> {
        let disk = crate::testing::SmallDisk::mount(16)?;
        let state = open(disk.path());
        let (before, _) = state.submit_job(spec("before", frames, 0)).expect("submit");
        let filler = disk.fill("filler");
        Some(Self {
            state,
            before,
            filler,
            disk,
        })
    }
}

#[test]
fn a_database_the_full_disk_failed_is_opened_again_with_all_it_had_flushed() {
    // The disk first, so dropped last: the database on it closes before it is unmounted.
    let Some(FullDisk {
        disk,
        state,
        before,
        filler,
    }) = FullDisk::after_a_job_of(4)
    else {
        return;
    };
    // Requests ids of a few KiB: the log needs new pages within a few writes. Written past
    // the room check a submission makes, as a frame's records are.
    let refused = (0..1000)
        .map(|i| {
            let spec = spec(&format!("{i:04}{}", "x".repeat(4000)), 1, 0);
            state.with(|records| records.submit_job(spec))
        })
        .find_map(Result::err)
        .expect("the full disk refuses a write");
    assert!(
        matches!(&refused, StateError::Unwritable(m) if m.contains("disk is full")),
        "{refused}"
    );
    assert!(state.outage().is_some());
    assert!(state.disk.database_failed(), "sled met the error");
    assert!(
        !state.end_outage().expect("probe"),
        "the disk is still full"
    );

    std::fs::remove_file(filler).expect("free the disk");
    assert!(state.end_outage().expect("reopen"), "space is back");
    assert!(state.outage().is_none());
    assert_eq!(
        state.job(&before.id).expect("read").map(|j| j.frames_total),
        Some(4),
        "what was flushed before the outage is kept"
    );
    let (after, created) = state.submit_job(spec("after", 1, 0)).expect("writes again");
    assert!(created);
    assert!(after.id > before.id, "ids still sort by creation");
    drop(state);
    let reopened = open(disk.path());
    assert!(reopened.job(&after.id).expect("read").is_some());
}

#[test]
fn a_job_submitted_to_a_full_disk_is_refused_before_anyone_sees_it() {
    // The disk first, so dropped last: the database on it closes before it is unmounted.
    let Some(FullDisk {
        disk: _disk,
        state,
        before,
        filler,
    }) = FullDisk::after_a_job_of(2)
    else {
        return;
    };
    let refused = state
        .submit_job(spec("refused", 3, 0))
        .expect_err("no room for the job");
    assert!(
        matches!(&refused, StateError::Unwritable(m) if m.contains("disk is full")),
        "{refused}"
    );
    assert!(state.outage().is_some(), "the refusal starts an outage");
    assert!(
        !state.disk.database_failed(),
        "sled never met the full disk"
    );
    let listed: Vec<String> = state
        .list_jobs(None, 100, "")
        .expect("list")
        .items
        .into_iter()
        .map(|job| job.id)
        .collect();
    assert_eq!(listed, [before.id], "the refused job is nowhere");
    // The same request again, once the disk has room, is a new job.
    std::fs::remove_file(filler).expect("free the disk");
    assert!(state.end_outage().expect("probe"), "space is back");
    let (after, created) = state.submit_job(spec("refused", 3, 0)).expect("room again");
    assert!(created);
    assert_eq!(
        state.job(&after.id).expect("read").map(|j| j.frames_total),
        Some(3)
    );
}

/// A preview kept by a daemon from before preview versions opens as version 0 (the chunk
/// starts alone); a versioned one keeps its version across a reopening.
#[test]
fn a_preview_record_without_a_version_opens_as_version_0() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("state.sled");
    let job_id = {
        let state = open(dir.path());
        let job = submit_preview_job(&state, 2);
        // The record as an older daemon wrote it.
        let old = br#"{"index":0,"timings":[],"dataset_cache_hit":null,"failed_attempts":0,"cut":null,"worker":"w","preview":0.25}"#;
        state
            .with(|records| {
                records
                    .trees
                    .previews
                    .insert(frame_key(&job.id, 0), &old[..])?;
                Ok(())
            })
            .expect("old record");
        let lease = Lease {
            id: "lease-1".into(),
            job_id: job.id.clone(),
            index: 1,
            worker: "w".into(),
            embedded: false,
            expires_unix_ms: 0,
            preview_version: Some(4),
        };
        state.put_lease(&lease).expect("lease");
        let report = FrameReport {
            index: 1,
            preview: Some(0.5),
            preview_version: 4,
            ..FrameReport::default()
        };
        state.keep_preview(&lease, &report).expect("preview");
        job.id
    };
    let (state, loss) = StateDb::open(&path, false).expect("reopen");
    assert!(loss.is_empty(), "every record is readable: {loss:?}");
    assert_eq!(state.preview_version(&job_id, 0).expect("read"), Some(0));
    assert_eq!(state.preview_version(&job_id, 1).expect("read"), Some(4));
    let reports = state.frame_reports(&job_id).expect("reports");
    let versions: Vec<(Option<f64>, u32)> = reports
        .iter()
        .map(|r| (r.preview, r.preview_version))
        .collect();
    assert_eq!(versions, [(Some(0.25), 0), (Some(0.5), 4)]);
    // The scheduler is told each frame's preview version.
    let told = std::cell::RefCell::new(Vec::new());
    let waits = |_: &Job, version: Option<u32>| {
        told.borrow_mut().push(version);
        None
    };
    let next = state.next_task(&HashSet::new(), &|_| true, &waits);
    assert!(next.expect("next").is_none(), "both frames wait");
    assert_eq!(*told.borrow(), [Some(0), Some(4)]);
}

/// Of a preview job, the frame of the lowest turn is taken (the first of equal turns), a
/// frame of turn 0 at once, and one without a turn never; a job without previews is taken in
/// order whatever the turns say.
#[test]
fn a_preview_jobs_frames_are_taken_by_turn() {
    let dir = tempfile::tempdir().expect("tempdir");
    let state = open(dir.path());
    let job = submit_preview_job(&state, 4);
    for (index, version) in [(0, 2), (1, 0), (2, 1), (3, 0)] {
        let lease = Lease {
            id: format!("lease-{index}"),
            job_id: job.id.clone(),
            index,
            worker: "w".into(),
            embedded: false,
            expires_unix_ms: 0,
            preview_version: Some(version),
        };
        state.put_lease(&lease).expect("lease");
        let report = FrameReport {
            index,
            preview: Some(0.5),
            preview_version: version,
            ..FrameReport::default()
        };
        state.keep_preview(&lease, &report).expect("preview");
    }
    // The oldest preview first: the turn is its version and one.
    let oldest_first = |_: &Job, drawn: Option<u32>| drawn.map(|version| version + 1);
    let mut order = Vec::new();
    let mut leased = HashSet::new();
    while let Some((job, index)) = state
        .next_task(&leased, &|_| true, &oldest_first)
        .expect("next")
    {
        leased.insert((job.id, index));
        order.push(index);
    }
    assert_eq!(order, [1, 3, 2, 0]);
    // Frame 2's turn 0 takes it at once, over frame 1 found before it with a later turn;
    // no turn passes a frame over.
    let turns = |_: &Job, drawn: Option<u32>| match drawn {
        Some(2) => None,
        Some(1) => Some(0),
        _ => Some(5),
    };
    let next = state.next_task(&HashSet::new(), &|_| true, &turns);
    assert_eq!(next.expect("next").map(|(_, index)| index), Some(2));
    let only_passed = |_: &Job, _: Option<u32>| None;
    let next = state.next_task(&HashSet::new(), &|_| true, &only_passed);
    assert!(next.expect("next").is_none());

    let (plain, _) = state.submit_job(spec("b", 2, 1)).expect("submit");
    let next = state.next_task(&HashSet::new(), &|_| true, &only_passed);
    assert_eq!(
        next.expect("next").map(|(job, index)| (job.id, index)),
        Some((plain.id, 0))
    );
}
