//! Datasets registered by URL: a real nginx on loopback serves COPC files, a real daemon
//! registers them under its operator's allowed prefixes, from a HEAD and the header read by
//! range. Refusals carry the status a client can act on, and the daemon keeps serving after
//! each. Each test skips, saying so, where nginx is not installed.

use pointfarm_daemon::access::Access;
use pointfarm_daemon::service::DaemonConfig;
use pointfarm_proto::v1 as pb;
use pointfarm_tests::datasets::{assert_jobs_render_alike, daemon_on_served_scans};
use pointfarm_tests::nginx::NginxServer;
use pointfarm_tests::service::{submit, turntable_job, watch_to_end, write_sample, TestDaemon};
use pointfarm_tests::{copc_file, free_address, pointfarm, pointfarm_ok, stdout, ServeProcess};
use tonic::Code;

const OBJECT: &str = "scans/simple.copc.laz";

/// nginx serving a folder with `scans/simple.copc.laz`; none, having said why, without nginx.
fn served_scans() -> Option<(tempfile::TempDir, NginxServer)> {
    let bytes = std::fs::read(copc_file("simple.copc.laz")).expect("COPC file");
    NginxServer::serve_scans(&[("simple.copc.laz", bytes)])
}

/// A daemon without a worker that allows datasets by URL under `prefixes`.
async fn daemon_allowing(prefixes: &[String]) -> TestDaemon {
    let allowed =
        pointfarm_daemon::remote_datasets::url_prefixes(prefixes).expect("valid prefixes");
    TestDaemon::start_without_worker(
        move |config: &mut DaemonConfig| config.allowed_url_prefixes = allowed,
        Access::default(),
    )
    .await
}

async fn register(daemon: &TestDaemon, path: &str) -> Result<pb::Dataset, tonic::Status> {
    let request = pb::RegisterDatasetRequest {
        path: path.to_owned(),
        ..Default::default()
    };
    daemon
        .datasets()
        .await
        .register_dataset(request)
        .await
        .map(tonic::Response::into_inner)
}

/// The refusal of registering `path`, checked for its code and for every text it must hold.
async fn refused(daemon: &TestDaemon, path: &str, code: Code, says: &[&str]) -> tonic::Status {
    let status = register(daemon, path).await.expect_err(path);
    assert_eq!(status.code(), code, "{path}: {status:?}");
    for needle in says {
        assert!(
            status.message().contains(needle),
            "{path}: {needle:?} not in {:?}",
            status.message()
        );
    }
    status
}

/// The daemon still answers, and holds exactly `expected` datasets.
async fn still_serving(daemon: &TestDaemon, expected: usize) {
    let listed = daemon
        .datasets()
        .await
        .list_datasets(pb::ListDatasetsRequest::default())
        .await
        .expect("the daemon still serves")
        .into_inner();
    assert_eq!(listed.datasets.len(), expected, "{listed:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_allowed_url_registers_by_its_version_without_being_downloaded() {
    let Some((root, server)) = served_scans() else {
        return;
    };
    let daemon = daemon_allowing(&[server.url("scans/")]).await;
    let url = server.url(OBJECT);
    let size = std::fs::metadata(root.path().join(OBJECT))
        .expect("size")
        .len();

    let dataset = register(&daemon, &url).await.expect("registered");
    assert_eq!(dataset.url, url);
    assert!(!dataset.version.is_empty(), "nginx sends an ETag");
    assert_eq!(dataset.size_bytes, size);
    assert_eq!(dataset.name, "simple.copc.laz");
    assert!(
        dataset.path.is_empty() && dataset.sha256.is_empty(),
        "{dataset:?}"
    );
    let [file] = dataset.files.as_slice() else {
        panic!("one object: {dataset:?}");
    };
    assert_eq!((file.url.as_str(), file.size_bytes), (url.as_str(), size));
    // A HEAD and the header by range: never a whole answer.
    let log = server.access_log(2);
    assert!(log.iter().any(|line| line.contains("\"HEAD ")), "{log:?}");
    let gets: Vec<&String> = log.iter().filter(|line| line.contains("\"GET ")).collect();
    assert!(!gets.is_empty(), "{log:?}");
    assert!(gets.iter().all(|line| line.contains(" 206 ")), "{log:?}");

    let again = register(&daemon, &url).await.expect("registered again");
    assert_eq!(again.id, dataset.id);
    let got = daemon
        .datasets()
        .await
        .get_dataset(pb::GetDatasetRequest {
            id: dataset.id.clone(),
        })
        .await
        .expect("get")
        .into_inner();
    assert_eq!(
        (got.url, got.version),
        (url.clone(), dataset.version.clone())
    );
    still_serving(&daemon, 1).await;

    // Another object at the same URL is another dataset.
    std::fs::copy(
        copc_file("simple_with_page.copc.laz"),
        root.path().join(OBJECT),
    )
    .expect("replace");
    let replaced = register(&daemon, &url).await.expect("the new object");
    assert_ne!(replaced.id, dataset.id);
    assert_ne!(replaced.version, dataset.version);
    still_serving(&daemon, 2).await;

    // Described from the object by range, at the version registered: the object as it is now.
    let described = daemon
        .datasets()
        .await
        .describe_dataset(pb::DescribeDatasetRequest {
            dataset_id: replaced.id.clone(),
            ..Default::default()
        })
        .await
        .expect("described by range")
        .into_inner();
    assert_eq!(described.files.len(), 1, "{described:?}");
    let file = &described.files[0];
    assert_eq!(
        (file.path.as_str(), file.error.as_str()),
        (url.as_str(), "")
    );
    assert!(
        file.points > 0 && file.file_bytes == replaced.size_bytes,
        "{file:?}"
    );
    assert!(file
        .copc
        .as_ref()
        .is_some_and(|copc| copc.error.is_empty() && copc.nodes > 0));
    // Its files are not on the server: work that needs them says so.
    let composed = daemon
        .datasets()
        .await
        .compose_dataset(pb::ComposeDatasetRequest {
            dataset_ids: vec![dataset.id.clone(), replaced.id.clone()],
            ..Default::default()
        })
        .await
        .expect_err("not composed");
    assert_eq!(composed.code(), Code::FailedPrecondition, "{composed:?}");
    assert!(composed.message().contains("composing"), "{composed:?}");
    still_serving(&daemon, 2).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_url_outside_the_allowed_prefixes_is_refused_naming_the_rule() {
    let Some((root, server)) = served_scans() else {
        return;
    };
    std::fs::create_dir(root.path().join("scans-other")).expect("folder");
    std::fs::copy(
        copc_file("simple.copc.laz"),
        root.path().join("scans-other/simple.copc.laz"),
    )
    .expect("copy");
    let allowed = server.url("scans");
    let daemon = daemon_allowing(std::slice::from_ref(&allowed)).await;
    for outside in [
        server.url("scans-other/simple.copc.laz"),
        server.url("simple.copc.laz"),
        format!("https://{}/{OBJECT}", server.address),
    ] {
        let rule = format!("the operator allows only {allowed}");
        refused(
            &daemon,
            &outside,
            Code::PermissionDenied,
            &[&outside, &rule],
        )
        .await;
    }
    // Refused before any request reaches the server.
    assert!(server.access_log(0).is_empty());
    still_serving(&daemon, 0).await;

    let none_allowed = daemon_allowing(&[]).await;
    refused(
        &none_allowed,
        &server.url(OBJECT),
        Code::PermissionDenied,
        &[&server.url(OBJECT), "allow-list is empty"],
    )
    .await;
    still_serving(&none_allowed, 0).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn missing_unreachable_and_malformed_urls_have_their_status() {
    let Some((_root, server)) = served_scans() else {
        return;
    };
    let unreachable = format!("http://{}/scans/", free_address());
    let daemon = daemon_allowing(&[server.url("scans/"), unreachable.clone()]).await;

    let missing = server.url("scans/missing.copc.laz");
    let away = format!("{unreachable}simple.copc.laz");
    let with_credentials = format!("http://reader:hunter2@{}/{OBJECT}", server.address);
    let cases = [
        (missing.as_str(), Code::NotFound, missing.as_str()),
        (away.as_str(), Code::Unavailable, away.as_str()),
        (
            with_credentials.as_str(),
            Code::InvalidArgument,
            "credentials",
        ),
        (
            "ftp://data.example/simple.copc.laz",
            Code::InvalidArgument,
            "ftp://",
        ),
    ];
    for (url, code, says) in cases {
        let status = refused(&daemon, url, code, &[says]).await;
        assert!(!status.message().contains("hunter2"), "{status:?}");
    }
    still_serving(&daemon, 0).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_copc_object_or_las_tiles_register_by_url() {
    let Some((root, server)) = served_scans() else {
        return;
    };
    write_sample(&root.path().join("scans/plain.las"), 2_000, 7);
    std::fs::write(root.path().join("scans/notes.laz"), "not a point cloud").expect("notes");
    let daemon = daemon_allowing(&[server.url("scans/")]).await;
    let notes = server.url("scans/notes.laz");
    refused(&daemon, &notes, Code::InvalidArgument, &[&notes]).await;
    // An HTTP server is listed only through WebDAV, which nginx here lacks.
    let prefix = server.url("scans/");
    refused(&daemon, &prefix, Code::FailedPrecondition, &["WebDAV"]).await;
    let mixed = daemon
        .datasets()
        .await
        .register_dataset(pb::RegisterDatasetRequest {
            path: server.url(OBJECT),
            paths: vec!["scans/plain.las".into()],
            ..Default::default()
        })
        .await
        .expect_err("a URL with a path");
    assert_eq!(mixed.code(), Code::InvalidArgument, "{mixed:?}");
    assert!(mixed.message().contains("not both"), "{mixed:?}");
    still_serving(&daemon, 0).await;
    let tiles = register(&daemon, &server.url("scans/plain.las"))
        .await
        .expect("a LAS object registers as a tile");
    let copc = register(&daemon, &server.url(OBJECT))
        .await
        .expect("a COPC object");
    assert_ne!(tiles.id, copc.id);
    still_serving(&daemon, 2).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_file_url_is_a_path_under_the_data_roots() {
    let roots = tempfile::tempdir().expect("roots");
    let inside = roots.path().join("inside");
    let outside = roots.path().join("outside");
    for folder in [&inside, &outside] {
        std::fs::create_dir(folder).expect("folder");
        write_sample(&folder.join("scan.las"), 1_000, 3);
    }
    let root = inside.clone();
    let daemon = TestDaemon::start_without_worker(
        move |config: &mut DaemonConfig| config.data_roots = vec![root],
        Access::default(),
    )
    .await;
    let by_path = register(&daemon, "scan.las").await.expect("by path");
    let file_url = format!("file://{}", inside.join("scan.las").display());
    let by_url = register(&daemon, &file_url).await.expect("by file:// URL");
    assert_eq!(by_url.id, by_path.id);
    assert!(by_url.url.is_empty(), "{by_url:?}");
    let elsewhere = format!("file://{}", outside.join("scan.las").display());
    refused(
        &daemon,
        &elsewhere,
        Code::InvalidArgument,
        &["outside the server's data roots"],
    )
    .await;
    still_serving(&daemon, 1).await;
}

/// The worker reads a dataset by URL itself, by range: its frames are those of the same
/// file registered by path, and an object replaced since registration fails the job saying so.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_on_a_url_dataset_renders_as_the_same_file_by_path() {
    let Some((root, server)) = served_scans() else {
        return;
    };
    let daemon = daemon_on_served_scans(&server, true).await;
    let by_path = register(&daemon, OBJECT).await.expect("by path");
    let by_url = register(&daemon, &server.url(OBJECT))
        .await
        .expect("by URL");
    assert_ne!(by_path.id, by_url.id);
    std::fs::copy(
        copc_file("simple.copc.laz"),
        root.path().join("scans/second.copc.laz"),
    )
    .expect("copy");
    let second = register(&daemon, &server.url("scans/second.copc.laz"))
        .await
        .expect("a second object");
    let mut jobs = daemon.jobs().await;
    assert_jobs_render_alike(
        &mut jobs,
        [
            turntable_job("by-path", &by_path.id, 3, 160, 120),
            turntable_job("by-url", &by_url.id, 3, 160, 120),
        ],
        3,
        "the frames by URL and by path",
    )
    .await;
    let log = server.access_log(3);
    let gets: Vec<&String> = log.iter().filter(|line| line.contains("\"GET ")).collect();
    assert!(gets.len() > 1, "{log:?}");
    assert!(gets.iter().all(|line| line.contains(" 206 ")), "{log:?}");

    // Another object, registered but not yet rendered, is replaced meanwhile.
    std::fs::copy(
        copc_file("simple_with_page.copc.laz"),
        root.path().join("scans/second.copc.laz"),
    )
    .expect("replace");
    let job = submit(
        &mut jobs,
        turntable_job("replaced", &second.id, 1, 160, 120),
    )
    .await;
    let (ended, _) = watch_to_end(&mut jobs, &job.id).await;
    assert_eq!(ended.state, pb::JobState::Failed as i32, "{ended:?}");
    assert!(ended.error.contains("register it again"), "{}", ended.error);
}

/// The operator's flag and the CLI, as a user runs them: `serve --allow-url-prefix`, then
/// `dataset register URL`, `dataset get` and `dataset list` showing the URL.
#[test]
fn the_cli_registers_a_url_the_operator_allows() {
    let Some((_root, server)) = served_scans() else {
        return;
    };
    let refused = pointfarm(&[
        "serve",
        "--allow-url-prefix",
        "https://reader:hunter2@data.example/scans/",
    ]);
    assert!(!refused.status.success());
    let said = String::from_utf8_lossy(&refused.stderr).into_owned();
    assert!(said.contains("--allow-url-prefix"), "{said}");
    assert!(
        said.contains("credentials") && !said.contains("hunter2"),
        "{said}"
    );
    // The same check holds for the configuration file's key.
    let config = tempfile::tempdir().expect("config folder");
    let file = config.path().join("pointfarm.toml");
    std::fs::write(
        &file,
        "[serve]\nallow_url_prefix = [\"ftp://data.example/scans/\"]\n",
    )
    .expect("config file");
    let refused = pointfarm(&["serve", "--config", &file.display().to_string()]);
    assert!(!refused.status.success());
    let said = String::from_utf8_lossy(&refused.stderr).into_owned();
    assert!(
        said.contains("--allow-url-prefix") && said.contains("ftp://"),
        "{said}"
    );

    let data = tempfile::tempdir().expect("data");
    let serve = ServeProcess::start_with(
        data.path(),
        &[
            "--no-embedded-worker",
            "--allow-url-prefix",
            &server.url("scans/"),
        ],
    );
    let address = format!("http://{}", serve.address);
    let url = server.url(OBJECT);
    let registered = pointfarm_ok(&["dataset", "register", &url, "--server", &address, "--json"]);
    let dataset: serde_json::Value =
        serde_json::from_str(stdout(&registered).trim()).expect("one JSON line");
    assert_eq!(dataset["url"], url.as_str());
    let id = dataset["id"].as_str().expect("an id").to_owned();
    let got = stdout(&pointfarm_ok(&[
        "dataset", "get", &id, "--server", &address,
    ]));
    assert!(got.contains(&id) && got.contains(&url), "{got}");
    let listed = stdout(&pointfarm_ok(&["dataset", "list", "--server", &address]));
    assert!(listed.contains(&id) && listed.contains(&url), "{listed}");
    let outside = pointfarm(&[
        "dataset",
        "register",
        &server.url("simple.copc.laz"),
        "--server",
        &address,
    ]);
    assert!(!outside.status.success());
    let said = String::from_utf8_lossy(&outside.stderr).into_owned();
    assert!(said.contains("allows only"), "{said}");
}
