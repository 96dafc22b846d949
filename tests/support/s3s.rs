//! A real S3-compatible server for the tests that read datasets from `s3://`: crates.io's
//! `s3s-fs`, which serves a folder's subfolders as buckets, where `POINTFARM_TEST_S3S_FS`
//! names its binary (deploy/test.sh installs it). The launcher is the object-storage
//! benchmarks' own.

use std::path::{Path, PathBuf};
use std::process::Output;

use pointfarm_bench::object_storage::s3_server::S3Server;

use crate::tools::tool_or_skip;
use crate::{output_text, run_with};
pub use pointfarm_bench::object_storage::s3_server::{ACCESS_KEY, SECRET_KEY};

/// The variable that names the `s3s-fs` binary.
pub const S3S_FS_VARIABLE: &str = "POINTFARM_TEST_S3S_FS";

/// An `s3s-fs` child process serving `root`'s folders as buckets on a loopback port; killed
/// when dropped, whether the test passes or not.
pub struct S3sServer {
    pub address: String,
    server: S3Server,
}

impl S3sServer {
    /// Starts the server over `root`, or None, having said why, without a binary (a failure
    /// where `CI` is set).
    pub fn start_or_skip(root: &Path) -> Option<Self> {
        let binary = tool_or_skip(S3S_FS_VARIABLE, "s3s-fs")?;
        let server = S3Server::serve(&binary, root).expect("start the S3 server");
        Some(Self {
            address: server.address().to_string(),
            server,
        })
    }

    /// The environment a client of this server reads its endpoint and credentials from, as
    /// object_store reads them.
    pub fn environment(&self) -> Vec<(&'static str, String)> {
        self.server.environment()
    }

    /// Stops the server, as one that goes away while its clients read.
    pub fn stop(&mut self) {
        self.server.stop();
    }
}

/// `pointfarm ARGS` with `environment` (an S3 server's endpoint and credentials, or those
/// altered), checked to show neither the secret key nor a panic, whatever its status.
pub fn run_s3(environment: &[(&'static str, String)], args: &[&str]) -> Output {
    let output = run_with(environment, args);
    let text = output_text(&output);
    assert!(!text.contains(SECRET_KEY), "{text}");
    assert!(!text.contains("panicked"), "{text}");
    output
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
    /// binary (a failure where `CI` is set).
    pub fn start_or_skip(name: &'static str) -> Option<Self> {
        let root = tempfile::tempdir().expect("root");
        std::fs::create_dir_all(root.path().join(name)).expect("bucket folder");
        let server = S3sServer::start_or_skip(root.path())?;
        Some(Self { server, root, name })
    }

    /// Starts the server again over the same root on the same address, once stopped.
    pub fn restart(&mut self) {
        self.server.server.restart().expect("restart the S3 server");
    }

    /// The folder the server keeps the bucket in.
    pub fn folder(&self) -> PathBuf {
        self.root.path().join(self.name)
    }

    /// Where the server keeps the object `key` of the bucket.
    pub fn stored(&self, key: &str) -> PathBuf {
        self.server.server.stored(self.name, key)
    }

    /// Keys of the bucket's objects, sorted; the server's own bookkeeping (its dot files and
    /// folders) left out.
    pub fn objects(&self) -> Vec<String> {
        let bucket = self.folder();
        let keys = self.server.server.stored_files(self.name).into_iter();
        keys.map(|path| {
            let key = path.strip_prefix(&bucket).expect("under the bucket");
            key.to_string_lossy().into_owned()
        })
        .collect()
    }
}
