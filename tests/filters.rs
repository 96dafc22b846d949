//! `pointfarm render`'s filters on a real scan: what they keep against the file's own
//! attributes, the framing of a clip box in the resident and the level-of-detail paths, and
//! filters refused with the reason, over the command line and by the service.

use std::path::Path;

use pointfarm_proto::v1 as pb;
use pointfarm_render::filter::PointFilter;
use pointfarm_render::ingest::load_point_cloud;
use pointfarm_tests::service::{
    daemon_with_sample, run_job, scan, still_clipped_outside_the_sample,
};
use pointfarm_tests::{assert_fails_saying, assert_ok, path_arg, pointfarm, stdout};

/// `render FILE --local` at a small size into `dir`/`name`, with `options`.
fn render(file: &Path, dir: &Path, name: &str, options: &[&str]) -> std::process::Output {
    let out = dir.join(name);
    let mut args = vec![
        "render",
        path_arg(file),
        "--local",
        "--size",
        "160x120",
        "--out",
        path_arg(&out),
    ];
    args.extend_from_slice(options);
    pointfarm(&args)
}

/// The value of the line that starts with `label` (`bounds:`, ...).
fn line_after(output: &str, label: &str) -> String {
    output
        .lines()
        .find_map(|line| {
            line.split_once(label)
                .map(|(_, rest)| rest.trim().to_string())
        })
        .unwrap_or_else(|| panic!("no '{label}' line in:\n{output}"))
}

#[test]
fn a_class_filter_keeps_the_points_the_file_classifies_so() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = scan(dir.path());
    let cloud = load_point_cloud(&file).expect("load");
    let ground = cloud.classification.iter().filter(|&&c| c == 2).count();
    assert!(ground > 0 && ground < cloud.len(), "{ground} ground points");

    let all = render(&file, dir.path(), "all.png", &[]);
    assert_ok(&all);
    let filtered = render(&file, dir.path(), "ground.png", &["--classes", "ground"]);
    assert_ok(&filtered);
    let text = stdout(&filtered);
    let expected = format!("the filter keeps {ground} of {} points", cloud.len());
    assert!(
        text.contains(&expected),
        "expected '{expected}' in:\n{text}"
    );
    // The class filter keeps the whole dataset's camera, so layers line up.
    assert_eq!(
        line_after(&text, "camera:"),
        line_after(&stdout(&all), "camera:")
    );
    let all = image::open(dir.path().join("all.png"))
        .expect("png")
        .to_rgba8();
    let ground = image::open(dir.path().join("ground.png"))
        .expect("png")
        .to_rgba8();
    assert_ne!(all, ground, "the filter changes the picture");

    // Every class but ground is the rest of the points.
    let rest = render(&file, dir.path(), "rest.png", &["--exclude-classes", "2"]);
    assert_ok(&rest);
    let expected = format!(
        "keeps {} of",
        cloud.len() - cloud.classification.iter().filter(|&&c| c == 2).count()
    );
    assert!(stdout(&rest).contains(&expected), "{}", stdout(&rest));
}

#[test]
fn a_clip_box_frames_its_part_in_both_paths_alike() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = scan(dir.path());
    let bounds = load_point_cloud(&file).expect("load").bounds;
    let center = bounds.center();
    // The lower-x, lower-y quarter, every height.
    let clip = format!(
        "{},{}..{},{}",
        bounds.min.x - 1.0,
        bounds.min.y - 1.0,
        center.x,
        center.y
    );
    let expected = format!(
        "x {:.3} .. {:.3}, y {:.3} .. {:.3}, z {:.3} .. {:.3}",
        bounds.min.x, center.x, bounds.min.y, center.y, bounds.min.z, bounds.max.z
    );
    let clip_flag = format!("--clip={clip}");
    let resident = render(&file, dir.path(), "resident.png", &[&clip_flag]);
    assert_ok(&resident);
    assert_eq!(line_after(&stdout(&resident), "bounds:"), expected);

    let cache = dir.path().join("stores");
    let cut = render(
        &file,
        dir.path(),
        "cut.png",
        &[
            &clip_flag,
            "--lod-error",
            "0",
            "--cache-dir",
            path_arg(&cache),
        ],
    );
    assert_ok(&cut);
    // The store's bounds are the files' header bounds, rounded to their scale: the framing
    // agrees to that.
    let numbers = |line: String| -> Vec<f64> {
        line.split([' ', ','])
            .filter_map(|word| word.parse::<f64>().ok())
            .collect()
    };
    let (cut, resident) = (
        numbers(line_after(&stdout(&cut), "bounds:")),
        numbers(expected),
    );
    assert_eq!(cut.len(), 6);
    for (c, r) in cut.iter().zip(&resident) {
        assert!((c - r).abs() <= 0.01, "{cut:?} against {resident:?}");
    }
}

#[test]
fn filters_that_cannot_apply_are_refused_with_the_reason() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = scan(dir.path());
    let outside = render(&file, dir.path(), "outside.png", &["--clip=0,0,0..1,1,1"]);
    assert_fails_saying(&outside, "lies outside the dataset's bounds");
    assert!(!dir.path().join("outside.png").exists(), "nothing written");
    let cases: [(&[&str], &str); 5] = [
        (&["--classes", "trees"], "'trees' is not a class"),
        (&["--returns", "16"], "must be 0 to 15"),
        (&["--intensity", "900..100"], "is empty"),
        (&["--clip=5,0..1,1"], "empty along x"),
        (
            &["--classes", "2", "--exclude-classes", "7"],
            "cannot be used with",
        ),
    ];
    for (options, reason) in cases {
        assert_fails_saying(&render(&file, dir.path(), "x.png", options), reason);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_whose_clip_box_misses_the_dataset_fails_saying_so_and_the_next_one_renders() {
    let (daemon, dataset) = daemon_with_sample(5_000, 4).await;
    let mut jobs = daemon.jobs().await;
    let mut request = still_clipped_outside_the_sample();
    let outcomes = [
        ("outside", request.clone()),
        ("unfiltered", {
            request.render.filter = PointFilter::default();
            request
        }),
    ];
    for (name, request) in outcomes {
        let finished = run_job(&mut jobs, &dataset.id, name, request).await;
        if name == "outside" {
            assert_eq!(finished.state, pb::JobState::Failed as i32);
            assert!(
                finished.error.contains("lies outside the dataset's bounds"),
                "{}",
                finished.error
            );
        } else {
            assert_eq!(
                finished.state,
                pb::JobState::Succeeded as i32,
                "{}",
                finished.error
            );
        }
    }
    daemon.stop().await;
}
