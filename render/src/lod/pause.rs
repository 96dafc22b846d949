//! The build's test hook: with `POINTFARM_TEST_PAUSE_AT=STAGE:N` in its environment, a build stops
//! for good at that point, after saying so on stderr (`build paused at STAGE:N`), so that a test
//! can kill the process there (tests/build_resume.rs). Stages: `counting:N` as the counting pass
//! takes the source's batch N; `checkpoint:N` once it has recorded its checkpoint N (at the start
//! of a file after the first); `partition:N`, `split:N` and `parent:N` as the unit after the N this
//! run queued of that kind has written its output but not queued its record (records are synced a
//! group at a time, so only on a pool of one thread are those N durable); `hierarchy:0` once every
//! unit is recorded, before the hierarchy is written; `update:0` once a store update has stored its
//! nodes, before it switches to them. Read once, by the build alone; a build without the variable
//! never stops.

use std::io::Write;
use std::sync::OnceLock;

const VARIABLE: &str = "POINTFARM_TEST_PAUSE_AT";

/// Stops here for good when the variable names `stage` and `n`.
pub fn at(stage: &str, n: u64) {
    static WANTED: OnceLock<Option<(String, u64)>> = OnceLock::new();
    let wanted = WANTED.get_or_init(|| {
        let value = std::env::var(VARIABLE).ok()?;
        let (stage, n) = value.split_once(':')?;
        Some((stage.to_string(), n.parse().ok()?))
    });
    if wanted
        .as_ref()
        .is_some_and(|(wanted, at)| wanted == stage && *at == n)
    {
        let mut stderr = std::io::stderr().lock();
        let _ = writeln!(stderr, "build paused at {stage}:{n}");
        let _ = stderr.flush();
        drop(stderr);
        loop {
            std::thread::park();
        }
    }
}
