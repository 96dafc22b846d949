//! A real nginx serving a folder on a loopback port, for the tests that read datasets over
//! HTTP or HTTPS: ranges, ETags and `If-Match` as a production server answers them.

use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::free_address;
use crate::pki::TestPki;
use crate::tools::ServerChild;

/// Where Debian's nginx packages put the binary.
const NGINX: &str = "/usr/sbin/nginx";

/// How long nginx may take to listen.
const START_TIMEOUT: Duration = Duration::from_secs(10);

/// An nginx child process serving `root` on `address`; killed when dropped. Its config, pid,
/// logs and temporary folders are in a folder of its own, so it needs no privileges.
pub struct NginxServer {
    pub address: String,
    pub root: PathBuf,
    child: ServerChild,
    dir: tempfile::TempDir,
}

impl NginxServer {
    /// The nginx binary, or None where it is not installed (deploy/test.sh installs it).
    pub fn binary() -> Option<PathBuf> {
        let path = Path::new(NGINX);
        path.is_file().then(|| path.to_owned())
    }

    /// Starts nginx serving `root`, or None, having said why, where nginx is not installed.
    pub fn start_or_skip(root: &Path) -> Option<Self> {
        let binary = Self::binary_or_skip()?;
        Some(Self::start(&binary, root, None))
    }

    /// Starts nginx serving `root` over TLS with `pki`'s certificate (see [`Self::https_url`]),
    /// or None, having said why, where nginx is not installed.
    pub fn start_tls_or_skip(root: &Path, pki: &TestPki) -> Option<Self> {
        let binary = Self::binary_or_skip()?;
        Some(Self::start(&binary, root, Some(pki)))
    }

    /// Starts nginx serving a new folder whose `scans/` holds `files` (name, bytes), or None,
    /// having said why, where nginx is not installed. The folder lasts as long as the TempDir.
    pub fn serve_scans(files: &[(&str, Vec<u8>)]) -> Option<(tempfile::TempDir, Self)> {
        let binary = Self::binary_or_skip()?;
        let root = tempfile::tempdir().expect("root");
        std::fs::create_dir(root.path().join("scans")).expect("scans folder");
        for (name, bytes) in files {
            std::fs::write(root.path().join("scans").join(name), bytes).expect("served file");
        }
        let server = Self::start(&binary, root.path(), None);
        Some((root, server))
    }

    /// Starts nginx serving `root` with `directives` added to its server block (a location
    /// that redirects, `max_ranges 0;`), on `address` or a free one, or None, having said why,
    /// where nginx is not installed.
    pub fn start_configured_or_skip(
        root: &Path,
        address: Option<&str>,
        directives: &str,
    ) -> Option<Self> {
        let binary = Self::binary_or_skip()?;
        Some(Self::start_at(&binary, root, None, address, directives))
    }

    /// Starts nginx serving `root` over TLS with `pki`'s certificate and `directives` added
    /// to its server block, on `address`, or None, having said why, where nginx is not
    /// installed.
    pub fn start_tls_configured_or_skip(
        root: &Path,
        pki: &TestPki,
        address: &str,
        directives: &str,
    ) -> Option<Self> {
        let binary = Self::binary_or_skip()?;
        Some(Self::start_at(
            &binary,
            root,
            Some(pki),
            Some(address),
            directives,
        ))
    }

    fn binary_or_skip() -> Option<PathBuf> {
        let binary = Self::binary();
        if binary.is_none() {
            eprintln!("skipped: nginx is not installed (deploy/test.sh installs nginx-light)");
        }
        binary
    }

    fn start(binary: &Path, root: &Path, tls: Option<&TestPki>) -> Self {
        Self::start_at(binary, root, tls, None, "")
    }

    fn start_at(
        binary: &Path,
        root: &Path,
        tls: Option<&TestPki>,
        address: Option<&str>,
        directives: &str,
    ) -> Self {
        let dir = tempfile::tempdir().expect("nginx folder");
        let address = address.map_or_else(free_address, str::to_owned);
        let config = config(dir.path(), &address, root, tls, directives);
        let config_path = dir.path().join("nginx.conf");
        std::fs::write(&config_path, config).expect("nginx.conf");
        let error_log = dir.path().join("error.log");
        let child = ServerChild::spawn(
            Command::new(binary)
                .arg("-p")
                .arg(dir.path())
                .arg("-c")
                .arg(&config_path)
                .arg("-e")
                .arg(&error_log)
                .stdin(Stdio::null())
                .stderr(
                    std::fs::File::create(dir.path().join("stderr.log")).expect("nginx stderr"),
                ),
            "nginx",
        );
        let mut server = Self {
            address,
            root: root.to_owned(),
            child,
            dir,
        };
        server.wait_until_listening();
        server
    }

    /// `http://ADDRESS/` followed by `path`.
    pub fn url(&self, path: &str) -> String {
        format!("http://{}/{}", self.address, path.trim_start_matches('/'))
    }

    /// `https://ADDRESS/` followed by `path`, for a server started with TLS.
    pub fn https_url(&self, path: &str) -> String {
        format!("https://{}/{}", self.address, path.trim_start_matches('/'))
    }

    /// The requests nginx answered, one access-log line each, once there are at least
    /// `expected` of them or a few seconds passed: nginx logs a request after its answer
    /// left, so a client can read the answer before the line is written.
    pub fn access_log(&self, expected: usize) -> Vec<String> {
        let started = Instant::now();
        loop {
            let lines: Vec<String> = std::fs::read_to_string(self.dir.path().join("access.log"))
                .unwrap_or_default()
                .lines()
                .map(str::to_owned)
                .collect();
            if lines.len() >= expected || started.elapsed() > START_TIMEOUT {
                return lines;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn wait_until_listening(&mut self) {
        let started = Instant::now();
        while TcpStream::connect(&self.address).is_err() {
            if let Some(status) = self.child.exited() {
                panic!("nginx exited with {status}: {}", self.logs());
            }
            assert!(
                started.elapsed() < START_TIMEOUT,
                "nginx did not listen on {} within {START_TIMEOUT:?}: {}",
                self.address,
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn logs(&self) -> String {
        ["stderr.log", "error.log"]
            .iter()
            .map(|name| std::fs::read_to_string(self.dir.path().join(name)).unwrap_or_default())
            .collect::<Vec<_>>()
            .join("\n")
    }
}

/// One process (no master, so a kill ends it), in the foreground, every path in `dir`;
/// everything under `/denied/` is refused with 403. With `tls`, it answers HTTPS alone.
fn config(
    dir: &Path,
    address: &str,
    root: &Path,
    tls: Option<&TestPki>,
    directives: &str,
) -> String {
    let dir = dir.display();
    let root = root.display();
    let listen = match tls {
        None => format!("listen {address};"),
        Some(pki) => format!(
            "listen {address} ssl;\n        ssl_certificate {};\n        ssl_certificate_key {};",
            pki.cert.display(),
            pki.key.display()
        ),
    };
    format!(
        "daemon off;
master_process off;
worker_processes 1;
pid {dir}/nginx.pid;
error_log {dir}/error.log info;
events {{ worker_connections 64; }}
http {{
    access_log {dir}/access.log;
    client_body_temp_path {dir}/client_body;
    proxy_temp_path {dir}/proxy;
    fastcgi_temp_path {dir}/fastcgi;
    uwsgi_temp_path {dir}/uwsgi;
    scgi_temp_path {dir}/scgi;
    default_type application/octet-stream;
    server {{
        {listen}
        root {root};
        # What a server answers a request it refuses.
        location /denied/ {{ return 403; }}
        {directives}
    }}
}}
"
    )
}
