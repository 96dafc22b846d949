//! Datasets of LAS/LAZ tiles registered by URL with a daemon, against a real `s3s-fs` on
//! loopback: a prefix of LAZ tiles registers under the operator's allow-list, its store is
//! built by streaming the tiles, its previews (from the tiles' chunk starts, read by range while
//! the store waits to be built) and its frames are those of the same files registered by path,
//! pixel for pixel; a URL outside the allow-list is refused naming the rule; a tile replaced
//! after registration fails the job naming it, and the daemon keeps serving. Skips, saying so,
//! without `s3s-fs`.

use pointfarm_daemon::access::Access;
use pointfarm_daemon::service::DaemonConfig;
use pointfarm_daemon::stores::StoreBuildGate;
use pointfarm_proto::v1 as pb;
use pointfarm_render::testing::write_scene_tiles;
use pointfarm_tests::datasets::assert_jobs_render_alike;
use pointfarm_tests::s3s::S3sServer;
use pointfarm_tests::service::{
    fetch_images, get_job, submit, turntable_job, watch_to_end, TestDaemon,
};
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
    pb::SubmitJobRequest {
        render: Some(pb::RenderOptions {
            lod_error: Some(1.0),
            ..Default::default()
        }),
        ..turntable_job(name, dataset_id, 2, 160, 120)
    }
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
    let allowed =
        pointfarm_daemon::remote_datasets::url_prefixes(&[format!("s3://{BUCKET}/tiles/")])
            .expect("valid prefix");
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
    gate.open();

    assert_jobs_render_alike(
        &mut jobs,
        [job("by-path", &by_path.id), job("by-url", &by_url.id)],
        2,
        "the frames of the tiles by URL and by path",
    )
    .await;

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
