//! The remote storage layer against a real nginx on loopback: ranges, coalescing, versions
//! pinned by ETag, missing objects, stalls and the operator's allow-list. Each test skips,
//! saying so, where nginx is not installed.

use std::net::TcpListener;
use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime};

use pointfarm_render::remote::{
    AllowedPrefixes, ObjectUrl, RemoteClient, RemoteError, RemoteObject, RemoteSettings,
};
use pointfarm_tests::copc_file;
use pointfarm_tests::nginx::NginxServer;
use pointfarm_tests::s3s::{self, S3sServer};

/// The LAS header of a COPC file (LAS 1.4).
const LAS_HEADER_LEN: u64 = 375;

/// The COPC file every test serves.
fn simple_copc() -> PathBuf {
    copc_file("simple.copc.laz")
}

/// nginx serving a folder whose `scans/` holds a copy of the COPC file; None, having said why,
/// where nginx is not installed.
fn served_copc() -> Option<(tempfile::TempDir, NginxServer)> {
    let bytes = std::fs::read(simple_copc()).expect("COPC file");
    NginxServer::serve_scans(&[("simple.copc.laz", bytes)])
}

fn client() -> RemoteClient {
    RemoteClient::new(RemoteSettings::default()).expect("client")
}

/// `url` opened by `client`, which must succeed.
fn open(client: &RemoteClient, url: &str) -> RemoteObject {
    client
        .open(&ObjectUrl::parse(url).expect("url"))
        .expect("open")
}

/// The error of opening `url` with `client`, which must fail.
fn open_error(client: &RemoteClient, url: &str) -> RemoteError {
    client
        .open(&ObjectUrl::parse(url).expect("url"))
        .expect_err("the open fails")
}

#[test]
fn reads_the_las_header_by_range() {
    let Some((_root, server)) = served_copc() else {
        return;
    };
    let local = std::fs::read(simple_copc()).expect("local file");
    let client = client();
    let object = open(&client, &server.url("scans/simple.copc.laz"));
    assert_eq!(object.size(), local.len() as u64);
    assert!(object.version().is_some(), "nginx sends an ETag");
    let header = object.read_range(0..LAS_HEADER_LEN).expect("header");
    assert_eq!(&header[..4], b"LASF");
    assert_eq!(header, local[..LAS_HEADER_LEN as usize]);
    let tail = object
        .read_range(object.size() - 100..object.size())
        .expect("tail");
    assert_eq!(tail, local[local.len() - 100..]);
    let counts = client.counts();
    assert_eq!(counts.requests, 3, "a HEAD and two GETs");
    assert_eq!(counts.bytes, LAS_HEADER_LEN + 100);
    let log = server.access_log(3);
    assert_eq!(log.len(), 3, "{log:?}");
}

#[test]
fn coalesces_near_ranges_into_parallel_requests() {
    let Some((_root, server)) = served_copc() else {
        return;
    };
    let local = std::fs::read(simple_copc()).expect("local file");
    let size = local.len() as u64;
    let client = RemoteClient::new(RemoteSettings {
        coalesce_gap: 1000,
        ..RemoteSettings::default()
    })
    .expect("client");
    let object = open(&client, &server.url("scans/simple.copc.laz"));
    // Two groups of near ranges, far apart, asked out of order, one of them empty.
    let ranges = [
        size - 200..size - 100,
        0..LAS_HEADER_LEN,
        400..900,
        size - 50..size,
        1200..1300,
        10_000..10_000,
    ];
    let parts = object.read_ranges(&ranges).expect("ranges");
    for (range, part) in ranges.iter().zip(&parts) {
        assert_eq!(
            part[..],
            local[range.start as usize..range.end as usize],
            "{range:?}"
        );
    }
    let counts = client.counts();
    assert_eq!(counts.requests, 3, "a HEAD and one GET per group");
    assert_eq!(counts.bytes, 1300 + 200);
    let log = server.access_log(3);
    let gets: Vec<&String> = log.iter().filter(|line| line.contains("\"GET ")).collect();
    assert_eq!(gets.len(), 2, "{log:?}");
    assert!(
        gets.iter().all(|line| line.contains(" 206 ")),
        "only partial answers: {log:?}"
    );
}

#[test]
fn a_read_past_the_end_is_refused_before_any_request() {
    let Some((_root, server)) = served_copc() else {
        return;
    };
    let client = client();
    let object = open(&client, &server.url("scans/simple.copc.laz"));
    let size = object.size();
    let error = object
        .read_range(size - 10..size + 1)
        .expect_err("past the end");
    assert!(
        matches!(error, RemoteError::RangeOutOfBounds { .. }),
        "{error}"
    );
    assert!(error.to_string().contains("simple.copc.laz"), "{error}");
    assert_eq!(client.counts().requests, 1, "only the HEAD");
}

/// The error of opening `path` of the served folder, which must fail naming its URL; None
/// where nginx is not installed.
fn served_open_error(path: &str) -> Option<RemoteError> {
    let (_root, server) = served_copc()?;
    let url = server.url(path);
    let error = open_error(&client(), &url);
    assert!(error.to_string().contains(&url), "{error}");
    Some(error)
}

#[test]
fn a_missing_object_is_named() {
    let Some(error) = served_open_error("scans/absent.copc.laz") else {
        return;
    };
    assert!(matches!(error, RemoteError::NotFound { .. }), "{error}");
}

#[test]
fn a_refused_object_is_denied_and_named() {
    let Some(error) = served_open_error("denied/simple.copc.laz") else {
        return;
    };
    assert!(matches!(error, RemoteError::Denied { .. }), "{error}");
    assert!(error.to_string().contains("403"), "{error}");
}

#[test]
fn an_object_replaced_after_open_is_object_changed() {
    let Some((root, server)) = served_copc() else {
        return;
    };
    let url = server.url("scans/simple.copc.laz");
    let client = client();
    let object = open(&client, &url);
    object
        .read_range(0..LAS_HEADER_LEN)
        .expect("before the change");
    // Another version of the same size, so only the version tells them apart.
    let path = root.path().join("scans/simple.copc.laz");
    let replacement = root.path().join("scans/replacement.tmp");
    let mut bytes = std::fs::read(&path).expect("bytes");
    bytes[LAS_HEADER_LEN as usize] ^= 0xff;
    std::fs::write(&replacement, &bytes).expect("replacement");
    let file = std::fs::File::options()
        .write(true)
        .open(&replacement)
        .expect("open replacement");
    file.set_modified(SystemTime::now() + Duration::from_secs(60))
        .expect("newer modification time");
    drop(file);
    std::fs::rename(&replacement, &path).expect("replace");
    let error = object
        .read_ranges(&[0..LAS_HEADER_LEN, 1000..2000])
        .expect_err("changed");
    assert!(
        matches!(error, RemoteError::ObjectChanged { .. }),
        "{error}"
    );
    assert!(error.to_string().contains(&url), "{error}");
    // Opened again, the new version reads.
    let reopened = open(&client, &url);
    assert_ne!(reopened.version(), object.version());
    let after = reopened
        .read_range(LAS_HEADER_LEN..LAS_HEADER_LEN + 1)
        .expect("new version");
    assert_eq!(after[0], bytes[LAS_HEADER_LEN as usize]);
}

#[test]
fn a_plain_http_server_cannot_be_listed_and_says_why() {
    let Some((_root, server)) = served_copc() else {
        return;
    };
    let prefix = ObjectUrl::parse(&server.url("scans/")).expect("url");
    let error = client().list_point_files(&prefix).expect_err("no WebDAV");
    assert!(matches!(error, RemoteError::Listing { .. }), "{error}");
    assert!(error.to_string().contains("WebDAV"), "{error}");
    assert!(error.to_string().contains(prefix.as_str()), "{error}");
}

/// A server that accepts connections and never answers.
fn stalled_server() -> (TcpListener, std::thread::JoinHandle<()>, String) {
    let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
    let address = listener.local_addr().expect("address").to_string();
    let accepting = listener.try_clone().expect("listener");
    let handle = std::thread::spawn(move || {
        let mut held = Vec::new();
        while let Ok((stream, _)) = accepting.accept() {
            held.push(stream);
            if held.len() > 16 {
                break;
            }
        }
    });
    (listener, handle, address)
}

/// The error of opening an object on a server that never answers, with `settings`, which must
/// name its URL; and how long the open took.
fn open_stalled(settings: RemoteSettings) -> (RemoteError, Duration) {
    let (_listener, _handle, address) = stalled_server();
    let client = RemoteClient::new(settings).expect("client");
    let url = format!("http://{address}/stalled.copc.laz");
    let started = Instant::now();
    let error = open_error(&client, &url);
    let took = started.elapsed();
    assert!(error.to_string().contains(&url), "{error}");
    (error, took)
}

#[test]
fn a_stalled_server_times_out_after_the_retries() {
    let (error, took) = open_stalled(RemoteSettings {
        connect_timeout: Duration::from_millis(300),
        request_timeout: Duration::from_millis(300),
        max_retries: 2,
        retry_timeout: Duration::from_secs(2),
        initial_backoff: Duration::from_millis(20),
        max_backoff: Duration::from_millis(100),
        operation_deadline: Duration::from_secs(20),
        ..RemoteSettings::default()
    });
    assert!(error.is_timeout(), "{error}");
    // Three attempts of 300 ms and two short backoffs, well inside the deadline.
    assert!(took >= Duration::from_millis(600), "{took:?}");
    assert!(took < Duration::from_secs(5), "{took:?}");
}

#[test]
fn the_operation_deadline_bounds_a_stall_whatever_the_retries() {
    let (error, took) = open_stalled(RemoteSettings {
        operation_deadline: Duration::from_secs(1),
        ..RemoteSettings::default()
    });
    assert!(matches!(error, RemoteError::TimedOut { .. }), "{error}");
    assert!(took < Duration::from_secs(3), "{took:?}");
}

#[test]
fn urls_outside_the_allowed_prefixes_are_refused_naming_the_rule() {
    let allowed = AllowedPrefixes::new(&["s3://campaigns/site-a/", "https://data.example/scans"])
        .expect("rules");
    let inside = ObjectUrl::parse("https://data.example/scans/tile.copc.laz").expect("url");
    assert!(allowed.check(&inside).is_ok());
    let outside = ObjectUrl::parse("s3://campaigns/site-b/tile.laz").expect("url");
    let error = allowed.check(&outside).expect_err("outside").to_string();
    assert!(error.contains("s3://campaigns/site-b/tile.laz"), "{error}");
    assert!(
        error.contains("allows only s3://campaigns/site-a/, https://data.example/scans"),
        "{error}"
    );
}

/// The URL the S3 test's child process reads, and the file behind it that it replaces.
const S3_URL_VARIABLE: &str = "POINTFARM_TEST_S3_URL";
const S3_FILE_VARIABLE: &str = "POINTFARM_TEST_S3_FILE";

#[test]
fn reads_from_an_s3_compatible_server() {
    let root = tempfile::tempdir().expect("root");
    let scans = root.path().join("pointfarm-test/scans");
    std::fs::create_dir_all(&scans).expect("bucket folder");
    let file = scans.join("simple.copc.laz");
    std::fs::copy(simple_copc(), &file).expect("copy");
    let Some(server) = S3sServer::start_or_skip(root.path()) else {
        return;
    };
    // Credentials reach object_store only through the environment, so the reads run in a
    // child process of this test binary with the server's.
    let output = std::process::Command::new(std::env::current_exe().expect("test binary"))
        .args([
            "--exact",
            "s3_reads_in_a_child_process",
            "--ignored",
            "--nocapture",
        ])
        .envs(server.environment())
        .env(S3_URL_VARIABLE, "s3://pointfarm-test/scans/simple.copc.laz")
        .env(S3_FILE_VARIABLE, &file)
        .output()
        .expect("run the child");
    let text = format!(
        "{}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(output.status.success(), "{text}");
    assert!(text.contains("1 passed"), "{text}");
    assert!(!text.contains(s3s::SECRET_KEY), "{text}");
}

#[test]
#[ignore = "run by reads_from_an_s3_compatible_server, with a server's credentials"]
fn s3_reads_in_a_child_process() {
    let url = std::env::var(S3_URL_VARIABLE).expect("the URL");
    let file = std::env::var(S3_FILE_VARIABLE).expect("the file");
    let local = std::fs::read(simple_copc()).expect("local file");
    let client = client();
    let object = open(&client, &url);
    assert_eq!(object.size(), local.len() as u64);
    let parts = object
        .read_ranges(&[0..LAS_HEADER_LEN, 1000..1100])
        .expect("ranges");
    assert_eq!(parts[0], local[..LAS_HEADER_LEN as usize]);
    assert_eq!(parts[1], local[1000..1100]);
    let listed = client
        .list_point_files(&ObjectUrl::parse("s3://pointfarm-test/scans/").expect("prefix"))
        .expect("list");
    assert_eq!(listed.len(), 1, "{listed:?}");
    assert_eq!(listed[0].url.as_str(), url);
    assert_eq!(listed[0].size, local.len() as u64);
    let missing = open_error(&client, "s3://pointfarm-test/scans/absent.laz");
    assert!(matches!(missing, RemoteError::NotFound { .. }), "{missing}");
    // Another version of the same size, written where the server keeps the object.
    let mut replaced = local.clone();
    replaced[LAS_HEADER_LEN as usize] ^= 0xff;
    let replacement = format!("{file}.new");
    std::fs::write(&replacement, &replaced).expect("replacement");
    std::fs::rename(&replacement, &file).expect("replace");
    let error = object
        .read_range(LAS_HEADER_LEN..LAS_HEADER_LEN + 10)
        .expect_err("changed");
    assert!(
        matches!(error, RemoteError::ObjectChanged { .. }),
        "{error}"
    );
    assert!(!format!("{client:?} {object:?}").contains(s3s::SECRET_KEY));
}
