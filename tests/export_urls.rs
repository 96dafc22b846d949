//! Exports written to object storage, as a user runs `pointfarm export FILES --copc s3://...`
//! and `pointfarm dataset export ID --copc s3://...`, against a real S3-compatible server
//! (`s3s-fs`, serving a folder's subfolders as buckets): the object equals the file exported
//! here byte for byte, an existing object is refused without `--force`, a missing bucket and
//! refused credentials are one line each, and a multipart upload of several parts arrives
//! whole while one given up leaves no object. Each test skips, saying so, where
//! `POINTFARM_TEST_S3S_FS` names no `s3s-fs` binary.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use pointfarm_render::remote::{ObjectUrl, RemoteClient, RemoteSettings};
use pointfarm_tests::datasets::add_with_cli;
use pointfarm_tests::s3s::{self, S3Bucket, S3sServer};
use pointfarm_tests::{
    assert_fails_saying, assert_ok, assert_one_error_line, json_lines, output_text, path_arg,
    pointfarm_with, shared_data, ServeProcess,
};

/// The bucket every test writes to: a folder of the server's root.
const BUCKET: &str = "pointfarm-exports";

/// An S3 server holding one empty bucket, and a scratch folder for what is exported here and
/// its cache.
struct S3Exports {
    bucket: S3Bucket,
    dir: tempfile::TempDir,
}

impl S3Exports {
    /// Starts the server; None, having said so, without the binary.
    fn start() -> Option<Self> {
        let bucket = S3Bucket::start_or_skip(BUCKET)?;
        let dir = tempfile::tempdir().expect("tempdir");
        Some(Self { bucket, dir })
    }

    /// The shared scan `name` and a started server; None, having said which is missing.
    fn with_scan(name: &str) -> Option<(PathBuf, Self)> {
        let scan = shared_data(name)?;
        Some((scan, Self::start()?))
    }

    /// A `pointfarm` command with the server's endpoint and credentials in its environment.
    fn pointfarm(&self) -> Command {
        pointfarm_with(&self.bucket.server.environment())
    }

    /// `pointfarm ARGS` with the server's endpoint and credentials in its environment.
    fn run(&self, args: &[&str]) -> Output {
        self.pointfarm().args(args).output().expect("run pointfarm")
    }

    /// `pointfarm export SCAN --copc OUT`, its cache in the scratch folder, to run.
    fn export_command(&self, scan: &Path, out: &str) -> Command {
        let mut command = self.pointfarm();
        command.args(["export", path_arg(scan), "--copc", out, "--cache-dir"]);
        command.arg(self.dir.path().join("cache"));
        command
    }

    /// Runs `pointfarm export SCAN --copc OUT MORE`, its cache in the scratch folder.
    fn export(&self, scan: &Path, out: &str, more: &[&str]) -> Output {
        let mut command = self.export_command(scan, out);
        command.args(more).output().expect("run pointfarm")
    }

    /// Checks an export to the object `key` of the bucket that succeeded: its JSON report
    /// names the object's URL, and the object holds the bytes of `here`, the same export
    /// written to a file. Returns the report and the object's size.
    fn assert_exported_as(
        &self,
        output: &Output,
        key: &str,
        here: &Path,
    ) -> (serde_json::Value, usize) {
        assert_ok(output);
        let report = json_lines(output).remove(0);
        assert_eq!(report["file"], format!("s3://{BUCKET}/{key}"), "{report}");
        let uploaded = std::fs::read(self.bucket.stored(key)).expect("object");
        assert_eq!(uploaded, std::fs::read(here).expect("file here"));
        (report, uploaded.len())
    }
}

#[test]
fn an_export_to_s3_is_the_file_exported_here_byte_for_byte() {
    let Some((scan, exports)) = S3Exports::with_scan("autzen_trim.laz") else {
        return;
    };
    let here = exports.dir.path().join("here.copc.laz");
    assert_ok(&exports.export(&scan, path_arg(&here), &[]));
    let url = format!("s3://{BUCKET}/campaign/autzen.copc.laz");
    let export = |more: &[&str]| exports.export(&scan, &url, more);
    let output = export(&["--json"]);
    let (report, size) = exports.assert_exported_as(&output, "campaign/autzen.copc.laz", &here);
    assert_eq!(report["bytes"], size, "{report}");
    assert!(!output_text(&output).contains(s3s::SECRET_KEY));

    // The object exists now: refused without --force, before any work, and left as it was.
    assert_one_error_line(&export(&[]), &[&url, "exists: pass --force"]);
    assert_ok(&export(&["--force"]));
    assert_eq!(exports.bucket.objects(), ["campaign/autzen.copc.laz"]);

    // A prefix is not an object to write.
    let prefix = format!("s3://{BUCKET}/campaign/");
    let output = exports.run(&["export", path_arg(&scan), "--copc", &prefix]);
    assert_fails_saying(&output, "names a prefix");
    // A web server's URL is read from, never written to.
    let web = "https://127.0.0.1:9/scans/autzen.copc.laz";
    let output = exports.run(&["export", path_arg(&scan), "--copc", web]);
    assert_one_error_line(&output, &[web, "read-only"]);
}

#[test]
fn a_missing_bucket_and_refused_credentials_are_one_line_each() {
    let Some((scan, exports)) = S3Exports::with_scan("lone-star.laz") else {
        return;
    };
    let missing = "s3://no-such-bucket/scan.copc.laz";
    let output = exports.export(&scan, missing, &[]);
    assert_one_error_line(&output, &[missing, "no such bucket"]);

    let url = format!("s3://{BUCKET}/scan.copc.laz");
    let output = exports
        .export_command(&scan, &url)
        .env("AWS_SECRET_ACCESS_KEY", "not-the-secret")
        .output()
        .expect("run pointfarm");
    assert_one_error_line(&output, &[&url, "access denied"]);
    assert!(!output_text(&output).contains("not-the-secret"));
    assert!(exports.bucket.objects().is_empty());
}

/// A client of the server with parts of 5 MiB (S3's smallest), two in flight.
fn small_part_client(server: &S3sServer) -> RemoteClient {
    // object_store reads its endpoint and credentials from the environment only; std's own
    // readers (the other tests' child processes) take the same lock as this write.
    for (key, value) in server.environment() {
        std::env::set_var(key, value);
    }
    RemoteClient::new(RemoteSettings {
        upload_part_bytes: 5 * 1024 * 1024,
        upload_parts_in_flight: 2,
        ..RemoteSettings::default()
    })
    .expect("client")
}

#[test]
fn a_multipart_upload_arrives_whole_and_one_given_up_leaves_no_object() {
    let Some(exports) = S3Exports::start() else {
        return;
    };
    let client = small_part_client(&exports.bucket.server);
    // Over four parts, the last one short, of bytes that differ from part to part.
    let bytes: Vec<u8> = (0..(21 * 1024 * 1024 + 123) as u64)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    let file = exports.dir.path().join("big.bin");
    std::fs::write(&file, &bytes).expect("file");
    let url = ObjectUrl::parse(&format!("s3://{BUCKET}/big.bin")).expect("url");
    assert!(!client.exists(&url).expect("head"));
    let sent = client.upload_file(&file, &url).expect("upload");
    assert_eq!(sent, bytes.len() as u64);
    assert!(client.exists(&url).expect("head"));
    assert!(std::fs::read(exports.bucket.stored("big.bin")).expect("object") == bytes);

    // Parts sent, then given up (as an export that fails midway drops its upload).
    let given_up = ObjectUrl::parse(&format!("s3://{BUCKET}/given-up.bin")).expect("url");
    let mut upload = client.start_upload(&given_up).expect("start");
    upload.write(&bytes[..12 * 1024 * 1024]).expect("parts");
    drop(upload);
    assert!(!client.exists(&given_up).expect("head"));
    assert_eq!(exports.bucket.objects(), ["big.bin"]);
}

#[test]
fn a_dataset_exported_by_the_server_to_s3_is_the_file_it_exports_here() {
    let Some((scan, exports)) = S3Exports::with_scan("lone-star.laz") else {
        return;
    };
    let dir = &exports.dir;
    let server = ServeProcess::start(&dir.path().join("data"));
    let address = server.address.clone();
    let dataset = add_with_cli(&address, &scan);
    let here = dir.path().join("here.copc.laz");
    let export = |out: &str, more: &[&str]| {
        let mut args = vec!["dataset", "export", &dataset.id, "--copc", out];
        args.extend(["--server", &address]);
        args.extend_from_slice(more);
        exports.run(&args)
    };
    assert_ok(&export(path_arg(&here), &[]));
    let url = format!("s3://{BUCKET}/server/lone-star.copc.laz");
    let output = export(&url, &["--json"]);
    let (report, size) = exports.assert_exported_as(&output, "server/lone-star.copc.laz", &here);
    assert_eq!(report["summary"]["sizeBytes"], size.to_string(), "{report}");
    assert_one_error_line(&export(&url, &[]), &[&url, "exists: pass --force"]);
    assert_one_error_line(
        &export("s3://no-such-bucket/x.copc.laz", &[]),
        &["s3://no-such-bucket/x.copc.laz", "no such bucket"],
    );
    assert_eq!(exports.bucket.objects(), ["server/lone-star.copc.laz"]);
}
