//! Google Cloud Storage (`gs://`) and Azure Blob Storage (`az://`) as the farm's object
//! storage, against real servers: Azurite (npm's Azure Blob Storage server) and
//! fake-gcs-server (shipped by a PyPI wheel), each on a loopback port of its own, credentials
//! only in the environment of the child processes. An export to `az://` is read back byte for
//! byte as the file exported here, a COPC file by URL renders as the file here, a job's frames
//! land under an `az://` output prefix, and a missing container or bucket and refused
//! credentials are one line naming the URL, no secret in it. Each test skips, saying so,
//! where its server's variable names no binary, and fails so in CI.
//!
//! A COPC object registered by `gs://` URL under the operator's allow-list renders through the
//! farm as the file renders here, and a store published under an `az://` `--store-url` is read
//! from the container by a worker.
//!
//! fake-gcs-server answers object_store's reads (HEAD, ranged GETs pinned to a generation,
//! listing) but not its XML API writes, so the `gs://` tests seed objects through its JSON
//! API and check reads and refusals.

use std::path::Path;
use std::process::Output;
use std::time::Duration;

use pointfarm_tests::azurite::{self, Azurite};
use pointfarm_tests::fake_gcs::{self, FakeGcs};
use pointfarm_tests::service::{self, render_detached};
use pointfarm_tests::{
    assert_ok, assert_one_error_line, assert_same_frames, copc_file, json_lines, output_text,
    path_arg, pointfarm, pointfarm_ok, pointfarm_with, run_with, sampled_copc, stdout, wait_for,
    ServeProcess, WorkerProcess,
};

/// The container and bucket the tests write to and read from.
const CONTAINER: &str = "pointfarm-scans";

/// The render every comparison makes: every node, the child pages included.
const RENDER: [&str; 5] = [
    "--size=200x150",
    "--point-size=3",
    "--lod-error",
    "0",
    "--json",
];

/// `pointfarm serve ARGS` with `environment` (and so its embedded worker, where it runs one),
/// its data and log in `dir`.
fn serve(environment: &[(&'static str, String)], dir: &Path, args: &[&str]) -> ServeProcess {
    ServeProcess::start_in_environment(environment, &dir.join("data"), args)
}

/// Renders the COPC file `input` (a path or a URL) with [`RENDER`] to `out`: its one frame's
/// report.
fn render(environment: &[(&'static str, String)], input: &str, out: &Path) -> serde_json::Value {
    let mut args = vec!["render", input, "--out", path_arg(out)];
    args.extend_from_slice(&RENDER);
    let output = run_with(environment, &args);
    assert_ok(&output);
    let mut frames = json_lines(&output);
    assert_eq!(frames.len(), 1, "{}", output_text(&output));
    frames.remove(0)
}

/// `pointfarm render URL --out OUT` with `environment`, its output as it came, for a test of
/// what a failure says.
fn try_render(environment: &[(&'static str, String)], url: &str, out: &Path) -> Output {
    run_with(environment, &["render", url, "--out", path_arg(out)])
}

/// Renders `local` here and `url` by URL, and checks they are the same image, pixel for pixel,
/// that the URL's frame fetched by range, and that `info` of the URL says what `info` of the
/// file here says of its octree.
fn assert_renders_as_here(environment: &[(&'static str, String)], local: &Path, url: &str) {
    let dir = tempfile::tempdir().expect("tempdir");
    let here = dir.path().join("here.png");
    let by_url = dir.path().join("url.png");
    let local_report = render(&[], path_arg(local), &here);
    let report = render(environment, url, &by_url);
    let image = |path: &Path| image::open(path).expect("png").to_rgba8();
    assert!(image(&here) == image(&by_url), "{url}: {report}");
    assert_eq!(report["pointsRendered"], local_report["pointsRendered"]);
    let requests = report["fetched"]["requests"].as_u64().expect("fetched");
    assert!(requests > 1, "{report}");

    let info = run_with(environment, &["info", url, "--no-points"]);
    assert_ok(&info);
    let info_here = pointfarm_ok(&["info", path_arg(local), "--no-points"]);
    let copc = |text: String| {
        let line = text.lines().find(|l| l.trim_start().starts_with("copc "));
        line.map(str::to_owned)
    };
    let described = copc(stdout(&info));
    assert!(described.is_some(), "{}", stdout(&info));
    assert_eq!(described, copc(stdout(&info_here)));
}

#[test]
fn an_export_to_azure_is_the_file_exported_here_and_renders_as_it() {
    let Some(azurite) = Azurite::start_or_skip() else {
        return;
    };
    azurite.create_container(CONTAINER);
    let dir = tempfile::tempdir().expect("tempdir");
    let (scene, here) = sampled_copc(dir.path(), 60_000);
    let url = format!("az://{CONTAINER}/campaign/scene.copc.laz");
    let cache = dir.path().join("cache");
    let export = |more: &[&str]| {
        let mut args = vec!["export", path_arg(&scene), "--copc", &url];
        args.extend_from_slice(&["--cache-dir", path_arg(&cache)]);
        args.extend_from_slice(more);
        run_with(&azurite.environment(), &args)
    };
    let output = export(&["--json"]);
    assert_ok(&output);
    assert_eq!(json_lines(&output)[0]["file"], url.as_str());
    let uploaded = azurite
        .blob(CONTAINER, "campaign/scene.copc.laz")
        .expect("the exported blob");
    assert!(uploaded == std::fs::read(&here).expect("the file here"));
    // An existing blob is refused without --force, as an object is in S3.
    assert_one_error_line(&export(&[]), &[&url, "exists: pass --force"]);
    assert_ok(&export(&["--force"]));
    assert_eq!(azurite.blob_names(CONTAINER), ["campaign/scene.copc.laz"]);

    // The same object read back by range renders as the file here, written `azure://` too.
    assert_renders_as_here(&azurite.environment(), &here, &url);
    let alias = format!("azure://{CONTAINER}/campaign/scene.copc.laz");
    assert_renders_as_here(&azurite.environment(), &here, &alias);
}

#[test]
fn a_missing_container_and_a_wrong_azure_key_are_one_line_naming_the_url() {
    let Some(azurite) = Azurite::start_or_skip() else {
        return;
    };
    azurite.create_container(CONTAINER);
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = dir.path().join("scene.laz");
    pointfarm_ok(&["sample", path_arg(&scene), "--points", "2000"]);
    let cache = dir.path().join("cache");
    let export = |environment: &[(&'static str, String)], url: &str| {
        let args = ["export", path_arg(&scene), "--copc", url, "--cache-dir"];
        run_with(environment, &[&args[..], &[path_arg(&cache)]].concat())
    };

    let missing = "az://no-such-container/scene.copc.laz";
    let output = export(&azurite.environment(), missing);
    assert_one_error_line(&output, &[missing, "no such container"]);
    let absent = format!("az://{CONTAINER}/absent.copc.laz");
    let out = dir.path().join("absent.png");
    let output = try_render(&azurite.environment(), &absent, &out);
    assert_one_error_line(&output, &[&absent, "no such object"]);

    let url = format!("az://{CONTAINER}/scene.copc.laz");
    for output in [
        export(&azurite.wrong_key_environment(), &url),
        try_render(&azurite.wrong_key_environment(), &url, &out),
    ] {
        assert_one_error_line(
            &output,
            &[&url, "access denied", "AZURE_STORAGE_ACCOUNT_KEY"],
        );
        assert!(!output_text(&output).contains(azurite::WRONG_KEY));
    }
    assert!(azurite.blob_names(CONTAINER).is_empty());
}

#[test]
fn a_jobs_frames_are_written_under_an_azure_output_prefix() {
    let Some(azurite) = Azurite::start_or_skip() else {
        return;
    };
    azurite.create_container("pointfarm-renders");
    let dir = tempfile::tempdir().expect("tempdir");
    let prefix = ["--allow-output-prefix", "az://pointfarm-renders/farm"];
    let server = serve(&azurite.environment(), dir.path(), &prefix);
    let scan = service::scan(dir.path());
    let out = dir.path().join("out");
    let submitted = render_detached(
        &server.address,
        path_arg(&scan),
        path_arg(&out),
        &["--output-url", "az://pointfarm-renders/farm/turntable"],
    );
    assert_ok(&submitted);
    let id = stdout(&submitted).trim().to_owned();
    let job = wait_for(Duration::from_secs(120), "two outputs uploaded", || {
        let job = server.job_json(&id);
        (job["outputsUploaded"] == 2).then_some(job)
    });
    assert_eq!(job["state"], "JOB_STATE_SUCCEEDED", "{job}");
    let fetched = dir.path().join("fetched");
    assert_ok(&pointfarm(&[
        "frames",
        "fetch",
        &id,
        "--server",
        &server.address,
        "--out",
        path_arg(&fetched),
    ]));
    assert_eq!(
        azurite.blob_names("pointfarm-renders"),
        [
            "farm/turntable/frame_00000.png",
            "farm/turntable/frame_00001.png"
        ]
    );
    for name in ["frame_00000.png", "frame_00001.png"] {
        let blob = azurite
            .blob("pointfarm-renders", &format!("farm/turntable/{name}"))
            .expect("the frame's blob");
        assert!(
            blob == std::fs::read(fetched.join(name)).expect("fetched frame"),
            "{name}"
        );
    }
}

#[test]
fn a_copc_file_in_gcs_renders_as_the_file_here() {
    let Some(gcs) = FakeGcs::start_or_skip() else {
        return;
    };
    gcs.create_bucket(CONTAINER);
    let local = copc_file("simple_with_page.copc.laz");
    gcs.upload(CONTAINER, "campaign/scan.copc.laz", &local);
    let url = format!("gs://{CONTAINER}/campaign/scan.copc.laz");
    assert_renders_as_here(&gcs.environment(), &local, &url);
    assert!(gcs.object(CONTAINER, "campaign/scan.copc.laz").is_some());
}

#[test]
fn a_missing_gcs_bucket_and_a_bad_service_account_are_one_line_naming_the_url() {
    let Some(gcs) = FakeGcs::start_or_skip() else {
        return;
    };
    gcs.create_bucket(CONTAINER);
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("frame.png");
    let missing = "gs://no-such-bucket/scan.copc.laz";
    let output = try_render(&gcs.environment(), missing, &out);
    assert_one_error_line(&output, &[missing, "no such object"]);

    let url = format!("gs://{CONTAINER}/scan.copc.laz");
    let output = try_render(&gcs.bad_key_environment(), &url, &out);
    assert_one_error_line(&output, &[&url, "could not be set up"]);
    assert!(!output_text(&output).contains(fake_gcs::BAD_KEY_MARKER));
}

#[test]
fn a_gcs_object_registered_under_the_allow_list_renders_through_the_farm() {
    let Some(gcs) = FakeGcs::start_or_skip() else {
        return;
    };
    gcs.create_bucket(CONTAINER);
    let local = copc_file("simple_with_page.copc.laz");
    gcs.upload(CONTAINER, "campaign/scan.copc.laz", &local);
    gcs.upload(CONTAINER, "other/scan.copc.laz", &local);
    let dir = tempfile::tempdir().expect("tempdir");
    let prefix = format!("gs://{CONTAINER}/campaign");
    let server = serve(
        &gcs.environment(),
        dir.path(),
        &["--allow-url-prefix", &prefix],
    );
    let address = server.address.as_str();
    let url = format!("gs://{CONTAINER}/campaign/scan.copc.laz");
    let registered = pointfarm_ok(&["dataset", "register", &url, "--server", address, "--json"]);
    let dataset: serde_json::Value =
        serde_json::from_str(stdout(&registered).trim()).expect("one JSON line");
    assert_eq!(dataset["url"], url.as_str());
    let outside = format!("gs://{CONTAINER}/other/scan.copc.laz");
    let refused = pointfarm(&["dataset", "register", &outside, "--server", address]);
    assert_one_error_line(&refused, &["allows only", "gs://pointfarm-scans/campaign"]);

    let id = dataset["id"].as_str().expect("an id");
    let by_url = dir.path().join("farm.png");
    let size = "--size=160x120";
    let out = ["--out", path_arg(&by_url)];
    let args = ["render", "--dataset", id, "--server", address, size];
    assert_ok(&pointfarm(&[&args[..], &out[..]].concat()));
    let here = dir.path().join("here.png");
    pointfarm_ok(&["render", path_arg(&local), size, "--out", path_arg(&here)]);
    pointfarm_tests::assert_pngs_alike("gcs-farm", &by_url, &here, "the farm's frame by gs://");
}

#[test]
fn a_store_published_to_an_azure_container_is_read_from_it_by_a_worker() {
    let Some(azurite) = Azurite::start_or_skip() else {
        return;
    };
    azurite.create_container("pointfarm-stores");
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = dir.path().join("scene.laz");
    pointfarm_ok(&["sample", path_arg(&scene), "--points", "300000"]);
    let args = [
        "--no-embedded-worker",
        "--store-url",
        "az://pointfarm-stores/farm",
    ];
    let daemon = serve(&azurite.environment(), dir.path(), &args);
    let worker = |name: &str| {
        let cache = dir.path().join(name);
        let command = pointfarm_with(&azurite.environment());
        WorkerProcess::start_in(command, &daemon.address, &cache, name, &[])
    };
    let render = |out: &str| {
        let out = dir.path().join(out);
        let job = ["render", path_arg(&scene), "--out", path_arg(&out)];
        let options = ["--size=120x90", "--turntable", "2", "--lod-error", "0.25"];
        pointfarm_ok(&[&job[..], &["--server", &daemon.address], &options[..]].concat());
        out
    };

    // The first job builds the store; once ready, the daemon publishes it to the container.
    let builder = worker("builder");
    let first = render("first");
    wait_for(Duration::from_secs(60), "the store published", || {
        daemon.log().contains("store published").then_some(())
    });
    let names = azurite.blob_names("pointfarm-stores");
    let digest = names
        .iter()
        .find_map(|name| name.strip_prefix("farm/")?.strip_suffix("/nodes.bin"))
        .unwrap_or_else(|| panic!("the store's payload: {names:?}"));
    let hierarchy = format!("farm/{digest}/hierarchy.pfps");
    assert_eq!(names, [hierarchy, format!("farm/{digest}/nodes.bin")]);

    // A worker new to the dataset reads its nodes from the container, frames unchanged.
    drop(builder);
    let reader = worker("reader");
    let published = render("published");
    assert_same_frames(&first, &published, 2, "the frames from the store in Azure");
    let said = reader.log();
    assert!(said.contains("from=Published"), "{said}");
}
