//! A real Prometheus server (Debian's package) for the metrics tests, and the plain HTTP they
//! read `/metrics` and Prometheus's API with.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use crate::rest::try_request;
use crate::tools::ServerChild;
use crate::{free_address, wait_for};

/// Where Debian's `prometheus` package puts the server (`deploy/test.sh` installs it).
pub const PROMETHEUS: &str = "/usr/bin/prometheus";

/// Whether the Prometheus server is installed; says that the test skips when it is not.
pub fn prometheus_installed() -> bool {
    let installed = Path::new(PROMETHEUS).is_file();
    if !installed {
        eprintln!(
            "skipped: {PROMETHEUS} is missing (Debian's `prometheus` package; deploy/test.sh \
             installs it)"
        );
    }
    installed
}

/// `GET http://{address}{path}`: the status code and the body. HTTP/1.0, so that the answer
/// is the plain body up to the end of the connection.
pub fn http_get(address: &str, path: &str) -> std::io::Result<(u16, String)> {
    let answer = try_request(address, "GET", path, &[], &[])?;
    Ok((answer.status, answer.text()))
}

/// The metrics at `http://{address}/metrics`, by series (`name{labels}` as written).
pub fn scrape(address: &str) -> BTreeMap<String, f64> {
    let (status, body) = http_get(address, "/metrics").expect("GET /metrics");
    assert_eq!(status, 200, "{body}");
    assert!(body.ends_with("# EOF\n"), "{body}");
    body.lines()
        .filter(|line| !line.starts_with('#') && !line.is_empty())
        .map(|line| {
            let (series, value) = line.rsplit_once(' ').expect("series value");
            (series.to_owned(), value.parse().expect("a number"))
        })
        .collect()
}

/// A Prometheus server scraping `targets` every second as the job `pointfarm`; killed when
/// dropped.
pub struct Prometheus {
    address: String,
    _child: ServerChild,
    log: PathBuf,
}

impl Prometheus {
    /// Starts the server with its configuration and data in `dir`, and waits until it is ready.
    pub fn start(dir: &Path, targets: &[&str]) -> Self {
        let config = dir.join("prometheus.yml");
        let targets: Vec<String> = targets.iter().map(|t| format!("'{t}'")).collect();
        std::fs::write(
            &config,
            format!(
                "global:\n  scrape_interval: 1s\n  scrape_timeout: 1s\n\
                 scrape_configs:\n  - job_name: pointfarm\n    static_configs:\n      \
                 - targets: [{}]\n",
                targets.join(", ")
            ),
        )
        .expect("prometheus.yml");
        let address = free_address();
        let log = dir.join("prometheus.log");
        let child = ServerChild::spawn(
            Command::new(PROMETHEUS)
                .arg(format!("--config.file={}", config.display()))
                .arg(format!(
                    "--storage.tsdb.path={}",
                    dir.join("tsdb").display()
                ))
                .arg(format!("--web.listen-address={address}"))
                .stderr(std::fs::File::create(&log).expect("prometheus log")),
            "prometheus",
        );
        let prometheus = Self {
            address,
            _child: child,
            log,
        };
        wait_for(Duration::from_secs(60), "a ready Prometheus", || {
            matches!(http_get(&prometheus.address, "/-/ready"), Ok((200, _))).then_some(())
        });
        prometheus
    }

    /// The answer to the instant query `query`: its result's series, or Prometheus's error.
    pub fn query_series(&self, query: &str) -> Result<Vec<serde_json::Value>, String> {
        let path = format!("/api/v1/query?query={}", percent_encoded(query));
        let (_, body) = http_get(&self.address, &path).expect("query Prometheus");
        let answer: serde_json::Value =
            serde_json::from_str(&body).map_err(|e| format!("{e}: {body}"))?;
        if answer["status"] != "success" {
            return Err(format!("{}: {}", answer["errorType"], answer["error"]));
        }
        Ok(answer["data"]["result"]
            .as_array()
            .cloned()
            .unwrap_or_default())
    }

    /// The value of the instant query `query`'s single series, if it has one.
    pub fn query(&self, query: &str) -> Option<f64> {
        let series = self
            .query_series(query)
            .unwrap_or_else(|error| panic!("{query}: {error}"));
        match series.as_slice() {
            [] => None,
            [one] => one["value"][1].as_str()?.parse().ok(),
            more => panic!("{} series for {query}: {more:?}", more.len()),
        }
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

/// `text` as a URL query value: unreserved bytes as they are, every other byte `%XX`.
fn percent_encoded(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'.' | b'_' | b'~' => {
                char::from(b).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}
