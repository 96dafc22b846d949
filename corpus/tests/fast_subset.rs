//! The fast subset of the hostile corpus, run as the full one is: every file through the
//! `pointfarm-corpus load` child process. Small written sources (and the real scans when the
//! checkout has them), the headline mutants of every kind: no panic escapes, nothing aborts
//! or times out, every failure is an error naming the file, and no load exceeds twice the
//! file's size plus 256 MiB.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::Duration;

use pointfarm_corpus::corpus_files;
use pointfarm_corpus::generate::{generate, kind_of};
use pointfarm_corpus::mutations::Kind;
use pointfarm_corpus::runner::{run_files, Outcome};
use pointfarm_corpus::summary::Summary;

fn real_scans() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    dir.is_dir().then_some(dir)
}

fn file_name(path: &Path) -> String {
    path.file_name()
        .map(|name| name.to_string_lossy().into_owned())
        .unwrap_or_default()
}

#[test]
fn the_fast_subset_fails_cleanly_within_the_memory_bound() {
    let dir = tempfile::tempdir().expect("temp dir");
    let generated = generate(dir.path(), real_scans().as_deref(), true).expect("generate");
    let files = corpus_files(dir.path()).expect("list");
    assert_eq!(files.len(), generated.sources + generated.mutants);

    let child = Path::new(env!("CARGO_BIN_EXE_pointfarm-corpus"));
    let runs = run_files(child, &files, Duration::from_secs(120), 2, |_, _| {}).expect("run");
    let summary = Summary::of(&runs);
    eprintln!("{summary}");

    let kinds: BTreeSet<Kind> = files.iter().filter_map(|path| kind_of(path)).collect();
    assert_eq!(
        kinds,
        Kind::ALL.into_iter().collect(),
        "every mutation kind"
    );
    for run in &runs {
        let name = file_name(&run.path);
        match &run.outcome {
            Outcome::Loaded(_) => {}
            Outcome::Error { message, .. } | Outcome::ContainedPanic(message) => {
                assert!(
                    message.contains(&name),
                    "{name}: error without the file: {message}"
                );
                assert!(!message.contains('\n'), "{name}: not one line: {message}");
            }
            other => panic!("{name}: {other:?}"),
        }
        assert!(
            run.peak_kib <= run.bound_kib(),
            "{name}: peak {} KiB over the bound {} KiB",
            run.peak_kib,
            run.bound_kib()
        );
        let is_source = kind_of(&run.path).is_none();
        if is_source {
            assert!(
                matches!(run.outcome, Outcome::Loaded(_)),
                "{name}: {:?}",
                run.outcome
            );
        }
    }
}

#[test]
fn headline_field_mutants_are_errors_naming_the_field() {
    let dir = tempfile::tempdir().expect("temp dir");
    generate(dir.path(), None, true).expect("generate");
    let child = Path::new(env!("CARGO_BIN_EXE_pointfarm-corpus"));
    let expectations = [
        (
            "written-v12-f3-2k--header--x-scale=nan.las",
            "x scale factor is NaN",
        ),
        (
            "written-v12-f3-2k--header--x-scale=0.las",
            "x scale factor is zero",
        ),
        (
            "written-v12-f3-2k--header--x-offset=inf.las",
            "x offset is infinite",
        ),
        ("written-v14-f7-2k--evlr--length=1tib.laz", "EVLR 0's data"),
        (
            "written-v14-f7-2k--chunks--chunk-count=4294967295.laz",
            "4294967295 chunks",
        ),
        ("written-v14-f7-2k--laszip--item0-size=0.laz", "of 0 bytes"),
        (
            "written-v12-f3-2k--header--record-length=0.las",
            "point record length 0",
        ),
    ];
    let files: Vec<PathBuf> = expectations
        .iter()
        .map(|(name, _)| dir.path().join("mutants").join(name))
        .collect();
    let runs = run_files(child, &files, Duration::from_secs(60), 2, |_, _| {}).expect("run");
    for (run, (name, expected)) in runs.iter().zip(expectations) {
        match &run.outcome {
            Outcome::Error {
                message,
                names_file: true,
            } => assert!(message.contains(expected), "{name}: {message}"),
            other => panic!("{name}: {other:?}"),
        }
    }
}
