//! The commands' output on stdout, which may be a pipe whose reader has gone away
//! (`pointfarm render … | head -1`).

use std::io::{ErrorKind, Write};
use std::sync::atomic::{AtomicBool, Ordering};

/// Whether a failure other than a closed pipe has been reported.
static REPORTED: AtomicBool = AtomicBool::new(false);

/// Writes one line to stdout. A reader that has gone away is not the command's failure: the
/// line is dropped and the work goes on (frames are still written). Any other failure is
/// reported once, on stderr.
pub fn line(args: std::fmt::Arguments<'_>) {
    let mut out = std::io::stdout().lock();
    let written = out
        .write_fmt(args)
        .and_then(|()| out.write_all(b"\n"))
        .and_then(|()| out.flush());
    if let Err(error) = written {
        if error.kind() != ErrorKind::BrokenPipe && !REPORTED.swap(true, Ordering::Relaxed) {
            let _ = writeln!(
                std::io::stderr(),
                "warning: could not write to standard output: {error}"
            );
        }
    }
}

/// Says a command's progress lines: on stdout, or with `--json` on stderr, so that stdout
/// carries only the JSON objects. Made once from the command's flags and handed to each step.
#[derive(Debug, Clone, Copy)]
pub struct Reporter {
    json: bool,
}

impl Reporter {
    pub fn new(json: bool) -> Self {
        Self { json }
    }

    /// Whether stdout carries the command's JSON objects alone.
    pub fn is_json(self) -> bool {
        self.json
    }

    /// Says one progress line.
    pub fn say(self, line: impl std::fmt::Display) {
        if self.json {
            eprintln!("{line}");
        } else {
            self::line(format_args!("{line}"));
        }
    }
}
