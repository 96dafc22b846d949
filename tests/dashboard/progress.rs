//! What the farm is doing, as a browser sees it: the worker that a job has blocklisted (and
//! `/api/workers` saying so), a dataset's store build by stage and share stored, held at
//! the daemon's gates, with its bytes on disk, and each job's stage, from the store build
//! and previews to done, on a row the jobs page adds live too.

use std::time::{Duration, Instant};

use pointfarm_daemon::access::Access;
use pointfarm_daemon::dashboard::LoginLimit;
use pointfarm_daemon::stores::StoreBuildGate;
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::dataset_service_client::DatasetServiceClient;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_proto::v1::worker_service_client::WorkerServiceClient;
use pointfarm_render::testing::write_scene_tiles;
use pointfarm_tests::datasets::register_path;
use pointfarm_tests::service::{connect, lod_turntable_job, turntable_job};
use pointfarm_tests::WorkerProcess;
use serde_json::{json, Value};
use tonic::transport::Channel;

use super::farm::Farm;
use super::webdriver::{chromium_installed, request, Browser};

/// A job of `frames` frames from levels of detail (its dataset needs a store), with
/// previews or without.
fn lod_job(name: &str, dataset_id: &str, frames: u32, preview: bool) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        preview,
        ..lod_turntable_job(name, dataset_id, frames, (160, 120), 0.5)
    }
}

/// Leases three frames as worker `name` and fails each, so that the job blocklists it.
async fn fail_three_frames(workers: &mut WorkerServiceClient<Channel>, name: &str) {
    let mut leases = Vec::new();
    for _ in 0..3 {
        let task = workers
            .lease_frame(pb::LeaseFrameRequest {
                worker_name: name.into(),
                wait_ms: 0,
                capabilities: None,
            })
            .await
            .expect("lease")
            .into_inner()
            .task
            .expect("a frame");
        leases.push(task.lease_id);
    }
    for lease_id in leases {
        workers
            .fail_frame(pb::FailFrameRequest {
                lease_id,
                reason: "the GPU was lost".into(),
                kind: pb::FailureKind::Transient as i32,
            })
            .await
            .expect("fail");
    }
}

/// The worker `name` of `/api/workers`.
fn listed_worker(dashboard: &str, name: &str) -> Value {
    let listed = request(dashboard, "GET", "/api/workers", &[], "");
    assert_eq!(listed.status, 200, "{}", listed.body);
    let listed: Value = serde_json::from_str(&listed.body).expect("JSON");
    listed["workers"]
        .as_array()
        .and_then(|workers| workers.iter().find(|w| w["workerName"] == json!(name)))
        .cloned()
        .unwrap_or_else(|| panic!("{name} not listed: {listed}"))
}

/// Opens `url` until what `script` answers there is `what` is looked for; that answer.
fn wait_for_page(
    browser: &Browser,
    url: &str,
    (what, script, args): (&str, &str, Value),
    done: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        browser.goto(url);
        let found = browser.run(script, args.clone());
        if done(&found) {
            return found;
        }
        let page = browser.run("return document.body.innerText", json!([]));
        assert!(
            Instant::now() < deadline,
            "{what}: not shown; {url} says:\n{page}"
        );
        std::thread::sleep(Duration::from_millis(250));
    }
}

async fn job_state(jobs: &mut JobServiceClient<Channel>, id: &str) -> pb::JobState {
    let job = jobs
        .get_job(pb::GetJobRequest { id: id.into() })
        .await
        .expect("get")
        .into_inner();
    assert_ne!(job.state(), pb::JobState::Failed, "{job:?}");
    job.state()
}

const STAGE: &str = "return document.querySelector(`tr[data-job='${arguments[0]}'] .stage`)\
                     ?.textContent === arguments[1]";
const STORE: &str = "const row = document.querySelector(`tr[data-dataset='${arguments[0]}']`);\
                     const stage = row?.querySelector('.store-stage');\
                     return stage && [stage.dataset.stage, stage.textContent, \
                       row.querySelector('.store-progress')?.textContent ?? '', \
                       Number(row.querySelector('.disk-total').dataset.bytes)]";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_browser_follows_blocklists_store_builds_and_job_stages() {
    if !chromium_installed() {
        return;
    }
    let scratch = tempfile::tempdir().expect("tempdir");
    let tiles = scratch.path().join("tiles");
    std::fs::create_dir_all(&tiles).expect("tiles");
    write_scene_tiles(&tiles, 120_000, 3);
    let (build, ready) = (StoreBuildGate::closed(), StoreBuildGate::closed());
    let (held, held_ready, roots) = (build.clone(), ready.clone(), tiles.clone());
    let configure = move |config: &mut pointfarm_daemon::service::DaemonConfig| {
        config.data_roots = vec![roots];
        config.store_build_gate = Some(held);
        config.store_ready_gate = Some(held_ready);
    };
    let data = scratch.path().join("data");
    let farm = Farm::start(&data, configure, Access::default(), LoginLimit::DEFAULT).await;
    let channel = connect(&farm.address).await;
    let mut datasets = DatasetServiceClient::new(channel.clone());
    let mut jobs = JobServiceClient::new(channel.clone());
    let mut workers = WorkerServiceClient::new(channel);
    let dataset = register_path(&mut datasets, &tiles.display().to_string()).await;
    let base = format!("http://{}", farm.dashboard);
    let browser = Browser::start(1100, 700);

    // A worker that fails three frames of a job is blocklisted by it while it is unfinished.
    let blocklisting = jobs
        .submit_job(turntable_job("blocklisting", &dataset.id, 4, 64, 48))
        .await
        .expect("submit")
        .into_inner();
    fail_three_frames(&mut workers, "flaky").await;
    let flaky = listed_worker(&farm.dashboard, "flaky");
    let expected =
        json!([{"jobId": blocklisting.id, "jobName": "blocklisting", "failedFrames": 3}]);
    assert_eq!(flaky["blocklistedBy"], expected, "{flaky}");
    browser.goto(&format!("{base}/workers"));
    let shown = browser.run(
        "return document.querySelector(\"tr[data-worker='flaky'] .blocklisted-by\")?.innerText",
        json!([]),
    );
    assert_eq!(shown, json!("blocklisting (3 failed frames)"));
    let link = browser.run(
        "return document.querySelector(\"tr[data-worker='flaky'] .blocklisted-by a\")\
         .getAttribute('href')",
        json!([]),
    );
    assert_eq!(link, json!(format!("/jobs/{}", blocklisting.id)));
    jobs.cancel_job(pb::CancelJobRequest {
        id: blocklisting.id.clone(),
    })
    .await
    .expect("cancel");
    let flaky = listed_worker(&farm.dashboard, "flaky");
    assert!(
        flaky.get("blocklistedBy").is_none(),
        "an ended job: {flaky}"
    );

    // A worker asks for the store: its build waits at the first gate, still counting.
    let previewed = lod_job("previewed", &dataset.id, 3, true);
    let previewed = jobs
        .submit_job(previewed)
        .await
        .expect("submit")
        .into_inner();
    let waiting = lod_job("waiting", &dataset.id, 3, false);
    let waiting = jobs.submit_job(waiting).await.expect("submit").into_inner();
    let _worker = WorkerProcess::start(&farm.address, &scratch.path().join("cache"), "renderer");
    let datasets_page = format!("{base}/datasets");
    let store = |what| (what, STORE, json!([dataset.id]));
    let counting = wait_for_page(&browser, &datasets_page, store("a build"), |found| {
        !found.is_null()
    });
    assert_eq!(counting[0], json!("counting"), "{counting}");
    assert_eq!(counting[1], json!("building: counting the points"));
    let files_bytes = dataset.size_bytes as f64;
    assert!(counting[3].as_f64() >= Some(files_bytes), "{counting}");
    for (job, stage) in [(&previewed, "previews"), (&waiting, "store build")] {
        let shown = (stage, STAGE, json!([job.id, stage]));
        wait_for_page(&browser, &base, shown, |found| *found == json!(true));
    }
    // A job submitted while the jobs page is open is added to it live, with the stage the
    // server knows (no frame of it comes while the store builds).
    browser.goto(&base);
    super::wait_live(&browser);
    let live = lod_job("live", &dataset.id, 3, false);
    let live = jobs.submit_job(live).await.expect("submit").into_inner();
    let row = format!("the live row of {} in its stage", live.id);
    browser.wait_for(
        &row,
        Duration::from_secs(10),
        STAGE,
        json!([live.id, "store build"]),
    );
    jobs.cancel_job(pb::CancelJobRequest { id: live.id })
        .await
        .expect("cancel");

    // Past it, the build stores every node and waits at the second gate.
    build.open();
    let stored = wait_for_page(
        &browser,
        &datasets_page,
        store("every node stored"),
        |found| found[2] == json!("100%"),
    );
    assert_eq!(stored[0], json!("storing"), "{stored}");
    assert_eq!(stored[1], json!("building: storing the nodes"), "{stored}");

    // Ready: the jobs render their final frames and end; the store is built, on disk.
    ready.open();
    let started = Instant::now();
    for job in [&previewed, &waiting] {
        while job_state(&mut jobs, &job.id).await != pb::JobState::Succeeded {
            assert!(started.elapsed() < Duration::from_secs(180), "{job:?}");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
    browser.goto(&datasets_page);
    let built = browser.run(
        "const row = document.querySelector(`tr[data-dataset='${arguments[0]}']`);\
         return [row.querySelector('.store').textContent, \
                 Number(row.querySelector('.disk-total').dataset.bytes)]",
        json!([dataset.id]),
    );
    assert_eq!(built[0], json!("built"), "{built}");
    assert!(
        built[1].as_f64() > Some(files_bytes),
        "the store's bytes too: {built}"
    );
    browser.goto(&base);
    for job in [&previewed, &waiting] {
        let stage = browser.run(STAGE, json!([job.id, ""]));
        assert_eq!(stage, json!(true), "{} ended", job.id);
    }
}
