//! The worker's cache of ranges of datasets by URL, with a real nginx on loopback, a real
//! daemon and its embedded worker process: a dataset leased again reads its ranges from the
//! cache, not from the server; an object replaced and registered again never reads the old
//! version's ranges; a damaged entry is fetched again and the frames stay right; a worker's
//! `--url-cache` bounds the folder. Skips, saying so, where nginx is not installed.

use std::path::Path;
use std::time::Duration;

use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_tests::datasets::{daemon_on_served_scans, register_path};
use pointfarm_tests::nginx::NginxServer;
use pointfarm_tests::service::{fetch_images, submit, turntable_job, watch_to_success};
use pointfarm_tests::{copc_file, WorkerProcess};
use tonic::transport::Channel;

/// What a job's frames report they read of a dataset by URL, together.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
struct Reads {
    requests: u64,
    bytes: u64,
    from_cache: u64,
}

/// The frames of a new two-frame job on `dataset`, and what their reports say they read.
async fn render(
    jobs: &mut JobServiceClient<Channel>,
    name: &str,
    dataset: &pb::Dataset,
) -> (Vec<(u32, image::RgbaImage)>, Reads) {
    let job = submit(jobs, turntable_job(name, &dataset.id, 2, 160, 120)).await;
    let (_, frames) = watch_to_success(jobs, &job.id, || format!("the {name} job")).await;
    let mut reads = Reads::default();
    for cut in frames.iter().filter_map(|frame| frame.cut.as_ref()) {
        reads.requests += cut.object_requests;
        reads.bytes += cut.object_bytes;
        reads.from_cache += cut.range_cache_bytes;
    }
    (fetch_images(jobs, &job.id, 0).await, reads)
}

/// The GET requests nginx answered for `object` so far.
fn gets_of(server: &NginxServer, object: &str) -> usize {
    requests_of(server, "GET", object)
}

/// The `method` requests nginx answered for `object` so far.
fn requests_of(server: &NginxServer, method: &str, object: &str) -> usize {
    // nginx logs a request after its answer left.
    std::thread::sleep(Duration::from_millis(200));
    let request = format!("\"{method} /{object} ");
    (server.access_log(0).iter())
        .filter(|line| line.contains(&request))
        .count()
}

/// The entries of the worker's range cache, and their bytes together.
fn entries(dir: &Path) -> Vec<std::path::PathBuf> {
    std::fs::read_dir(dir)
        .map(|items| items.map(|item| item.expect("entry").path()).collect())
        .unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dataset_by_url_is_read_once_by_its_version_and_damaged_entries_fetched_again() {
    let simple = std::fs::read(copc_file("simple.copc.laz")).expect("COPC file");
    let Some((root, server)) =
        NginxServer::serve_scans(&[("a.copc.laz", simple.clone()), ("b.copc.laz", simple)])
    else {
        return;
    };
    let daemon = daemon_on_served_scans(&server, true).await;
    let mut datasets = daemon.datasets().await;
    let ranges = daemon.data_dir.path().join("embedded-worker/ranges");
    let a = register_path(&mut datasets, &server.url("scans/a.copc.laz")).await;
    let b = register_path(&mut datasets, &server.url("scans/b.copc.laz")).await;
    let mut jobs = daemon.jobs().await;

    // Registering read the header: what the worker reads comes after.
    let object = "scans/a.copc.laz";
    let registered = gets_of(&server, object) + requests_of(&server, "HEAD", object);
    let (first, first_reads) = render(&mut jobs, "a", &a).await;
    let fetched = gets_of(&server, object);
    assert!(fetched > 1, "the first job fetches the object's ranges");
    assert!(!entries(&ranges).is_empty(), "the ranges are cached");
    // The reports count every request the worker made of it.
    let requested = fetched + requests_of(&server, "HEAD", object) - registered;
    assert_eq!(first_reads.requests, requested as u64, "{first_reads:?}");
    assert!(first_reads.bytes > 0, "{first_reads:?}");
    // Another dataset in between, so that the worker opens the first one again.
    render(&mut jobs, "b", &b).await;
    let (again, again_reads) = render(&mut jobs, "a-again", &a).await;
    assert_eq!(
        gets_of(&server, object),
        fetched,
        "a dataset leased again is read from the cache"
    );
    assert!(first == again, "the cached ranges render the same frames");
    let only_the_head = Reads {
        requests: 1,
        bytes: 0,
        from_cache: again_reads.from_cache,
    };
    assert_eq!(again_reads, only_the_head);
    assert!(again_reads.from_cache > 0, "{again_reads:?}");

    // The object is replaced by another cloud and registered again: a new version.
    std::fs::copy(
        copc_file("autzen.copc.laz"),
        root.path().join("scans/a.copc.laz"),
    )
    .expect("replace");
    let replaced = register_path(&mut datasets, &server.url("scans/a.copc.laz")).await;
    assert_ne!(replaced.version, a.version, "nginx's ETag changed");
    let by_path = register_path(&mut datasets, "scans/a.copc.laz").await;
    let (expected, _) = render(&mut jobs, "by-path", &by_path).await;
    let (replaced_frames, _) = render(&mut jobs, "replaced", &replaced).await;
    assert!(
        replaced_frames == expected,
        "the replaced object renders as the new file, not from the old version's ranges"
    );
    assert!(replaced_frames != first, "the new file is another cloud");
    let fetched = gets_of(&server, "scans/a.copc.laz");

    // Every entry damaged: each is dropped and fetched again, and the frames stay right.
    for entry in entries(&ranges) {
        let mut bytes = std::fs::read(&entry).expect("entry");
        let last = bytes.len() - 1;
        bytes[last] ^= 0x5a;
        std::fs::write(&entry, bytes).expect("damaged");
    }
    render(&mut jobs, "b-again", &b).await;
    let (damaged, _) = render(&mut jobs, "after-damage", &replaced).await;
    assert!(damaged == expected, "damaged entries are never rendered");
    assert!(
        gets_of(&server, "scans/a.copc.laz") > fetched,
        "damaged entries are fetched again"
    );
}

/// The bytes of the files in `dir` together.
fn folder_bytes(dir: &Path) -> u64 {
    (entries(dir).iter())
        .map(|path| std::fs::metadata(path).expect("entry").len())
        .sum()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_workers_url_cache_budget_bounds_its_folder() {
    let simple = std::fs::read(copc_file("simple.copc.laz")).expect("COPC file");
    let Some((_root, server)) = NginxServer::serve_scans(&[("a.copc.laz", simple)]) else {
        return;
    };
    let daemon = daemon_on_served_scans(&server, false).await;
    let mut datasets = daemon.datasets().await;
    let scratch = tempfile::tempdir().expect("tempdir");
    let cache_dir = scratch.path().join("worker");
    // Less than the ranges one job reads of the 33 KB object.
    const BUDGET: u64 = 16 << 10;
    let worker = WorkerProcess::start_with(
        &daemon.url(),
        &cache_dir,
        "small-cache",
        &["--url-cache", "16KiB"],
    );
    let by_url = register_path(&mut datasets, &server.url("scans/a.copc.laz")).await;
    let by_path = register_path(&mut datasets, "scans/a.copc.laz").await;
    let mut jobs = daemon.jobs().await;
    let (frames, reads) = render(&mut jobs, "by-url", &by_url).await;
    assert!(reads.bytes > BUDGET, "{reads:?}\n{}", worker.log());
    let ranges = cache_dir.join("ranges");
    let cached = folder_bytes(&ranges);
    assert!(cached > 0, "some ranges are cached");
    assert!(
        cached <= BUDGET,
        "{cached} bytes cached over a {BUDGET}-byte budget"
    );
    let (expected, _) = render(&mut jobs, "by-path", &by_path).await;
    assert!(
        frames == expected,
        "the frames by URL differ from those by path"
    );
    // Opened again, within the budget still, and rendering the same.
    let (again, _) = render(&mut jobs, "by-url-again", &by_url).await;
    assert!(folder_bytes(&ranges) <= BUDGET);
    assert!(
        again == expected,
        "the frames read partly from the cache differ"
    );
}
