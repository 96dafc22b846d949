//! A COPC file rendered by `https://` URL from a real nginx whose certificate a private CA
//! signed (made by the test, as the TLS tests make theirs): trusted through `SSL_CERT_FILE`,
//! the usual setting, the frame equals the file's rendered here; without the CA the render
//! is refused in one line naming the URL. Skips, saying so, where nginx is not installed.

use std::path::Path;
use std::process::{Command, Output};

use pointfarm_tests::nginx::NginxServer;
use pointfarm_tests::pki::TestPki;
use pointfarm_tests::{
    assert_one_error_line, copc_file, output_text, path_arg, pointfarm_bin, pointfarm_ok,
};

/// `pointfarm render URL --out OUT ARGS` trusting the roots in `ca` alone.
fn render_trusting(ca: &Path, url: &str, out: &Path, args: &[&str]) -> Output {
    Command::new(pointfarm_bin())
        .args(["render", url, "--out", path_arg(out)])
        .args(args)
        .env("SSL_CERT_FILE", ca)
        .env_remove("SSL_CERT_DIR")
        .output()
        .expect("run pointfarm")
}

#[test]
fn a_copc_file_over_https_from_a_private_ca_renders_as_the_file_here() {
    let dir = tempfile::tempdir().expect("tempdir");
    let pki = TestPki::create(dir.path());
    let root = dir.path().join("root");
    std::fs::create_dir_all(root.join("scans")).expect("scans folder");
    let local = copc_file("simple_with_page.copc.laz");
    std::fs::copy(&local, root.join("scans/scan.copc.laz")).expect("served file");
    let Some(server) = NginxServer::start_tls_or_skip(&root, &pki) else {
        return;
    };
    let url = server.https_url("scans/scan.copc.laz");

    let args = ["--size=200x150", "--point-size=3", "--lod-error", "0"];
    let here = dir.path().join("here.png");
    let cache = dir.path().join("cache");
    let mut local_args = vec!["render", path_arg(&local), "--out", path_arg(&here)];
    local_args.extend(args);
    local_args.extend(["--cache-dir", path_arg(&cache)]);
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
