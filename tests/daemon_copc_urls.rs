//! A COPC object registered by URL with a real `pointfarm serve` (`--allow-url-prefix`) and a
//! real `s3s-fs` on loopback, driven through the CLI: `info ID --server` describes it as the same
//! file registered by path (its header, records and hierarchy read by range, and its points
//! streamed when asked), `dataset export --copc` writes the object itself, byte for byte, and an
//! object replaced after its registration fails both, naming it, with nothing written, while
//! the daemon keeps serving. Skips, saying so, without `s3s-fs`.

use std::path::Path;

use pointfarm_tests::s3s::{S3sServer, SECRET_KEY};
use pointfarm_tests::{copc_file, output_text, path_arg, pointfarm, pointfarm_ok, ServeProcess};

const BUCKET: &str = "scans";

/// `pointfarm ARGS --server ADDRESS`, which must succeed, as JSON.
fn json(daemon: &ServeProcess, args: &[&str]) -> serde_json::Value {
    let args = [args, &["--server", &daemon.address, "--json"]].concat();
    let output = pointfarm_ok(&args);
    serde_json::from_slice(&output.stdout).expect("one JSON document")
}

/// The id of the dataset `dataset register PATH_OR_URL` answers.
fn register(daemon: &ServeProcess, path: &str) -> String {
    let dataset = json(daemon, &["dataset", "register", path]);
    dataset["id"].as_str().expect("an id").to_owned()
}

/// A description's file without its path, which names the URL or the file.
fn unnamed(file: &serde_json::Value) -> serde_json::Value {
    let mut file = file.clone();
    file.as_object_mut().expect("an object").remove("path");
    file
}

/// `dataset export ID --copc OUT`: its output, and the file written, if any.
fn export(daemon: &ServeProcess, id: &str, out: &Path) -> (std::process::Output, Option<Vec<u8>>) {
    let args = ["dataset", "export", id, "--copc", path_arg(out)];
    let output = pointfarm(&[&args[..], &["--server", &daemon.address]].concat());
    (output, std::fs::read(out).ok())
}

#[test]
fn a_copc_object_by_url_is_described_and_exported_as_the_same_file_by_path() {
    let root = tempfile::tempdir().expect("root");
    let bucket = root.path().join(BUCKET);
    let files = root.path().join("files");
    for folder in [&bucket, &files] {
        std::fs::create_dir_all(folder).expect("folder");
    }
    // A file with child hierarchy pages, as an object, a second object to be replaced, and
    // the same file on the server.
    let local = copc_file("simple_with_page.copc.laz");
    for to in [
        bucket.join("scan.copc.laz"),
        bucket.join("replaced.copc.laz"),
        files.join("scan.copc.laz"),
    ] {
        std::fs::copy(&local, to).expect("a copy");
    }
    let Some(server) = S3sServer::start_or_skip(root.path()) else {
        return;
    };
    let args = [
        "--no-embedded-worker",
        "--allow-url-prefix",
        "s3://scans/",
        "--data-root",
        path_arg(&files),
    ];
    let data = root.path().join("data");
    let daemon = ServeProcess::start_in_environment(&server.environment(), &data, &args);

    let url = format!("s3://{BUCKET}/scan.copc.laz");
    let by_url = register(&daemon, &url);
    let by_path = register(&daemon, "scan.copc.laz");
    assert_ne!(by_url, by_path);

    // Described from its header, records and hierarchy, then with its points streamed: each as
    // the file by path is.
    for points in [&["--no-points"][..], &[]] {
        let described = |id: &str| json(&daemon, &[&["info", id][..], points].concat());
        let (urls, files) = (described(&by_url), described(&by_path));
        let file = &urls["files"][0];
        assert_eq!(file["path"], url.as_str(), "{urls}");
        assert!(file.get("error").is_none(), "{urls}");
        // 64-bit counts are strings in the JSON mapping.
        let nodes = file["copc"]["nodes"]
            .as_str()
            .and_then(|n| n.parse::<u64>().ok());
        assert!(nodes.unwrap_or(0) > 1, "{urls}");
        assert_eq!(
            file.get("pointsRead").is_some(),
            points.is_empty(),
            "{urls}"
        );
        assert_eq!(
            unnamed(file),
            unnamed(&files["files"][0]),
            "{urls}\n{files}"
        );
        assert_eq!(urls["summary"], files["summary"]);
    }

    // Exported, it is the object itself, byte for byte.
    let out = tempfile::tempdir().expect("out");
    let (said, written) = export(&daemon, &by_url, &out.path().join("by-url.copc.laz"));
    let text = output_text(&said);
    assert!(said.status.success(), "{text}\n{}", daemon.log());
    assert!(text.contains("COPC 1.0"), "{text}");
    let source = std::fs::read(&local).expect("the file");
    assert!(
        written == Some(source),
        "the export is not the object:\n{text}"
    );

    // Replaced after its registration: the description and the export fail naming it, and
    // nothing is written.
    let replaced_url = format!("s3://{BUCKET}/replaced.copc.laz");
    let replaced = register(&daemon, &replaced_url);
    std::fs::copy(
        copc_file("autzen.copc.laz"),
        bucket.join("replaced.copc.laz"),
    )
    .expect("replace the object");
    let info = pointfarm(&["info", &replaced, "--server", &daemon.address]);
    let (exported, written) = export(&daemon, &replaced, &out.path().join("replaced.copc.laz"));
    for (what, output) in [("info", &info), ("export", &exported)] {
        let text = output_text(output);
        assert!(!output.status.success(), "{what}: {text}");
        assert!(
            text.contains(&replaced_url) && text.contains("replaced after it was registered"),
            "{what}: {text}"
        );
        assert!(!text.contains(SECRET_KEY), "{what}: {text}");
    }
    assert!(
        written.is_none(),
        "an export of the replaced object was written"
    );
    // No export's temporary file is left on the server.
    let uploads = std::fs::read_dir(data.join("datasets")).map(|entries| {
        (entries.flatten())
            .filter(|entry| entry.file_name().to_string_lossy().starts_with("export-"))
            .count()
    });
    assert_eq!(uploads.unwrap_or(0), 0);

    // The daemon keeps serving, the first object still described.
    let again = json(&daemon, &["info", &by_url, "--no-points"]);
    assert_eq!(again["files"][0]["path"], url.as_str());
    assert!(!daemon.log().contains(SECRET_KEY));
}
