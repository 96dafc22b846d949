//! A real Azure Blob Storage server for the tests of `az://` URLs: Azurite, from the npm
//! registry, where `POINTFARM_TEST_AZURITE` names its `azurite-blob` script (deploy/test.sh
//! installs it). It runs on a free loopback port over a folder of its own, with the
//! emulator's well-known account, and is killed when dropped.

use std::time::{Duration, SystemTime};

use base64::Engine as _;
use hmac::{Hmac, Mac};
use sha2::Sha256;

use crate::rest::{request, Answer};
use crate::tools::ToolServer;

/// The variable that names the `azurite-blob` script.
pub const AZURITE_VARIABLE: &str = "POINTFARM_TEST_AZURITE";

/// The emulator's well-known development account and key (public, documented by Azure).
pub const ACCOUNT: &str = "devstoreaccount1";
const ACCOUNT_KEY: &str =
    "Eby8vdM02xNOcqFlqUwJPLlmEtlCDXJ1OUzFT50uSRZ6IFsuFq2UVErCz4I6tq/K1SZFPTOtr/KBHBeksoGMGw==";

/// A well-formed key that is not the account's; a test checks it never appears in an output.
pub const WRONG_KEY: &str =
    "cG9pbnRmYXJtLXdyb25nLWtleS1wb2ludGZhcm0td3Jvbmcta2V5LXBvaW50ZmFybS13cm9uZy1rZXk=";

/// The REST API version the setup requests ask for.
const API_VERSION: &str = "2021-08-06";

/// How long the server may take to listen.
const START_TIMEOUT: Duration = Duration::from_secs(60);

/// An `azurite-blob` child process on a loopback port over a folder of its own; killed when
/// dropped, before its folder goes.
pub struct Azurite {
    server: ToolServer,
}

impl Azurite {
    /// Starts the server, or None, having said why, without the script (a failure in CI).
    pub fn start_or_skip() -> Option<Self> {
        let server = ToolServer::start_or_skip(
            AZURITE_VARIABLE,
            "azurite-blob",
            START_TIMEOUT,
            |command, host, port, folder| {
                command
                    .args(["--blobHost", host, "--blobPort", port])
                    .arg("--location")
                    .arg(folder)
                    .args(["--skipApiVersionCheck", "--loose", "--silent"]);
            },
        )?;
        Some(Self { server })
    }

    /// The environment a client of this server reads its endpoint and account from, as
    /// object_store's Azure builder reads them.
    pub fn environment(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AZURE_STORAGE_USE_EMULATOR", "true".to_owned()),
            (
                "AZURITE_BLOB_STORAGE_URL",
                format!("http://{}", self.server.address),
            ),
        ]
    }

    /// The environment with a key the server does not accept.
    pub fn wrong_key_environment(&self) -> Vec<(&'static str, String)> {
        let mut environment = self.environment();
        environment.push(("AZURE_STORAGE_ACCOUNT_KEY", WRONG_KEY.to_owned()));
        environment
    }

    /// Makes the empty container `name`.
    pub fn create_container(&self, name: &str) {
        let answer = self.signed("PUT", &format!("/{name}"), &[("restype", "container")]);
        assert_eq!(answer.status, 201, "create {name}: {}", answer.text());
    }

    /// The bytes of the blob `key` of `container`, or None where there is none.
    pub fn blob(&self, container: &str, key: &str) -> Option<Vec<u8>> {
        let answer = self.signed("GET", &format!("/{container}/{key}"), &[]);
        match answer.status {
            200 => Some(answer.body),
            404 => None,
            status => panic!("GET {container}/{key}: {status} {}", answer.text()),
        }
    }

    /// The names of the blobs in `container`, as the server lists them.
    pub fn blob_names(&self, container: &str) -> Vec<String> {
        let answer = self.signed(
            "GET",
            &format!("/{container}"),
            &[("comp", "list"), ("restype", "container")],
        );
        assert_eq!(answer.status, 200, "list {container}: {}", answer.text());
        let text = answer.text();
        text.split("<Name>")
            .skip(1)
            .filter_map(|rest| rest.split_once("</Name>").map(|(name, _)| name.to_owned()))
            .collect()
    }

    /// Stores `bytes` as the block blob `key` of `container`, replacing any blob there.
    pub fn put_blob(&self, container: &str, key: &str, bytes: &[u8]) {
        let blob_type = [("x-ms-blob-type", "BlockBlob")];
        let path = format!("/{container}/{key}");
        let answer = self.signed_with("PUT", &path, &[], &blob_type, bytes);
        assert_eq!(answer.status, 201, "put {key}: {}", answer.text());
    }

    /// A body-less request to `/{ACCOUNT}{path}` with `query` (sorted by name), signed with
    /// the account's key as Azure's Shared Key scheme asks.
    fn signed(&self, method: &str, path: &str, query: &[(&str, &str)]) -> Answer {
        self.signed_with(method, path, query, &[], &[])
    }

    /// [`Self::signed`] with `x-ms-` headers (sorted by name, before `x-ms-date`) and `body`.
    fn signed_with(
        &self,
        method: &str,
        path: &str,
        query: &[(&str, &str)],
        ms_headers: &[(&str, &str)],
        body: &[u8],
    ) -> Answer {
        let date = httpdate::fmt_http_date(SystemTime::now());
        let resource_path = format!("/{ACCOUNT}{path}");
        let mut canonical_resource = format!("/{ACCOUNT}{resource_path}");
        for (name, value) in query {
            canonical_resource.push_str(&format!("\n{name}:{value}"));
        }
        // An empty body's length is signed as nothing, as the scheme asks since 2015.
        let length = if body.is_empty() {
            String::new()
        } else {
            body.len().to_string()
        };
        let canonical_headers: String = ms_headers
            .iter()
            .map(|(name, value)| format!("{name}:{value}\n"))
            .collect();
        let string_to_sign = format!(
            "{method}\n\n\n{length}\n\n\n\n\n\n\n\n\n{canonical_headers}x-ms-date:{date}\n\
             x-ms-version:{API_VERSION}\n{canonical_resource}"
        );
        let engine = base64::engine::general_purpose::STANDARD;
        let key = engine.decode(ACCOUNT_KEY).expect("the account key");
        let mut mac = Hmac::<Sha256>::new_from_slice(&key).expect("an HMAC key");
        mac.update(string_to_sign.as_bytes());
        let signature = engine.encode(mac.finalize().into_bytes());
        let mut target = resource_path;
        let joined: Vec<String> = query
            .iter()
            .map(|(name, value)| format!("{name}={value}"))
            .collect();
        if !joined.is_empty() {
            target.push('?');
            target.push_str(&joined.join("&"));
        }
        let mut headers: Vec<(&str, String)> = ms_headers
            .iter()
            .map(|(name, value)| (*name, (*value).to_owned()))
            .collect();
        headers.extend([
            ("x-ms-date", date),
            ("x-ms-version", API_VERSION.to_owned()),
            ("Authorization", format!("SharedKey {ACCOUNT}:{signature}")),
        ]);
        request(&self.server.address, method, &target, &headers, body)
    }
}
