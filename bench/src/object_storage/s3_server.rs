//! A real S3-compatible server on loopback for the object-storage benchmarks and the tests
//! that read and write `s3://`: `s3s-fs`, which serves a folder's subfolders as buckets and
//! keeps each object as a plain file there, so a benchmark can drop an object's pages from the
//! OS's cache as it drops a local file's.

use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use crate::serve::listens_within;
use crate::BenchError;

/// The credentials the server accepts; they stay on loopback, and a test checks they never
/// appear in an output.
pub const ACCESS_KEY: &str = "pointfarm-loopback-key";
pub const SECRET_KEY: &str = "pointfarm-loopback-secret";
/// How long the server may take to listen.
const START_TIMEOUT: Duration = Duration::from_secs(20);

/// An `s3s-fs` child process serving `root`'s folders as buckets; killed when dropped.
pub struct S3Server {
    address: SocketAddr,
    root: PathBuf,
    binary: PathBuf,
    child: Child,
}

impl S3Server {
    /// Starts `binary` over `root` (created with the folder of `bucket`) on a free loopback
    /// port, and waits until it listens.
    pub fn start(binary: &Path, root: &Path, bucket: &str) -> Result<Self, BenchError> {
        std::fs::create_dir_all(root.join(bucket)).map_err(|e| scratch("the bucket folder", e))?;
        Self::serve(binary, root)
    }

    /// Starts `binary` over the folders `root` holds on a free loopback port, and waits until
    /// it listens.
    pub fn serve(binary: &Path, root: &Path) -> Result<Self, BenchError> {
        let address = TcpListener::bind("127.0.0.1:0")
            .and_then(|listener| listener.local_addr())
            .map_err(|e| scratch("a free loopback port", e))?;
        let child = listening(binary, address, root)?;
        Ok(Self {
            address,
            root: root.to_path_buf(),
            binary: binary.to_path_buf(),
            child,
        })
    }

    /// The loopback address the server listens on.
    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// Stops the server, as one that goes away while its clients read.
    pub fn stop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Starts the server again over the same root on the same address, once stopped.
    pub fn restart(&mut self) -> Result<(), BenchError> {
        self.child = listening(&self.binary, self.address, &self.root)?;
        Ok(())
    }

    /// The variables a client of this server reads its endpoint and credentials from, as
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

    /// Sets [`S3Server::environment`] in this process, for its own `RemoteClient`s (object_store
    /// reads credentials from the environment only). Called before the process starts threads
    /// of its own, since a C library reading the environment takes no lock.
    pub fn export_environment(&self) {
        for (key, value) in self.environment() {
            std::env::set_var(key, value);
        }
    }

    /// The file the server keeps `key` of `bucket` in.
    pub fn stored(&self, bucket: &str, key: &str) -> PathBuf {
        self.root.join(bucket).join(key)
    }

    /// Every object file of `bucket`, sorted (the server's own bookkeeping, dot files, left
    /// out).
    pub fn stored_files(&self, bucket: &str) -> Vec<PathBuf> {
        let mut found = Vec::new();
        let mut folders = vec![self.root.join(bucket)];
        while let Some(folder) = folders.pop() {
            let Ok(entries) = std::fs::read_dir(&folder) else {
                continue;
            };
            for path in entries.flatten().map(|entry| entry.path()) {
                let hidden = path
                    .file_name()
                    .is_some_and(|name| name.to_string_lossy().starts_with('.'));
                if hidden {
                    continue;
                }
                if path.is_dir() {
                    folders.push(path);
                } else {
                    found.push(path);
                }
            }
        }
        found.sort();
        found
    }
}

impl Drop for S3Server {
    fn drop(&mut self) {
        self.stop();
    }
}

/// `binary` serving `root` on `address`, once it listens there; killed if it does not in time.
fn listening(binary: &Path, address: SocketAddr, root: &Path) -> Result<Child, BenchError> {
    let mut child = Command::new(binary)
        .args(["--host", &address.ip().to_string()])
        .args(["--port", &address.port().to_string()])
        .args(["--access-key", ACCESS_KEY, "--secret-key", SECRET_KEY])
        .arg(root)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| scratch(&format!("starting {}", binary.display()), e))?;
    if !listens_within(address, START_TIMEOUT) {
        let _ = child.kill();
        let _ = child.wait();
        return Err(BenchError::Scratch(format!(
            "{} did not listen on {address} within {START_TIMEOUT:?}",
            binary.display()
        )));
    }
    Ok(child)
}

/// A setup step that failed, as the benchmark's scratch error.
fn scratch(what: &str, error: std::io::Error) -> BenchError {
    BenchError::Scratch(format!("{what}: {error}"))
}
