//! `pointfarm info` on the real scans (against what the `las` crate reads from them on its
//! own), on a truncated file and into a closed pipe; and on datasets through a real daemon,
//! whose report is the one made here of the same files, as text and as the API's JSON.

use std::path::Path;

use pointfarm_proto::v1 as pb;
use pointfarm_tests::datasets::add_files_with_cli;
use pointfarm_tests::{
    assert_fails_saying, assert_ok, path_arg, pointfarm, run_into_a_closed_pipe, shared_data,
    stdout, ServeProcess,
};

/// `pointfarm info --json ARGS`, parsed back with the proto3 JSON mapping.
fn info_json(args: &[&str]) -> pb::DatasetDescription {
    let mut all = vec!["info", "--json"];
    all.extend_from_slice(args);
    let output = pointfarm(&all);
    assert_ok(&output);
    description_of(&output)
}

fn description_of(output: &std::process::Output) -> pb::DatasetDescription {
    serde_json::from_slice(&output.stdout)
        .unwrap_or_else(|e| panic!("not a DatasetDescription ({e}):\n{}", stdout(output)))
}

/// What the `las` crate reads from a file by itself: the points' bounds, classes and returns.
struct Independent {
    min: [f64; 3],
    max: [f64; 3],
    /// `(value, points)` as the API reports them.
    classes: Vec<(u32, u64)>,
    returns: Vec<(u32, u64)>,
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
            .map(|(i, n)| (i as u32, n))
            .collect()
    };
    Independent {
        min,
        max,
        classes: nonzero(classes),
        returns: nonzero(returns),
    }
}

fn xyz(v: Option<&pb::Vec3>) -> [f64; 3] {
    let v = v.expect("a vector");
    [v.x, v.y, v.z]
}

fn corners(bounds: Option<&pb::Bounds>) -> ([f64; 3], [f64; 3]) {
    let bounds = bounds.expect("bounds");
    (xyz(bounds.min.as_ref()), xyz(bounds.max.as_ref()))
}

#[test]
fn the_real_scans_report_their_header_points_and_colors() {
    let (Some(las), Some(laz), Some(lone_star)) = (
        shared_data("autzen_trim.las"),
        shared_data("autzen_trim.laz"),
        shared_data("lone-star.laz"),
    ) else {
        return;
    };
    let document = info_json(&[path_arg(&las), path_arg(&laz), path_arg(&lone_star)]);
    assert_eq!(document.dataset_id, "");
    let [autzen_las, autzen_laz, lone] = &document.files[..] else {
        panic!("3 files: {document:?}");
    };

    assert_eq!((autzen_las.version_major, autzen_las.version_minor), (1, 2));
    assert_eq!(autzen_las.point_format, 3);
    assert_eq!(autzen_las.points, 110_000);
    assert!(!autzen_las.compressed && autzen_laz.compressed);
    assert_eq!(xyz(autzen_las.scale.as_ref())[0], 0.01);
    assert!(autzen_las.attributes.as_ref().expect("attributes").rgb);
    let crs = |file: &pb::FileDescription| file.crs.clone().and_then(|crs| crs.source);
    match crs(autzen_las) {
        Some(pb::crs::Source::Wkt(wkt)) => assert_eq!(
            wkt.name.as_deref(),
            Some("NAD_1983_HARN_Lambert_Conformal_Conic")
        ),
        other => panic!("not a WKT CRS: {other:?}"),
    }
    assert_eq!((lone.version_major, lone.version_minor), (1, 1));
    assert_eq!(lone.point_format, 1);
    assert_eq!(lone.points, 518_862);
    assert!(!lone.attributes.as_ref().expect("attributes").rgb);
    assert!(matches!(crs(lone), Some(pb::crs::Source::Geotiff(_))));

    // The points' own bounds and histograms, against the las crate's reading.
    for (file, path) in [(autzen_las, &las), (lone, &lone_star)] {
        let expected = read_independently(path);
        let stats = file.points_read.as_ref().expect("the points were read");
        let (min, max) = corners(stats.bounds.as_ref());
        assert_eq!((min, max), (expected.min, expected.max), "{path:?}");
        let classes: Vec<_> = stats.classes.iter().map(|c| (c.code, c.points)).collect();
        assert_eq!(classes, expected.classes);
        let returns: Vec<_> = stats
            .returns
            .iter()
            .map(|r| (r.return_number, r.points))
            .collect();
        assert_eq!(returns, expected.returns);
        // The header's bounds hold the points (rounded to the scale).
        let (header_min, header_max) = corners(file.bounds.as_ref());
        for axis in 0..3 {
            assert!(header_min[axis] <= min[axis] + 1e-6, "{path:?}");
            assert!(max[axis] <= header_max[axis] + 1e-6, "{path:?}");
        }
    }
    // Autzen around its state-plane position, in feet.
    let (min, _) = corners(autzen_las.bounds.as_ref());
    assert!((min[0] - 636_000.0).abs() < 5_000.0 && (min[1] - 849_000.0).abs() < 5_000.0);

    // LAS and LAZ of the same points read the same.
    assert_eq!(autzen_las.points_read, autzen_laz.points_read);
    let stats = autzen_las.points_read.as_ref().expect("points");
    assert_eq!(stats.classes[1].name, "ground");
    let rgb = stats.rgb.as_ref().expect("RGB fields");
    assert!(rgb.varies && rgb.eight_bit_values);
    assert!(lone.points_read.as_ref().expect("points").rgb.is_none());

    let summary = document.summary.expect("summary");
    assert_eq!((summary.files, summary.unreadable), (3, 0));
    assert_eq!(summary.points, 110_000 + 110_000 + 518_862);
    let (_, union_max) = corners(summary.bounds.as_ref());
    assert_eq!(union_max[1], corners(lone.bounds.as_ref()).1[1]);
}

/// The API's JSON mapping: lowerCamelCase names, 64-bit integers as strings, defaults left out.
#[test]
fn json_is_the_api_message_in_its_json_mapping() {
    let Some(las) = shared_data("autzen_trim.las") else {
        return;
    };
    let output = pointfarm(&["info", "--json", path_arg(&las)]);
    assert_ok(&output);
    let value: serde_json::Value = serde_json::from_slice(&output.stdout).expect("JSON");
    let file = &value["files"][0];
    assert_eq!(file["points"], "110000");
    assert_eq!(file["pointFormat"], 3);
    assert_eq!(file["versionMinor"], 2);
    assert!(
        file.get("compressed").is_none(),
        "false is left out: {file}"
    );
    assert_eq!(
        file["crs"]["wkt"]["name"],
        "NAD_1983_HARN_Lambert_Conformal_Conic"
    );
    assert_eq!(file["pointsRead"]["rgb"]["eightBitValues"], true);
    assert_eq!(value["summary"]["files"], 1);
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
    assert_eq!(document.files[0].points, 110_000);
    assert!(document.files[0].points_read.is_none());
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
            let document = description_of(&output);
            assert!(document.files[0].error.contains("cut_short.las"));
            assert_eq!(document.files[2].points, 110_000);
            assert_eq!(document.summary.expect("summary").unreadable, 2);
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

/// `pointfarm info DATASET --server`: the server reads the dataset's files and reports them
/// as `pointfarm info` reports the same files here, in text and in JSON; with or without the
/// points; an unreadable file named while the others are reported; an unknown id refused.
#[test]
fn a_dataset_on_a_server_reports_as_its_files_do_here() {
    let (Some(autzen), Some(lone_star)) =
        (shared_data("autzen_trim.laz"), shared_data("lone-star.laz"))
    else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let server = ServeProcess::start_with(&dir.path().join("data"), &["--no-embedded-worker"]);
    let address = server.address.as_str();
    let dataset = add_files_with_cli(address, &[&autzen, &lone_star]);
    // The same files here, where the server keeps them: the local report of the same paths.
    let server_paths: Vec<&str> = dataset.files.iter().map(|f| f.path.as_str()).collect();
    assert_eq!(server_paths.len(), 2);

    for flags in [&[][..], &["--no-points"][..]] {
        let info = |inputs: &[&str], json: bool| {
            let mut args = vec!["info"];
            args.extend(inputs);
            args.extend(flags);
            if json {
                args.push("--json");
            }
            let output = pointfarm(&args);
            assert_ok(&output);
            output
        };
        let remote = |json: bool| info(&[dataset.id.as_str(), "--server", address], json);
        let local = |json: bool| info(&server_paths, json);
        let text = stdout(&remote(false));
        assert_eq!(text, stdout(&local(false)), "{flags:?}");
        assert!(text.contains("points      518862"), "{text}");
        assert_eq!(text.contains("points read"), flags.is_empty(), "{text}");

        let (remote, local) = (description_of(&remote(true)), description_of(&local(true)));
        assert_eq!(remote.dataset_id, dataset.id);
        assert_eq!(remote.files, local.files, "{flags:?}");
        assert_eq!(remote.summary, local.summary, "{flags:?}");
        assert_eq!(remote.files[0].points, 110_000);
        assert_eq!(remote.files[0].points_read.is_some(), flags.is_empty());
    }

    // A file the server cannot read is named; the dataset's other file is still reported.
    let bytes = std::fs::read(&autzen).expect("read autzen");
    let cut = dir.path().join("cut_short.laz");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).expect("write the cut file");
    let damaged = add_files_with_cli(address, &[&cut, &lone_star]);
    let output = pointfarm(&["info", &damaged.id, "--server", address]);
    assert_fails_saying(&output, "1 of 2 files could not be read");
    assert_fails_saying(&output, "truncated");
    assert!(stdout(&output).contains("points      518862"));

    // An unknown id: refused, saying so; an input that is neither a path nor, without a
    // server, a dataset id: said so.
    let output = pointfarm(&["info", "0123456789abcdef", "--server", address]);
    assert_fails_saying(&output, "dataset 0123456789abcdef");
    assert_fails_saying(&output, "not found");
    let output = pointfarm(&["info", "0123456789abcdef", "--local"]);
    assert_fails_saying(&output, "no such file or folder");

    // The daemon is still there after the damaged file.
    let output = pointfarm(&["info", &dataset.id, "--server", address, "--no-points"]);
    assert_ok(&output);
}
