//! A daemon killed with SIGKILL while it builds a dataset's level-of-detail store resumes
//! that build when it starts again, on its own (no worker asks), taking over the units the
//! killed build recorded: a real `pointfarm serve` whose build is stopped for good at a
//! partition by the build's test hook (`POINTFARM_TEST_PAUSE_AT`, render/src/lod/pause.rs),
//! killed there, and started again on the same data folder. Its store equals an
//! uninterrupted daemon's node for node, and its job ends with the same frames.

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use pointfarm_proto::v1 as pb;
use pointfarm_render::cut::StoredLod;
use pointfarm_tests::datasets::register_path;
use pointfarm_tests::service::{
    clients, fetch_images, lod_turntable_job, submit, watch_to_success, write_sample,
};
use pointfarm_tests::stores::{
    assert_same_nodes, count_after, serve_command_pausing_at, store_folder, store_nodes,
};
use pointfarm_tests::{free_address, pointfarm_bin, wait_for, ServeProcess, WorkerProcess};

/// Points of the dataset: enough for several partitions on two cores.
const POINTS: usize = 400_000;
const MEMORY_BUDGET: &str = "64MiB";
const FRAMES: u32 = 2;
const PAUSE_AT: &str = "partition:2";

/// `pointfarm serve` on `address` with its data in `data` and the scans in `root`, without an
/// embedded worker; its build stops for good at `pause_at` when given.
fn serve(address: &str, data: &Path, root: &str, pause_at: Option<&str>) -> ServeProcess {
    let args = [
        "--no-embedded-worker",
        "--data-root",
        root,
        "--store-memory-budget",
        MEMORY_BUDGET,
    ];
    // One build thread: each unit is durable before the next starts, so a kill at the pause
    // leaves exactly the units before it recorded (units queued together are synced together).
    let mut command = Command::new(pointfarm_bin());
    command.env("RAYON_NUM_THREADS", "1");
    serve_command_pausing_at(
        command,
        address,
        (data, &data.join("serve.log")),
        &args,
        pause_at,
    )
}

/// A turntable from levels of detail: the dataset needs the daemon's store.
fn job(name: &str, dataset_id: &str) -> pb::SubmitJobRequest {
    lod_turntable_job(name, dataset_id, FRAMES, (160, 120), 0.5)
}

/// The units the daemon said its build of `dataset_id` took over, once it has said so.
fn units_taken_over(log: &str, dataset_id: &str) -> Option<u64> {
    let said = format!("resumed the store build of {dataset_id}: ");
    let line = log.lines().find(|line| line.contains(&said))?;
    count_after(line, &said)
}

/// A job's frames, rendered and fetched, and the finished store's nodes.
struct Rendered {
    frames: Vec<(u32, image::RgbaImage)>,
    nodes: Vec<String>,
}

/// Runs job `job_id` to its end with a worker named `worker_name`, its cache in `scratch`,
/// then stops the daemon and reads its store from its data folder `data`.
async fn finish(
    mut server: ServeProcess,
    data: &Path,
    job_id: &str,
    scratch: &Path,
    worker_name: &str,
) -> Rendered {
    let address = server.address.clone();
    let worker = WorkerProcess::start(&address, &scratch.join(worker_name), worker_name);
    let (_, mut jobs) = clients(&address).await;
    watch_to_success(&mut jobs, job_id, || {
        format!("{}\n{}", server.log(), worker.log())
    })
    .await;
    let frames = fetch_images(&mut jobs, job_id, 0).await;
    assert_eq!(frames.len(), FRAMES as usize, "every frame");
    drop(worker);
    // The store's index is locked while the daemon holds it open.
    server
        .terminate(Duration::from_secs(30))
        .expect("the daemon stops");
    Rendered {
        frames,
        nodes: store_nodes(data),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_daemon_killed_while_a_store_builds_resumes_the_build_at_startup() {
    let scans = tempfile::tempdir().expect("tempdir");
    write_sample(&scans.path().join("scan.las"), POINTS, 5);
    let root = scans.path().display().to_string();

    // Uninterrupted.
    let reference_dir = tempfile::tempdir().expect("tempdir");
    let data = reference_dir.path().join("daemon");
    let server = serve(&free_address(), &data, &root, None);
    let (mut datasets, mut jobs) = clients(&server.address).await;
    let dataset = register_path(&mut datasets, &root).await;
    let job_id = submit(&mut jobs, job("uninterrupted", &dataset.id))
        .await
        .id;
    let reference = finish(server, &data, &job_id, reference_dir.path(), "first").await;

    // Killed with a partition built but not recorded, the two before it recorded.
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("daemon");
    let address = free_address();
    let mut server = serve(&address, &data, &root, Some(PAUSE_AT));
    let (mut datasets, mut jobs) = clients(&address).await;
    let dataset = register_path(&mut datasets, &root).await;
    let job_id = submit(&mut jobs, job("killed", &dataset.id)).await.id;
    let worker = WorkerProcess::start(&address, &dir.path().join("asking"), "asking");
    let paused = format!("build paused at {PAUSE_AT}");
    wait_for(Duration::from_secs(300), &paused, || {
        server.log().contains(&paused).then_some(())
    });
    server.kill();
    drop(worker);
    let folder = store_folder(&data);
    assert!(!StoredLod::is_built(&folder), "the build was under way");
    assert_eq!(units_taken_over(&server.log(), &dataset.id), None);

    // Started again with no worker: the build goes on at once, from the units recorded.
    let server = serve(&address, &data, &root, None);
    let units = wait_for(Duration::from_secs(300), "a resumed build", || {
        units_taken_over(&server.log(), &dataset.id)
    });
    eprintln!("{units} units taken over");
    assert_eq!(units, 2, "{}", server.log());
    assert!(StoredLod::is_built(&folder), "{}", server.log());
    let log = server.log();
    assert!(
        !log.contains("starting the build over"),
        "the journal was refused:\n{log}"
    );

    let resumed = finish(server, &data, &job_id, dir.path(), "second").await;
    assert_same_nodes(&resumed.nodes, &reference.nodes, "the resumed store");
    for ((index, resumed), (_, uninterrupted)) in resumed.frames.iter().zip(&reference.frames) {
        assert!(resumed == uninterrupted, "frame {index} differs");
    }
}
