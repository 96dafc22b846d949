//! `pointfarm`: render point clouds from a terminal or a script.

/// `println!` for a command's output, which a closed pipe does not stop ([`output::line`]).
macro_rules! outln {
    ($($arg:tt)*) => {
        $crate::output::line(format_args!($($arg)*))
    };
}

mod admin;
mod admin_json;
mod bench;
mod camera_path;
mod config_file;
mod credentials;
mod demo;
mod download;
mod export;
mod filter_args;
mod frame_lines;
mod generate;
mod info;
mod jobs_video;
mod logging;
mod output;
mod parse;
mod paths;
mod progress;
mod remote;
mod remote_render;
mod render;
mod render_args;
mod render_json;
mod render_outputs;
mod sample;
mod serve;
mod signals;
mod source_words;
mod url_input;
mod worker;

use std::process::ExitCode;

use clap::{CommandFactory, Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "pointfarm",
    version,
    about = "A headless render farm for point clouds"
)]
struct Cli {
    /// Log more (-v: info, -vv: debug). RUST_LOG overrides this.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    /// How logs are written on stderr: text, or JSON lines for a log collector.
    #[arg(
        long,
        value_enum,
        default_value_t,
        global = true,
        env = "POINTFARM_LOG_FORMAT"
    )]
    log_format: logging::LogFormat,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Benchmark the compute rasterizer against a PointList render pipeline on this GPU.
    Bench(bench::BenchArgs),
    /// Render frames of a LAS/LAZ file on this machine's GPU (or lavapipe).
    Render(Box<render::RenderArgs>),
    /// What LAS/LAZ files hold, before rendering them: version, point format, counts, bounds,
    /// scale and offset, CRS, attributes, and (reading the points once, in a stream)
    /// classes, returns, intensity and whether the colors carry information.
    Info(info::InfoArgs),
    /// Write a dataset as a COPC 1.0 file (Cloud Optimized Point Cloud, a LAZ 1.4 file that
    /// PDAL, QGIS and Potree open) from its levels of detail, built once and kept like
    /// `render`'s.
    Export(Box<export::ExportArgs>),
    /// Write a generated sample scene (survey-like coordinates, RGB) as LAS or LAZ.
    Sample(sample::SampleArgs),
    /// The service end to end in one process: daemon, worker, upload, turntable, frames.
    Demo(Box<demo::DemoArgs>),
    /// Run the render service: the daemon, with an embedded worker unless told otherwise.
    Serve(Box<serve::ServeArgs>),
    /// Render for a daemon in this process: lease frames over gRPC, hand back the PNGs.
    Worker(Box<worker::WorkerArgs>),
    /// Datasets on a server.
    Dataset {
        #[command(flatten)]
        server: admin::ServerArgs,
        #[command(subcommand)]
        command: admin::DatasetCommand,
    },
    /// Jobs on a server.
    Jobs {
        #[command(flatten)]
        server: admin::ServerArgs,
        #[command(subcommand)]
        command: admin::JobsCommand,
    },
    /// Frames of a job on a server.
    Frames {
        #[command(flatten)]
        server: admin::ServerArgs,
        #[command(subcommand)]
        command: admin::FramesCommand,
    },
    /// Print a shell completion script (bash, zsh, fish, elvish, powershell).
    Completions(generate::CompletionsArgs),
    /// Write man pages: one for pointfarm and one for each subcommand.
    Man(generate::ManArgs),
}

fn main() -> ExitCode {
    let cli: Cli = config_file::parse(std::env::args_os().collect());
    logging::init(cli.verbose, cli.log_format);

    let result = match cli.command {
        Command::Render(args) => render::run(*args),
        Command::Bench(args) => bench::run(args),
        Command::Info(args) => info::run(args),
        Command::Sample(args) => sample::run(args),
        Command::Export(args) => export::run(*args),
        Command::Serve(args) => serve::run(*args),
        Command::Worker(args) => worker::run(*args),
        Command::Demo(args) => demo::run(*args),
        Command::Dataset { server, command } => admin::dataset(&server, command),
        Command::Jobs { server, command } => admin::jobs(&server, command),
        Command::Frames { server, command } => admin::frames(&server, command),
        Command::Completions(args) => generate::completions(args, Cli::command()),
        Command::Man(args) => generate::man(args, Cli::command()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // One line: the context chain joined, as scripts expect.
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every command and every flag or argument says what it is in `--help`.
    #[test]
    fn every_command_and_argument_has_help() {
        fn walk(command: &clap::Command, path: &str, missing: &mut Vec<String>) {
            if command
                .get_about()
                .is_none_or(|a| a.to_string().trim().is_empty())
            {
                missing.push(format!("command `{path}`"));
            }
            for arg in command.get_arguments() {
                let id = arg.get_id().as_str();
                if matches!(id, "help" | "version") {
                    continue;
                }
                if arg
                    .get_help()
                    .is_none_or(|h| h.to_string().trim().is_empty())
                {
                    missing.push(format!("`{path}` argument `{id}`"));
                }
            }
            for sub in command.get_subcommands() {
                walk(sub, &format!("{path} {}", sub.get_name()), missing);
            }
        }
        let mut command = Cli::command();
        command.build();
        let mut missing = Vec::new();
        walk(&command, "pointfarm", &mut missing);
        assert!(missing.is_empty(), "without help:\n{}", missing.join("\n"));
    }
}
