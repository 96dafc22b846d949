//! A job's frames sent to a `gs://` output URL, as a user asks with
//! `pointfarm render --server ADDR --output-url gs://bucket/prefix`, against a real daemon
//! (`pointfarm serve`, its embedded worker rendering on lavapipe) and a real Google Cloud
//! Storage server (fake-gcs-server, which answers a write to a bucket that does not exist
//! `404`, as GCS does): a missing bucket is recorded in the job naming each frame's URL, while
//! the frames stay fetchable from the daemon, nothing reaches the bucket that exists, and the
//! daemon goes on. The test skips, saying so, where `POINTFARM_TEST_FAKE_GCS` names no binary
//! (and fails where `CI` is set).
//!
//! A frame written whole is not tested: no GCS server on the package registries answers
//! object_store's XML API writes as GCS does (docs/design/remote.md names each one tried and
//! its answer).

use std::path::{Path, PathBuf};
use std::time::Duration;

use pointfarm_tests::fake_gcs::FakeGcs;
use pointfarm_tests::service::{render_detached, scan};
use pointfarm_tests::{assert_ok, path_arg, stdout, wait_for, ServeProcess};

/// The bucket the farm may write to.
const BUCKET: &str = "pointfarm-renders";
/// The prefix under it the operator allows.
const ALLOWED: &str = "gs://pointfarm-renders/farm";
/// A prefix the operator allows in a bucket that does not exist.
const MISSING: &str = "gs://pointfarm-no-such-bucket/farm";
/// The frames of each job (`render_detached`'s turntable).
const FRAMES: [&str; 2] = ["frame_00000.png", "frame_00001.png"];

/// A farm writing outputs to GCS: the server with the bucket, a daemon allowed to write
/// under `ALLOWED` and `MISSING` (so that a write to the missing bucket is not refused at
/// submission) with the server's service account in its environment, and
/// a scan to render, all in a scratch folder. The fields drop in order: the servers stop
/// before their folders go.
struct GcsFarm {
    server: ServeProcess,
    gcs: FakeGcs,
    dir: tempfile::TempDir,
    scan: PathBuf,
}

impl GcsFarm {
    /// Starts the farm; None, having said so, without the server.
    fn start() -> Option<Self> {
        let gcs = FakeGcs::start_or_skip()?;
        gcs.create_bucket(BUCKET);
        let dir = tempfile::tempdir().expect("tempdir");
        let allowed = format!("{ALLOWED},{MISSING}");
        let server = ServeProcess::start_in_environment(
            &gcs.environment(),
            &dir.path().join("data"),
            &["--allow-output-prefix", &allowed],
        );
        let scan = scan(dir.path());
        Some(Self {
            server,
            gcs,
            dir,
            scan,
        })
    }

    /// Submits the two-frame turntable of the scan with `url` as its output URL; the job's id.
    fn submit(&self, url: &str) -> String {
        let out = self.dir.path().join("out");
        let submitted = render_detached(
            &self.server.address,
            path_arg(&self.scan),
            path_arg(&out),
            &["--output-url", url],
        );
        assert_ok(&submitted);
        stdout(&submitted).trim().to_owned()
    }

    /// The job `id` once all its frames' outputs are done, uploaded or failed.
    fn finished(&self, id: &str) -> serde_json::Value {
        wait_for(Duration::from_secs(120), "the outputs done", || {
            let job = self.server.job_json(id);
            let failed = job["outputErrors"].as_array().map_or(0, Vec::len);
            let uploaded = job["outputsUploaded"].as_u64().unwrap_or(0) as usize;
            (uploaded + failed == FRAMES.len()).then_some(job)
        })
    }

    /// `frames fetch ID` into a folder of its own: the folder.
    fn fetch_frames(&self, id: &str) -> PathBuf {
        let fetched = self.dir.path().join(format!("fetched-{id}"));
        assert_ok(&self.server.fetch_frames(id, &fetched));
        fetched
    }
}

/// The frames a fetch wrote to `folder`, read whole.
fn fetched_frames(folder: &Path) -> Vec<Vec<u8>> {
    (FRAMES.iter())
        .map(|name| std::fs::read(folder.join(name)).expect("fetched frame"))
        .collect()
}

#[test]
fn a_missing_bucket_is_recorded_in_the_job_naming_the_url_and_the_daemon_goes_on() {
    let Some(mut farm) = GcsFarm::start() else {
        return;
    };
    let url = format!("{MISSING}/turntable");
    let id = farm.submit(&url);
    let job = farm.finished(&id);
    let text = job.to_string();
    assert_eq!(job["state"], "JOB_STATE_SUCCEEDED", "{text}");
    assert_eq!(job["outputsUploaded"].as_u64().unwrap_or(0), 0, "{text}");
    let errors = job["outputErrors"].as_array().expect("the failures");
    assert_eq!(errors.len(), 2, "{text}");
    for (error, name) in errors.iter().zip(FRAMES) {
        let error = error.as_str().expect("a failure's text");
        assert!(error.contains(&format!("{url}/{name}")), "{error}");
        assert!(!error.contains('\n'), "{error}");
        // A 404 of the write: the server's answer names no bucket, real GCS's `NoSuchBucket`
        // does, so the product says "no such object" here and "no such bucket" there.
        assert!(error.contains("no such"), "{error}");
    }
    assert!(!farm.server.log().contains("panicked"));
    // Nothing is lost: the frames stay fetchable, and nothing went to the bucket that exists.
    let fetched = fetched_frames(&farm.fetch_frames(&id));
    assert!(fetched.iter().all(|frame| frame.starts_with(b"\x89PNG")));
    assert!(farm.gcs.object_names(BUCKET, "").is_empty());

    // The daemon goes on: it still runs and takes the next job, whose frames it renders.
    assert!(farm.server.is_running());
    let next = farm.submit(&format!("{MISSING}/after"));
    assert_eq!(farm.finished(&next)["framesDone"], 2);
    assert!(farm.server.is_running());
}
