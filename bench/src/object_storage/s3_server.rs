//! A real S3-compatible server on loopback for the object-storage benchmarks: `s3s-fs`, which
//! serves a folder's subfolders as buckets and keeps each object as a plain file there, so a
//! benchmark can drop an object's pages from the OS's cache as it drops a local file's.

use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::BenchError;

/// The credentials the server is started with; they stay on loopback.
const ACCESS_KEY: &str = "pointfarm-bench-key";
const SECRET_KEY: &str = "pointfarm-bench-secret";
/// How long the server may take to listen.
const START_TIMEOUT: Duration = Duration::from_secs(20);

/// An `s3s-fs` child process serving `root`'s folders as buckets; killed when dropped.
pub struct S3Server {
    address: SocketAddr,
    root: PathBuf,
    child: Child,
}

impl S3Server {
    /// Starts `binary` over `root` (created with the folder of `bucket`) on a free loopback
    /// port, and waits until it listens.
    pub fn start(binary: &Path, root: &Path, bucket: &str) -> Result<Self, BenchError> {
        let setup = |what: &str, e: std::io::Error| BenchError::Scratch(format!("{what}: {e}"));
        std::fs::create_dir_all(root.join(bucket)).map_err(|e| setup("the bucket folder", e))?;
        let address = TcpListener::bind("127.0.0.1:0")
            .and_then(|listener| listener.local_addr())
            .map_err(|e| setup("a free loopback port", e))?;
        let child = Command::new(binary)
            .args(["--host", &address.ip().to_string()])
            .args(["--port", &address.port().to_string()])
            .args(["--access-key", ACCESS_KEY, "--secret-key", SECRET_KEY])
            .arg(root)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| setup(&format!("starting {}", binary.display()), e))?;
        let server = Self {
            address,
            root: root.to_path_buf(),
            child,
        };
        let started = Instant::now();
        while TcpStream::connect(address).is_err() {
            if started.elapsed() > START_TIMEOUT {
                return Err(BenchError::Scratch(format!(
                    "{} did not listen on {address} within {START_TIMEOUT:?}",
                    binary.display()
                )));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        Ok(server)
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

    /// Every object file of `bucket` (the server's own bookkeeping, dot files, left out).
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
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
