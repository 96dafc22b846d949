//! A job's frames written to object storage by the server, as a user asks with
//! `pointfarm render --server ADDR --output-url s3://bucket/prefix`, against a real daemon
//! (`pointfarm serve`, its embedded worker rendering on lavapipe) and a real S3-compatible
//! server (`s3s-fs`): each final frame appears as PREFIX/frame_NNNNN.png equal to the frame
//! fetched from the daemon, and the video beside them equals the video fetched; a prefix
//! outside the operator's `--allow-output-prefix` is PERMISSION_DENIED naming the rule, and
//! uploads that fail are recorded in the job while its frames stay fetchable. Each test
//! skips, saying so, where `POINTFARM_TEST_S3S_FS` names no `s3s-fs` binary.

use std::path::{Path, PathBuf};
use std::time::Duration;

use pointfarm_tests::s3s::{self, S3Bucket};
use pointfarm_tests::service::{scan, submit_detached};
use pointfarm_tests::{
    assert_fails_saying, assert_ok, output_text, path_arg, pointfarm, pointfarm_ok, stdout,
    wait_for, ServeProcess,
};

/// The bucket the farm writes to: a folder of the S3 server's root.
const BUCKET: &str = "pointfarm-renders";
/// The prefix the operator allows.
const ALLOWED: &str = "s3://pointfarm-renders/farm";

/// A farm writing outputs to object storage: an S3 server over a fresh root holding the
/// bucket, a daemon allowed to write under `ALLOWED` with the server's endpoint and
/// credentials in its environment, and a scan to render, all in a scratch folder. The
/// fields drop in order: the servers stop before their folders go.
struct OutputFarm {
    server: ServeProcess,
    bucket: S3Bucket,
    dir: tempfile::TempDir,
    scan: PathBuf,
}

impl OutputFarm {
    /// Starts the farm (`secret` replacing the right secret key when given); None, having
    /// said so, without the S3 binary.
    fn start(secret: Option<&str>) -> Option<Self> {
        let dir = tempfile::tempdir().expect("tempdir");
        let bucket = S3Bucket::start_or_skip(BUCKET)?;
        let mut environment = bucket.server.environment();
        if let Some(secret) = secret {
            // Set after the right one, so it is the one the daemon reads.
            environment.push(("AWS_SECRET_ACCESS_KEY", secret.to_owned()));
        }
        let server = ServeProcess::start_in_environment(
            &environment,
            &dir.path().join("data"),
            &["--allow-output-prefix", ALLOWED],
        );
        let scan = scan(dir.path());
        Some(Self {
            server,
            bucket,
            dir,
            scan,
        })
    }

    /// `frames fetch ID --out DIR/fetched`: the command's output, and the folder.
    fn fetch_frames(&self, id: &str) -> (std::process::Output, PathBuf) {
        let fetched = self.dir.path().join("fetched");
        let output = pointfarm(&[
            "frames",
            "fetch",
            id,
            "--out",
            path_arg(&fetched),
            "--server",
            &self.server.address,
        ]);
        (output, fetched)
    }
}

/// `render SCAN --server ... --turntable FRAMES --detach --output-url URL` on `farm`'s scan:
/// the job's id.
fn submit(farm: &OutputFarm, frames: u32, url: &str) -> String {
    let out = farm.dir.path().join("out");
    submit_detached(&farm.server.address, &farm.scan, frames, (&out, url))
}

/// The files under `folder`, sorted by name.
fn files_in(folder: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(folder)
        .map(|entries| entries.map(|e| e.expect("entry").path()).collect())
        .unwrap_or_default();
    files.sort();
    files
}

#[test]
fn each_final_frame_appears_under_the_output_url_as_the_daemon_stores_it() {
    let Some(farm) = OutputFarm::start(None) else {
        return;
    };
    let url = format!("{ALLOWED}/turntable");
    let id = submit(&farm, 3, &url);
    let uploaded = wait_for(Duration::from_secs(120), "three outputs uploaded", || {
        let job = farm.server.job_json(&id);
        (job["outputsUploaded"] == 3).then_some(job)
    });
    assert_eq!(uploaded["state"], "JOB_STATE_SUCCEEDED", "{uploaded}");
    let errors = uploaded["outputErrors"].as_array().map_or(0, Vec::len);
    assert_eq!(errors, 0, "{uploaded}");

    let (output, fetched) = farm.fetch_frames(&id);
    assert_ok(&output);
    let objects = files_in(&farm.bucket.folder().join("farm/turntable"));
    let names: Vec<String> = objects
        .iter()
        .map(|path| {
            path.file_name()
                .expect("name")
                .to_string_lossy()
                .into_owned()
        })
        .collect();
    assert_eq!(
        names,
        ["frame_00000.png", "frame_00001.png", "frame_00002.png"]
    );
    for (object, name) in objects.iter().zip(&names) {
        let frame = std::fs::read(fetched.join(name)).expect("fetched frame");
        assert!(std::fs::read(object).expect("object") == frame, "{name}");
    }
    assert!(!farm.server.log().contains(s3s::SECRET_KEY));
}

#[test]
fn an_output_url_outside_the_operators_prefixes_is_refused_naming_the_rule() {
    let Some(farm) = OutputFarm::start(None) else {
        return;
    };
    let (dir, scan) = (&farm.dir, &farm.scan);
    let refused = pointfarm(&[
        "render",
        path_arg(scan),
        "--server",
        &farm.server.address,
        "--size",
        "32x24",
        "--out",
        path_arg(&dir.path().join("out.png")),
        "--output-url",
        "s3://pointfarm-renders/farm-other/x",
    ]);
    assert_fails_saying(&refused, "--allow-output-prefix");
    assert_fails_saying(&refused, "allows only s3://pointfarm-renders/farm");
    let not_s3 = pointfarm(&[
        "render",
        path_arg(scan),
        "--server",
        &farm.server.address,
        "--out",
        path_arg(&dir.path().join("out.png")),
        "--output-url",
        "https://example.com/renders/",
    ]);
    assert_fails_saying(&not_s3, "s3://");
    assert!(files_in(&farm.bucket.folder()).is_empty());

    // A daemon that allows none says so.
    let bare = ServeProcess::start(&dir.path().join("bare"));
    let refused = pointfarm(&[
        "render",
        path_arg(scan),
        "--server",
        &bare.address,
        "--out",
        path_arg(&dir.path().join("out.png")),
        "--output-url",
        "s3://pointfarm-renders/farm/x",
    ]);
    assert_fails_saying(&refused, "allow-list is empty");
}

#[test]
fn uploads_refused_by_the_store_are_recorded_and_the_frames_stay_fetchable() {
    let Some(farm) = OutputFarm::start(Some("not-the-secret")) else {
        return;
    };
    let url = format!("{ALLOWED}/refused");
    let id = submit(&farm, 2, &url);
    let recorded = wait_for(Duration::from_secs(120), "two failures recorded", || {
        let job = farm.server.job_json(&id);
        let errors = job["outputErrors"].as_array().map_or(0, Vec::len);
        (errors == 2).then_some(job)
    });
    let text = recorded.to_string();
    assert_eq!(recorded["state"], "JOB_STATE_SUCCEEDED", "{text}");
    assert!(text.contains(&format!("{url}/frame_00000.png")), "{text}");
    assert!(text.contains("access denied"), "{text}");
    assert!(!text.contains("not-the-secret"), "{text}");
    assert!(files_in(&farm.bucket.folder()).is_empty());
    let (output, fetched) = farm.fetch_frames(&id);
    assert_ok(&output);
    assert_eq!(files_in(&fetched).len(), 2, "{}", output_text(&output));
}

#[test]
fn a_jobs_video_appears_beside_its_frames_under_the_output_url() {
    if !pointfarm_tests::installed_or_skip("ffmpeg", "-version", "deploy/test.sh") {
        return;
    }
    let Some(farm) = OutputFarm::start(None) else {
        return;
    };
    let (dir, server) = (&farm.dir, &farm.server);
    let video = dir.path().join("spin.webm");
    assert_ok(&pointfarm(&[
        "render",
        path_arg(&farm.scan),
        "--server",
        &server.address,
        "--turntable",
        "3",
        "--size",
        "48x32",
        "--out",
        path_arg(&dir.path().join("frames")),
        "--video",
        path_arg(&video),
        "--output-url",
        &format!("{ALLOWED}/with-video"),
    ]));
    let listed = pointfarm_ok(&["jobs", "list", "--server", &server.address, "--json"]);
    let listed: serde_json::Value = serde_json::from_str(stdout(&listed).trim()).expect("jobs");
    let id = listed["jobs"][0]["id"]
        .as_str()
        .expect("the render's job")
        .to_owned();
    wait_for(
        Duration::from_secs(120),
        "frames and video uploaded",
        || (server.job_json(&id)["outputsUploaded"] == 4).then_some(()),
    );
    let folder = farm.bucket.folder().join("farm/with-video");
    let object = std::fs::read(folder.join("video.webm")).expect("the video's object");
    assert!(object == std::fs::read(&video).expect("the video fetched"));
    assert_eq!(files_in(&folder).len(), 4);
}
