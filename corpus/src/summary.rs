//! What a corpus run gave: counts per outcome (overall and per mutation kind), the peak
//! memory against the bound of twice the file's size plus 256 MiB, the worst files, and
//! every file that did not end in a load or a clean error naming it.

use std::collections::BTreeMap;
use std::fmt::{self, Write as _};

use crate::generate::kind_of;
use crate::runner::{FileRun, Outcome};

/// The outcome classes counted, in report order.
pub const CLASSES: [&str; 8] = [
    "loaded",
    "clean error",
    "unnamed error",
    "contained panic",
    "panic",
    "abort",
    "timeout",
    "unexpected",
];

pub fn class_of(outcome: &Outcome) -> &'static str {
    match outcome {
        Outcome::Loaded(_) => CLASSES[0],
        Outcome::Error {
            names_file: true, ..
        } => CLASSES[1],
        Outcome::Error { .. } => CLASSES[2],
        Outcome::ContainedPanic(_) => CLASSES[3],
        Outcome::Panic(_) => CLASSES[4],
        Outcome::Abort { .. } => CLASSES[5],
        Outcome::Timeout => CLASSES[6],
        Outcome::Unexpected(_) => CLASSES[7],
    }
}

/// Counts and extremes of a run.
pub struct Summary<'a> {
    pub runs: &'a [FileRun],
    pub counts: BTreeMap<&'static str, usize>,
    pub over_bound: Vec<&'a FileRun>,
}

impl<'a> Summary<'a> {
    pub fn of(runs: &'a [FileRun]) -> Self {
        let mut counts = BTreeMap::new();
        for run in runs {
            *counts.entry(class_of(&run.outcome)).or_default() += 1;
        }
        let over_bound = runs
            .iter()
            .filter(|run| run.peak_kib > run.bound_kib())
            .collect();
        Self {
            runs,
            counts,
            over_bound,
        }
    }

    pub fn count(&self, class: &str) -> usize {
        self.counts.get(class).copied().unwrap_or(0)
    }

    /// Whether every file loaded or failed with a clean error naming it, within the bound.
    pub fn is_clean(&self) -> bool {
        self.count("loaded") + self.count("clean error") == self.runs.len()
            && self.over_bound.is_empty()
    }

    /// The runs by peak memory relative to their bound, worst first.
    pub fn worst_by_memory(&self, count: usize) -> Vec<&'a FileRun> {
        let mut runs: Vec<&FileRun> = self.runs.iter().collect();
        runs.sort_by(|a, b| {
            let ratio = |run: &FileRun| run.peak_kib as f64 / run.bound_kib() as f64;
            ratio(b).total_cmp(&ratio(a))
        });
        runs.truncate(count);
        runs
    }
}

fn mib(kib: u64) -> f64 {
    kib as f64 / 1024.0
}

impl fmt::Display for Summary<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "{} files", self.runs.len())?;
        for class in CLASSES {
            writeln!(f, "  {class:<16} {}", self.count(class))?;
        }
        writeln!(f, "\nper mutation kind:")?;
        let mut per_kind: BTreeMap<String, BTreeMap<&str, usize>> = BTreeMap::new();
        for run in self.runs {
            let kind = kind_of(&run.path).map_or("source", |kind| kind.label());
            *per_kind
                .entry(kind.to_owned())
                .or_default()
                .entry(class_of(&run.outcome))
                .or_default() += 1;
        }
        for (kind, counts) in &per_kind {
            let mut line = String::new();
            for (class, count) in counts {
                let _ = write!(line, " {class} {count},");
            }
            writeln!(f, "  {kind:<12}{}", line.trim_end_matches(','))?;
        }
        let max_peak = self.runs.iter().map(|run| run.peak_kib).max().unwrap_or(0);
        writeln!(
            f,
            "\npeak memory: max {:.1} MiB; {} files over 2 x file size + 256 MiB",
            mib(max_peak),
            self.over_bound.len()
        )?;
        writeln!(f, "worst files (peak / bound):")?;
        for run in self.worst_by_memory(8) {
            writeln!(
                f,
                "  {:>8.1} MiB / {:>7.1} MiB  {} ({})",
                mib(run.peak_kib),
                mib(run.bound_kib()),
                file_name(run),
                class_of(&run.outcome)
            )?;
        }
        let trouble: Vec<&FileRun> = self
            .runs
            .iter()
            .filter(|run| !matches!(class_of(&run.outcome), "loaded" | "clean error"))
            .collect();
        if !trouble.is_empty() {
            writeln!(f, "\nnot a load or a clean error naming the file:")?;
            for run in trouble {
                writeln!(f, "  {}: {:?}", file_name(run), run.outcome)?;
            }
        }
        Ok(())
    }
}

fn file_name(run: &FileRun) -> String {
    run.path
        .file_name()
        .map(|name| name.to_string_lossy().into_owned())
        .unwrap_or_default()
}
