//! Stores every worker reads directly (`serve --store-url s3://...`), against a real
//! S3-compatible server (`s3s-fs`) and a separate `pointfarm worker` process with the
//! server's credentials in its own environment: the daemon publishes the store it built, the
//! worker reads its nodes from the bucket and none through the daemon, the frames are those
//! of a daemon without `--store-url`, a restart publishes nothing again, no credential reaches
//! a job, a lease or a log, a damaged published object fails the frame clearly while the
//! job still ends, through the daemon, a deleted dataset's published store is deleted,
//! even while it is being published, and a publish that gives up after the operator's tries
//! (`--store-publish-attempts`) says so with its last error and when, while frames render
//! through the daemon, until a later job publishes it once object storage is back. Each test
//! skips, saying so, where `POINTFARM_TEST_S3S_FS` names no `s3s-fs` binary.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use pointfarm_proto::v1 as pb;
use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::sample::sample_scene;
use pointfarm_tests::prometheus::scrape;
use pointfarm_tests::s3s::{self, S3Bucket};
use pointfarm_tests::service::{connect, lease_at_once};
use pointfarm_tests::{
    assert_same_frames, free_address, path_arg, pointfarm_ok, pointfarm_with, ServeProcess,
    WorkerProcess,
};

/// The bucket stores are published to: a folder of the server's root.
const BUCKET: &str = "pointfarm-stores";
/// Where the daemon publishes them.
const STORE_URL: &str = "s3://pointfarm-stores/farm";
/// Points of the scene: several leaves of the store's octree.
const SCENE_POINTS: usize = 300_000;
/// A job drawn from levels of detail: two frames of a cut.
const OPTIONS: [&str; 5] = ["--size=120x90", "--turntable", "2", "--lod-error", "0.25"];
/// The frames of a job of [`OPTIONS`].
const FRAMES: u32 = 2;
/// The daemon's count of node records it served to workers.
const RECORDS_SERVED: &str = "pointfarm_store_records_served_total";

/// An S3 server holding the bucket, a scene to render and a scratch folder.
struct Farm {
    bucket: S3Bucket,
    dir: tempfile::TempDir,
    scene: PathBuf,
}

impl Farm {
    /// Starts the server; None, having said so, without the binary.
    fn start() -> Option<Self> {
        let bucket = S3Bucket::start_or_skip(BUCKET)?;
        let dir = tempfile::tempdir().expect("tempdir");
        let scene = dir.path().join("scene.laz");
        write_las(
            &scene,
            &sample_scene(SCENE_POINTS, 9),
            &LasWriteOptions::default(),
        )
        .expect("scene");
        Some(Self { bucket, dir, scene })
    }

    /// The `pointfarm` binary with the server's endpoint and credentials in its environment.
    fn pointfarm(&self) -> Command {
        pointfarm_with(&self.bucket.server.environment())
    }

    /// A daemon publishing its stores under [`STORE_URL`], with no embedded worker, its
    /// metrics at `metrics`.
    fn publishing_daemon(&self, address: &str, metrics: &str) -> ServeProcess {
        self.publishing_daemon_with(address, metrics, &[])
    }

    /// [`Self::publishing_daemon`] with more `serve` arguments.
    fn publishing_daemon_with(&self, address: &str, metrics: &str, more: &[&str]) -> ServeProcess {
        let data = self.dir.path().join("data");
        let args = ["--no-embedded-worker", "--store-url", STORE_URL];
        let args = [&args[..], &["--metrics-listen", metrics], more].concat();
        ServeProcess::start_command(
            self.pointfarm(),
            address,
            &data,
            &data.join("serve.log"),
            &args,
        )
    }

    /// A `pointfarm worker` with the server's credentials, its cache in a folder of `name`.
    fn worker(&self, daemon: &ServeProcess, name: &str) -> WorkerProcess {
        let cache = self.dir.path().join(name);
        WorkerProcess::start_in(self.pointfarm(), &daemon.address, &cache, name, &[])
    }

    /// Renders the scene through `daemon` into the folder `out`.
    fn render(&self, daemon: &ServeProcess, out: &str) -> PathBuf {
        let out = self.dir.path().join(out);
        let mut args = vec!["render", path_arg(&self.scene), "--out", path_arg(&out)];
        args.extend(["--server", &daemon.address]);
        args.extend(OPTIONS);
        pointfarm_ok(&args);
        out
    }
}

/// Waits until `daemon` has said `times` times that it published a store.
fn wait_for_published(daemon: &ServeProcess, times: usize) {
    wait_for_log(daemon, "store published", times);
}

/// Waits until `daemon` has logged `words` `times` times.
fn wait_for_log(daemon: &ServeProcess, words: &str, times: usize) {
    let started = Instant::now();
    while daemon.log().matches(words).count() < times {
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "the daemon did not log {words:?} {times} times:\n{}",
            daemon.log()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Waits until `bucket` holds `count` objects that `daemon` publishes.
fn wait_for_objects(bucket: &S3Bucket, daemon: &ServeProcess, count: usize) {
    let started = Instant::now();
    while bucket.objects().len() != count {
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "the bucket holds {:?}, not {count} objects:\n{}",
            bucket.objects(),
            daemon.log()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The ids of the jobs `daemon` knows.
fn job_ids(daemon: &ServeProcess) -> BTreeSet<String> {
    let listed = pointfarm_ok(&["jobs", "list", "--server", &daemon.address, "--json"]);
    let jobs: serde_json::Value = serde_json::from_slice(&listed.stdout).expect("json");
    // An empty list is left out of the JSON.
    jobs["jobs"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|job| job["id"].as_str().expect("an id").to_owned())
        .collect()
}

/// `jobs show ID --json` of `daemon`, as printed, and as a Job.
fn shown_job(daemon: &ServeProcess, id: &str) -> (String, pb::Job) {
    let shown = pointfarm_ok(&["jobs", "show", id, "--server", &daemon.address, "--json"]);
    let text = String::from_utf8_lossy(&shown.stdout).into_owned();
    let value: serde_json::Value = serde_json::from_str(&text).expect("json");
    let job = serde_json::from_value(value["job"].clone()).expect("a Job");
    (text, job)
}

/// The job `daemon` ran since it knew `before`.
fn new_job(daemon: &ServeProcess, before: &BTreeSet<String>) -> (String, pb::Job) {
    let after = job_ids(daemon);
    let mut new = after.difference(before);
    let id = new.next().expect("a new job").clone();
    assert!(new.next().is_none(), "one new job");
    shown_job(daemon, &id)
}

/// `dataset get ID --json` of the dataset registered from `file`, as printed, and its
/// store's publication.
fn store_publication(daemon: &ServeProcess, file: &Path) -> (String, serde_json::Value) {
    let server = ["--server", daemon.address.as_str(), "--json"];
    let id = dataset_id(daemon, file);
    let shown = pointfarm_ok(&[&["dataset", "get", &id], &server[..]].concat());
    let text = String::from_utf8_lossy(&shown.stdout).into_owned();
    let dataset: serde_json::Value = serde_json::from_str(&text).expect("json");
    (text, dataset["storePublication"].clone())
}

fn assert_no_credential(text: &str, what: &str) {
    for secret in [s3s::SECRET_KEY, s3s::ACCESS_KEY] {
        assert!(!text.contains(secret), "{what} holds a credential:\n{text}");
    }
}

#[test]
fn workers_read_a_published_store_from_object_storage_and_none_of_it_through_the_daemon() {
    let Some(farm) = Farm::start() else {
        return;
    };
    // The same job through a daemon without --store-url: its worker reads the daemon's store.
    let plain_daemon = ServeProcess::start(&farm.dir.path().join("plain"));
    let plain = farm.render(&plain_daemon, "plain");
    let (text, publication) = store_publication(&plain_daemon, &farm.scene);
    assert_eq!(publication["state"], "NOT_PUBLISHED", "{text}");
    assert!(text.contains("--store-url"), "{text}");
    drop(plain_daemon);

    let (address, metrics) = (free_address(), free_address());
    let daemon = farm.publishing_daemon(&address, &metrics);
    let worker = farm.worker(&daemon, "far");
    // The first job builds the store; once ready, the daemon publishes it.
    let first = farm.render(&daemon, "first");
    assert_same_frames(&plain, &first, FRAMES, "frames during publishing");
    wait_for_published(&daemon, 1);
    let objects = farm.bucket.objects();
    let [hierarchy, payload] = objects.as_slice() else {
        panic!("the store's two objects: {objects:?}");
    };
    let sha256 = payload
        .strip_prefix("farm/")
        .and_then(|rest| rest.strip_suffix("/nodes.bin"))
        .expect("farm/SHA256/nodes.bin");
    assert_eq!(hierarchy, &format!("farm/{sha256}/hierarchy.pfps"));
    // The dataset says where its store is published, and nothing of the credentials.
    let (text, publication) = store_publication(&daemon, &farm.scene);
    assert_eq!(
        publication["state"],
        "PUBLISHED",
        "{text}\n{}",
        daemon.log()
    );
    assert_eq!(
        publication["url"],
        format!("{STORE_URL}/{sha256}/"),
        "{text}"
    );
    assert_no_credential(&text, "the dataset");

    // Published: a worker new to the dataset reads every node from the bucket, none from the
    // daemon.
    drop(worker);
    let worker = farm.worker(&daemon, "reader");
    let served_before = scrape(&metrics)[RECORDS_SERVED];
    let jobs_before = job_ids(&daemon);
    let published = farm.render(&daemon, "published");
    assert_same_frames(&plain, &published, FRAMES, "frames read from the bucket");
    assert_eq!(
        scrape(&metrics)[RECORDS_SERVED],
        served_before,
        "the daemon served node records:\n{}",
        worker.log()
    );
    let log = worker.log();
    assert!(log.contains("from=Published"), "{log}");
    let (shown, job) = new_job(&daemon, &jobs_before);
    assert_eq!(job.state, pb::JobState::Succeeded as i32, "{shown}");
    let cuts: Vec<pb::FrameCut> = job.frames.iter().filter_map(|f| f.cut).collect();
    assert_eq!(cuts.len(), 2, "{shown}");
    assert!(cuts[0].nodes_read > 1, "{shown}");
    assert!(
        cuts.iter().map(|c| c.object_requests).sum::<u64>() > 0
            && cuts.iter().map(|c| c.object_bytes).sum::<u64>() > 0,
        "no object reads reported: {shown}"
    );
    assert_no_credential(&shown, "the job");

    // A lease names the published store by its prefix and versions, and nothing more.
    let mut daemon = daemon;
    drop(worker);
    let before = job_ids(&daemon);
    let detached = farm.dir.path().join("detached");
    let mut args = vec![
        "render",
        path_arg(&farm.scene),
        "--out",
        path_arg(&detached),
    ];
    args.extend(["--server", &address, "--detach"]);
    args.extend(OPTIONS);
    pointfarm_ok(&args);
    assert_eq!(job_ids(&daemon).len(), before.len() + 1);
    let runtime = tokio::runtime::Runtime::new().expect("runtime");
    let task = runtime.block_on(async {
        let mut workers =
            pb::worker_service_client::WorkerServiceClient::new(connect(&address).await);
        let leased = workers
            .lease_frame(lease_at_once("probe"))
            .await
            .expect("lease");
        leased.into_inner().task.expect("a task")
    });
    let dataset = task.dataset.expect("a dataset");
    let store = dataset
        .published_store
        .clone()
        .expect("the published store");
    assert_eq!(store.url, format!("{STORE_URL}/{sha256}/"));
    assert!(!store.hierarchy_version.is_empty() && !store.payload_version.is_empty());
    assert_no_credential(&format!("{dataset:?}"), "the lease");

    // Restarted, the daemon finds the store published and publishes nothing again.
    assert!(daemon
        .terminate(Duration::from_secs(60))
        .is_some_and(|status| status.success()));
    let daemon = farm.publishing_daemon(&address, &metrics);
    let worker = farm.worker(&daemon, "again");
    let again = farm.render(&daemon, "again");
    assert_same_frames(&plain, &again, FRAMES, "frames after a restart");
    assert_eq!(scrape(&metrics)[RECORDS_SERVED], 0.0, "{}", worker.log());
    let served = daemon.log();
    assert_eq!(served.matches("store published").count(), 1, "{served}");
    assert_no_credential(&served, "the daemon's log");
    assert_no_credential(&worker.log(), "the worker's log");
    assert_no_credential(&log, "the worker's log");
}

#[test]
fn a_damaged_published_store_fails_the_frame_and_the_job_ends_through_the_daemon() {
    let Some(farm) = Farm::start() else {
        return;
    };
    let (address, metrics) = (free_address(), free_address());
    let daemon = farm.publishing_daemon(&address, &metrics);
    let mut first_worker = farm.worker(&daemon, "first");
    let first = farm.render(&daemon, "first");
    wait_for_published(&daemon, 1);
    first_worker.kill();

    // Every byte of the published payload damaged, its size kept.
    let payload = farm
        .bucket
        .objects()
        .into_iter()
        .find(|key| key.ends_with("/nodes.bin"))
        .expect("the payload object");
    let path = farm.bucket.stored(&payload);
    let damaged: Vec<u8> = std::fs::read(&path)
        .expect("payload")
        .iter()
        .map(|b| b ^ 0x5a)
        .collect();
    std::fs::write(&path, damaged).expect("damage");

    // A worker new to the dataset fails its first frame saying which store failed, reads
    // the dataset through the daemon from then on, and the job ends as the first did.
    let worker = farm.worker(&daemon, "second");
    let jobs_before = job_ids(&daemon);
    let second = farm.render(&daemon, "second");
    assert_same_frames(&first, &second, FRAMES, "frames after the damage");
    let log = worker.log();
    assert!(
        log.contains("the published store failed") && log.contains(&format!("{STORE_URL}/")),
        "{log}"
    );
    let (shown, job) = new_job(&daemon, &jobs_before);
    assert_eq!(job.state, pb::JobState::Succeeded as i32, "{shown}");
    assert!(scrape(&metrics)[RECORDS_SERVED] > 0.0);
    assert_no_credential(&log, "the worker's log");
    assert_no_credential(&daemon.log(), "the daemon's log");
}

#[test]
fn deleting_a_dataset_deletes_its_published_store_even_while_it_is_being_published() {
    let Some(farm) = Farm::start() else {
        return;
    };
    let (address, metrics) = (free_address(), free_address());
    let daemon = farm.publishing_daemon(&address, &metrics);
    let worker = farm.worker(&daemon, "first");
    let delete_dataset_of = |job: &pb::Job| {
        pointfarm_ok(&["dataset", "rm", &job.dataset_id, "--server", &address]);
    };

    // Deleted as soon as its job ends, as its store is being published or just after.
    let before = job_ids(&daemon);
    farm.render(&daemon, "first");
    let (_, job) = new_job(&daemon, &before);
    delete_dataset_of(&job);
    wait_for_log(&daemon, "published store deleted", 1);
    assert_eq!(farm.bucket.objects(), Vec::<String>::new());

    // Registered again, it is published again (its record went with its objects), then
    // deleted once published. A worker new to it asks for the store again.
    drop(worker);
    let _worker = farm.worker(&daemon, "second");
    let before = job_ids(&daemon);
    farm.render(&daemon, "again");
    wait_for_objects(&farm.bucket, &daemon, 2);
    let (_, job) = new_job(&daemon, &before);
    delete_dataset_of(&job);
    wait_for_log(&daemon, "published store deleted", 2);
    assert_eq!(farm.bucket.objects(), Vec::<String>::new());
    // Nothing is published or deleted after that.
    std::thread::sleep(Duration::from_secs(2));
    assert_eq!(farm.bucket.objects(), Vec::<String>::new());
    let log = daemon.log();
    assert!(!log.contains("deleting a published store failed"), "{log}");
    assert_no_credential(&log, "the daemon's log");
}

#[test]
fn a_store_published_while_object_storage_is_down_is_published_once_it_is_back() {
    let Some(mut farm) = Farm::start() else {
        return;
    };
    let (address, metrics) = (free_address(), free_address());
    farm.bucket.server.stop();
    let daemon = farm.publishing_daemon(&address, &metrics);
    let worker = farm.worker(&daemon, "first");
    // Built while the object store is down: the frames render through the daemon.
    let first = farm.render(&daemon, "first");
    std::thread::sleep(Duration::from_secs(2));
    assert!(farm.bucket.objects().is_empty());
    assert!(scrape(&metrics)[RECORDS_SERVED] > 0.0);
    let (text, publication) = store_publication(&daemon, &farm.scene);
    assert_eq!(publication["state"], "PUBLISHING", "{text}");

    // Back, the publish goes through on a later try, and a worker new to the dataset reads
    // the published store, none of it through the daemon.
    farm.bucket.restart();
    wait_for_log(&daemon, "store published", 1);
    assert_eq!(farm.bucket.objects().len(), 2, "{}", daemon.log());
    drop(worker);
    let _worker = farm.worker(&daemon, "second");
    let served_before = scrape(&metrics)[RECORDS_SERVED];
    let second = farm.render(&daemon, "second");
    assert_same_frames(&first, &second, FRAMES, "frames of the late store");
    assert_eq!(scrape(&metrics)[RECORDS_SERVED], served_before);
    assert_no_credential(&daemon.log(), "the daemon's log");
}

#[test]
fn a_publish_that_gives_up_says_why_and_when_and_a_later_job_publishes_it() {
    let Some(mut farm) = Farm::start() else {
        return;
    };
    let (address, metrics) = (free_address(), free_address());
    farm.bucket.server.stop();
    let tries = ["--store-publish-attempts", "2"];
    let daemon = farm.publishing_daemon_with(&address, &metrics, &tries);
    let worker = farm.worker(&daemon, "first");
    let started_ms = now_unix_ms();
    // Object storage is down for good: the two tries fail, and the frames render through the
    // daemon all the same.
    let first = farm.render(&daemon, "first");
    assert!(scrape(&metrics)[RECORDS_SERVED] > 0.0);
    wait_for_log(&daemon, GAVE_UP, 1);
    let (text, publication) = wait_for_publication(&daemon, &farm.scene, "FAILED");
    // Two tries each time it is offered: one retry logged per giving up.
    let log = daemon.log();
    assert_eq!(
        log.matches("failed; trying again").count(),
        log.matches(GAVE_UP).count(),
        "{log}"
    );
    let reason = publication["reason"].as_str().expect("the last error");
    assert!(reason.contains(STORE_URL), "{text}");
    let failed_ms: i64 = match &publication["failedUnixMs"] {
        serde_json::Value::String(ms) => ms.parse().expect("milliseconds"),
        other => panic!("no time of failure: {other} in {text}"),
    };
    assert!(
        (started_ms..=now_unix_ms()).contains(&failed_ms),
        "{failed_ms} {text}"
    );
    let id = dataset_id(&daemon, &farm.scene);
    let shown = pointfarm_ok(&["dataset", "get", &id, "--server", &address]);
    let shown = String::from_utf8_lossy(&shown.stdout).into_owned();
    assert!(
        shown.contains(&format!("store: publishing under {STORE_URL}/"))
            && shown.contains(&format!("failed (unix ms {failed_ms}): ")),
        "{shown}"
    );
    assert_no_credential(&shown, "the dataset");
    // Given up, nothing is tried while no frame of the store is leased.
    let gave_up = daemon.log().matches(GAVE_UP).count();
    std::thread::sleep(Duration::from_secs(3));
    assert_eq!(daemon.log().matches(GAVE_UP).count(), gave_up);
    assert_eq!(store_publication(&daemon, &farm.scene).1["state"], "FAILED");

    // Back, the next job's leases offer the store again and it is published; its frames are
    // the same.
    farm.bucket.restart();
    let second = farm.render(&daemon, "second");
    assert_same_frames(&first, &second, FRAMES, "frames during publishing again");
    let (text, _) = wait_for_publication(&daemon, &farm.scene, "PUBLISHED");
    assert_eq!(farm.bucket.objects().len(), 2, "{text}\n{}", daemon.log());
    drop(worker);
    assert_no_credential(&daemon.log(), "the daemon's log");
}

/// What the daemon logs when every try at a publish failed.
const GAVE_UP: &str = "publishing a store failed; tried again when a frame of it is next leased";

/// Waits until the store of the dataset registered from `file` is in `state`; as
/// [`store_publication`] says it.
fn wait_for_publication(
    daemon: &ServeProcess,
    file: &Path,
    state: &str,
) -> (String, serde_json::Value) {
    let started = Instant::now();
    loop {
        let (text, publication) = store_publication(daemon, file);
        if publication["state"] == state {
            return (text, publication);
        }
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "not {state}: {text}\n{}",
            daemon.log()
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn now_unix_ms() -> i64 {
    let since = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH);
    since.expect("after 1970").as_millis() as i64
}

/// The id of the dataset registered from `file`.
fn dataset_id(daemon: &ServeProcess, file: &Path) -> String {
    let server = ["--server", daemon.address.as_str(), "--json"];
    let registered = pointfarm_ok(&[&["dataset", "add", path_arg(file)], &server[..]].concat());
    let dataset: serde_json::Value = serde_json::from_slice(&registered.stdout).expect("json");
    dataset["id"].as_str().expect("an id").to_owned()
}
