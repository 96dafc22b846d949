//! `render --server` on files the server already has under its data roots: the campaign is
//! found by its content (nothing is uploaded), `--dataset ID` renders it by id, and a job
//! with previews has each preview downloaded as it comes, where its final frame replaces it.

use std::path::Path;

use pointfarm_render::testing::write_scene_tiles;
use pointfarm_tests::{assert_ok, json_lines, path_arg, pointfarm, stdout, ServeProcess};

const FRAMES: usize = 3;

/// `render` through `server` with previews, as JSON lines, into `out`; `source` names the
/// dataset (files or `--dataset ID`).
fn render_previewed(server: &ServeProcess, source: &[&str], out: &Path) -> Vec<serde_json::Value> {
    let mut args = vec!["render"];
    args.extend(source);
    args.extend([
        "--server",
        &server.address,
        "--preview",
        "--lod-error=0.5",
        "--turntable=3",
        "--size=160x120",
        "--json",
        "--out",
        path_arg(out),
    ]);
    let output = pointfarm(&args);
    assert_ok(&output);
    json_lines(&output)
}

fn frame_image(dir: &Path, index: usize) -> image::RgbaImage {
    image::open(dir.join(format!("frame_{index:05}.png")))
        .expect("a frame")
        .to_rgba8()
}

#[test]
fn a_registered_campaign_renders_with_its_previews_and_is_never_uploaded() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let campaign = scratch.path().join("campaign");
    // Four tiles of 1M points: a store whose build outlasts the download of a small preview.
    write_scene_tiles(&campaign, 1_000_000, 4);
    let server = ServeProcess::start_with(
        &scratch.path().join("data"),
        &["--data-root", path_arg(&campaign)],
    );
    let registered = pointfarm(&[
        "dataset",
        "register",
        path_arg(&campaign),
        "--server",
        &server.address,
        "--json",
    ]);
    assert_ok(&registered);
    let registered: serde_json::Value =
        serde_json::from_str(&stdout(&registered)).expect("the dataset as JSON");
    let id = registered["id"].as_str().expect("an id").to_owned();

    // The folder's files are the registered dataset: found by their content, not uploaded.
    let previewed = scratch.path().join("previewed");
    let reports = render_previewed(&server, &[path_arg(&campaign)], &previewed);
    let job_ids: Vec<_> = reports.iter().map(|r| r["jobId"].clone()).collect();
    assert!(job_ids.windows(2).all(|w| w[0] == w[1]), "{reports:?}");
    let listed = pointfarm(&["dataset", "list", "--server", &server.address, "--json"]);
    assert_ok(&listed);
    let listed: serde_json::Value = serde_json::from_str(&stdout(&listed)).expect("json");
    let ids: Vec<_> = listed["datasets"]
        .as_array()
        .expect("a list")
        .iter()
        .map(|d| d["id"].as_str().unwrap_or_default().to_owned())
        .collect();
    assert_eq!(
        ids,
        std::slice::from_ref(&id),
        "a file was uploaded\n{}",
        server.log()
    );

    // The first frame is leased as the store's build starts: it comes as a preview,
    // downloaded and reported before the final frames, which come last and all final.
    let is_preview = |report: &serde_json::Value| report["finished"]["preview"] == true;
    let previews = reports.iter().take_while(|r| is_preview(r)).count();
    assert!(previews >= 1, "no preview: {reports:?}\n{}", server.log());
    // A preview leased after the build stored its last node, before it finished, draws
    // every point: complete, and still a preview.
    for report in &reports[..previews] {
        let completeness = report["finished"]["completeness"].as_f64().unwrap_or(0.0);
        assert!(completeness > 0.0 && completeness <= 1.0, "{report}");
    }
    let finals = &reports[previews..];
    assert_eq!(finals.len(), FRAMES, "{reports:?}");
    for (index, report) in finals.iter().enumerate() {
        assert_eq!(report["frame"], index, "{report}");
        assert!(!is_preview(report), "{report}");
    }
    // Nothing of the downloads is left beside the frames.
    let left: Vec<_> = std::fs::read_dir(&previewed)
        .expect("frames")
        .map(|entry| entry.expect("entry").file_name())
        .collect();
    assert_eq!(left.len(), FRAMES, "{left:?}");

    // By id, with the store built: final frames at once, the same images.
    let by_id = scratch.path().join("by-id");
    let reports = render_previewed(&server, &["--dataset", &id], &by_id);
    assert_eq!(reports.len(), FRAMES, "{reports:?}");
    assert!(reports.iter().all(|r| !is_preview(r)), "{reports:?}");
    for index in 0..FRAMES {
        assert!(
            frame_image(&previewed, index) == frame_image(&by_id, index),
            "frame {index} differs by id"
        );
    }

    // An id needs a server, and files and an id do not go together.
    let alone = pointfarm(&["render", "--dataset", &id, "--local"]);
    assert!(!alone.status.success());
    let both = pointfarm(&["render", path_arg(&campaign), "--dataset", &id]);
    assert!(!both.status.success());
}
