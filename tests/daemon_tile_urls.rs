//! Datasets of LAS/LAZ tiles registered by URL with a daemon, against a real `s3s-fs` on
//! loopback: a prefix of LAZ tiles registers under the operator's allow-list, its store is
//! built by streaming the tiles, its previews (from the tiles' chunk starts, read by range while
//! the store waits to be built) and its frames are those of the same files registered by path,
//! pixel for pixel; a URL outside the allow-list is refused naming the rule; `dataset get`
//! lists each tile's URL, size and version, never a credential; a description from the tiles'
//! headers read by range (their points streamed by range when asked, through the API and
//! `pointfarm info ID --server`), and a COPC export, are those of the same files by path, byte
//! for byte; a tile replaced after registration fails the description, the preview and the job
//! naming it, no preview shows it, and the daemon keeps serving. A description of 24 tiles,
//! read as many at once as the client's parallel requests, is the one read one at a time, in
//! the dataset's order (both timings printed). Skips, saying so, without `s3s-fs`.

use pointfarm_daemon::access::Access;
use pointfarm_daemon::service::DaemonConfig;
use pointfarm_daemon::stores::StoreBuildGate;
use pointfarm_proto::v1 as pb;
use pointfarm_render::testing::write_scene_tiles;
use pointfarm_tests::datasets::assert_jobs_render_alike;
use pointfarm_tests::s3s::{S3sServer, SECRET_KEY};
use pointfarm_tests::service::{
    fetch_images, get_job, lod_turntable_job, submit, watch_to_end, TestDaemon,
};
use pointfarm_tests::{output_text, pointfarm_ok, stdout};
use tonic::Code;

const BUCKET: &str = "campaigns";

async fn register(daemon: &TestDaemon, paths: Vec<String>) -> Result<pb::Dataset, tonic::Status> {
    let request = pb::RegisterDatasetRequest {
        paths,
        ..Default::default()
    };
    (daemon.datasets().await.register_dataset(request).await).map(tonic::Response::into_inner)
}

/// A turntable from levels of detail, so that both datasets are cut from a store.
fn job(name: &str, dataset_id: &str) -> pb::SubmitJobRequest {
    lod_turntable_job(name, dataset_id, 2, (160, 120), 1.0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiles_by_url_render_as_the_same_files_by_path() {
    let root = tempfile::tempdir().expect("root");
    let folder = root.path().join(BUCKET).join("tiles");
    let paths = write_scene_tiles(&folder, 40_000, 3);
    let Some(server) = S3sServer::start_or_skip(root.path()) else {
        return;
    };
    // The daemon reads the server's endpoint and credentials as object_store does, from its
    // environment; this file's only test sets them once.
    for (key, value) in server.environment() {
        std::env::set_var(key, value);
    }
    // Two tiles of their own, one of which is replaced while its store waits to be built.
    let swap = root.path().join(BUCKET).join("swap");
    std::fs::create_dir_all(&swap).expect("swap folder");
    for (from, to) in [(&paths[0], "a.laz"), (&paths[1], "b.laz")] {
        std::fs::copy(from, swap.join(to)).expect("a swap tile");
    }
    let allowed = pointfarm_daemon::remote_datasets::url_prefixes(&[
        format!("s3://{BUCKET}/tiles/"),
        format!("s3://{BUCKET}/swap/"),
    ])
    .expect("valid prefixes");
    let data_root = folder.clone();
    let gate = StoreBuildGate::closed();
    let held = gate.clone();
    let daemon = TestDaemon::start(
        move |config: &mut DaemonConfig| {
            config.allowed_url_prefixes = allowed;
            config.data_roots = vec![data_root];
            config.store_build_gate = Some(held);
        },
        Access::default(),
    )
    .await;

    assert_described_in_parallel(root.path()).await;

    let outside = format!("s3://{BUCKET}/other/");
    let denied = register(&daemon, vec![outside.clone()])
        .await
        .expect_err("outside the allow-list");
    assert_eq!(denied.code(), Code::PermissionDenied, "{denied:?}");
    assert!(
        denied.message().contains(&format!("s3://{BUCKET}/tiles")),
        "{denied:?}"
    );

    let by_url = register(&daemon, vec![format!("s3://{BUCKET}/tiles/")])
        .await
        .expect("a prefix of tiles");
    let names: Vec<String> = (1..=paths.len()).map(|k| format!("t{k}.laz")).collect();
    let by_path = register(&daemon, names)
        .await
        .expect("the same files by path");
    assert_ne!(by_url.id, by_path.id);
    let again = register(&daemon, vec![format!("s3://{BUCKET}/tiles/")])
        .await
        .expect("the same tiles again");
    assert_eq!(again.id, by_url.id);
    assert_tiles_listed(&daemon, &by_url, &paths).await;
    assert_described_alike(&daemon, &by_url, &by_path).await;

    // While the stores wait to be built, previews from the tiles' chunk starts read by range
    // are those of the files by path.
    let mut jobs = daemon.jobs().await;
    let mut previews = Vec::new();
    for dataset in [&by_path, &by_url] {
        let request = pb::SubmitJobRequest {
            preview: true,
            ..job(&format!("preview-{}", dataset.id), &dataset.id)
        };
        let previewed = submit(&mut jobs, request).await;
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
        loop {
            let shown = get_job(&mut jobs, &previewed.id).await;
            if shown.frames.len() == 2 && shown.frames.iter().all(|frame| frame.preview) {
                break;
            }
            assert!(
                std::time::Instant::now() < deadline,
                "no previews: {shown:?}"
            );
            tokio::time::sleep(std::time::Duration::from_millis(100)).await;
        }
        previews.push(fetch_images(&mut jobs, &previewed.id, 0).await);
    }
    assert_eq!(previews[0].len(), 2);
    assert!(previews[0] == previews[1], "the previews differ");
    assert_replaced_tile_not_previewed(&daemon, &swap.join("b.laz"), &paths[2]).await;
    gate.open();

    assert_jobs_render_alike(
        &mut jobs,
        [job("by-path", &by_path.id), job("by-url", &by_url.id)],
        2,
        "the frames of the tiles by URL and by path",
    )
    .await;

    // Exported from the stores built for the jobs, and from one the export builds.
    assert_exported_alike(&daemon, &by_url, &by_path).await;
    let some = register(
        &daemon,
        [1, 3]
            .map(|k| format!("s3://{BUCKET}/tiles/t{k}.laz"))
            .to_vec(),
    )
    .await
    .expect("two of the tiles");
    let some_by_path = register(&daemon, vec!["t1.laz".into(), "t3.laz".into()])
        .await
        .expect("the same two by path");
    assert_exported_alike(&daemon, &some, &some_by_path).await;

    // Two tiles registered, then one of them replaced before its store is built.
    let two = [1, 2].map(|k| format!("s3://{BUCKET}/tiles/t{k}.laz"));
    let registered = register(&daemon, two.to_vec()).await.expect("two tiles");
    std::fs::copy(&paths[2], &paths[1]).expect("replace a tile");
    let job = submit(&mut jobs, job("replaced", &registered.id)).await;
    let (ended, _) = watch_to_end(&mut jobs, &job.id).await;
    assert_eq!(ended.state, pb::JobState::Failed as i32, "{ended:?}");
    assert!(ended.error.contains(&two[1]), "{}", ended.error);
    assert!(
        !ended.error.contains(pointfarm_tests::s3s::SECRET_KEY),
        "{}",
        ended.error
    );
    // The daemon keeps serving.
    register(&daemon, vec![format!("s3://{BUCKET}/tiles/t1.laz")])
        .await
        .expect("still serving");
}

/// `pointfarm ARGS --server DAEMON`, off the runtime that serves the daemon; its output, which
/// never holds the object store's secret.
async fn cli(daemon: &TestDaemon, args: &[&str]) -> std::process::Output {
    let mut args: Vec<String> = args.iter().map(|arg| arg.to_string()).collect();
    args.extend(["--server".to_owned(), daemon.url()]);
    let output = tokio::task::spawn_blocking(move || {
        pointfarm_ok(&args.iter().map(String::as_str).collect::<Vec<_>>())
    })
    .await
    .expect("the CLI ran");
    let text = output_text(&output);
    assert!(!text.contains(SECRET_KEY), "{text}");
    output
}

/// `dataset get` lists every tile of a dataset by URL with its size and version: in JSON as
/// the API's files, in text one a line.
async fn assert_tiles_listed(
    daemon: &TestDaemon,
    by_url: &pb::Dataset,
    paths: &[std::path::PathBuf],
) {
    assert_eq!(by_url.files.len(), paths.len(), "{by_url:?}");
    assert!(by_url.sha256.is_empty(), "{by_url:?}");
    let json = cli(daemon, &["dataset", "get", &by_url.id, "--json"]).await;
    let got: serde_json::Value =
        serde_json::from_str(stdout(&json).trim()).expect("one JSON value");
    let files = got["files"].as_array().expect("files");
    assert_eq!(files.len(), paths.len(), "{got}");
    let text = stdout(&cli(daemon, &["dataset", "get", &by_url.id]).await);
    for ((file, path), message) in files.iter().zip(paths).zip(&by_url.files) {
        let name = path.file_name().and_then(|n| n.to_str()).expect("a name");
        let url = format!("s3://{BUCKET}/tiles/{name}");
        let size = std::fs::metadata(path).expect("tile").len();
        assert_eq!(file["url"], url.as_str(), "{got}");
        assert_eq!(file["sizeBytes"], size.to_string().as_str(), "{got}");
        assert!(!message.version.is_empty(), "{message:?}");
        assert_eq!(file["version"], message.version.as_str(), "{got}");
        let line = format!("  {url}  {size} bytes  version {}", message.version);
        assert!(text.lines().any(|l| l == line), "{line:?} not in:\n{text}");
    }
}

/// The daemon's description of dataset `id`.
async fn describe(daemon: &TestDaemon, id: &str, read_points: bool) -> pb::DatasetDescription {
    let request = pb::DescribeDatasetRequest {
        dataset_id: id.to_owned(),
        read_points,
    };
    (daemon.datasets().await.describe_dataset(request).await)
        .expect("described")
        .into_inner()
}

/// The description of the tiles by URL, from their headers read by range, is that of the
/// same files by path, each tile named by its URL.
async fn assert_described_alike(daemon: &TestDaemon, by_url: &pb::Dataset, by_path: &pb::Dataset) {
    let urls = describe(daemon, &by_url.id, false).await;
    let files = describe(daemon, &by_path.id, false).await;
    assert_eq!(urls.summary, files.summary);
    assert_eq!(urls.files.len(), files.files.len());
    for ((url, file), tile) in urls.files.iter().zip(&files.files).zip(&by_url.files) {
        assert!(url.error.is_empty(), "{url:?}");
        assert_eq!(url.path, tile.url);
        let unnamed = |d: &pb::FileDescription| pb::FileDescription {
            path: String::new(),
            ..d.clone()
        };
        assert_eq!(unnamed(url), unnamed(file));
    }
    assert!(
        urls.summary.as_ref().is_some_and(|s| s.points > 0),
        "{urls:?}"
    );
    // Asked for, each tile's points are streamed by range at its version: what the files say.
    let asked = describe(daemon, &by_url.id, true).await;
    let read = describe(daemon, &by_path.id, true).await;
    assert!(
        asked.files.iter().all(|f| f.points_read.is_some()),
        "{asked:?}"
    );
    assert_eq!(asked.summary, read.summary);
    for (url, file) in asked.files.iter().zip(&read.files) {
        assert_eq!(url.points_read, file.points_read, "{}", url.path);
    }
    // The CLI's `info ID --server` says so too: every file's points, but for its name.
    let points = |id: String| async move {
        let said = cli(daemon, &["info", &id, "--json"]).await;
        let mut said: serde_json::Value =
            serde_json::from_str(stdout(&said).trim()).expect("one JSON value");
        for file in said["files"].as_array_mut().expect("files") {
            file["path"].take();
        }
        (said["files"].take(), said["summary"].take())
    };
    let (by_url_points, by_path_points) = (
        points(by_url.id.clone()).await,
        points(by_path.id.clone()).await,
    );
    assert!(
        by_url_points.0[0]["pointsRead"].is_object(),
        "{by_url_points:?}"
    );
    assert_eq!(by_url_points, by_path_points);
}

/// Describing 24 tiles reads their headers as many at once as the remote client sends
/// requests in parallel: the same description, in the dataset's order, as a daemon reading
/// them one at a time; how long each took is printed, not asserted.
async fn assert_described_in_parallel(root: &std::path::Path) {
    let many = root.join(BUCKET).join("many");
    write_scene_tiles(&many, 2_000, 24);
    let prefix = format!("s3://{BUCKET}/many/");
    let mut descriptions = Vec::new();
    for parallel in [1, 8, 1, 8] {
        let allowed =
            pointfarm_daemon::remote_datasets::url_prefixes(std::slice::from_ref(&prefix))
                .expect("a valid prefix");
        let daemon = TestDaemon::start_without_worker(
            move |config: &mut DaemonConfig| {
                config.allowed_url_prefixes = allowed;
                config.remote_settings.parallel_requests = parallel;
            },
            Access::default(),
        )
        .await;
        let dataset = register(&daemon, vec![prefix.clone()])
            .await
            .expect("24 tiles");
        let started = std::time::Instant::now();
        let description = describe(&daemon, &dataset.id, false).await;
        println!(
            "describing 24 tiles by URL on s3s-fs, {parallel} at a time: {:.1} ms",
            started.elapsed().as_secs_f64() * 1000.0
        );
        let paths: Vec<&str> = description.files.iter().map(|f| f.path.as_str()).collect();
        let urls: Vec<&str> = dataset.files.iter().map(|f| f.url.as_str()).collect();
        assert_eq!(paths, urls, "not in the dataset's order");
        assert!(
            description.files.iter().all(|f| f.error.is_empty()),
            "{description:?}"
        );
        descriptions.push(description);
    }
    assert!(descriptions.iter().all(|d| *d == descriptions[0]));
}

/// A tile replaced after its dataset's store was counted is not previewed: its description
/// and its preview job fail naming it, and no preview frame is kept.
async fn assert_replaced_tile_not_previewed(
    daemon: &TestDaemon,
    replaced: &std::path::Path,
    new_content: &std::path::Path,
) {
    let urls = ["a", "b"].map(|name| format!("s3://{BUCKET}/swap/{name}.laz"));
    let registered = register(daemon, urls.to_vec()).await.expect("two tiles");
    // The store is counted at the registered versions and its build waits at the gate.
    let opened = (daemon.workers().await)
        .open_dataset_store(pb::OpenDatasetStoreRequest {
            dataset_id: registered.id.clone(),
            levels_of_detail: true,
        })
        .await
        .expect("the store opens")
        .into_inner();
    assert_eq!(
        opened.state,
        pb::open_dataset_store_response::State::Building as i32,
        "{opened:?}"
    );
    std::fs::copy(new_content, replaced).expect("replace a tile");

    // Described with its points or without, the replaced tile is refused naming it.
    for read_points in [false, true] {
        let description = describe(daemon, &registered.id, read_points).await;
        assert!(description.files[0].error.is_empty(), "{description:?}");
        let changed = &description.files[1].error;
        assert!(
            changed.contains(&urls[1]) && changed.contains("changed"),
            "{changed}"
        );
    }

    let mut jobs = daemon.jobs().await;
    let request = pb::SubmitJobRequest {
        preview: true,
        ..job("preview-replaced", &registered.id)
    };
    let previewed = submit(&mut jobs, request).await;
    // Its store waits at the gate: the job ends only by failing, and draws no preview first.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    let ended = loop {
        let shown = get_job(&mut jobs, &previewed.id).await;
        assert!(
            shown.frames.iter().all(|frame| !frame.preview),
            "a preview of the replaced tile was drawn: {shown:?}"
        );
        if shown.state == pb::JobState::Failed as i32 {
            break shown;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "not failed: {shown:?}"
        );
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    };
    assert!(ended.error.contains(&urls[1]), "{}", ended.error);
    assert!(!ended.error.contains(SECRET_KEY), "{}", ended.error);
    assert!(fetch_images(&mut jobs, &previewed.id, 0).await.is_empty());
}

/// `dataset export` of the tiles by URL writes the COPC file of the same files by path.
async fn assert_exported_alike(daemon: &TestDaemon, by_url: &pb::Dataset, by_path: &pb::Dataset) {
    let out = tempfile::tempdir().expect("out");
    let mut written = Vec::new();
    for dataset in [by_url, by_path] {
        let file = out.path().join(format!("{}.copc.laz", dataset.id));
        let path = file.to_str().expect("a UTF-8 path");
        let said = cli(daemon, &["dataset", "export", &dataset.id, "--copc", path]).await;
        assert!(stdout(&said).contains("COPC 1.0"), "{}", output_text(&said));
        written.push(std::fs::read(&file).expect("the export"));
    }
    assert!(written[0].len() > 1000);
    assert!(written[0] == written[1], "the exports differ");
}
