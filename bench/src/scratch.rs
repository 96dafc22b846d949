//! What a long benchmark runs with: the scratch folder it writes its files into (removed when
//! dropped), its log of progress lines, and the machine's load it reports beside its figures.

use std::path::Path;

use tempfile::TempDir;

use crate::error::BenchError;

/// A fresh folder named `pointfarm-NAME-…` in `parent`, or in the system's temporary folder.
pub(crate) fn scratch_dir(parent: Option<&Path>, name: &str) -> Result<TempDir, BenchError> {
    let prefix = format!("pointfarm-{name}-");
    let mut builder = tempfile::Builder::new();
    builder.prefix(&prefix);
    match parent {
        Some(parent) => builder.tempdir_in(parent),
        None => builder.tempdir(),
    }
    .map_err(|e| BenchError::Scratch(e.to_string()))
}

/// Each line goes to the log (as benchmark `name`'s) and to `progress`.
pub(crate) fn progress_log<'p>(
    name: &'static str,
    progress: &'p mut dyn FnMut(&str),
) -> impl FnMut(String) + 'p {
    move |line| {
        tracing::info!(benchmark = name, "{line}");
        progress(&line);
    }
}

/// The 1-minute load average (Linux; None elsewhere), which a benchmark reports so that a
/// busy machine's figures are read as such.
pub(crate) fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}
