//! Campaigns of plain LAS/LAZ tiles by URL, against real servers on loopback: a real scan
//! (`shared/data/lone-star.laz`) cut into 20 tiles, served by nginx and by `s3s-fs`. A
//! preview from the tiles' chunk starts read by range is the preview of the same files here,
//! pixel for pixel, and fetches a bounded share of their bytes; `info` of a prefix says what
//! it says of the folder, and is followed by the final frame; a missing bucket or
//! object, an empty prefix, a truncated or hostile tile, refused credentials and a server that
//! stops are each one line naming the URL, a tile's checks the same as a file's. Each test
//! skips, saying so, without the scan, nginx or `s3s-fs`.

use std::io::Cursor;
use std::path::{Path, PathBuf};
use std::process::Output;
use std::time::Instant;

use pointfarm_render::raster::Renderer;
use pointfarm_render::remote::{ObjectUrl, RemoteClient, RemoteSettings};
use pointfarm_render::request::{CameraPath, Lens, RenderOptions, RenderRequest, Turntable};
use pointfarm_render::source::{quiet, ChunkStarts, FrameSource, PreviewPoints};
use pointfarm_render::testing::{laz_of_las, LazChunks};
use pointfarm_tests::nginx::NginxServer;
use pointfarm_tests::s3s::{run_s3, S3sServer};
use pointfarm_tests::service::gpu;
use pointfarm_tests::{
    assert_one_error_line, info_files, json_lines, output_text, path_arg, pointfarm, shared_data,
};

const TILES: usize = 20;
/// Points per LAZ chunk of a tile: several chunks, so several chunk starts, in each.
const CHUNK_POINTS: u32 = 4096;
const BUCKET: &str = "campaigns";

/// lone-star.laz cut along x into [`TILES`] tiles of equal points: LAZ in chunks of
/// [`CHUNK_POINTS`] points (the `las` writer's are 50,000), tile 5 uncompressed and tile 19
/// named in capitals, as campaigns come. None, having said so, without the scan.
fn lone_star_tiles() -> Option<Vec<(String, Vec<u8>)>> {
    lone_star_cut(Some(5))
}

/// lone-star.laz cut into [`TILES`] tiles, each LAZ but the one at `las_tile`.
fn lone_star_cut(las_tile: Option<usize>) -> Option<Vec<(String, Vec<u8>)>> {
    let scan = shared_data("lone-star.laz")?;
    let mut reader = las::Reader::from_path(&scan).expect("las reader");
    let header = reader.header().clone();
    let mut points: Vec<las::Point> = (reader.read_all().expect("the scan's points"))
        .points()
        .collect::<Result<_, _>>()
        .expect("the scan's points");
    points.sort_by(|a, b| a.x.total_cmp(&b.x));
    let per_tile = points.len().div_ceil(TILES);
    let tiles = points
        .chunks(per_tile)
        .enumerate()
        .map(|(index, tile)| {
            let las = las_bytes(&header, tile);
            match index {
                _ if Some(index) == las_tile => (format!("tile-{index:02}.las"), las),
                19 => (
                    format!("tile-{index:02}.LAZ"),
                    laz_of_las(&las, LazChunks::Fixed(CHUNK_POINTS)),
                ),
                _ => (
                    format!("tile-{index:02}.laz"),
                    laz_of_las(&las, LazChunks::Fixed(CHUNK_POINTS)),
                ),
            }
        })
        .collect();
    Some(tiles)
}

/// `points` as an uncompressed LAS file of `like`'s version, point format and transforms,
/// without VLRs.
fn las_bytes(like: &las::Header, points: &[las::Point]) -> Vec<u8> {
    let mut builder = las::Builder::from(like.version());
    builder.point_format = *like.point_format();
    builder.point_format.is_compressed = false;
    builder.transforms = *like.transforms();
    let header = builder.into_header().expect("tile header");
    let mut writer = las::Writer::new(Cursor::new(Vec::new()), header).expect("writer");
    for point in points {
        writer.write_point(point.clone()).expect("point");
    }
    writer.into_inner().expect("written").into_inner()
}

/// `tiles` written into `folder`, with a file that is no tile beside them; their paths here,
/// in order.
fn write_tiles(folder: &Path, tiles: &[(String, Vec<u8>)]) -> Vec<PathBuf> {
    std::fs::create_dir_all(folder).expect("tiles folder");
    std::fs::write(folder.join("README.txt"), "not a tile").expect("readme");
    tiles
        .iter()
        .map(|(name, bytes)| {
            let path = folder.join(name);
            std::fs::write(&path, bytes).expect("tile");
            path
        })
        .collect()
}

/// One still frame of a preview's points, as the command draws a preview.
fn preview_image(points: PreviewPoints) -> image::RgbaImage {
    let request = RenderRequest {
        width: 200,
        height: 150,
        camera_path: CameraPath::Turntable(Turntable::around_the_cloud(1)),
        lens: Lens::default(),
        render: RenderOptions::default(),
    };
    let mut source = FrameSource::preview(Renderer::new(gpu()), points, &request.render, &quiet)
        .expect("a preview");
    let settings = source.frame_settings(&request, 0);
    let rendered = source.render(&settings, &quiet).expect("render");
    assert!(rendered.preview.is_some(), "a preview's frame");
    rendered.frame.image
}

#[test]
fn a_preview_of_tiles_by_url_is_the_preview_of_the_same_files_here() {
    let Some(tiles) = lone_star_tiles() else {
        return;
    };
    let root = tempfile::tempdir().expect("root");
    let paths = write_tiles(&root.path().join("scans"), &tiles);
    let Some(server) = NginxServer::start_or_skip(root.path()) else {
        return;
    };
    let urls: Vec<ObjectUrl> = (tiles.iter())
        .map(|(name, _)| ObjectUrl::parse(&server.url(&format!("scans/{name}"))).expect("URL"))
        .collect();
    let client = RemoteClient::new(RemoteSettings::default()).expect("client");
    let here = ChunkStarts::read(&paths).expect("chunk starts here");
    let by_url = ChunkStarts::read_urls(&client, &urls).expect("chunk starts by URL");
    let (here, by_url) = (here.with_nodes(&[]), by_url.with_nodes(&[]));
    assert_eq!(by_url.points_in_files, 518_862);
    assert_eq!(by_url.points_in_files, here.points_in_files);
    assert_eq!(by_url.files_bounds, here.files_bounds);
    assert!(by_url.cloud == here.cloud, "the samples differ");
    // Every chunk's first point: 19 LAZ tiles of ceil(25,944 / 4,096) = 7 chunks (the last one
    // with a point fewer), and the LAS tile's first record.
    let sampled = here.cloud.len();
    assert_eq!(sampled, 19 * 7 + 1);

    // Bounded: per tile a HEAD, the block of its header and chunk table's offset, the blocks
    // of its chunk table, and its sampled records; never the points between them.
    let total: u64 = tiles.iter().map(|(_, bytes)| bytes.len() as u64).sum();
    let fetched = client.counts();
    eprintln!(
        "{TILES} tiles, {total} bytes: {} requests, {} bytes fetched for {sampled} points",
        fetched.requests, fetched.bytes
    );
    let block = 16 * 1024;
    assert!(
        fetched.bytes <= TILES as u64 * 3 * block + sampled as u64 * 28,
        "{fetched:?} of {total} bytes"
    );
    assert!(fetched.bytes < total / 2, "{fetched:?} of {total} bytes");
    assert!(
        fetched.requests <= TILES as u64 * 4 + sampled as u64,
        "{fetched:?}"
    );

    assert_eq!(
        preview_image(by_url),
        preview_image(here),
        "the previews' pixels"
    );
}

/// `pointfarm ARGS` with the S3 server's endpoint and credentials in its environment.
fn pointfarm_s3(server: &S3sServer, args: &[&str]) -> Output {
    run_s3(&server.environment(), args)
}

#[test]
fn a_prefix_in_s3_is_described_and_previewed_as_the_folder_here() {
    let Some(tiles) = lone_star_tiles() else {
        return;
    };
    let root = tempfile::tempdir().expect("root");
    let folder = root.path().join(BUCKET).join("lone-star");
    write_tiles(&folder, &tiles);
    let Some(server) = S3sServer::start_or_skip(root.path()) else {
        return;
    };
    let prefix = format!("s3://{BUCKET}/lone-star/");

    let here = pointfarm(&["info", path_arg(&folder), "--no-points", "--json"]);
    let by_url = pointfarm_s3(&server, &["info", &prefix, "--no-points", "--json"]);
    let ((files_here, paths_here), (files, paths)) = (info_files(&here), info_files(&by_url));
    assert_eq!(files, files_here, "what info says of the tiles");
    let names = |paths: &[String]| -> Vec<String> {
        (paths.iter())
            .map(|path| path.rsplit('/').next().expect("a name").to_owned())
            .collect()
    };
    assert_eq!(names(&paths), names(&paths_here));
    assert_eq!(paths[0], format!("{prefix}tile-00.laz"));
    assert_eq!(paths[19], format!("{prefix}tile-19.LAZ"));

    let dir = tempfile::tempdir().expect("out");
    let out = dir.path().join("preview.png");
    let cache = dir.path().join("cache");
    let render = ["render", &prefix, "--preview", "--json", "--size=160x120"];
    let places = ["--out", path_arg(&out), "--cache-dir", path_arg(&cache)];
    let output = pointfarm_s3(&server, &[&render[..], &places].concat());
    let text = output_text(&output);
    assert!(output.status.success(), "{text}");
    // The preview (drawn again as the store builds), then the final frame from the store
    // (tests/tile_urls.rs).
    let frames = json_lines(&output);
    assert_eq!(frames[0]["preview"], true, "{text}");
    assert_eq!(frames.last().expect("a frame")["preview"], false, "{text}");
    assert_eq!(frames[0]["pointsRendered"], 19 * 7 + 1, "{text}");
    let fetched = |key: &str| frames[0]["fetched"][key].as_u64().expect("fetched counts");
    let total: u64 = tiles.iter().map(|(_, bytes)| bytes.len() as u64).sum();
    assert!(fetched("requests") > TILES as u64, "{text}");
    assert!(fetched("bytes") < total / 2, "{text}");
    assert!(image::open(&out).is_ok(), "{text}");
}

#[test]
fn faults_by_url_are_one_line_errors_and_a_tile_fails_its_checks_as_a_file() {
    let Some(tiles) = lone_star_tiles() else {
        return;
    };
    let root = tempfile::tempdir().expect("root");
    let good = &tiles[0].1;
    // Cut short inside its points, and a chunk table offset past the end of the object.
    let truncated = good[..good.len() / 2].to_vec();
    let mut hostile = good.clone();
    let data_start = u32::from_le_bytes(hostile[96..100].try_into().expect("4 bytes")) as usize;
    hostile[data_start..data_start + 8].copy_from_slice(&(1u64 << 40).to_le_bytes());
    let faulty = [
        ("truncated.laz".to_owned(), truncated),
        ("hostile.laz".to_owned(), hostile),
    ];
    let paths = write_tiles(&root.path().join(BUCKET).join("faulty"), &faulty);
    std::fs::create_dir_all(root.path().join(BUCKET).join("empty")).expect("empty");
    std::fs::write(root.path().join(BUCKET).join("empty/notes.txt"), "x").expect("no tile");
    let Some(mut server) = S3sServer::start_or_skip(root.path()) else {
        return;
    };
    let info = |url: &str| pointfarm_s3(&server, &["info", url, "--no-points"]);

    for (path, (name, _)) in paths.iter().zip(&faulty) {
        let url = format!("s3://{BUCKET}/faulty/{name}");
        let here = pointfarm(&["info", path_arg(path), "--no-points"]);
        let by_url = info(&url);
        let error_line = |output: &Output| -> String {
            let stderr = String::from_utf8_lossy(&output.stderr);
            let line = stderr.lines().find(|l| l.starts_with("error:"));
            line.expect("an error").to_owned()
        };
        assert_eq!(
            error_line(&by_url).replace(&url, "TILE"),
            error_line(&here).replace(path_arg(path), "TILE"),
            "{name}"
        );
        assert!(!by_url.status.success());
    }
    let out = root.path().join("preview.png");
    let preview = |url: &str| {
        pointfarm_s3(
            &server,
            &["render", url, "--preview", "--out", path_arg(&out)],
        )
    };
    let missing = format!("s3://{BUCKET}/faulty/absent.laz");
    assert_one_error_line(&preview(&missing), &[&missing, "no such object"]);
    let no_bucket = "s3://no-such-bucket/tiles/";
    assert_one_error_line(&preview(no_bucket), &[no_bucket, "no such bucket"]);
    let empty = format!("s3://{BUCKET}/empty/");
    assert_one_error_line(&preview(&empty), &[&empty, "no .las or .laz object"]);

    let mut refused = server.environment();
    refused.retain(|(key, _)| *key != "AWS_SECRET_ACCESS_KEY");
    refused.push(("AWS_SECRET_ACCESS_KEY", "not-the-secret".to_owned()));
    let tile = format!("s3://{BUCKET}/faulty/hostile.laz");
    let preview_args = ["render", &tile, "--preview", "--out", path_arg(&out)];
    let denied = run_s3(&refused, &preview_args);
    assert_one_error_line(&denied, &[&tile, "access denied"]);

    // A server that stops answering: the error names the URL, after the client's retries.
    let environment = server.environment();
    server.stop();
    let started = Instant::now();
    let stopped = run_s3(&environment, &preview_args);
    eprintln!("a stopped server failed in {:.1?}", started.elapsed());
    assert_one_error_line(&stopped, &[&tile]);
}

/// The figures of docs/perf/remote-tile-previews.md: `render --preview` of 20 LAZ tiles under an
/// `s3://` prefix, the whole command timed three times, and the chunk starts of the same
/// files read here. Run with `--ignored --nocapture`.
#[test]
#[ignore = "a measurement, not a check"]
fn first_preview_frame_of_twenty_laz_tiles_in_s3() {
    let Some(tiles) = lone_star_cut(None) else {
        return;
    };
    let root = tempfile::tempdir().expect("root");
    let paths = write_tiles(&root.path().join(BUCKET).join("lone-star"), &tiles);
    let Some(server) = S3sServer::start_or_skip(root.path()) else {
        return;
    };
    let prefix = format!("s3://{BUCKET}/lone-star/");
    let total: u64 = tiles.iter().map(|(_, bytes)| bytes.len() as u64).sum();
    let out = root.path().join("preview.png");
    for run in 1..=3 {
        let started = Instant::now();
        let render = ["render", &prefix, "--preview", "--json", "--size=1280x720"];
        let output = pointfarm_s3(&server, &[&render[..], &["--out", path_arg(&out)]].concat());
        let took = started.elapsed();
        assert!(output.status.success(), "{}", output_text(&output));
        let frame = json_lines(&output).remove(0);
        eprintln!(
            "run {run}: render --preview {took:.2?} (process start to PNG); {} points; fetched {} of \
             {total} bytes in {} requests",
            frame["pointsRendered"], frame["fetched"]["bytes"], frame["fetched"]["requests"]
        );
    }
    let started = Instant::now();
    ChunkStarts::read(&paths).expect("chunk starts here");
    eprintln!("chunk starts of the files here: {:.1?}", started.elapsed());
}
