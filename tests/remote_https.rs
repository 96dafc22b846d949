//! A COPC file rendered by `https://` URL from a real nginx whose certificate a private CA
//! signed (made by the test, as the TLS tests make theirs): trusted through `SSL_CERT_FILE`,
//! the usual setting, the frame equals the file's rendered here; without the CA the render
//! is refused in one line naming the URL. Skips, saying so, where nginx is not installed.

use std::path::Path;
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use pointfarm_tests::nginx::NginxServer;
use pointfarm_tests::pki::TestPki;
use pointfarm_tests::{
    assert_one_error_line, copc_file, free_address, output_text, pointfarm_bin, pointfarm_ok,
};

fn arg(path: &Path) -> &str {
    path.to_str().expect("temporary paths are UTF-8")
}

/// nginx serving `root` over TLS with `pki`'s certificate on a loopback port; killed when
/// dropped.
struct TlsNginx {
    address: String,
    child: Child,
}

impl TlsNginx {
    fn start(binary: &Path, dir: &Path, root: &Path, pki: &TestPki) -> Self {
        let address = free_address();
        let config = format!(
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
        listen {address} ssl;
        ssl_certificate {cert};
        ssl_certificate_key {key};
        root {root};
    }}
}}
",
            dir = dir.display(),
            cert = pki.cert.display(),
            key = pki.key.display(),
            root = root.display(),
        );
        let config_path = dir.join("nginx.conf");
        std::fs::write(&config_path, config).expect("nginx.conf");
        let child = Command::new(binary)
            .arg("-p")
            .arg(dir)
            .arg("-c")
            .arg(&config_path)
            .arg("-e")
            .arg(dir.join("error.log"))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start nginx");
        let started = Instant::now();
        while std::net::TcpStream::connect(&address).is_err() {
            assert!(
                started.elapsed() < Duration::from_secs(10),
                "nginx did not listen: {}",
                std::fs::read_to_string(dir.join("error.log")).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        Self { address, child }
    }
}

impl Drop for TlsNginx {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `pointfarm render URL --out OUT ARGS` trusting the roots in `ca` alone.
fn render_trusting(ca: &Path, url: &str, out: &Path, args: &[&str]) -> Output {
    Command::new(pointfarm_bin())
        .args(["render", url, "--out", arg(out)])
        .args(args)
        .env("SSL_CERT_FILE", ca)
        .env_remove("SSL_CERT_DIR")
        .output()
        .expect("run pointfarm")
}

#[test]
fn a_copc_file_over_https_from_a_private_ca_renders_as_the_file_here() {
    let Some(binary) = NginxServer::binary() else {
        eprintln!("skipped: nginx is not installed (deploy/test.sh installs nginx-light)");
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let pki = TestPki::create(dir.path());
    let root = dir.path().join("root");
    std::fs::create_dir_all(root.join("scans")).expect("scans folder");
    let local = copc_file("simple_with_page.copc.laz");
    std::fs::copy(&local, root.join("scans/scan.copc.laz")).expect("served file");
    let nginx_dir = dir.path().join("nginx");
    std::fs::create_dir_all(&nginx_dir).expect("nginx folder");
    let server = TlsNginx::start(&binary, &nginx_dir, &root, &pki);
    let url = format!("https://{}/scans/scan.copc.laz", server.address);

    let args = ["--size=200x150", "--point-size=3", "--lod-error", "0"];
    let here = dir.path().join("here.png");
    let cache = dir.path().join("cache");
    let mut local_args = vec!["render", arg(&local), "--out", arg(&here)];
    local_args.extend(args);
    local_args.extend(["--cache-dir", arg(&cache)]);
    pointfarm_ok(&local_args);

    let by_url = dir.path().join("https.png");
    let output = render_trusting(&pki.ca, &url, &by_url, &args);
    assert!(output.status.success(), "{}", output_text(&output));
    let image = |path: &Path| image::open(path).expect("png").to_rgba8();
    assert!(image(&here) == image(&by_url), "the same pixels");

    // The system's roots do not hold the private CA: refused, in one line naming the URL.
    let system_roots = Path::new("/etc/ssl/certs/ca-certificates.crt");
    if system_roots.is_file() {
        let refused = render_trusting(system_roots, &url, &dir.path().join("no.png"), &args);
        assert_one_error_line(&refused, &[&url]);
    }
}
