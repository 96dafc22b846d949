//! The command line for scripts: `--json` on every `dataset`, `jobs` and `frames` subcommand
//! against a real daemon (the API's messages in their proto3 JSON mapping, parsed back into
//! the messages the API returns), `jobs watch --json` as a stream, completions, man pages and
//! help.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::Duration;

use pointfarm_proto::v1 as pb;
use pointfarm_tests::service::clients;
use pointfarm_tests::tools::wait_until_listening;
use pointfarm_tests::{
    assert_fails_saying, assert_ok, free_address, path_arg, pointfarm, pointfarm_bin, pointfarm_ok,
    stdout, wait_for, ServeProcess, WorkerProcess,
};

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

/// The ids of the jobs a `jobs list --json` printed (a `ListJobsResponse`, whose `jobs` is
/// left out when there are none).
fn job_ids(listed: &serde_json::Value) -> Vec<String> {
    listed["jobs"]
        .as_array()
        .map(|jobs| {
            jobs.iter()
                .filter_map(|j| j["id"].as_str().map(str::to_owned))
                .collect()
        })
        .unwrap_or_default()
}

/// The message the API answers `call` with, the call run to its end on `api`; `what` names
/// the call where it fails.
fn answer<T>(
    api: &tokio::runtime::Runtime,
    call: impl std::future::Future<Output = Result<tonic::Response<T>, tonic::Status>>,
    what: &str,
) -> T {
    api.block_on(call).expect(what).into_inner()
}

/// Asserts that `pointfarm ARGS --server ADDRESS --json` printed the very message the API
/// answers `call` with, and returns it.
fn printed_as_answered<T: serde::de::DeserializeOwned + PartialEq + std::fmt::Debug>(
    api: &tokio::runtime::Runtime,
    address: &str,
    args: &[&str],
    call: impl std::future::Future<Output = Result<tonic::Response<T>, tonic::Status>>,
) -> T {
    let printed = parsed::<T>(&server_json(address, args));
    assert_eq!(printed, answer(api, call, &args.join(" ")), "{args:?}");
    printed
}

/// `value` parsed with the proto3 JSON mapping into the message `T`.
fn parsed<T: serde::de::DeserializeOwned>(value: &serde_json::Value) -> T {
    serde_json::from_value(value.clone())
        .unwrap_or_else(|e| panic!("not the message's JSON mapping ({e}): {value}"))
}

/// A `render --server` running in the background, which submits a turntable job and follows
/// it; returns the process and the job's id once the job is listed.
fn submit(address: &str, cloud: &Path, out: &Path, frames: u32) -> (std::process::Child, String) {
    let known = job_ids(&server_json(address, &["jobs", "list"]));
    let child = Command::new(pointfarm_bin())
        .args([
            "render",
            path_arg(cloud),
            "--server",
            address,
            "--out",
            path_arg(out),
        ])
        .args([format!("--turntable={frames}").as_str(), "--size=64x48"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start render --server");
    let id = wait_for(Duration::from_secs(60), "the job to be submitted", || {
        job_ids(&server_json(address, &["jobs", "list"]))
            .into_iter()
            .find(|id| !known.contains(id))
    });
    (child, id)
}

#[test]
fn dataset_jobs_and_frames_print_json_a_script_can_read() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path();
    let cloud = dir.join("cloud.laz");
    let other = dir.join("other.laz");
    pointfarm_ok(&["sample", path_arg(&cloud), "--points", "10000"]);
    pointfarm_ok(&[
        "sample",
        path_arg(&other),
        "--points",
        "10000",
        "--seed",
        "2",
    ]);
    // No embedded worker: jobs wait until a worker process is started, so a cancel and a
    // watch see them unfinished.
    let server = ServeProcess::start_with(&dir.join("data"), &["--no-embedded-worker"]);
    let address = server.address.clone();
    // The API's own answers, to compare with what the CLI prints.
    let api = tokio::runtime::Runtime::new().expect("runtime");

    // No job yet: the ListJobsResponse has no field to print.
    assert_eq!(
        server_json(&address, &["jobs", "list"]),
        serde_json::json!({})
    );

    // dataset add, list, rm: the Dataset, the ListDatasetsResponse as the API returns them.
    let added = server_json(&address, &["dataset", "add", path_arg(&other)]);
    let id = added["id"].as_str().expect("the dataset's id").to_owned();
    assert!(
        added["sizeBytes"].is_string(),
        "uint64 as a string: {added}"
    );
    assert!(
        added["createdUnixMs"].is_string(),
        "int64 as a string: {added}"
    );
    assert!(added.get("size_bytes").is_none(), "{added}");
    let (mut datasets, _) = api.block_on(clients(&address));
    let listed = printed_as_answered(
        &api,
        &address,
        &["dataset", "list"],
        datasets.list_datasets(pb::ListDatasetsRequest {
            page_size: 0,
            page_token: String::new(),
        }),
    );
    assert!(listed.datasets.iter().any(|d| d.id == id));
    let removed = server_json(&address, &["dataset", "rm", &id]);
    assert_eq!(removed, serde_json::json!({ "deleted": id }));

    // jobs cancel: the Job, cancelled, with lowerCamelCase names and the state's enum name.
    let (mut first, job) = submit(&address, &cloud, &dir.join("cancelled"), 2);
    let cancelled = server_json(&address, &["jobs", "cancel", &job]);
    assert_eq!(cancelled["id"], job.as_str());
    assert_eq!(cancelled["state"], "JOB_STATE_CANCELLED");
    for field in ["datasetId", "framesTotal", "createdUnixMs", "updatedUnixMs"] {
        assert!(cancelled.get(field).is_some(), "no {field} in {cancelled}");
    }
    // Default values are left out: no frame is done, there is no error.
    for field in ["framesDone", "error", "frames_total"] {
        assert!(cancelled.get(field).is_none(), "{field} in {cancelled}");
    }
    let shown = server_json(&address, &["jobs", "show", &job]);
    assert_eq!(shown["job"]["state"], "JOB_STATE_CANCELLED");
    // Cancelling again says there is nothing to cancel and succeeds, in words, never with
    // the enum's Rust names; with --json it prints the job as it is.
    let again = pointfarm(&["jobs", "cancel", &job, "--server", &address]);
    assert_ok(&again);
    let message = String::from_utf8_lossy(&again.stdout);
    assert_eq!(
        message.trim(),
        format!("job {job} already cancelled; nothing to cancel")
    );
    let again = server_json(&address, &["jobs", "cancel", &job]);
    assert_eq!(again["state"], "JOB_STATE_CANCELLED");
    assert!(again.get("frames").is_none(), "{again}");
    // The daemon logged the cancel once, as the job's end.
    let log = server.log();
    let ends: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("job cancelled") && l.contains(job.as_str()))
        .collect();
    assert_eq!(ends.len(), 1, "{log}");
    assert!(
        ends[0].contains("frames_done=0") && ends[0].contains("failed_attempts=0"),
        "{log}"
    );
    let _ = first.wait();

    // jobs watch --json: one JobEvent a line as it comes; the last one's job has ended.
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
    let first_job = parsed::<pb::JobEvent>(&first_event).job.expect("a job");
    assert_eq!(first_job.id, job);
    assert_eq!(first_job.frames_done, 0);
    assert_eq!(first_job.frames_total, frames);
    assert_eq!(first_event["job"]["framesTotal"], frames, "{first_line}");
    let worker = WorkerProcess::start(&format!("http://{address}"), &dir.join("cache"), "w");
    let rest: Vec<pb::JobEvent> = lines
        .map(|l| parsed(&serde_json::from_str(&l.expect("a line")).expect("JSON")))
        .collect();
    assert!(watch.wait().expect("watch").success(), "{}", worker.log());
    let (last, progress) = rest.split_last().expect("more lines");
    // Every frame reported once: by the event that finished it, or in a catching-up job.
    let mut finished: Vec<u32> = progress
        .iter()
        .chain([last])
        .flat_map(|event| {
            let listed = event.job.iter().flat_map(|job| &job.frames);
            listed.chain(&event.frame).map(|f| f.index)
        })
        .collect();
    finished.sort_unstable();
    assert_eq!(finished, [0, 1, 2], "each frame once");
    let last = last.job.as_ref().expect("the job");
    assert_eq!(last.id, job);
    assert_eq!(last.state(), pb::JobState::Succeeded, "{last:?}");
    assert_eq!(last.frames_done, frames);
    assert!(second.wait().expect("render").success());

    // jobs show --json: the Job exactly as GetJob returns it, with its stages' statistics.
    let shown = server_json(&address, &["jobs", "show", &job]);
    let (_, mut jobs) = api.block_on(clients(&address));
    let from_api = answer(
        &api,
        jobs.get_job(pb::GetJobRequest { id: job.clone() }),
        "GetJob",
    );
    assert_eq!(parsed::<pb::Job>(&shown["job"]), from_api);
    assert_eq!(from_api.frames.len(), frames as usize);
    assert!(shown["job"]["frames"][1]["timings"].is_array(), "{shown}");
    let stages = shown["stageStatistics"].as_array().expect("statistics");
    assert!(
        stages
            .iter()
            .any(|s| s["stage"] == "rasterize" && s["medianMs"].is_number()),
        "{shown}"
    );

    // frames fetch --json: every file written, with its frame.
    let out = dir.join("fetched");
    let fetched = server_json(
        &address,
        &["frames", "fetch", &job, "--out", path_arg(&out)],
    );
    assert_eq!(fetched["jobId"], job.as_str());
    let written = fetched["frames"].as_array().expect("frames");
    assert_eq!(written.len(), frames as usize);
    for (index, frame) in written.iter().enumerate() {
        assert_eq!(frame["index"], index);
        let path = Path::new(frame["path"].as_str().expect("a path"));
        assert!(path.is_file(), "{} missing", path.display());
    }
    let from = server_json(
        &address,
        &[
            "frames",
            "fetch",
            &job,
            "--out",
            path_arg(&out),
            "--from",
            "2",
        ],
    );
    assert_eq!(from["frames"].as_array().map(Vec::len), Some(1));
    assert_eq!(from["frames"][0]["index"], 2);

    // jobs list and leases: the ListJobsResponse and ListLeasesResponse as the API returns them.
    let list_jobs = jobs.list_jobs(pb::ListJobsRequest::default());
    let listed = printed_as_answered(&api, &address, &["jobs", "list"], list_jobs);
    assert_eq!(listed.jobs.len(), 2);
    let leases = parsed::<pb::ListLeasesResponse>(&server_json(&address, &["jobs", "leases"]));
    assert_eq!(leases, pb::ListLeasesResponse::default());
    // jobs workers: the ListWorkersResponse, here the one worker with its adapter.
    let list_workers = jobs.list_workers(pb::ListWorkersRequest::default());
    let workers = printed_as_answered(&api, &address, &["jobs", "workers"], list_workers);
    let adapters: Vec<bool> = workers
        .workers
        .iter()
        .map(|w| {
            w.capabilities
                .as_ref()
                .is_some_and(|c| !c.adapter_name.is_empty())
        })
        .collect();
    assert_eq!(adapters, [true], "{workers:?}");
}

#[test]
fn a_closed_pipe_ends_jobs_watch_quietly() {
    // `jobs watch | head -1` on a finished job: one line of JSON, no complaint about the pipe.
    let dir = tempfile::tempdir().expect("tempdir");
    let cloud = dir.path().join("cloud.laz");
    pointfarm_ok(&["sample", path_arg(&cloud), "--points", "10000"]);
    let server = ServeProcess::start(&dir.path().join("data"));
    let rendered = pointfarm(&[
        "render",
        path_arg(&cloud),
        "--server",
        &server.address,
        "--out",
        path_arg(&dir.path().join("frames")),
        "--turntable=2",
        "--size=64x48",
    ]);
    assert_ok(&rendered);
    let job = job_ids(&server_json(&server.address, &["jobs", "list"]))
        .pop()
        .expect("a job");
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
    assert_eq!(line["job"]["id"], job.as_str());
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
    assert_ok(&pointfarm(&["man", "--out", path_arg(&out)]));
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

/// `-v --log-format json`: the daemon's own logs come out at info, one JSON object a line,
/// for a log collector.
#[test]
fn the_daemon_logs_json_lines_at_the_level_v_asks_for() {
    let data = tempfile::tempdir().expect("tempdir");
    let address = free_address();
    let mut serve = Command::new(pointfarm_bin())
        .args(["-v", "--log-format", "json", "serve", "--listen", &address])
        .arg("--data-dir")
        .arg(data.path())
        .env_remove("RUST_LOG")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start serve");
    let stderr = serve.stderr.take().expect("stderr");
    let (lines, received) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if lines.send(line).is_err() {
                break;
            }
        }
    });
    let mut seen = Vec::new();
    let serving = loop {
        let Ok(line) = received.recv_timeout(Duration::from_secs(60)) else {
            break None;
        };
        let object: serde_json::Value =
            serde_json::from_str(&line).unwrap_or_else(|e| panic!("not a JSON line ({e}): {line}"));
        seen.push(line);
        if object["fields"]["message"] == "serving pointfarm.v1" {
            break Some(object);
        }
    };
    let _ = serve.kill();
    let _ = serve.wait();
    let serving = serving.unwrap_or_else(|| panic!("no serving line in:\n{}", seen.join("\n")));
    assert_eq!(serving["level"], "INFO", "{serving}");
    assert!(
        serving["target"]
            .as_str()
            .is_some_and(|t| t.starts_with("pointfarm_daemon")),
        "{serving}"
    );
    assert_eq!(serving["fields"]["address"], address.as_str(), "{serving}");
}

/// Settings in layers: a TOML file (`--config`), then `POINTFARM_*` variables, then flags. A
/// real daemon listens where the file says and keeps its data where the environment says;
/// `--print-config` shows each setting's layer; a mistake in the file stops the command with
/// the file's and the key's names.
#[test]
fn serve_and_worker_take_settings_from_a_file_the_environment_and_flags() {
    let dir = tempfile::tempdir().expect("tempdir");
    let address = free_address();
    let (file_data, env_data) = (dir.path().join("from-file"), dir.path().join("from-env"));
    let config = dir.path().join("pointfarm.toml");
    std::fs::write(
        &config,
        format!(
            "[serve]\nlisten = \"{address}\"\ndata_dir = {:?}\nno_embedded_worker = true\nmax_frames = 5\n\n[worker]\ncache_gib = 3\n",
            path_arg(&file_data)
        ),
    )
    .expect("write the configuration");

    let mut serve = Command::new(pointfarm_bin())
        .args(["serve", "--config", path_arg(&config), "--max-frames", "7"])
        .env("POINTFARM_DATA_DIR", &env_data)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("start serve");
    let lines: Vec<String> = BufReader::new(serve.stdout.take().expect("stdout"))
        .lines()
        .take(2)
        .map(|line| line.expect("serve's output"))
        .collect();
    wait_until_listening(&address, Duration::from_secs(30), "the daemon");
    let _ = serve.kill();
    let _ = serve.wait();
    let said = lines.join("\n");
    assert!(said.contains("no embedded worker"), "{said}");
    assert!(
        said.contains(&format!("serving on http://{address}")),
        "{said}"
    );
    assert!(said.contains(path_arg(&env_data)), "{said}");
    assert!(env_data.is_dir());
    assert!(
        !file_data.exists(),
        "the environment's data folder wins over the file's"
    );

    let printed = pointfarm(&[
        "serve",
        "--config",
        path_arg(&config),
        "--max-frames",
        "7",
        "--print-config",
    ]);
    let printed = stdout(&printed);
    assert!(
        printed.contains(&format!("listen = \"{address}\"  # file")),
        "{printed}"
    );
    assert!(printed.contains("max_frames = 7  # flag"), "{printed}");
    assert!(
        printed.contains("lease_timeout = 30  # default"),
        "{printed}"
    );
    let worker = Command::new(pointfarm_bin())
        .args(["worker", "--print-config"])
        .env("POINTFARM_CONFIG", &config)
        .env("POINTFARM_LOD_ERROR", "2.5")
        .output()
        .expect("worker --print-config");
    let worker = stdout(&worker);
    assert!(worker.contains("cache_gib = 3  # file"), "{worker}");
    assert!(worker.contains("lod_error = 2.5  # env"), "{worker}");

    std::fs::write(&config, "[worker]\nlod_error = -1\n").expect("write");
    let refused = pointfarm(&["serve", "--config", path_arg(&config)]);
    assert_fails_saying(
        &refused,
        "pointfarm.toml: [worker] lod_error: invalid value '-1'",
    );
}
