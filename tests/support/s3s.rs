//! A real S3-compatible server for the tests that read datasets from `s3://`: crates.io's
//! `s3s-fs`, which serves a folder's subfolders as buckets, where `POINTFARM_TEST_S3S_FS`
//! names its binary (deploy/test.sh installs it).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::free_address;

/// The variable that names the `s3s-fs` binary.
pub const S3S_FS_VARIABLE: &str = "POINTFARM_TEST_S3S_FS";

/// The credentials the server accepts; a test checks they never appear in an output.
pub const ACCESS_KEY: &str = "pointfarm-test-key";
pub const SECRET_KEY: &str = "pointfarm-test-secret";

/// How long the server may take to listen.
const START_TIMEOUT: Duration = Duration::from_secs(20);

/// An `s3s-fs` child process serving `root`'s folders as buckets on a loopback port; killed
/// when dropped, whether the test passes or not.
pub struct S3sServer {
    pub address: String,
    child: Child,
}

impl S3sServer {
    /// The binary `POINTFARM_TEST_S3S_FS` names, or None, having said so.
    pub fn binary_or_skip() -> Option<PathBuf> {
        let binary = std::env::var_os(S3S_FS_VARIABLE)
            .map(PathBuf::from)
            .filter(|path| path.is_file());
        if binary.is_none() {
            eprintln!("skipped: {S3S_FS_VARIABLE} names no s3s-fs binary");
        }
        binary
    }

    /// Starts the server over `root`, or None, having said why, without a binary.
    pub fn start_or_skip(root: &Path) -> Option<Self> {
        let binary = Self::binary_or_skip()?;
        let address = free_address();
        let child = Self::spawn(&binary, &address, root);
        Some(Self { address, child })
    }

    /// Starts `binary` over `root` on `address` and waits until it listens.
    fn spawn(binary: &Path, address: &str, root: &Path) -> Child {
        let (host, port) = address.split_once(':').expect("host:port");
        let child = Command::new(binary)
            .args(["--host", host, "--port", port])
            .args(["--access-key", ACCESS_KEY, "--secret-key", SECRET_KEY])
            .arg(root)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start the S3 server");
        let started = Instant::now();
        while std::net::TcpStream::connect(address).is_err() {
            assert!(
                started.elapsed() < START_TIMEOUT,
                "the S3 server did not listen"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        child
    }

    /// The environment a client of this server reads its endpoint and credentials from, as
    /// object_store reads them.
    pub fn environment(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ENDPOINT", format!("http://{}", self.address)),
            ("AWS_ALLOW_HTTP", "true".to_owned()),
            ("AWS_ACCESS_KEY_ID", ACCESS_KEY.to_owned()),
            ("AWS_SECRET_ACCESS_KEY", SECRET_KEY.to_owned()),
            ("AWS_REGION", "us-east-1".to_owned()),
        ]
    }
}

impl S3sServer {
    /// Stops the server, as one that goes away while its clients read.
    pub fn stop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// An S3 server over a fresh root holding one empty bucket. The fields drop in order: the
/// server stops before its root goes.
pub struct S3Bucket {
    pub server: S3sServer,
    root: tempfile::TempDir,
    name: &'static str,
}

impl S3Bucket {
    /// Starts a server holding the empty bucket `name`; None, having said so, without the
    /// binary.
    pub fn start_or_skip(name: &'static str) -> Option<Self> {
        let root = tempfile::tempdir().expect("root");
        std::fs::create_dir_all(root.path().join(name)).expect("bucket folder");
        let server = S3sServer::start_or_skip(root.path())?;
        Some(Self { server, root, name })
    }

    /// Starts the server again over the same root on the same address, once stopped.
    pub fn restart(&mut self) {
        let binary = S3sServer::binary_or_skip().expect("the s3s-fs binary");
        self.server.child = S3sServer::spawn(&binary, &self.server.address, self.root.path());
    }

    /// The folder the server keeps the bucket in.
    pub fn folder(&self) -> PathBuf {
        self.root.path().join(self.name)
    }

    /// Where the server keeps the object `key` of the bucket.
    pub fn stored(&self, key: &str) -> PathBuf {
        self.folder().join(key)
    }

    /// Keys of the bucket's objects, sorted; the server's own bookkeeping (its dot files and
    /// folders) left out.
    pub fn objects(&self) -> Vec<String> {
        let bucket = self.folder();
        let mut found = Vec::new();
        let mut folders = vec![bucket.clone()];
        while let Some(folder) = folders.pop() {
            for entry in std::fs::read_dir(&folder).expect("bucket folder") {
                let path = entry.expect("entry").path();
                if path.is_dir() {
                    folders.push(path);
                } else {
                    let key = path.strip_prefix(&bucket).expect("under the bucket");
                    found.push(key.to_string_lossy().into_owned());
                }
            }
        }
        found.retain(|key| !key.starts_with('.') && !key.contains("/."));
        found.sort();
        found
    }
}

impl Drop for S3sServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
