//! Web servers that redirect or ignore ranges, with real nginx servers on loopback, the real
//! `pointfarm` binary rendering by URL here, and a real `pointfarm serve --allow-url-prefix`
//! with its embedded worker. A redirect is followed only within the origin asked (and, by the
//! daemon, only under its allowed prefixes): a redirect to another origin, out of the allowed
//! prefixes, into a loop, to `file://` or to a metadata address fails in one line naming it
//! and the rule, and nginx's log shows no request reached what was refused; over HTTPS from a
//! private CA a redirect to the same host by plain HTTP is refused too. A server that
//! answers a range request with the whole object (`max_ranges 0;`) is refused at its answer's
//! headers: of a 512 MiB object the server sends a few buffers at most, the daemon's and the
//! worker's peak memory stay put, and the frame fails once, without retries. Each test skips,
//! saying so, where nginx is not installed.

use std::path::Path;
use std::time::{Duration, Instant};

use pointfarm_tests::nginx::NginxServer;
use pointfarm_tests::{
    assert_one_error_line, copc_file, free_address, output_text, path_arg, pointfarm, pointfarm_ok,
    stdout, ServeProcess,
};

const SCAN: &str = "scans/scan.copc.laz";

/// The size of the object served without ranges: far above any bound a reader keeps.
const LARGE_OBJECT_BYTES: u64 = 512 << 20;

/// The most a reader refusing the answer may let the server send or grow by: a few socket
/// buffers, and nothing near the object's size.
const BOUND_BYTES: u64 = 64 << 20;

/// A new folder whose `folders` each hold a copy of a small COPC file as `scan.copc.laz`.
fn served_root(folders: &[&str]) -> tempfile::TempDir {
    let root = tempfile::tempdir().expect("root");
    for folder in folders {
        let dir = root.path().join(folder);
        std::fs::create_dir_all(&dir).expect("folder");
        std::fs::copy(copc_file("simple.copc.laz"), dir.join("scan.copc.laz")).expect("a scan");
    }
    root
}

/// The origin asked (`front`, whose `scans/` answers redirects) and another origin (`other`)
/// holding the scan its redirect points to, with their folders.
struct Origins {
    front: NginxServer,
    other: NginxServer,
    _roots: [tempfile::TempDir; 2],
}

/// The redirects `front` answers, each a name under `scans/` and where it points.
fn redirects(front: &str, other: &str) -> Vec<(&'static str, String)> {
    vec![
        ("moved.copc.laz", format!("http://{front}/{SCAN}")),
        ("elsewhere.copc.laz", format!("http://{other}/{SCAN}")),
        (
            "outside.copc.laz",
            format!("http://{front}/private/scan.copc.laz"),
        ),
        (
            "loop-a.copc.laz",
            format!("http://{front}/scans/loop-b.copc.laz"),
        ),
        (
            "loop-b.copc.laz",
            format!("http://{front}/scans/loop-a.copc.laz"),
        ),
        ("file.copc.laz", "file:///etc/passwd".to_owned()),
        (
            "metadata.copc.laz",
            "http://169.254.169.254/latest/meta-data/".to_owned(),
        ),
    ]
}

fn origins() -> Option<Origins> {
    let other_root = served_root(&["scans"]);
    let other = NginxServer::start_configured_or_skip(other_root.path(), None, "")?;
    let front_root = served_root(&["scans", "private"]);
    let address = free_address();
    let directives: String = redirects(&address, &other.address)
        .iter()
        .map(|(name, to)| format!("location = /scans/{name} {{ return 302 {to}; }}\n"))
        .collect();
    let front =
        NginxServer::start_configured_or_skip(front_root.path(), Some(&address), &directives)?;
    Some(Origins {
        front,
        other,
        _roots: [front_root, other_root],
    })
}

/// The requests of an access log, as `METHOD PATH`, with their status and body bytes sent.
fn requests(log: &[String]) -> Vec<(String, u16, u64)> {
    log.iter()
        .filter_map(|line| {
            let mut parts = line.split('"');
            let request = parts.nth(1)?;
            let mut answer = parts.next()?.split_whitespace();
            let status = answer.next()?.parse().ok()?;
            let sent = answer.next()?.parse().ok()?;
            let method_path = request.rsplit_once(' ').map_or(request, |(head, _)| head);
            Some((method_path.to_owned(), status, sent))
        })
        .collect()
}

/// `pointfarm render URL --out OUT --size=160x120`.
fn render_url(url: &str, out: &Path) -> std::process::Output {
    pointfarm(&["render", url, "--out", path_arg(out), "--size=160x120"])
}

/// The refusals every reader makes, with what each must say.
fn refused_everywhere(origins: &Origins) -> Vec<(String, Vec<String>)> {
    let front = &origins.front;
    let origin = format!("http://{}", front.address);
    let other = origins.other.url(SCAN);
    vec![
        (
            front.url("scans/elsewhere.copc.laz"),
            vec![other, "only within the origin asked".into(), origin.clone()],
        ),
        (
            front.url("scans/loop-a.copc.laz"),
            vec!["the redirects loop back to".into()],
        ),
        (
            front.url("scans/file.copc.laz"),
            vec!["file:///etc/passwd".into(), origin.clone()],
        ),
        (
            front.url("scans/metadata.copc.laz"),
            vec!["169.254.169.254".into(), origin],
        ),
    ]
}

/// Asserts that no request reached the other origin, nor the front's private folder.
fn assert_nothing_refused_was_asked(origins: &Origins) {
    assert!(
        origins.other.access_log(0).is_empty(),
        "{:?}",
        origins.other.access_log(0)
    );
    let front = requests(&origins.front.access_log(1));
    assert!(
        front
            .iter()
            .all(|(request, ..)| !request.contains("/private/")),
        "{front:?}"
    );
}

#[test]
fn a_local_render_follows_a_redirect_only_within_the_origin_asked() {
    let Some(origins) = origins() else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let moved = dir.path().join("moved.png");
    let output = render_url(&origins.front.url("scans/moved.copc.laz"), &moved);
    assert!(output.status.success(), "{}", output_text(&output));
    let direct = dir.path().join("direct.png");
    pointfarm_ok(&[
        "render",
        &origins.front.url(SCAN),
        "--out",
        path_arg(&direct),
        "--size=160x120",
    ]);
    let image = |path: &Path| image::open(path).expect("png").to_rgba8();
    assert!(
        image(&moved) == image(&direct),
        "the redirect's target drawn"
    );

    for (url, says) in refused_everywhere(&origins) {
        let output = render_url(&url, &dir.path().join("refused.png"));
        let mut needles: Vec<&str> = vec![&url, "redirected to"];
        needles.extend(says.iter().map(String::as_str));
        assert_one_error_line(&output, &needles);
    }
    assert!(!dir.path().join("refused.png").exists());
    assert_nothing_refused_was_asked(&origins);
    // Each refusal is one request: never retried.
    let loops = requests(&origins.front.access_log(1))
        .into_iter()
        .filter(|(request, ..)| request.contains("/scans/loop-"))
        .count();
    assert!(loops <= 3, "{loops} requests of the loop");
}

#[test]
fn over_https_a_redirect_stays_on_https_and_the_private_ca_is_still_trusted() {
    let dir = tempfile::tempdir().expect("tempdir");
    let pki = pointfarm_tests::pki::TestPki::create(dir.path());
    let root = served_root(&["scans"]);
    let address = free_address();
    let directives = format!(
        "location = /scans/moved.copc.laz {{ return 302 https://{address}/{SCAN}; }}\n\
         location = /scans/plain.copc.laz {{ return 302 http://{address}/{SCAN}; }}\n"
    );
    let Some(server) =
        NginxServer::start_tls_configured_or_skip(root.path(), &pki, &address, &directives)
    else {
        return;
    };
    let render = |name: &str, out: &Path| {
        std::process::Command::new(pointfarm_tests::pointfarm_bin())
            .args(["render", &server.https_url(name), "--out", path_arg(out)])
            .arg("--size=160x120")
            .env("SSL_CERT_FILE", &pki.ca)
            .env_remove("SSL_CERT_DIR")
            .output()
            .expect("run pointfarm")
    };
    let moved = render("scans/moved.copc.laz", &dir.path().join("moved.png"));
    assert!(moved.status.success(), "{}", output_text(&moved));
    let plain = server.https_url("scans/plain.copc.laz");
    let refused = render("scans/plain.copc.laz", &dir.path().join("plain.png"));
    let target = format!("http://{address}/{SCAN}");
    let needles = [
        &plain,
        "redirected to",
        &target,
        "only within the origin asked",
    ];
    assert_one_error_line(&refused, &needles);
}

/// `pointfarm ARGS --server ADDRESS`.
fn on(daemon: &ServeProcess, args: &[&str]) -> std::process::Output {
    pointfarm(&[args, &["--server", &daemon.address]].concat())
}

/// The id of the dataset `dataset register URL` answers, which must succeed.
fn register(daemon: &ServeProcess, url: &str) -> String {
    let output = on(daemon, &["dataset", "register", url, "--json"]);
    assert!(output.status.success(), "{}", output_text(&output));
    let dataset: serde_json::Value =
        serde_json::from_str(stdout(&output).trim()).expect("one JSON line");
    dataset["id"].as_str().expect("an id").to_owned()
}

#[test]
fn a_daemon_follows_a_redirect_only_within_the_origin_and_its_allowed_prefixes() {
    let Some(origins) = origins() else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let allowed = origins.front.url("scans/");
    // The other origin is allowed too: a redirect there is still not followed.
    let also = origins.other.url("scans/");
    let args = ["--allow-url-prefix", &allowed, "--allow-url-prefix", &also];
    let daemon = ServeProcess::start_with(&dir.path().join("data"), &args);

    let id = register(&daemon, &origins.front.url("scans/moved.copc.laz"));
    let frame = dir.path().join("frame.png");
    let output = on(
        &daemon,
        &[
            "render",
            "--dataset",
            &id,
            "--size=160x120",
            "--out",
            path_arg(&frame),
        ],
    );
    assert!(output.status.success(), "{}", output_text(&output));
    assert!(frame.is_file());

    let outside = origins.front.url("scans/outside.copc.laz");
    let rule = format!("the operator allows only {allowed}");
    let refused = on(&daemon, &["dataset", "register", &outside]);
    let needles = [&outside, PRECONDITION, "redirected to", "/private/", &rule];
    assert_one_error_line(&refused, &needles);
    for (url, says) in refused_everywhere(&origins) {
        let refused = on(&daemon, &["dataset", "register", &url]);
        let mut needles: Vec<&str> = vec![&url, PRECONDITION, "redirected to"];
        needles.extend(says.iter().map(String::as_str));
        assert_one_error_line(&refused, &needles);
    }
    assert_nothing_refused_was_asked(&origins);
    let listed = on(&daemon, &["dataset", "list", "--json"]);
    assert!(listed.status.success(), "{}", output_text(&listed));
    assert_eq!(stdout(&listed).matches("\"id\"").count(), 1, "one dataset");
}

/// A folder whose `scans/large.copc.laz` is a valid COPC head followed by zeros up to
/// [`LARGE_OBJECT_BYTES`], a sparse file that costs no disk.
fn large_object_root() -> tempfile::TempDir {
    let root = tempfile::tempdir().expect("root");
    std::fs::create_dir(root.path().join("scans")).expect("scans");
    let path = root.path().join("scans/large.copc.laz");
    std::fs::copy(copc_file("simple.copc.laz"), &path).expect("a scan");
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(&path)
        .expect("open");
    file.set_len(LARGE_OBJECT_BYTES).expect("extend");
    root
}

/// A process's peak resident memory so far, in bytes.
fn peak_bytes(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("its status");
    let kib: u64 = status
        .lines()
        .find_map(|line| line.strip_prefix("VmHWM:"))
        .and_then(|value| value.split_whitespace().next()?.parse().ok())
        .expect("VmHWM");
    kib << 10
}

/// The GETs nginx logged, once there are at least `at_least` or a few seconds passed: nginx
/// logs an answer the client dropped only once it notices, after the client has moved on.
fn logged_gets(server: &NginxServer, at_least: usize) -> Vec<(String, u16, u64)> {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let gets: Vec<(String, u16, u64)> = requests(&server.access_log(0))
            .into_iter()
            .filter(|(request, ..)| request.starts_with("GET "))
            .collect();
        if gets.len() >= at_least || Instant::now() > deadline {
            return gets;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Asserts that the GETs nginx answered (at least `at_least` of them) sent few bytes in all,
/// and returns how many there were.
fn assert_little_sent(server: &NginxServer, at_least: usize) -> usize {
    let gets = logged_gets(server, at_least);
    assert!(gets.len() >= at_least, "{gets:?}");
    let sent: u64 = gets.iter().map(|(.., sent)| sent).sum();
    eprintln!("nginx sent {sent} bytes in {} GETs", gets.len());
    assert!(sent < BOUND_BYTES, "{sent} bytes sent: {gets:?}");
    assert!(gets.iter().all(|(_, status, _)| *status == 200), "{gets:?}");
    gets.len()
}

/// How the CLI words the status of a refusal the server's configuration causes.
const PRECONDITION: &str = "failed precondition";

const IGNORED: &str = "the server ignored the range request of bytes";

#[test]
fn a_server_ignoring_ranges_is_refused_without_pulling_the_object() {
    let root = large_object_root();
    let Some(server) = NginxServer::start_configured_or_skip(root.path(), None, "max_ranges 0;")
    else {
        return;
    };
    let url = server.url("scans/large.copc.laz");
    let dir = tempfile::tempdir().expect("tempdir");
    let output = render_url(&url, &dir.path().join("frame.png"));
    assert_one_error_line(&output, &[&url, IGNORED, "206 Partial Content"]);
    let gets = assert_little_sent(&server, 1);
    assert_eq!(gets, 1, "refused once, not retried");

    let allowed = server.url("scans/");
    let daemon =
        ServeProcess::start_with(&dir.path().join("data"), &["--allow-url-prefix", &allowed]);
    let before = peak_bytes(daemon.pid());
    let refused = on(&daemon, &["dataset", "register", &url]);
    assert_one_error_line(&refused, &[&url, PRECONDITION, IGNORED]);
    let grown = peak_bytes(daemon.pid()).saturating_sub(before);
    eprintln!("the daemon's peak grew by {grown} bytes");
    assert!(
        grown < BOUND_BYTES,
        "the daemon's peak grew by {grown} bytes"
    );
    assert_eq!(
        assert_little_sent(&server, 2),
        2,
        "refused once, not retried"
    );
}

#[test]
fn a_worker_meeting_a_server_that_stopped_answering_ranges_fails_the_frame_once() {
    let root = large_object_root();
    let address = free_address();
    let Some(ranged) = NginxServer::start_configured_or_skip(root.path(), Some(&address), "")
    else {
        return;
    };
    let url = ranged.url("scans/large.copc.laz");
    let dir = tempfile::tempdir().expect("tempdir");
    let allowed = ranged.url("scans/");
    let daemon =
        ServeProcess::start_with(&dir.path().join("data"), &["--allow-url-prefix", &allowed]);
    let id = register(&daemon, &url);
    // A frame of another object first, so that the worker's GPU and caches are set up
    // before its peak is taken.
    std::fs::copy(copc_file("simple.copc.laz"), root.path().join(SCAN)).expect("a scan");
    let warm = register(&daemon, &ranged.url(SCAN));
    let render = |id: &str, out: &Path| {
        let args = ["render", "--dataset", id, "--size=160x120"];
        on(&daemon, &[&args[..], &["--out", path_arg(out)]].concat())
    };
    let warmed = render(&warm, &dir.path().join("warm.png"));
    assert!(warmed.status.success(), "{}", output_text(&warmed));
    // The same file, at the same address and ETag, now served without ranges.
    drop(ranged);
    let whole = NginxServer::start_configured_or_skip(root.path(), Some(&address), "max_ranges 0;")
        .expect("nginx again");
    let worker = daemon.embedded_worker_pid();
    let before = peak_bytes(worker);
    let frame = dir.path().join("frame.png");
    let failed = render(&id, &frame);
    assert!(!failed.status.success(), "{}", output_text(&failed));
    assert!(
        output_text(&failed).contains(IGNORED),
        "{}",
        output_text(&failed)
    );
    assert!(!frame.exists());
    let grown = peak_bytes(worker).saturating_sub(before);
    eprintln!("the worker's peak grew by {grown} bytes");
    assert!(
        grown < BOUND_BYTES,
        "the worker's peak grew by {grown} bytes"
    );
    // A permanent failure: the frame is not leased again and again.
    let gets = assert_little_sent(&whole, 1);
    assert!(gets <= 2, "{gets} GETs");
    std::thread::sleep(Duration::from_millis(500));
    let after = assert_little_sent(&whole, gets);
    assert_eq!(after, gets, "no retries after the failure");
}
