//! A Google Cloud Storage server that takes object_store's single-request writes, for the
//! tests of what the farm writes to `gs://` URLs: PyPI's gcp-storage-emulator, where
//! `POINTFARM_TEST_GCS_EMULATOR` names its script (deploy/test.sh installs it). It runs on a
//! free loopback port with one bucket, keeps its objects in a temporary folder, and is killed
//! when dropped.
//!
//! It stores an XML API `PUT /bucket/key` (how a job's frames go out) but answers `HEAD` and
//! a multipart upload with `501`, so what writes through those (an export, a store published
//! by URL) is not tested against it. Objects are read back through its JSON API.

use std::path::Path;
use std::time::Duration;

use crate::rest::request;
use crate::tools::ToolServer;

/// The variable that names the `gcp-storage-emulator` script.
pub const GCS_EMULATOR_VARIABLE: &str = "POINTFARM_TEST_GCS_EMULATOR";

/// How long the server may take to listen (a Python interpreter starting).
const START_TIMEOUT: Duration = Duration::from_secs(30);

/// A `gcp-storage-emulator` child process on a loopback port holding the empty bucket
/// `bucket`, its objects and the service account file that points a client at it in a
/// folder of its own; killed when dropped.
pub struct GcsEmulator {
    server: ToolServer,
    bucket: String,
}

impl GcsEmulator {
    /// Starts the server with the empty bucket `bucket` (not `b` or `o`, which its JSON
    /// API's routes take), or None, having said why, without the script (a failure in CI).
    pub fn start_or_skip(bucket: &str) -> Option<Self> {
        let server = ToolServer::start_or_skip(
            GCS_EMULATOR_VARIABLE,
            "gcp-storage-emulator",
            START_TIMEOUT,
            |command, host, port, folder| {
                command
                    .arg("--data-dir")
                    .arg(folder.join("objects"))
                    .args(["start", "--host", host, "--port", port])
                    .args(["--default-bucket", bucket, "--quiet"]);
            },
        )?;
        Some(Self {
            server,
            bucket: bucket.to_owned(),
        })
    }

    /// The environment a client of this server reads its credentials from.
    pub fn environment(&self) -> Vec<(&'static str, String)> {
        emulator_environment(self.server.folder.path(), &self.server.address)
    }

    /// The names of the bucket's objects under `prefix`, sorted, through the JSON API.
    pub fn object_names(&self, prefix: &str) -> Vec<String> {
        let target = format!("/storage/v1/b/{}/o?prefix={prefix}", self.bucket);
        let answer = request(&self.server.address, "GET", &target, &[], &[]);
        assert_eq!(answer.status, 200, "list {prefix}: {}", answer.text());
        let listing: serde_json::Value =
            serde_json::from_slice(&answer.body).expect("a listing as JSON");
        let items = listing["items"].as_array().map(Vec::as_slice);
        let mut names: Vec<String> = (items.unwrap_or_default().iter())
            .map(|item| item["name"].as_str().expect("an object's name").to_owned())
            .collect();
        names.sort();
        names
    }
}

/// The environment that points object_store's GCS client at the emulator listening on
/// `address`: a service account file, written in `folder`, with its base URL and without
/// OAuth, as object_store documents for emulators.
pub fn emulator_environment(folder: &Path, address: &str) -> Vec<(&'static str, String)> {
    let account = serde_json::json!({
        "client_email": "pointfarm-tests@example.iam.gserviceaccount.com",
        "private_key_id": "",
        "private_key": "",
        "disable_oauth": true,
        "gcs_base_url": format!("http://{address}"),
    });
    let path = folder.join("emulator.json");
    std::fs::write(&path, account.to_string()).expect("write the service account");
    vec![("GOOGLE_SERVICE_ACCOUNT", path.display().to_string())]
}
