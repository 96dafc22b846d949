//! The commands' logs, on stderr: plain text (colored only for a person at a terminal) or one
//! JSON object a line for a log collector, at the level `-v` asks for unless `RUST_LOG` says
//! otherwise.

use tracing_subscriber::EnvFilter;

/// How log lines are written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines.
    #[default]
    Text,
    /// One JSON object a line: timestamp, level, target, fields and the spans (job, frame).
    Json,
}

/// The filter `-v` given `verbose` times stands for: warnings only, then pointfarm's own
/// crates (the CLI, the daemon and its workers, the renderer) at info, then at debug.
fn verbosity_filter(verbose: u8) -> &'static str {
    match verbose {
        0 => "warn",
        1 => "warn,pointfarm=info,pointfarm_daemon=info,pointfarm_render=info",
        _ => "info,pointfarm=debug,pointfarm_daemon=debug,pointfarm_render=debug",
    }
}

pub fn init(verbose: u8, format: LogFormat) {
    let filter = EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| EnvFilter::new(verbosity_filter(verbose)));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    match format {
        // Colors only at a terminal: logs written to files stay plain text.
        LogFormat::Text => builder
            .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
            .init(),
        LogFormat::Json => builder.json().with_current_span(true).init(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_pointfarm_crate_logs_at_the_level_asked_for() {
        for (verbose, level) in [(1, "info"), (2, "debug")] {
            let filter = verbosity_filter(verbose);
            for target in ["pointfarm", "pointfarm_daemon", "pointfarm_render"] {
                assert!(filter.contains(&format!("{target}={level}")), "{filter}");
            }
        }
    }
}
