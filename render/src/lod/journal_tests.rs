use super::*;

fn counted() -> Counted {
    let mut stats = DatasetStats::new(true);
    stats.class_counts[2] = 7;
    stats.intensity_histogram[300] = 7;
    stats.z_range = [1.5, 9.0];
    Counted {
        points_read: 7,
        level: 1,
        segment_points: 1_000,
        counts: vec![0, 3, 0, 0, 4, 0, 0, 0],
        stats,
    }
}

fn unit(n: u32) -> UnitRecord {
    let key = NodeKey::new(2, glam::UVec3::new(n, 1, 0));
    UnitRecord {
        kind: UnitKind::Partition,
        key,
        payload_end: 1_000 * u64::from(n + 1),
        waiting: Some(WaitingRoot {
            count: 12,
            sample_grid: 64,
            bytes: 480,
            checksum: 0xfeed + u64::from(n),
        }),
        children: [0; 8],
        nodes: vec![
            NodeInfo {
                point_count: 12,
                byte_len: 200,
                head_len: 100,
                offset: 1_000 * u64::from(n),
                rest_offset: 1_000 * u64::from(n) + 100,
                ..NodeInfo::empty(key.child(3))
            },
            NodeInfo::empty(key.child(5)),
        ],
    }
}

/// A journal with the counting pass and `units` units recorded, as a killed build leaves it.
fn recorded(dir: &Path, inputs: &str, units: u32) -> BuildJournal {
    let (journal, replay) = BuildJournal::open(dir, inputs).expect("open");
    assert!(replay.is_none(), "a fresh folder has nothing to resume");
    journal.record_counted(&counted()).expect("counted");
    for n in 0..units {
        commit_unit(&journal, n);
    }
    journal
}

/// Queues unit `n` and waits until it is durable, with nothing else to sync.
fn commit_unit(journal: &BuildJournal, n: u32) {
    let queued = journal.commit().record(&unit(n)).expect("record");
    queued.wait(|| Ok(())).expect("durable");
}

fn log_len(dir: &Path) -> u64 {
    fs::metadata(dir.join(UNITS_FILE)).expect("log").len()
}

#[test]
fn a_journal_of_the_same_inputs_replays_every_unit() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path().join("build");
    recorded(&dir, "inputs a", 3);
    let (journal, replay) = BuildJournal::open(&dir, "inputs a").expect("reopen");
    let replay = replay.expect("resumed");
    assert_eq!(replay.counted, counted());
    assert_eq!(replay.units, (0..3).map(unit).collect::<Vec<_>>());
    // Units recorded after a resume follow the replayed ones.
    commit_unit(&journal, 3);
    drop(journal);
    let (_, replay) = BuildJournal::open(&dir, "inputs a").expect("reopen");
    assert_eq!(replay.expect("resumed").units.len(), 4);
}

#[test]
fn other_inputs_or_options_start_over() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path().join("build");
    recorded(&dir, "inputs a", 2);
    fs::write(dir.join("bucket-0-0.bin"), b"left by the earlier build").expect("write");
    let (journal, replay) = BuildJournal::open(&dir, "inputs b").expect("open");
    assert!(replay.is_none(), "a journal of other inputs is never read");
    assert!(
        !dir.join("bucket-0-0.bin").exists(),
        "the folder is emptied"
    );
    assert_eq!(log_len(&dir), 0);
    assert!(journal.is_enabled());
    // And the new inputs are what a later run resumes.
    journal.record_counted(&counted()).expect("counted");
    drop(journal);
    let (_, replay) = BuildJournal::open(&dir, "inputs b").expect("reopen");
    assert!(replay.expect("resumed").units.is_empty());
    let (_, replay) = BuildJournal::open(&dir, "inputs a").expect("reopen");
    assert!(replay.is_none());
}

#[test]
fn a_build_killed_before_its_counting_pass_was_recorded_starts_over() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path().join("build");
    let (journal, _) = BuildJournal::open(&dir, "inputs").expect("open");
    drop(journal);
    // A temporary file the rename never replaced is not the record.
    fs::write(dir.join("counted.partial"), b"half a grid").expect("write");
    let (_, replay) = BuildJournal::open(&dir, "inputs").expect("reopen");
    assert!(replay.is_none());
    assert!(!dir.join("counted.partial").exists());
}

#[test]
fn a_torn_last_frame_is_cut_off_and_its_unit_redone() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path().join("build");
    recorded(&dir, "inputs", 3);
    let whole = log_len(&dir);
    let frame = whole / 3;
    // Every length a write of the third frame could have stopped at.
    for torn in [1, FRAME_HEAD as u64 - 1, FRAME_HEAD as u64 + 5, frame - 1] {
        recorded(&dir, "inputs-torn", 0);
        recorded(&dir, "inputs", 3);
        let file = OpenOptions::new()
            .write(true)
            .open(dir.join(UNITS_FILE))
            .expect("log");
        file.set_len(2 * frame + torn).expect("tear");
        let (_, replay) = BuildJournal::open(&dir, "inputs").expect("reopen");
        let units = replay.expect("resumed").units;
        assert_eq!(units, vec![unit(0), unit(1)], "torn after {torn} bytes");
        assert_eq!(log_len(&dir), 2 * frame, "the torn bytes are cut off");
    }
}

#[test]
fn a_damaged_frame_ends_the_log_there() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path().join("build");
    recorded(&dir, "inputs", 3);
    let frame = log_len(&dir) / 3;
    let path = dir.join(UNITS_FILE);
    let mut bytes = fs::read(&path).expect("log");
    bytes[(frame + FRAME_HEAD as u64 + 20) as usize] ^= 0x10;
    fs::write(&path, &bytes).expect("damage");
    let (_, replay) = BuildJournal::open(&dir, "inputs").expect("reopen");
    assert_eq!(replay.expect("resumed").units, vec![unit(0)]);
    assert_eq!(log_len(&dir), frame);
}

#[test]
fn a_damaged_counting_record_starts_over() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path().join("build");
    recorded(&dir, "inputs", 1);
    let path = dir.join(COUNTED_FILE);
    let mut bytes = fs::read(&path).expect("counted");
    bytes[17] ^= 1;
    fs::write(&path, &bytes).expect("damage");
    let (_, replay) = BuildJournal::open(&dir, "inputs").expect("reopen");
    assert!(replay.is_none());
    assert_eq!(log_len(&dir), 0);
}

#[test]
fn a_disabled_journal_writes_nothing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let journal = BuildJournal::disabled(dir.path());
    assert!(!journal.is_enabled());
    let commit = journal.commit();
    let queued = commit.record(&unit(0)).expect("record");
    queued
        .wait(|| panic!("a disabled journal syncs nothing"))
        .expect("durable");
    journal.record_counted(&counted()).expect("counted");
    assert_eq!(journal.committed(UnitKind::Partition), 1);
    assert_eq!(fs::read_dir(dir.path()).expect("dir").count(), 0);
}

#[test]
fn one_flush_makes_every_queued_unit_durable_in_order() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path().join("build");
    let journal = recorded(&dir, "inputs", 0);
    let queued: Vec<_> = (0..3)
        .map(|n| journal.commit().record(&unit(n)).expect("record"))
        .collect();
    assert_eq!(log_len(&dir), 0, "nothing reaches the log before a flush");
    let mut syncs = 0;
    for q in queued.into_iter().rev() {
        q.wait(|| {
            syncs += 1;
            Ok(())
        })
        .expect("durable");
    }
    assert_eq!(syncs, 1, "the last unit's flush covers the two before it");
    drop(journal);
    let (_, replay) = BuildJournal::open(&dir, "inputs").expect("reopen");
    assert_eq!(
        replay.expect("resumed").units,
        (0..3).map(unit).collect::<Vec<_>>()
    );
}

#[test]
fn no_frame_reaches_the_log_when_its_outputs_fail_to_sync() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path().join("build");
    let journal = recorded(&dir, "inputs", 0);
    let first = journal.commit().record(&unit(0)).expect("record");
    let second = journal.commit().record(&unit(1)).expect("record");
    let failed = first.wait(|| {
        Err(LodError::spill(
            &dir,
            std::io::Error::other("the disk is gone"),
        ))
    });
    assert!(failed.is_err());
    assert!(
        second.wait(|| Ok(())).is_err(),
        "its frame was taken by the flush that failed"
    );
    assert_eq!(log_len(&dir), 0);
}

#[test]
fn units_committed_from_many_threads_are_all_replayed() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path().join("build");
    let journal = recorded(&dir, "inputs", 0);
    let syncs = AtomicU64::new(0);
    std::thread::scope(|scope| {
        for t in 0..4 {
            let (journal, syncs) = (&journal, &syncs);
            scope.spawn(move || {
                for n in 0..8 {
                    let queued = journal.commit().record(&unit(t * 8 + n)).expect("record");
                    queued
                        .wait(|| {
                            syncs.fetch_add(1, Ordering::Relaxed);
                            Ok(())
                        })
                        .expect("durable");
                }
            });
        }
    });
    assert!(syncs.load(Ordering::Relaxed) <= 32);
    drop(journal);
    let (_, replay) = BuildJournal::open(&dir, "inputs").expect("reopen");
    let mut keys: Vec<_> = replay
        .expect("resumed")
        .units
        .iter()
        .map(|u| u.key)
        .collect();
    keys.sort_unstable_by_key(|k| (k.level, k.morton()));
    let mut wanted: Vec<_> = (0..32).map(|n| unit(n).key).collect();
    wanted.sort_unstable_by_key(|k| (k.level, k.morton()));
    assert_eq!(keys, wanted);
}
