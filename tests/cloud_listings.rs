//! Prefixes of LAS/LAZ tiles and objects replaced while read, in Google Cloud Storage
//! (`gs://`) and Azure Blob Storage (`az://`), against real servers: fake-gcs-server and
//! Azurite, each on a loopback port of its own (`tests/support/fake_gcs.rs`, `azurite.rs`).
//! `info` of a prefix lists its `.las`/`.laz` objects, in order, and says of each what it says
//! of the same files in a folder here, objects of other kinds and outside the prefix left out;
//! an object replaced after it was opened fails the ranged read, and the stream (a tile's points
//! are read through one), that meet the new version, naming its URL, and is read whole at its
//! new version once opened again, never a mix of the two; a COPC object in Azure replaced after
//! it was opened refuses its nodes the same way. Each test skips, saying so, where its
//! server's variable names no binary, and fails so in CI.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use pointfarm_render::copc::open_copc_url;
use pointfarm_render::lod::NodeInfo;
use pointfarm_render::remote::{
    ObjectReader, ObjectUrl, RemoteClient, RemoteError, RemoteSettings,
};
use pointfarm_render::testing::write_scene_tiles;
use pointfarm_tests::azurite::Azurite;
use pointfarm_tests::fake_gcs::FakeGcs;
use pointfarm_tests::object_faults::assert_copc_object_changed;
use pointfarm_tests::{info_files, output_text, path_arg, run_with, sampled_copc};

/// The container and bucket the tests read from.
const CONTAINER: &str = "pointfarm-scans";

/// Three LAZ tiles written in `dir`'s `campaign` folder, and a file beside them that holds no
/// points, each stored by `put(key, path)` under `campaign/`, and a tile stored outside it:
/// the folder.
fn campaign(dir: &Path, put: impl Fn(&str, &Path)) -> PathBuf {
    let folder = dir.join("campaign");
    let tiles = write_scene_tiles(&folder, 4_000, 3);
    let note = folder.join("notes.txt");
    std::fs::write(&note, "not a point file").expect("a note");
    for file in tiles.iter().chain([&note]) {
        let name = file.file_name().and_then(|n| n.to_str()).expect("a name");
        put(&format!("campaign/{name}"), file);
    }
    put("other/t9.laz", &tiles[0]);
    folder
}

/// `pointfarm info INPUT --no-points --json` with `environment`: each file's description
/// without its path, and the paths, in the order told.
fn described(
    environment: &[(&'static str, String)],
    input: &str,
) -> (Vec<serde_json::Value>, Vec<String>) {
    info_files(&run_with(
        environment,
        &["info", input, "--no-points", "--json"],
    ))
}

/// `info` of `prefix` lists the tiles of `folder` under it, in their names' order, and says of
/// each what `info` of the folder says of the file.
fn assert_listed_as_the_folder(
    environment: &[(&'static str, String)],
    prefix: &str,
    folder: &Path,
) {
    let (here, paths_here) = described(&[], path_arg(folder));
    let (by_url, urls) = described(environment, prefix);
    assert_eq!(by_url, here, "what info says of the tiles under {prefix}");
    let names: Vec<&str> = (paths_here.iter())
        .map(|path| path.rsplit('/').next().expect("a name"))
        .collect();
    let expected: Vec<String> = names.iter().map(|name| format!("{prefix}{name}")).collect();
    assert_eq!(urls, expected);
    assert_eq!(names, ["t1.laz", "t2.laz", "t3.laz"]);
}

#[test]
fn a_gcs_prefix_lists_its_tiles_as_a_folder_does() {
    let Some(gcs) = FakeGcs::start_or_skip() else {
        return;
    };
    gcs.create_bucket(CONTAINER);
    let dir = tempfile::tempdir().expect("tempdir");
    let folder = campaign(dir.path(), |key, path| gcs.upload(CONTAINER, key, path));
    let prefix = format!("gs://{CONTAINER}/campaign/");
    assert_listed_as_the_folder(&gcs.environment(), &prefix, &folder);
}

#[test]
fn an_azure_prefix_lists_its_tiles_as_a_folder_does() {
    let Some(azurite) = Azurite::start_or_skip() else {
        return;
    };
    azurite.create_container(CONTAINER);
    let dir = tempfile::tempdir().expect("tempdir");
    let folder = campaign(dir.path(), |key, path| {
        azurite.put_blob(CONTAINER, key, &std::fs::read(path).expect("a file"));
    });
    let prefix = format!("az://{CONTAINER}/campaign/");
    assert_listed_as_the_folder(&azurite.environment(), &prefix, &folder);
    // An empty prefix is one line naming it, as in S3.
    let empty = format!("az://{CONTAINER}/nothing/");
    let output = run_with(&azurite.environment(), &["info", &empty, "--no-points"]);
    assert!(!output.status.success(), "{}", output_text(&output));
    assert!(
        output_text(&output).contains(&empty),
        "{}",
        output_text(&output)
    );
}

/// Bytes of an object the tests replace: many stream blocks long.
const OBJECT_BYTES: usize = 1 << 20;
/// The blocks the stream reads it in.
const BLOCK_BYTES: u64 = 64 * 1024;

/// Opens the object at `url` (holding `OBJECT_BYTES` ones), reads a range and a block of it as
/// a stream, lets `replace` put another version in its place (twos), and checks that the next
/// ranged read and the stream's next blocks are refused as changed, naming the URL, never
/// bytes of the new version; the object opened again reads the new version whole.
fn assert_replaced_mid_read_is_refused(url: &str, replace: impl FnOnce()) {
    let client = RemoteClient::new(RemoteSettings::default()).expect("a client");
    let parsed = ObjectUrl::parse(url).expect("a URL");
    let object = client.open(&parsed).expect("opens");
    assert_eq!(
        object.read_range(0..100).expect("the opened version"),
        [1u8; 100]
    );
    let mut stream = ObjectReader::with_blocks(Arc::new(object.clone()), BLOCK_BYTES, true);
    let mut block = vec![0u8; BLOCK_BYTES as usize];
    stream
        .read_exact(&mut block)
        .expect("a block of the opened version");
    assert!(block.iter().all(|&byte| byte == 1));
    replace();

    let assert_changed = |error: &RemoteError| {
        assert!(
            matches!(error, RemoteError::ObjectChanged { .. }),
            "{error}"
        );
        assert!(error.to_string().contains(url), "{error}");
    };
    let ranges = [1000..2000, 500_000..500_100];
    assert_changed(
        &object
            .read_ranges(&ranges)
            .expect_err("changed since opened"),
    );
    // The stream may still hold the block it read ahead, of the opened version; past it,
    // it is refused.
    let mut rest = Vec::new();
    let error = stream
        .read_to_end(&mut rest)
        .expect_err("changed while streamed");
    assert!(rest.iter().all(|&byte| byte == 1), "bytes of two versions");
    assert!(
        rest.len() < OBJECT_BYTES - BLOCK_BYTES as usize,
        "read {} bytes",
        rest.len()
    );
    let error = error
        .into_inner()
        .and_then(|inner| inner.downcast::<RemoteError>().ok())
        .expect("the stream's error is the object's");
    assert_changed(error.as_ref());

    let again = client.open(&parsed).expect("opens again");
    assert_ne!(again.version(), object.version());
    let whole = again
        .read_range(0..OBJECT_BYTES as u64)
        .expect("the new version");
    assert!(whole.iter().all(|&byte| byte == 2));
}

/// Opens the COPC object at `url`, lets `replace` put another object in its place, and checks
/// that reading every node, as a frame of every node does, is refused as changed, naming the
/// URL: never nodes of two versions.
fn assert_copc_replaced_mid_read_is_refused(url: &str, replace: impl FnOnce()) {
    let client = RemoteClient::new(RemoteSettings::default()).expect("a client");
    let copc = open_copc_url(&client, &ObjectUrl::parse(url).expect("a URL")).expect("opens");
    let nodes: Vec<NodeInfo> = (copc.dataset.hierarchy().nodes().iter())
        .filter(|node| node.point_count > 0)
        .copied()
        .collect();
    replace();
    let error = (copc.dataset.records().read_records(&nodes))
        .expect_err("the object changed since it was opened");
    assert_copc_object_changed(error, url);
}

/// Both stores in one test: the client reads its endpoints and credentials from this
/// process's environment, which each store's own variables set once.
#[test]
fn an_object_replaced_mid_read_in_azure_or_gcs_is_refused_naming_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let [first, second] = [1u8, 2].map(|byte| {
        let path = dir.path().join(format!("version-{byte}.bin"));
        std::fs::write(&path, vec![byte; OBJECT_BYTES]).expect("a version");
        path
    });
    let key = "campaign/scan.copc.laz";
    if let Some(azurite) = Azurite::start_or_skip() {
        for (name, value) in azurite.environment() {
            std::env::set_var(name, value);
        }
        azurite.create_container(CONTAINER);
        azurite.put_blob(CONTAINER, key, &std::fs::read(&first).expect("ones"));
        assert_replaced_mid_read_is_refused(&format!("az://{CONTAINER}/{key}"), || {
            azurite.put_blob(CONTAINER, key, &std::fs::read(&second).expect("twos"));
        });
        // More points than opening reads for the color ranges (1M), so the finer nodes are
        // read only when asked.
        let (_, copc) = sampled_copc(dir.path(), 1_500_000);
        let key = "campaign/large.copc.laz";
        azurite.put_blob(
            CONTAINER,
            key,
            &std::fs::read(&copc).expect("the COPC file"),
        );
        assert_copc_replaced_mid_read_is_refused(&format!("az://{CONTAINER}/{key}"), || {
            azurite.put_blob(CONTAINER, key, &std::fs::read(&second).expect("twos"));
        });
    }
    if let Some(gcs) = FakeGcs::start_or_skip() {
        for (name, value) in gcs.environment() {
            std::env::set_var(name, value);
        }
        gcs.create_bucket(CONTAINER);
        gcs.upload(CONTAINER, key, &first);
        assert_replaced_mid_read_is_refused(&format!("gs://{CONTAINER}/{key}"), || {
            gcs.upload(CONTAINER, key, &second);
        });
    }
}
