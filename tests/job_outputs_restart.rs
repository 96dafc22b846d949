//! A job's outputs survive a daemon killed before they reach object storage: a real daemon
//! (`pointfarm serve`, its embedded worker rendering on lavapipe) finishes a job whose output
//! URL's store does not answer (an endpoint that takes connections and never replies), is
//! killed with SIGKILL while every output still waits, and started again with a real
//! S3-compatible server (`s3s-fs`) reachable: every frame arrives in the bucket equal to the
//! frame fetched from the daemon, and its log says the uploads were resumed. Skips, saying
//! so, where `POINTFARM_TEST_S3S_FS` names no `s3s-fs` binary.

use std::net::TcpListener;
use std::path::Path;
use std::time::Duration;

use pointfarm_tests::s3s::S3Bucket;
use pointfarm_tests::service::{scan, submit_detached};
use pointfarm_tests::{
    free_address, path_arg, pointfarm_ok, pointfarm_with, stdout, wait_for, ServeProcess,
};

/// The bucket the farm writes to: a folder of the S3 server's root.
const BUCKET: &str = "pointfarm-renders";
/// The prefix the operator allows, and the job's output URL under it.
const ALLOWED: &str = "s3://pointfarm-renders/farm";
const OUTPUT_URL: &str = "s3://pointfarm-renders/farm/resumed";
const FRAMES: u32 = 3;

/// `pointfarm serve` on `data`, logging to `log`, with `bucket`'s credentials and its
/// endpoint replaced by `endpoint` when given.
fn serve(
    address: &str,
    data: &Path,
    log: &Path,
    bucket: &S3Bucket,
    endpoint: Option<&str>,
) -> ServeProcess {
    let mut command = pointfarm_with(&bucket.server.environment());
    if let Some(endpoint) = endpoint {
        command.env("AWS_ENDPOINT", endpoint);
    }
    ServeProcess::start_command(
        command,
        address,
        data,
        log,
        &["--allow-output-prefix", ALLOWED],
    )
}

fn count(job: &serde_json::Value, field: &str) -> u64 {
    job[field].as_u64().unwrap_or(0)
}

/// Asserts that `job` counts `uploaded` outputs written and `pending` waiting, and none failed.
fn assert_outputs(job: &serde_json::Value, uploaded: u64, pending: u64) {
    let counted = (count(job, "outputsUploaded"), count(job, "outputsPending"));
    assert_eq!(counted, (uploaded, pending), "{job}");
    let errors = job["outputErrors"].as_array().map_or(0, Vec::len);
    assert_eq!(errors, 0, "{job}");
}

#[test]
fn outputs_waiting_when_the_daemon_is_killed_reach_the_bucket_after_it_starts_again() {
    let Some(bucket) = S3Bucket::start_or_skip(BUCKET) else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let (data, log) = (dir.path().join("data"), dir.path().join("serve.log"));
    // Takes connections into its backlog and never answers them: a store that does not reply.
    let silent = TcpListener::bind("127.0.0.1:0").expect("a silent endpoint");
    let silent_endpoint = format!("http://{}", silent.local_addr().expect("address"));
    let address = free_address();
    let mut server = serve(&address, &data, &log, &bucket, Some(&silent_endpoint));

    let scan = scan(dir.path());
    let out = dir.path().join("out");
    let id = submit_detached(&address, &scan, FRAMES, (&out, OUTPUT_URL));
    let finished = wait_for(
        Duration::from_secs(120),
        "the job done, its outputs waiting",
        || {
            let job = server.job_json(&id);
            (job["state"] == "JOB_STATE_SUCCEEDED" && count(&job, "outputsPending") == 3)
                .then_some(job)
        },
    );
    assert_outputs(&finished, 0, 3);
    server.kill();
    drop(silent);
    assert!(bucket.objects().is_empty(), "{:?}", bucket.objects());

    // Started again with the store reachable: every waiting output is sent.
    let server = serve(&address, &data, &log, &bucket, None);
    let uploaded = wait_for(Duration::from_secs(120), "three outputs uploaded", || {
        let job = server.job_json(&id);
        (count(&job, "outputsUploaded") == 3).then_some(job)
    });
    assert_outputs(&uploaded, 3, 0);
    assert!(
        server.log().contains("resumed 3 pending output upload(s)"),
        "{}",
        server.log()
    );
    let shown = pointfarm_ok(&["jobs", "show", &id, "--server", &address]);
    assert!(
        stdout(&shown).contains("outputs: 3 uploaded, 0 pending"),
        "{}",
        stdout(&shown)
    );

    let fetched = dir.path().join("fetched");
    pointfarm_ok(&[
        "frames",
        "fetch",
        &id,
        "--out",
        path_arg(&fetched),
        "--server",
        &address,
    ]);
    let names: Vec<String> = (0..FRAMES).map(|i| format!("frame_{i:05}.png")).collect();
    let keys: Vec<String> = names
        .iter()
        .map(|name| format!("farm/resumed/{name}"))
        .collect();
    assert_eq!(bucket.objects(), keys);
    for (key, name) in keys.iter().zip(&names) {
        let frame = std::fs::read(fetched.join(name)).expect("fetched frame");
        let object = std::fs::read(bucket.stored(key)).expect("object");
        assert!(object == frame, "{name} differs from the fetched frame");
    }
}
