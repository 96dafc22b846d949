//! `pointfarm completions SHELL` and `pointfarm man`: shell completion scripts and man pages,
//! generated from the command line's own definition (so they never fall behind it).

use std::io::{ErrorKind, Write};
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use clap_complete::Shell;

#[derive(Args)]
pub struct CompletionsArgs {
    /// The shell to complete for.
    shell: Shell,
}

#[derive(Args)]
pub struct ManArgs {
    /// Folder to write the pages to (created if missing): pointfarm.1 and one page per
    /// subcommand (pointfarm-render.1, pointfarm-jobs-watch.1, ...).
    #[arg(long, short, value_name = "DIR", default_value = ".")]
    out: PathBuf,
}

/// Prints the completion script of `args.shell` for `command` on stdout (e.g.
/// `pointfarm completions bash > /etc/bash_completion.d/pointfarm`).
pub fn completions(args: CompletionsArgs, mut command: clap::Command) -> Result<()> {
    let mut script = Vec::new();
    let name = command.get_name().to_string();
    clap_complete::generate(args.shell, &mut command, name, &mut script);
    match std::io::stdout().lock().write_all(&script) {
        Err(e) if e.kind() != ErrorKind::BrokenPipe => Err(e).context("writing the script"),
        _ => Ok(()),
    }
}

/// Writes the man pages of `command` and of each of its subcommands into `args.out`, and
/// names each page written.
pub fn man(args: ManArgs, command: clap::Command) -> Result<()> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let before = pages(&args.out);
    clap_mangen::generate_to(command, &args.out)
        .with_context(|| format!("writing man pages to {}", args.out.display()))?;
    let mut written: Vec<PathBuf> = pages(&args.out);
    written.sort();
    outln!(
        "{} man pages in {}{}",
        written.len(),
        args.out.display(),
        if before.is_empty() {
            String::new()
        } else {
            format!(" ({} replaced)", before.len())
        }
    );
    Ok(())
}

/// The `pointfarm*.1` files in `dir`.
fn pages(dir: &std::path::Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension().is_some_and(|e| e == "1")
                && p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with("pointfarm"))
        })
        .collect()
}
