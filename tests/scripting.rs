//! The command line for scripts: `--json` on every `dataset`, `jobs` and `frames` subcommand
//! against a real daemon, `jobs watch --json` as a stream, completions, man pages and help.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::Duration;

use pointfarm_tests::{
    assert_ok, pointfarm, pointfarm_bin, stdout, wait_for, ServeProcess, WorkerProcess,
};

fn arg(path: &Path) -> &str {
    path.to_str().expect("temporary paths are UTF-8")
}

/// The one JSON value a command printed on stdout.
fn json_of(output: &Output) -> serde_json::Value {
    assert_ok(output);
    serde_json::from_slice(&output.stdout)
        .unwrap_or_else(|e| panic!("not JSON ({e}):\n{}", stdout(output)))
}

/// `pointfarm GROUP ARGS --server ADDRESS --json`.
fn server_json(address: &str, args: &[&str]) -> serde_json::Value {
    let mut all = args.to_vec();
    all.extend(["--server", address, "--json"]);
    json_of(&pointfarm(&all))
}

/// A `render --server` running in the background, which submits a turntable job and follows
/// it; returns the process and the job's id once the job is listed.
fn submit(address: &str, cloud: &Path, out: &Path, frames: u32) -> (std::process::Child, String) {
    let before = server_json(address, &["jobs", "list"]);
    let known: Vec<String> = before
        .as_array()
        .expect("a list")
        .iter()
        .map(|j| j["id"].as_str().unwrap_or_default().to_owned())
        .collect();
    let child = Command::new(pointfarm_bin())
        .args(["render", arg(cloud), "--server", address, "--out", arg(out)])
        .args([format!("--turntable={frames}").as_str(), "--size=64x48"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start render --server");
    let id = wait_for(Duration::from_secs(60), "the job to be submitted", || {
        let jobs = server_json(address, &["jobs", "list"]);
        jobs.as_array()?
            .iter()
            .filter_map(|j| j["id"].as_str())
            .find(|id| !known.iter().any(|k| k == id))
            .map(str::to_owned)
    });
    (child, id)
}

#[test]
fn dataset_jobs_and_frames_print_json_a_script_can_read() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path();
    let cloud = dir.join("cloud.laz");
    let other = dir.join("other.laz");
    assert_ok(&pointfarm(&["sample", arg(&cloud), "--points", "10000"]));
    assert_ok(&pointfarm(&[
        "sample",
        arg(&other),
        "--points",
        "10000",
        "--seed",
        "2",
    ]));
    // No embedded worker: jobs wait until a worker process is started, so a cancel and a
    // watch see them unfinished.
    let server = ServeProcess::start_with(&dir.join("data"), &["--no-embedded-worker"]);
    let address = server.address.clone();

    // dataset add, list, rm.
    let added = server_json(&address, &["dataset", "add", arg(&other)]);
    let id = added["id"].as_str().expect("the dataset's id").to_owned();
    let listed = server_json(&address, &["dataset", "list"]);
    assert!(listed
        .as_array()
        .is_some_and(|l| l.iter().any(|d| d["id"] == id.as_str())));
    let removed = server_json(&address, &["dataset", "rm", &id]);
    assert_eq!(removed, serde_json::json!({ "deleted": id }));

    // jobs cancel: the job object of `jobs show`, cancelled.
    let (mut first, job) = submit(&address, &cloud, &dir.join("cancelled"), 2);
    let cancelled = server_json(&address, &["jobs", "cancel", &job]);
    assert_eq!(cancelled["id"], job.as_str());
    assert_eq!(cancelled["state"], "cancelled");
    for field in [
        "dataset_id",
        "frames_total",
        "frames_done",
        "priority",
        "error",
    ] {
        assert!(cancelled.get(field).is_some(), "no {field} in {cancelled}");
    }
    let shown = server_json(&address, &["jobs", "show", &job]);
    assert_eq!(shown["state"], "cancelled");
    // Cancelling again fails in words, never with the enum's Rust names.
    let again = pointfarm(&["jobs", "cancel", &job, "--server", &address]);
    assert!(!again.status.success());
    let message = String::from_utf8_lossy(&again.stderr);
    assert!(message.contains("failed precondition"), "{message}");
    assert!(message.contains("(cancelled)"), "{message}");
    assert!(
        !message.contains("Cancelled") && !message.contains("FailedPrecondition"),
        "{message}"
    );
    let _ = first.wait();

    // jobs watch --json: one line per event as it comes, the finished job last.
    let frames = 3;
    let (mut second, job) = submit(&address, &cloud, &dir.join("rendered"), frames);
    let mut watch = Command::new(pointfarm_bin())
        .args(["jobs", "watch", &job, "--server", &address, "--json"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("start jobs watch");
    let mut lines = BufReader::new(watch.stdout.take().expect("piped")).lines();
    // The first event comes before any frame is rendered.
    let first_line = lines.next().expect("a first event").expect("a line");
    let first_event: serde_json::Value = serde_json::from_str(&first_line).expect("JSON");
    assert_eq!(first_event["event"], "progress", "{first_line}");
    assert_eq!(first_event["job"], job.as_str());
    assert_eq!(first_event["frames_done"], 0);
    assert_eq!(first_event["frames_total"], frames);
    let worker = WorkerProcess::start(&format!("http://{address}"), &dir.join("cache"), "w");
    let rest: Vec<serde_json::Value> = lines
        .map(|l| serde_json::from_str(&l.expect("a line")).expect("every line is JSON"))
        .collect();
    assert!(watch.wait().expect("watch").success(), "{}", worker.log());
    let (last, progress) = rest.split_last().expect("more lines");
    assert!(
        !progress.is_empty(),
        "no progress between the first and the last line"
    );
    for event in progress {
        assert_eq!(event["event"], "progress", "{event}");
    }
    assert_eq!(last["event"], "finished");
    assert_eq!(last["id"], job.as_str());
    assert_eq!(last["state"], "succeeded", "{last}");
    assert_eq!(last["frames_done"], frames);
    assert!(second.wait().expect("render").success());

    // frames fetch --json: every file written, with its frame.
    let out = dir.join("fetched");
    let fetched = server_json(&address, &["frames", "fetch", &job, "--out", arg(&out)]);
    assert_eq!(fetched["job"], job.as_str());
    let written = fetched["frames"].as_array().expect("frames");
    assert_eq!(written.len(), frames as usize);
    for (index, frame) in written.iter().enumerate() {
        assert_eq!(frame["index"], index);
        let path = Path::new(frame["path"].as_str().expect("a path"));
        assert!(path.is_file(), "{} missing", path.display());
    }
    let from = server_json(
        &address,
        &["frames", "fetch", &job, "--out", arg(&out), "--from", "2"],
    );
    assert_eq!(from["frames"].as_array().map(Vec::len), Some(1));
    assert_eq!(from["frames"][0]["index"], 2);

    // jobs list, show and leases parse too.
    assert!(server_json(&address, &["jobs", "list"]).is_array());
    assert!(server_json(&address, &["jobs", "show", &job])["stages"].is_array());
    assert!(server_json(&address, &["jobs", "leases"]).is_array());
}

#[test]
fn a_closed_pipe_ends_jobs_watch_quietly() {
    // `jobs watch | head -1` on a finished job: one line of JSON, no complaint about the pipe.
    let dir = tempfile::tempdir().expect("tempdir");
    let cloud = dir.path().join("cloud.laz");
    assert_ok(&pointfarm(&["sample", arg(&cloud), "--points", "10000"]));
    let server = ServeProcess::start(&dir.path().join("data"));
    let rendered = pointfarm(&[
        "render",
        arg(&cloud),
        "--server",
        &server.address,
        "--out",
        arg(&dir.path().join("frames")),
        "--turntable=2",
        "--size=64x48",
    ]);
    assert_ok(&rendered);
    let job = server_json(&server.address, &["jobs", "list"])[0]["id"]
        .as_str()
        .expect("a job")
        .to_owned();
    let script = format!(
        "'{}' jobs watch {job} --server {} --json | head -1",
        pointfarm_bin().display(),
        server.address
    );
    let output = Command::new("sh")
        .args(["-c", &script])
        .output()
        .expect("sh");
    assert!(output.status.success());
    let line: serde_json::Value = serde_json::from_str(stdout(&output).trim()).expect("JSON");
    assert_eq!(line["job"], job.as_str());
    assert!(
        output.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
}

#[test]
fn completions_and_man_pages_come_from_the_command_line() {
    let bash = pointfarm(&["completions", "bash"]);
    assert_ok(&bash);
    let script = stdout(&bash);
    assert!(
        script.contains("pointfarm") && script.contains("render"),
        "{script}"
    );
    for shell in ["zsh", "fish", "elvish", "powershell"] {
        let output = pointfarm(&["completions", shell]);
        assert_ok(&output);
        assert!(stdout(&output).contains("pointfarm"), "{shell}");
    }
    assert!(!pointfarm(&["completions", "tcsh"]).status.success());

    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("man");
    assert_ok(&pointfarm(&["man", "--out", arg(&out)]));
    for page in [
        "pointfarm.1",
        "pointfarm-render.1",
        "pointfarm-jobs-watch.1",
    ] {
        let text = std::fs::read_to_string(out.join(page)).unwrap_or_else(|_| panic!("{page}"));
        assert!(text.contains(".TH"), "{page} is no man page");
    }
}

/// The subcommands `pointfarm ARGS --help` lists.
fn subcommands(help: &str) -> Vec<String> {
    help.lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .filter_map(|l| l.split_whitespace().next())
        .filter(|name| *name != "help")
        .map(str::to_owned)
        .collect()
}

#[test]
fn every_command_says_what_it_does() {
    let mut pending: Vec<Vec<String>> = vec![Vec::new()];
    let mut seen = 0;
    while let Some(path) = pending.pop() {
        let mut args: Vec<&str> = path.iter().map(String::as_str).collect();
        args.push("--help");
        let output = pointfarm(&args);
        assert_ok(&output);
        let help = stdout(&output);
        let about = help.lines().next().unwrap_or_default().trim();
        assert!(
            !about.is_empty() && !about.starts_with("Usage:"),
            "`pointfarm {}` has no about line:\n{help}",
            path.join(" ")
        );
        for sub in subcommands(&help) {
            let mut next = path.clone();
            next.push(sub);
            pending.push(next);
        }
        seen += 1;
    }
    assert!(seen > 20, "only {seen} commands");
}
