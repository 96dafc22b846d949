//! Registering server files never leaves the data roots, never blocks, and never shows a
//! client the server's paths: a real `pointfarm serve` with a `--data-root`, real symbolic
//! links, a real FIFO, and its gRPC API called as a client and as a worker would.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::dataset_service_client::DatasetServiceClient;
use pointfarm_proto::v1::worker_service_client::WorkerServiceClient;
use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::sample::sample_scene;
use pointfarm_tests::path_arg;
use pointfarm_tests::service::{clients, connect};
use pointfarm_tests::ServeProcess;
use tonic::transport::Channel;
use tonic::{Code, Status};

/// Longer than any of these calls takes; a call that blocks is stopped here.
const CALL_TIMEOUT: Duration = Duration::from_secs(20);

/// A scratch folder (canonical) with a data root `root` holding `tiles/a.las`, a folder
/// `outside` beside it holding `secret.las`, and a daemon without a worker serving `root`.
struct Farm {
    _scratch: tempfile::TempDir,
    base: PathBuf,
    root: PathBuf,
    outside: PathBuf,
    server: ServeProcess,
}

impl Farm {
    fn start() -> Self {
        let scratch = tempfile::tempdir().expect("tempdir");
        let base = scratch.path().canonicalize().expect("canonical");
        let (root, outside) = (base.join("root"), base.join("outside"));
        std::fs::create_dir_all(root.join("tiles")).expect("root");
        std::fs::create_dir_all(&outside).expect("outside");
        let options = LasWriteOptions::default();
        write_las(&root.join("tiles/a.las"), &sample_scene(2_000, 1), &options).expect("tile");
        write_las(
            &outside.join("secret.las"),
            &sample_scene(2_000, 2),
            &options,
        )
        .expect("outside file");
        let server = ServeProcess::start_with(
            &base.join("data"),
            &["--no-embedded-worker", "--data-root", path_arg(&root)],
        );
        Self {
            _scratch: scratch,
            base,
            root,
            outside,
            server,
        }
    }

    async fn datasets(&self) -> DatasetServiceClient<Channel> {
        clients(&self.server.address).await.0
    }

    /// Registers `paths` (relative to the data root), within [`CALL_TIMEOUT`].
    async fn register(&self, paths: &[&str]) -> Result<pb::Dataset, Status> {
        let request = pb::RegisterDatasetRequest {
            paths: paths.iter().map(|p| p.to_string()).collect(),
            ..Default::default()
        };
        let mut datasets = self.datasets().await;
        let call = datasets.register_dataset(request);
        match tokio::time::timeout(CALL_TIMEOUT, call).await {
            Ok(answer) => answer.map(tonic::Response::into_inner),
            Err(_) => panic!("registering {paths:?} blocked:\n{}", self.server.log()),
        }
    }

    /// A refusal of registering `paths`, checked to name no server path.
    async fn refused(&self, paths: &[&str]) -> Status {
        let status = self.register(paths).await.expect_err("refused");
        self.assert_no_server_path(status.message());
        status
    }

    /// The datasets ListDatasets answers, so a test sees what is registered.
    async fn listed(&self) -> Vec<pb::Dataset> {
        self.datasets()
            .await
            .list_datasets(pb::ListDatasetsRequest::default())
            .await
            .expect("list")
            .into_inner()
            .datasets
    }

    /// The bytes FetchDataset serves of a dataset's file, as a worker downloads them.
    async fn fetch(&self, dataset_id: &str, file_index: u32) -> Result<Vec<u8>, Status> {
        let mut workers = WorkerServiceClient::new(connect(&self.server.address).await);
        let request = pb::FetchDatasetRequest {
            dataset_id: dataset_id.into(),
            file_index,
        };
        let fetched = async {
            let mut stream = workers.fetch_dataset(request).await?.into_inner();
            let mut bytes = Vec::new();
            while let Some(chunk) = stream.message().await? {
                bytes.extend(chunk.data);
            }
            Ok(bytes)
        };
        tokio::time::timeout(CALL_TIMEOUT, fetched)
            .await
            .expect("FetchDataset answers")
    }

    /// How DescribeDataset reports the first file of dataset `id`, without reading points.
    async fn described_first_file(&self, id: &str) -> pb::FileDescription {
        let described = self
            .datasets()
            .await
            .describe_dataset(pb::DescribeDatasetRequest {
                dataset_id: id.into(),
                read_points: false,
            })
            .await
            .expect("described")
            .into_inner();
        described.files.into_iter().next().expect("a file")
    }

    /// `status` names `tiles/a.las` of dataset `id` by the dataset's id and the file's path
    /// under the root, and no server path.
    fn assert_names_the_tile(&self, status: &Status, id: &str) {
        assert!(
            status
                .message()
                .starts_with(&format!("dataset {id}, file tiles/a.las: ")),
            "named by the dataset's id and the file's name: {}",
            status.message()
        );
        self.assert_no_server_path(status.message());
    }

    fn assert_no_server_path(&self, message: &str) {
        assert!(
            !message.contains(path_arg(&self.base)),
            "a client is shown a server path: {message}"
        );
    }
}

/// Asserts that `status` says `needle`, showing what it says instead where it does not.
fn assert_says(status: &Status, needle: &str) {
    assert!(status.message().contains(needle), "{}", status.message());
}

fn secret_bytes(farm: &Farm) -> Vec<u8> {
    std::fs::read(farm.outside.join("secret.las")).expect("the outside file")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn links_out_of_the_data_roots_are_never_registered_and_never_served() {
    use std::os::unix::fs::symlink;
    let farm = Farm::start();
    let tiles = farm.root.join("tiles");

    // A file link out of the roots, in a folder and named directly.
    symlink(farm.outside.join("secret.las"), tiles.join("leak.las")).expect("file link");
    let status = farm.refused(&["tiles"]).await;
    assert_eq!(status.code(), Code::InvalidArgument);
    assert_says(
        &status,
        "tiles/leak.las: a symbolic link that leads outside the data roots",
    );
    let status = farm.refused(&["tiles/leak.las"]).await;
    assert_says(&status, "outside the server's data roots");
    std::fs::remove_file(tiles.join("leak.las")).expect("remove the link");

    // A folder link out of the roots.
    symlink(&farm.outside, tiles.join("more")).expect("folder link");
    let status = farm.refused(&["tiles"]).await;
    assert_says(&status, "tiles/more: a symbolic link");
    farm.refused(&["tiles/more/secret.las"]).await;
    std::fs::remove_file(tiles.join("more")).expect("remove the link");

    // Registered while it is a regular file inside the root...
    let dataset = farm.register(&["tiles"]).await.expect("registered");
    assert_eq!(dataset.files.len(), 1);
    let served = farm.fetch(&dataset.id, 0).await.expect("served");
    assert_eq!(served, std::fs::read(tiles.join("a.las")).expect("tile"));

    // ...and never served once a link out of the roots takes its place,
    std::fs::rename(tiles.join("a.las"), farm.root.join("a.las.kept")).expect("move");
    symlink(farm.outside.join("secret.las"), tiles.join("a.las")).expect("swapped file");
    let status = farm.fetch(&dataset.id, 0).await.expect_err("a link now");
    assert_eq!(status.code(), Code::FailedPrecondition);
    farm.assert_names_the_tile(&status, &dataset.id);
    // Nor is it described: not even the outside file's header is read.
    let file = farm.described_first_file(&dataset.id).await;
    assert_eq!(
        (file.error.as_str(), file.file_bytes),
        ("tiles/a.las: now lies outside the server's data roots", 0)
    );
    // Nor does a store build or a preview sample read it.
    let mut workers = WorkerServiceClient::new(connect(&farm.server.address).await);
    let store = workers
        .open_dataset_store(pb::OpenDatasetStoreRequest {
            dataset_id: dataset.id.clone(),
            levels_of_detail: true,
        })
        .await
        .expect_err("no store of a file outside the roots");
    assert_eq!(store.code(), Code::FailedPrecondition);
    assert_says(&store, "a.las: now lies outside");
    farm.assert_no_server_path(store.message());
    let sample = workers
        .fetch_preview_sample(pb::FetchPreviewSampleRequest {
            dataset_id: dataset.id.clone(),
        })
        .await
        .map(|_| ())
        .expect_err("no preview sample of a file outside the roots");
    assert_says(&sample, "now lies outside");
    std::fs::remove_file(tiles.join("a.las")).expect("remove the link");

    // or of the folder it lies in.
    std::fs::rename(&tiles, farm.root.join("tiles.kept")).expect("move the folder");
    std::fs::copy(farm.outside.join("secret.las"), farm.outside.join("a.las")).expect("copy");
    symlink(&farm.outside, &tiles).expect("swapped folder");
    let status = farm.fetch(&dataset.id, 0).await.expect_err("outside now");
    assert_says(&status, "outside the server's data roots");
    farm.assert_no_server_path(status.message());

    // Nothing registered holds the outside file's bytes.
    let secret = secret_bytes(&farm);
    let listed = farm.listed().await;
    for dataset in &listed {
        for index in 0..dataset.files.len() as u32 {
            if let Ok(bytes) = farm.fetch(&dataset.id, index).await {
                assert_ne!(bytes, secret, "the outside file was served");
            }
        }
    }
    let log = farm.server.log();
    assert!(
        log.contains("refused: a symbolic link leads outside the data roots")
            && log.contains(path_arg(&farm.outside)),
        "the operator's log names the link's target:\n{log}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fifo_named_las_is_refused_at_once_and_the_daemon_goes_on() {
    let mut farm = Farm::start();
    let fifo = farm.root.join("tiles/x.las");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .expect("mkfifo");
    assert!(made.success());

    let started = Instant::now();
    let status = farm.refused(&["tiles"]).await;
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "took {:?}",
        started.elapsed()
    );
    assert_eq!(status.code(), Code::InvalidArgument);
    assert_says(&status, "tiles/x.las: not a regular file (a FIFO)");
    let status = farm.refused(&["tiles/x.las"]).await;
    assert_says(&status, "is not a file or a folder");

    // The daemon answers other calls, and registers the folder's real file.
    let dataset = farm.register(&["tiles/a.las"]).await.expect("registered");
    let listed = farm.listed().await;
    assert_eq!(
        listed.iter().map(|d| d.id.as_str()).collect::<Vec<_>>(),
        [dataset.id.as_str()]
    );

    // Nothing holds a thread on the FIFO: SIGTERM stops the daemon at once.
    let asked = Instant::now();
    let exit = farm.server.terminate(Duration::from_secs(10));
    assert!(
        exit.is_some(),
        "not stopped within 10 s of SIGTERM ({exit:?}):\n{}",
        farm.server.log()
    );
    assert!(
        asked.elapsed() < Duration::from_secs(5),
        "{:?}",
        asked.elapsed()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_link_loop_inside_the_roots_is_walked_once() {
    use std::os::unix::fs::symlink;
    let farm = Farm::start();
    let tiles = farm.root.join("tiles");
    symlink(&farm.root, tiles.join("up")).expect("a link to a folder above");
    symlink("round", tiles.join("round")).expect("a link to itself");
    std::fs::create_dir_all(farm.root.join("other")).expect("folder");
    write_las(
        &farm.root.join("other/b.las"),
        &sample_scene(2_000, 3),
        &LasWriteOptions::default(),
    )
    .expect("tile");
    symlink(farm.root.join("other/b.las"), tiles.join("b.las")).expect("a link inside");

    let dataset = farm.register(&["tiles"]).await.expect("registered");
    let names: Vec<&str> = dataset.files.iter().map(|f| f.name.as_str()).collect();
    // `tiles` first (a.las, then b.las through its link), then through `up` the root's
    // `other` folder, whose b.las is the same file: each file once.
    assert_eq!(names, ["a.las", "b.las"]);
    assert_eq!(
        dataset.files[1].path,
        path_arg(&farm.root.join("other/b.las")),
        "kept as the file it resolves to"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn errors_about_a_registered_files_name_it_by_dataset_and_name() {
    let farm = Farm::start();
    let dataset = farm.register(&["tiles/a.las"]).await.expect("registered");
    std::fs::remove_file(farm.root.join("tiles/a.las")).expect("remove the file");

    let status = farm.fetch(&dataset.id, 0).await.expect_err("gone");
    farm.assert_names_the_tile(&status, &dataset.id);

    let description = farm.described_first_file(&dataset.id).await;
    let error = &description.error;
    assert!(error.starts_with("tiles/a.las: "), "{error}");
    farm.assert_no_server_path(error);
    assert!(
        farm.server.log().contains(path_arg(&farm.root)),
        "the operator's log has the full path:\n{}",
        farm.server.log()
    );
}
