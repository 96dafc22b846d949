//! `pointfarm-corpus`: generates the hostile-file corpus, runs it (each file in a child
//! process) and, as that child, loads one file.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use clap::{Parser, Subcommand};

use pointfarm_corpus::child::load_and_report;
use pointfarm_corpus::generate::generate;
use pointfarm_corpus::runner::run_files;
use pointfarm_corpus::summary::{class_of, Summary};
use pointfarm_corpus::{corpus_files, CorpusError};

#[derive(Parser)]
#[command(about = "The hostile LAS/LAZ corpus: generate it, run it")]
struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Writes the corpus into DIR (sources and mutants), the same bytes on every run.
    Generate {
        dir: PathBuf,
        /// The real scans (autzen_trim.las/.laz, lone-star.laz); skipped where absent.
        #[arg(long, default_value = "../shared/data")]
        real: PathBuf,
        /// Only the fast subset: small written sources and the headline mutants.
        #[arg(long)]
        fast: bool,
    },
    /// Loads every file under DIR in a child process and reports the counts and memory.
    Run {
        dir: PathBuf,
        /// Seconds a child may take before it is killed and counted as a timeout.
        #[arg(long, default_value_t = 120)]
        timeout: u64,
        /// Children at a time.
        #[arg(long, default_value_t = 1)]
        jobs: usize,
        /// Print one line per file as it finishes.
        #[arg(long)]
        verbose: bool,
    },
    /// Loads one file and reports (the child side of `run`).
    Load { file: PathBuf },
}

fn main() -> ExitCode {
    match Args::parse().command {
        Command::Generate { dir, real, fast } => report(run_generate(&dir, &real, fast)),
        Command::Run {
            dir,
            timeout,
            jobs,
            verbose,
        } => report(run_corpus(&dir, timeout, jobs, verbose)),
        Command::Load { file } => ExitCode::from(load_and_report(&file) as u8),
    }
}

fn report(result: Result<bool, CorpusError>) -> ExitCode {
    match result {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(error) => {
            eprintln!("error: {error}");
            ExitCode::from(2)
        }
    }
}

fn run_generate(
    dir: &std::path::Path,
    real: &std::path::Path,
    fast: bool,
) -> Result<bool, CorpusError> {
    let real = real.is_dir().then_some(real);
    let generated = generate(dir, real, fast)?;
    println!(
        "{}: {} sources, {} mutants, {:.1} MiB",
        dir.display(),
        generated.sources,
        generated.mutants,
        generated.bytes as f64 / (1 << 20) as f64
    );
    Ok(true)
}

/// Runs the corpus; `Ok(false)` when any file did not load or fail cleanly within the bound.
fn run_corpus(
    dir: &std::path::Path,
    timeout: u64,
    jobs: usize,
    verbose: bool,
) -> Result<bool, CorpusError> {
    let files = corpus_files(dir)?;
    let exe = std::env::current_exe().map_err(|error| CorpusError::io(dir, error))?;
    let total = files.len();
    let runs = run_files(
        &exe,
        &files,
        Duration::from_secs(timeout),
        jobs,
        |done, run| {
            if verbose {
                println!(
                    "[{done}/{total}] {} {} {:.1} MiB {:.2}s",
                    run.path.display(),
                    class_of(&run.outcome),
                    run.peak_kib as f64 / 1024.0,
                    run.elapsed.as_secs_f64()
                );
            }
        },
    )?;
    let summary = Summary::of(&runs);
    println!("{summary}");
    Ok(summary.is_clean())
}
