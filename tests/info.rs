//! `pointfarm info` on the real scans (against what the `las` crate reads from them on its
//! own), on a truncated file and into a closed pipe.

use std::path::Path;

use pointfarm_tests::{assert_ok, pointfarm, run_into_a_closed_pipe, shared_data};
use serde_json::Value;

fn path_arg(path: &Path) -> &str {
    path.to_str().expect("paths are UTF-8")
}

fn info_json(args: &[&str]) -> Value {
    let mut all = vec!["info", "--json"];
    all.extend_from_slice(args);
    let output = pointfarm(&all);
    assert_ok(&output);
    serde_json::from_slice(&output.stdout).expect("one JSON document")
}

/// What the `las` crate reads from a file by itself: the points' bounds, classes and returns.
struct Independent {
    min: [f64; 3],
    max: [f64; 3],
    classes: Vec<(u64, u64)>,
    returns: Vec<(u64, u64)>,
}

fn read_independently(path: &Path) -> Independent {
    let mut reader = las::Reader::from_path(path).expect("las reader");
    let (mut min, mut max) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    let (mut classes, mut returns) = (vec![0u64; 256], vec![0u64; 16]);
    let points = reader.read_all().expect("read every point");
    for ((x, y), z) in points.x().zip(points.y()).zip(points.z()) {
        for (axis, value) in [x, y, z].into_iter().enumerate() {
            min[axis] = min[axis].min(value);
            max[axis] = max[axis].max(value);
        }
    }
    for class in points.classification() {
        classes[usize::from(class)] += 1;
    }
    for number in points.return_number() {
        returns[usize::from(number)] += 1;
    }
    let nonzero = |counts: Vec<u64>| {
        counts
            .into_iter()
            .enumerate()
            .filter(|(_, n)| *n > 0)
            .map(|(i, n)| (i as u64, n))
            .collect()
    };
    Independent {
        min,
        max,
        classes: nonzero(classes),
        returns: nonzero(returns),
    }
}

/// (key, points) pairs of a histogram in the JSON.
fn histogram(stats: &Value, name: &str, key: &str) -> Vec<(u64, u64)> {
    stats[name]
        .as_array()
        .expect("a histogram")
        .iter()
        .map(|entry| {
            let field = |k: &str| entry[k].as_u64().expect("a count");
            (field(key), field("points"))
        })
        .collect()
}

fn array3(value: &Value) -> [f64; 3] {
    let number = |i: usize| value[i].as_f64().expect("a coordinate");
    [number(0), number(1), number(2)]
}

#[test]
fn the_real_scans_report_their_header_points_and_colours() {
    let (Some(las), Some(laz), Some(lone_star)) = (
        shared_data("autzen_trim.las"),
        shared_data("autzen_trim.laz"),
        shared_data("lone-star.laz"),
    ) else {
        return;
    };
    let document = info_json(&[path_arg(&las), path_arg(&laz), path_arg(&lone_star)]);
    let files = document["files"].as_array().expect("files");
    assert_eq!(files.len(), 3);
    let (autzen_las, autzen_laz, lone) = (&files[0], &files[1], &files[2]);

    assert_eq!(autzen_las["version"], "1.2");
    assert_eq!(autzen_las["pointFormat"], 3);
    assert_eq!(autzen_las["points"], 110_000);
    assert_eq!(autzen_las["compressed"], false);
    assert_eq!(autzen_laz["compressed"], true);
    assert_eq!(autzen_las["scale"][0], 0.01);
    assert_eq!(autzen_las["attributes"]["rgb"], true);
    assert_eq!(autzen_las["crs"]["source"], "wkt");
    assert_eq!(
        autzen_las["crs"]["name"],
        "NAD_1983_HARN_Lambert_Conformal_Conic"
    );
    assert_eq!(lone["version"], "1.1");
    assert_eq!(lone["pointFormat"], 1);
    assert_eq!(lone["points"], 518_862);
    assert_eq!(lone["attributes"]["rgb"], false);
    assert_eq!(lone["crs"]["source"], "geotiff");

    // The points' own bounds and histograms, against the las crate's reading.
    for (file, path) in [(autzen_las, &las), (lone, &lone_star)] {
        let expected = read_independently(path);
        let stats = &file["pointStats"];
        let (min, max) = (
            array3(&stats["bounds"]["min"]),
            array3(&stats["bounds"]["max"]),
        );
        assert_eq!((min, max), (expected.min, expected.max), "{path:?}");
        assert_eq!(histogram(stats, "classes", "class"), expected.classes);
        assert_eq!(histogram(stats, "returns", "return"), expected.returns);
        // The header's bounds hold the points (rounded to the scale).
        let (header_min, header_max) = (
            array3(&file["bounds"]["min"]),
            array3(&file["bounds"]["max"]),
        );
        for axis in 0..3 {
            assert!(header_min[axis] <= min[axis] + 1e-6, "{path:?}");
            assert!(max[axis] <= header_max[axis] + 1e-6, "{path:?}");
        }
    }
    // Autzen around its state-plane position, in feet.
    let min = array3(&autzen_las["bounds"]["min"]);
    assert!((min[0] - 636_000.0).abs() < 5_000.0 && (min[1] - 849_000.0).abs() < 5_000.0);

    // LAS and LAZ of the same points read the same.
    assert_eq!(autzen_las["pointStats"], autzen_laz["pointStats"]);
    let color = &autzen_las["pointStats"]["color"];
    assert_eq!(color["rgb"], true);
    assert_eq!(color["varies"], true);
    assert_eq!(color["eightBitIn16BitFields"], true);
    assert_eq!(lone["pointStats"]["color"]["rgb"], false);

    let summary = &document["summary"];
    assert_eq!(summary["files"], 3);
    assert_eq!(summary["unreadable"], 0);
    assert_eq!(summary["points"], 110_000 + 110_000 + 518_862);
    let union_max = array3(&summary["bounds"]["max"]);
    assert_eq!(union_max[1], array3(&lone["bounds"]["max"])[1]);
}

#[test]
fn text_names_the_facts_in_words_and_no_points_skips_the_points() {
    let Some(las) = shared_data("autzen_trim.las") else {
        return;
    };
    let output = pointfarm(&["info", path_arg(&las)]);
    assert_ok(&output);
    let text = String::from_utf8_lossy(&output.stdout);
    for needle in [
        "LAS 1.2, point format 3",
        "points      110000",
        "2 ground:",
        "8-bit values in 16-bit fields",
        "NAD_1983_HARN_Lambert_Conformal_Conic",
    ] {
        assert!(text.contains(needle), "no {needle} in:\n{text}");
    }
    assert!(!text.contains("Rgb8In16Bit"), "{text}");

    let document = info_json(&["--no-points", path_arg(&las)]);
    assert_eq!(document["files"][0]["points"], 110_000);
    assert!(document["files"][0]["pointStats"].is_null());
}

#[test]
fn a_truncated_file_is_named_and_fails_the_command_after_the_others() {
    let Some(las) = shared_data("autzen_trim.las") else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let bytes = std::fs::read(&las).expect("read autzen");
    let cut = dir.path().join("cut_short.las");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).expect("write the cut file");
    let header_only = dir.path().join("header_only.las");
    std::fs::write(&header_only, &bytes[..100]).expect("write the header");

    for args in [vec!["info"], vec!["info", "--json"]] {
        let mut args = args;
        args.extend([path_arg(&cut), path_arg(&header_only), path_arg(&las)]);
        let output = pointfarm(&args);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{args:?} succeeded");
        assert!(!stderr.contains("panicked"), "{stderr}");
        assert!(stderr.contains("cut_short.las: truncated"), "{stderr}");
        assert!(stderr.contains("header_only.las"), "{stderr}");
        assert!(
            stderr.contains("2 of 3 files could not be read"),
            "{stderr}"
        );
        let stdout = String::from_utf8_lossy(&output.stdout);
        if args.contains(&"--json") {
            let document: Value = serde_json::from_str(&stdout).expect("JSON");
            assert!(document["files"][0]["error"]
                .as_str()
                .is_some_and(|e| e.contains("cut_short.las")));
            assert_eq!(document["files"][2]["points"], 110_000);
            assert_eq!(document["summary"]["unreadable"], 2);
        } else {
            assert!(stdout.contains("points      110000"), "{stdout}");
        }
    }
}

/// `pointfarm info … | head -1`: the reader goes away; the command ends quietly.
#[test]
fn a_closed_output_pipe_ends_quietly() {
    let Some(las) = shared_data("autzen_trim.las") else {
        return;
    };
    run_into_a_closed_pipe(&["info", "--no-points", path_arg(&las), path_arg(&las)]);
}
