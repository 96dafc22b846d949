//! COPC files rendered and described straight from a URL, as a user runs `pointfarm render URL`
//! and `pointfarm info URL`, against a real nginx on loopback: the same image as the same file
//! here, a coarse cut fetching less than the file, an object replaced after open refused as
//! changed, a missing or truncated object refused in one line naming the URL, and a plain LAZ
//! file rendered only as a preview (tests/remote_tiles.rs). Where `POINTFARM_TEST_S3S_FS` names an `s3s-fs` binary, the same file renders from
//! `s3://` too. Each test skips, saying so, where nginx is not installed.

use std::path::Path;

use pointfarm_render::copc::open_copc_url;
use pointfarm_render::lod::NodeInfo;
use pointfarm_render::remote::{ObjectUrl, RemoteClient, RemoteSettings};
use pointfarm_tests::nginx::NginxServer;
use pointfarm_tests::object_faults::assert_copc_object_changed;
use pointfarm_tests::s3s::{run_s3, S3sServer};
use pointfarm_tests::{
    assert_fails_saying, assert_one_error_line, copc_file, json_lines, output_text, path_arg,
    pointfarm, pointfarm_ok, sampled_copc, stdout,
};

/// nginx serving a copy of the file at `path` as `scans/SERVED_AS`; None, having said so,
/// where nginx is not installed.
fn serve_file(path: &Path, served_as: &str) -> Option<(tempfile::TempDir, NginxServer)> {
    let bytes = std::fs::read(path).expect("served file");
    NginxServer::serve_scans(&[(served_as, bytes)])
}

/// `pointfarm render INPUT --out OUT --json ARGS...`, which must succeed, and its one frame's
/// report.
fn render_json(input: &str, out: &Path, args: &[&str]) -> serde_json::Value {
    let mut all = vec!["render", input, "--out", path_arg(out), "--json"];
    all.extend_from_slice(args);
    let output = pointfarm_ok(&all);
    let mut frames = json_lines(&output);
    assert_eq!(frames.len(), 1, "{}", output_text(&output));
    frames.remove(0)
}

fn same_pixels(a: &Path, b: &Path) -> bool {
    let image = |path: &Path| image::open(path).expect("png").to_rgba8();
    image(a) == image(b)
}

/// What a frame's report says was fetched by URL: (requests, bytes).
fn fetched(report: &serde_json::Value) -> (u64, u64) {
    let count = |key: &str| report["fetched"][key].as_u64().expect("fetched counts");
    (count("requests"), count("bytes"))
}

#[test]
fn a_copc_file_by_url_renders_pixel_for_pixel_as_the_file_here() {
    let local = copc_file("simple_with_page.copc.laz");
    let Some((_root, server)) = serve_file(&local, "scan.copc.laz") else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let url = server.url("scans/scan.copc.laz");
    // Every node, the child pages included.
    let args = ["--size=200x150", "--point-size=3", "--lod-error", "0"];
    let here = dir.path().join("here.png");
    let by_url = dir.path().join("url.png");
    let cache = ["--cache-dir", path_arg(dir.path())];
    let local_report = render_json(path_arg(&local), &here, &[&args[..], &cache[..]].concat());
    let report = render_json(&url, &by_url, &args);
    assert!(same_pixels(&here, &by_url), "{report}");
    assert_eq!(report["pointsRendered"], local_report["pointsRendered"]);
    assert_eq!(report["cut"]["nodes"], local_report["cut"]["nodes"]);
    let (requests, bytes) = fetched(&report);
    assert!(requests > 1 && bytes > 0, "{report}");
    assert!(local_report.get("fetched").is_none(), "{local_report}");
}

/// Points of the scene exported: more than the color ranges' sample (1M) reads at open, so
/// that a coarse cut leaves most of the file unread.
const SCENE_POINTS: u64 = 2_500_000;

#[test]
fn a_coarse_cut_by_url_fetches_less_than_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let local = sampled_copc(dir.path(), SCENE_POINTS).1;
    let bytes = std::fs::read(&local).expect("COPC file");
    let size = bytes.len() as u64;
    let Some((_root, server)) = NginxServer::serve_scans(&[("scene.copc.laz", bytes)]) else {
        return;
    };
    let url = server.url("scans/scene.copc.laz");
    let args = ["--size=160x120", "--lod-error", "8"];
    let here = dir.path().join("here.png");
    let by_url = dir.path().join("url.png");
    let local_report = render_json(path_arg(&local), &here, &args);
    let report = render_json(&url, &by_url, &args);
    assert!(same_pixels(&here, &by_url), "{report}");
    let (requests, fetched_bytes) = fetched(&report);
    eprintln!("{url}: {requests} requests, {fetched_bytes} of {size} bytes");
    assert!(requests > 1, "{report}");
    assert!(
        fetched_bytes > 0 && fetched_bytes < size * 3 / 4,
        "fetched {fetched_bytes} of {size} bytes: {report}"
    );
    assert_eq!(report["pointsRendered"], local_report["pointsRendered"]);
    assert!(
        report["pointsRendered"].as_u64() < Some(100_000),
        "a coarse cut: {report}"
    );

    // Every node drawn: the chunks the color sample read at open are not fetched again, so
    // beyond the nodes' bytes only the header and hierarchy are.
    let all = render_json(&url, &by_url, &["--size=160x120", "--lod-error", "0"]);
    let (_, fetched_bytes) = fetched(&all);
    let node_bytes = all["cut"]["bytesRead"].as_u64().expect("the cut's bytes");
    assert!(
        fetched_bytes <= node_bytes + node_bytes / 100 + 256 * 1024,
        "fetched {fetched_bytes} for {node_bytes} bytes of nodes: {all}"
    );
}

#[test]
fn an_object_replaced_after_open_is_object_changed_naming_the_url() {
    let dir = tempfile::tempdir().expect("tempdir");
    let Some((root, server)) =
        serve_file(&sampled_copc(dir.path(), SCENE_POINTS).1, "scan.copc.laz")
    else {
        return;
    };
    let client = RemoteClient::new(RemoteSettings::default()).expect("client");
    let text = server.url("scans/scan.copc.laz");
    let url = ObjectUrl::parse(&text).expect("url");
    let copc = open_copc_url(&client, &url).expect("opens by URL");
    // Another file in its place: another size and modification time, so another ETag.
    let second = std::fs::read(copc_file("autzen.copc.laz")).expect("COPC file");
    std::fs::write(root.path().join("scans/scan.copc.laz"), second).expect("replace");
    let nodes: Vec<NodeInfo> = copc
        .dataset
        .hierarchy()
        .nodes()
        .iter()
        .filter(|node| node.point_count > 0)
        .copied()
        .collect();
    // The root's chunk, read at open for the color ranges, is still the opened version's.
    let root_node = nodes
        .iter()
        .find(|node| node.key.level == 0)
        .expect("a root");
    let records = copc.dataset.records();
    records
        .read_records(std::slice::from_ref(root_node))
        .expect("a chunk read at open");
    let error = copc
        .dataset
        .records()
        .read_records(&nodes)
        .expect_err("the object changed since it was opened");
    assert_copc_object_changed(error, &text);
}

#[test]
fn a_missing_object_is_one_line_naming_its_url() {
    let Some((_root, server)) = NginxServer::serve_scans(&[]) else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let url = server.url("scans/absent.copc.laz");
    let output = pointfarm(&["render", &url, "--out", path_arg(&dir.path().join("a.png"))]);
    assert_one_error_line(&output, &[&url, "no such object"]);
    let output = pointfarm(&["info", &url]);
    assert_fails_saying(&output, &url);
}

#[test]
fn a_truncated_copc_object_is_a_clear_error_never_a_panic() {
    let whole = std::fs::read(copc_file("simple_with_page.copc.laz")).expect("COPC file");
    let cuts = [400, 2_000, whole.len() / 2, whole.len() - 100];
    let files: Vec<(String, Vec<u8>)> = cuts
        .iter()
        .map(|&len| (format!("cut{len}.copc.laz"), whole[..len].to_vec()))
        .collect();
    let served: Vec<(&str, Vec<u8>)> = files
        .iter()
        .map(|(name, bytes)| (name.as_str(), bytes.clone()))
        .collect();
    let Some((_root, server)) = NginxServer::serve_scans(&served) else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    for (name, _) in &files {
        let url = server.url(&format!("scans/{name}"));
        let out = dir.path().join(format!("{name}.png"));
        let output = pointfarm(&["render", &url, "--out", path_arg(&out), "--lod-error", "0"]);
        assert_one_error_line(&output, &[&url]);
        assert!(!out.exists(), "{name}: no frame from a truncated file");
    }
}

#[test]
fn a_plain_laz_file_by_url_renders_from_a_store_built_here_and_an_http_prefix_is_not_listed() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = dir.path().join("scene.laz");
    pointfarm_ok(&["sample", path_arg(&scene), "--points", "2000"]);
    let Some((_root, server)) = serve_file(&scene, "scene.laz") else {
        return;
    };
    let out = dir.path().join("a.png");
    let url = server.url("scans/scene.laz");
    let cache = dir.path().join("cache");
    pointfarm_ok(&[
        "render",
        &url,
        "--out",
        path_arg(&out),
        "--cache-dir",
        path_arg(&cache),
    ]);
    assert!(image::open(&out).is_ok());
    let prefix = server.url("scans/");
    let output = pointfarm(&["render", &prefix, "--preview", "--out", path_arg(&out)]);
    assert_one_error_line(&output, &[&prefix, "name the files instead"]);
    // A server renders a URL once it is registered there, not as files it is sent.
    let on_server = [
        "render",
        &url,
        "--out",
        path_arg(&out),
        "--server",
        "http://127.0.0.1:9",
    ];
    let output = pointfarm(&on_server);
    assert_one_error_line(&output, &[&url, "dataset register"]);
}

#[test]
fn info_by_url_says_what_info_of_the_file_here_says_of_its_header_and_octree() {
    let local = copc_file("simple_with_page.copc.laz");
    let Some((_root, server)) = serve_file(&local, "scan.copc.laz") else {
        return;
    };
    let url = server.url("scans/scan.copc.laz");
    let describe = |input: &str| {
        let output = pointfarm_ok(&["info", input, "--json", "--no-points"]);
        let document: serde_json::Value =
            serde_json::from_str(&String::from_utf8_lossy(&output.stdout)).expect("JSON");
        document["files"][0].clone()
    };
    let (here, by_url) = (describe(path_arg(&local)), describe(&url));
    assert_eq!(by_url["path"], url.as_str());
    // 64-bit counts are strings in the proto3 JSON mapping.
    let nodes = by_url["copc"]["nodes"]
        .as_str()
        .and_then(|n| n.parse::<u64>().ok());
    assert!(nodes > Some(1), "{by_url}");
    for key in [
        "copc",
        "points",
        "pointFormat",
        "recordBytes",
        "fileBytes",
        "bounds",
        "scale",
        "offset",
        "vlrs",
        "evlrs",
        "attributes",
    ] {
        assert_eq!(by_url[key], here[key], "{key}: {by_url} against {here}");
    }
    let text = stdout(&pointfarm_ok(&["info", &url]));
    let copc_line = |text: &str| {
        let line = text
            .lines()
            .find(|line| line.trim_start().starts_with("copc"));
        line.expect("a copc line").to_owned()
    };
    let text_here = stdout(&pointfarm_ok(&["info", path_arg(&local), "--no-points"]));
    assert_eq!(copc_line(&text), copc_line(&text_here));
}

#[test]
fn a_copc_file_from_an_s3_compatible_server_renders_as_the_file_here() {
    let local = copc_file("simple_with_page.copc.laz");
    let root = tempfile::tempdir().expect("root");
    let scans = root.path().join("pointfarm-test/scans");
    std::fs::create_dir_all(&scans).expect("bucket folder");
    std::fs::copy(&local, scans.join("scan.copc.laz")).expect("copy");
    let Some(server) = S3sServer::start_or_skip(root.path()) else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let args = [
        "--size=200x150",
        "--point-size=3",
        "--lod-error",
        "0",
        "--json",
    ];
    let here = dir.path().join("here.png");
    let cache = ["--cache-dir", path_arg(dir.path())];
    render_json(path_arg(&local), &here, &[&args[..4], &cache[..]].concat());
    let url = "s3://pointfarm-test/scans/scan.copc.laz";
    let by_url = dir.path().join("s3.png");
    // Credentials reach the client only through the environment.
    let render = ["render", url, "--out", path_arg(&by_url)];
    let output = run_s3(&server.environment(), &[&render[..], &args[..]].concat());
    assert!(output.status.success(), "{}", output_text(&output));
    let report = json_lines(&output).remove(0);
    assert!(same_pixels(&here, &by_url), "{report}");
    let (requests, bytes) = fetched(&report);
    assert!(requests > 1 && bytes > 0, "{report}");
    let absent = dir.path().join("absent.png");
    let missing = run_s3(
        &server.environment(),
        &[
            "render",
            "s3://pointfarm-test/scans/absent.copc.laz",
            "--out",
            path_arg(&absent),
        ],
    );
    assert_one_error_line(&missing, &["s3://pointfarm-test/scans/absent.copc.laz"]);
}
