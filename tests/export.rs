//! `pointfarm export --copc` and `pointfarm dataset export --copc` as a user runs them: the
//! file read back by the `las` crate's COPC reader and by laspy's (an implementation
//! independent of pointfarm's crates), an existing file refused without `--force`, a missing
//! folder refused, an unknown dataset NOT_FOUND through the API.
//!
//! laspy runs in the virtualenv `deploy/test.sh` makes (`POINTFARM_PYTHON`, else
//! `target/python-venv`), with `tests/python/requirements.txt`; where there is none that part
//! skips, saying so, as the Python client test does.

use std::path::Path;
use std::process::{Command, Output};

use las::copc::{BoundsSelection, CopcReader, LodSelection};
use pointfarm_proto::v1 as pb;

use pointfarm_tests::datasets::add_with_cli;
use pointfarm_tests::{
    assert_fails_saying, assert_ok, json_lines, path_arg, pointfarm, run_ok, shared_data, stdout,
    test_python, ServeProcess,
};

/// What the export tests compare of a COPC file, read with the `las` crate's COPC reader.
#[derive(Debug, PartialEq)]
struct Facts {
    points: u64,
    queried: u64,
    point_format: u8,
    mins: [f64; 3],
    maxs: [f64; 3],
    sum: [i64; 3],
    first: Vec<[i64; 3]>,
    last: Vec<[i64; 3]>,
    nodes: usize,
    entry_points: u64,
}

fn read_facts(path: &Path) -> Facts {
    let mut reader = CopcReader::from_path(path).expect("a COPC file");
    let header = reader.header().clone();
    let entries: Vec<_> = reader.hierarchy_entries().collect();
    let all = reader
        .query(LodSelection::All, BoundsSelection::All)
        .expect("every point");
    let mut xyz: Vec<[i64; 3]> = all
        .x_raw()
        .zip(all.y_raw())
        .zip(all.z_raw())
        .map(|((x, y), z)| [i64::from(x), i64::from(y), i64::from(z)])
        .collect();
    let sum = xyz
        .iter()
        .fold([0i64; 3], |s, p| [s[0] + p[0], s[1] + p[1], s[2] + p[2]]);
    xyz.sort_unstable();
    let bounds = header.bounds();
    Facts {
        points: header.number_of_points(),
        queried: all.len() as u64,
        point_format: header.point_format().to_u8().expect("format"),
        mins: [bounds.min.x, bounds.min.y, bounds.min.z],
        maxs: [bounds.max.x, bounds.max.y, bounds.max.z],
        sum,
        first: xyz[..3].to_vec(),
        last: xyz[xyz.len() - 3..].to_vec(),
        nodes: entries.len(),
        entry_points: entries
            .iter()
            .map(|e| u64::try_from(e.point_count).unwrap_or(0))
            .sum(),
    }
}

/// The file as laspy's COPC reader sees it, checked against the `las` crate's reading.
fn check_with_laspy(path: &Path, facts: &Facts) {
    let Some(python) = test_python(&["laspy", "lazrs"], "tests/python/requirements.txt") else {
        return;
    };
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("python/read_copc.py");
    let output = run_ok(Command::new(python).arg(script).arg(path), "laspy");
    let seen: serde_json::Value = serde_json::from_slice(&output.stdout).expect("one JSON object");
    assert_eq!(seen["version"], "1.4", "{seen}");
    assert_eq!(seen["pointFormat"], facts.point_format, "{seen}");
    assert_eq!(seen["headerPoints"], facts.points, "{seen}");
    assert_eq!(seen["queried"], facts.points, "every point queried: {seen}");
    assert_eq!(seen["nodes"], facts.nodes, "{seen}");
    assert_eq!(seen["entryPoints"], facts.entry_points, "{seen}");
    let triple = |v: &serde_json::Value| -> [f64; 3] {
        std::array::from_fn(|i| v[i].as_f64().expect("a number"))
    };
    for (name, expected) in [("mins", facts.mins), ("maxs", facts.maxs)] {
        let got = triple(&seen[name]);
        for axis in 0..3 {
            assert!(
                (got[axis] - expected[axis]).abs() < 1e-6,
                "{name}: {got:?} vs {expected:?}"
            );
        }
    }
    let ints = |v: &serde_json::Value| -> Vec<[i64; 3]> {
        v.as_array()
            .expect("points")
            .iter()
            .map(|p| std::array::from_fn(|i| p[i].as_i64().expect("an integer")))
            .collect()
    };
    assert_eq!(ints(&seen["first"]), facts.first);
    assert_eq!(ints(&seen["last"]), facts.last);
    let sum: Vec<i64> = (0..3)
        .map(|i| seen["sum"][i].as_i64().expect("sum"))
        .collect();
    assert_eq!(sum, facts.sum);
    // Each point's weight, an extra dimension other readers see by its name: at least 1,
    // and more for the inner nodes' points, which stand for others.
    assert_eq!(
        seen["extraDimensions"],
        serde_json::json!(["pointfarm_weight"])
    );
    let weights = &seen["weightRange"];
    assert_eq!(weights[0], 1, "{seen}");
    assert!(weights[1].as_u64().expect("a weight") > 1, "{seen}");
    // The info VLR's cube holds the header's bounds.
    let (centre, half) = (
        triple(&seen["center"]),
        seen["halfsize"].as_f64().expect("half"),
    );
    for ((c, min), max) in centre.iter().zip(facts.mins).zip(facts.maxs) {
        assert!(c - half <= min + 1e-6 && c + half >= max - 1e-6, "{seen}");
    }
}

/// The scan's own points: count and integer coordinates, as the file has them.
fn scan_facts(file: &Path) -> (u64, [i64; 3]) {
    let mut reader = las::Reader::from_path(file).expect("the scan");
    let data = reader.read_all().expect("its points");
    let sum = data
        .x_raw()
        .zip(data.y_raw())
        .zip(data.z_raw())
        .fold([0i64; 3], |s, ((x, y), z)| {
            [
                s[0] + i64::from(x),
                s[1] + i64::from(y),
                s[2] + i64::from(z),
            ]
        });
    (data.len() as u64, sum)
}

/// The one JSON object a successful `export --json` printed.
fn one_report(output: &Output) -> serde_json::Value {
    assert_ok(output);
    let mut lines = json_lines(output);
    assert_eq!(lines.len(), 1, "one object:\n{}", stdout(output));
    lines.remove(0)
}

#[test]
fn export_writes_a_copc_file_that_laspy_and_the_las_crate_read_as_the_scan() {
    let Some(scan) = shared_data("autzen_trim.laz") else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("autzen.copc.laz");
    let cache = dir.path().join("cache");
    let export = |extra: &[&str]| {
        let mut args = vec!["export", path_arg(&scan), "--copc", path_arg(&out)];
        args.extend(["--cache-dir", path_arg(&cache)]);
        args.extend(extra);
        pointfarm(&args)
    };
    let output = export(&["--json"]);
    let report = &one_report(&output);
    assert_eq!(report["file"], path_arg(&out), "{report}");
    assert_eq!(report["points"], 110_000, "{report}");
    assert_eq!(report["pointFormat"], 7, "{report}");
    assert_eq!(report["scale"][0], 0.01, "the scan's own scale: {report}");

    let facts = read_facts(&out);
    let (points, sum) = scan_facts(&scan);
    assert_eq!((facts.points, facts.queried), (points, points));
    assert_eq!(facts.sum, sum, "the scan's integer coordinates, every one");
    assert_eq!(facts.entry_points, points);
    assert_eq!(report["nodes"], facts.nodes, "{report}");
    assert_eq!(
        report["bytes"],
        std::fs::metadata(&out).expect("file").len()
    );
    check_with_laspy(&out, &facts);

    // The file exists now: refused without --force, replaced with it.
    assert_fails_saying(&export(&[]), "pass --force");
    let output = export(&["--force"]);
    assert_ok(&output);
    assert!(
        stdout(&output).contains("110000 points"),
        "{}",
        stdout(&output)
    );
    assert_eq!(
        read_facts(&out),
        facts,
        "the same file again, from the kept store"
    );

    let nowhere = dir.path().join("missing").join("out.copc.laz");
    let output = pointfarm(&[
        "export",
        path_arg(&scan),
        "--copc",
        path_arg(&nowhere),
        "--cache-dir",
        path_arg(&cache),
    ]);
    assert_fails_saying(&output, "does not exist");
    assert!(!nowhere.parent().expect("folder").exists());
}

#[test]
fn dataset_export_streams_the_servers_copc_file() {
    let Some(scan) = shared_data("lone-star.laz") else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let server = ServeProcess::start(&dir.path().join("data"));
    let address = server.address.clone();
    let dataset = add_with_cli(&address, &scan);

    // `pointfarm dataset export ID --copc OUT` through the server, and `more` flags.
    let export = |id: &str, out: &Path, more: &[&str]| {
        let mut args = vec!["dataset", "export", id, "--copc", path_arg(out), "--server"];
        args.push(&address);
        args.extend_from_slice(more);
        pointfarm(&args)
    };
    let out = dir.path().join("lone-star.copc.laz");
    let output = export(&dataset.id, &out, &["--json"]);
    let report = &one_report(&output);
    assert_eq!(report["file"], path_arg(&out), "{report}");
    let summary: pb::ExportSummary =
        serde_json::from_value(report["summary"].clone()).expect("an ExportSummary");
    let facts = read_facts(&out);
    let (points, sum) = scan_facts(&scan);
    assert_eq!(summary.points, points);
    assert_eq!(summary.point_format, 6, "no RGB in the scan");
    assert_eq!(
        summary.size_bytes,
        std::fs::metadata(&out).expect("file").len()
    );
    assert_eq!(summary.nodes as usize, facts.nodes);
    assert_eq!((facts.points, facts.queried), (points, points));
    assert_eq!(facts.sum, sum);
    check_with_laspy(&out, &facts);
    assert!(
        !dir.path().join("lone-star.copc.laz.part").exists(),
        "no partial file left"
    );

    // Refusals: an existing file, an unknown dataset (NOT_FOUND through the API).
    assert_fails_saying(&export(&dataset.id, &out, &[]), "pass --force");
    let unknown_out = dir.path().join("unknown.copc.laz");
    let unknown = export("ds-0000000000000000", &unknown_out, &[]);
    assert_fails_saying(&unknown, "not found");
    assert!(!unknown_out.exists());
    let runtime = tokio::runtime::Runtime::new().expect("runtime");
    let code = runtime.block_on(async {
        let (mut datasets, _) = pointfarm_tests::service::clients(&address).await;
        let request = pb::ExportDatasetRequest {
            dataset_id: "ds-0000000000000000".into(),
        };
        datasets
            .export_dataset(request)
            .await
            .err()
            .map(|s| s.code())
    });
    assert_eq!(code, Some(tonic::Code::NotFound));
}

/// The formats whose points have RGB, near-infrared, GPS time and wave packets.
fn has_color(format: u8) -> bool {
    matches!(format, 2 | 3 | 5 | 7 | 8 | 10)
}

fn has_gps_time(format: u8) -> bool {
    format != 0 && format != 2
}

fn has_waveform(format: u8) -> bool {
    matches!(format, 4 | 5 | 9 | 10)
}

/// An extra bytes descriptor (LAS 1.4 record 4) of a plain attribute.
fn descriptor(name: &str, data_type: u8) -> Vec<u8> {
    let mut out = vec![0u8; 192];
    out[2] = data_type;
    out[4..4 + name.len()].copy_from_slice(name.as_bytes());
    out
}

/// The formats whose test files carry extra bytes: an `amplitude` (u16) and a `reflectance`
/// (f32), 6 bytes a point.
fn has_extra_bytes(format: u8) -> bool {
    matches!(format, 1 | 3 | 5 | 6 | 7 | 10)
}

/// A small LAS file of point format `format` whose points vary every attribute the format
/// has, at unique positions.
fn write_format(dir: &Path, format: u8) -> std::path::PathBuf {
    use las::point::{Classification, ScanDirection};
    let path = dir.join(format!("format-{format}.las"));
    let mut builder = las::Builder::from(match format {
        0..=3 => (1, 2),
        4 | 5 => (1, 3),
        _ => (1, 4),
    });
    builder.point_format = las::point::Format::new(format).expect("a point format");
    builder.transforms = las::Vector {
        x: las::Transform {
            scale: 0.01,
            offset: 500_000.0,
        },
        y: las::Transform {
            scale: 0.01,
            offset: 4_000_000.0,
        },
        z: las::Transform {
            scale: 0.001,
            offset: 0.0,
        },
    };
    if has_extra_bytes(format) {
        builder.point_format.extra_bytes = 6;
        let data = [descriptor("amplitude", 3), descriptor("reflectance", 9)].concat();
        builder.vlrs.push(las::Vlr {
            user_id: "LASF_Spec".into(),
            record_id: 4,
            description: "Extra Bytes Record".into(),
            data,
        });
    }
    let extended = format >= 6;
    let header = builder.into_header().expect("a header");
    let mut writer = las::Writer::from_path(&path, header).expect("a writer");
    let legacy_classes = [0u8, 1, 2, 7, 9, 17, 31];
    let extended_classes = [1u8, 2, 6, 40, 77, 200, 255];
    let mut state = 0x2545_f491_4f6c_dd1du64 ^ u64::from(format);
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    for i in 0..3_000u32 {
        let r = next();
        // The header of LAS 1.0 to 1.3 counts five returns.
        let max_returns = if extended { 15 } else { 5 };
        let returns = (r % max_returns) as u8 + 1;
        let return_number = ((r >> 8) % u64::from(returns)) as u8 + 1;
        let classes = if extended {
            &extended_classes
        } else {
            &legacy_classes
        };
        let class = classes[(r >> 16) as usize % classes.len()];
        let bit = |k: u32| (r >> (24 + k)) & 1 == 1;
        let scan_angle = if extended {
            ((r >> 32) % 20_000) as f32 * 0.006 - 60.0
        } else {
            ((r >> 32) % 61) as f32 - 30.0
        };
        let amplitude = (i as u16).wrapping_mul(37);
        let reflectance = -(i as f32) * 0.25;
        let point = las::Point {
            x: 500_000.0 + f64::from(i % 60) * 0.5,
            y: 4_000_000.0 + f64::from(i / 60) * 0.5,
            z: f64::from((i * 7) % 13) + 0.125,
            intensity: (r >> 40) as u16,
            return_number,
            number_of_returns: returns,
            scan_direction: if bit(0) {
                ScanDirection::LeftToRight
            } else {
                ScanDirection::RightToLeft
            },
            is_edge_of_flight_line: bit(1),
            classification: Classification::new(class).expect("a class"),
            is_synthetic: bit(2),
            is_key_point: bit(3),
            is_withheld: bit(4),
            is_overlap: extended && bit(5),
            scanner_channel: if extended { (r >> 56) as u8 & 3 } else { 0 },
            scan_angle,
            user_data: (r >> 48) as u8,
            point_source_id: (r >> 20) as u16,
            gps_time: has_gps_time(format).then(|| 3.0e8 + f64::from(i) * 0.001 + 1e-6),
            color: has_color(format)
                .then(|| las::Color::new((r >> 3) as u16, (r >> 19) as u16, (r >> 35) as u16)),
            waveform: has_waveform(format).then(|| las::raw::point::Waveform {
                wave_packet_descriptor_index: (r >> 7) as u8,
                byte_offset_to_waveform_data: r >> 5,
                waveform_packet_size_in_bytes: (r >> 11) as u32,
                return_point_waveform_location: i as f32 * 1.5,
                x_t: 0.25,
                y_t: -(i as f32),
                z_t: 1e-3 * i as f32,
            }),
            nir: matches!(format, 8 | 10).then(|| (r >> 27) as u16),
            extra_bytes: if has_extra_bytes(format) {
                [
                    amplitude.to_le_bytes().as_slice(),
                    &reflectance.to_le_bytes(),
                ]
                .concat()
            } else {
                Vec::new()
            },
        };
        writer.write_point(point).expect("a point");
    }
    writer.close().expect("closed");
    path
}

/// Exports `source` as COPC and compares every point of the two files with laspy: the same
/// points, every attribute, in point format `expected_format`.
fn assert_round_trip(python: &Path, source: &Path, dir: &Path, expected_format: u8) {
    let name = source.file_name().expect("a file name").to_string_lossy();
    let out = dir.join(format!("{name}.copc.laz"));
    let cache = dir.join("cache");
    let output = pointfarm(&[
        "export",
        path_arg(source),
        "--copc",
        path_arg(&out),
        "--cache-dir",
        path_arg(&cache),
        "--json",
    ]);
    assert_ok(&output);
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("python/compare_points.py");
    let compared = run_ok(
        Command::new(python).arg(script).arg(source).arg(&out),
        "laspy",
    );
    let seen: serde_json::Value =
        serde_json::from_slice(&compared.stdout).expect("one JSON object");
    assert_eq!(
        seen["sourcePoints"], seen["exportedPoints"],
        "{name}: {seen}"
    );
    assert_eq!(seen["exportedFormat"], expected_format, "{name}: {seen}");
    assert_eq!(seen["mismatched"], serde_json::json!({}), "{name}: {seen}");
    // Every extra dimension of the source is in the export, after the weight.
    let exported = seen["exportedExtra"].as_array().expect("names");
    assert_eq!(exported[0], "pointfarm_weight", "{name}: {seen}");
    for extra in seen["sourceExtra"].as_array().expect("names") {
        assert!(exported.contains(extra), "{name}: {extra} lost: {seen}");
    }
    let compared: Vec<&str> = seen["compared"]
        .as_array()
        .expect("names")
        .iter()
        .filter_map(|v| v.as_str())
        .collect();
    for dimension in [
        "gps_time",
        "scan_angle",
        "point_source_id",
        "user_data",
        "overlap",
    ] {
        assert!(compared.contains(&dimension), "{name}: {seen}");
    }
}

/// The export of a file of each point format pointfarm reads (0 to 10) gives back every
/// attribute of every point, as laspy reads both files: the format that holds them (6, 7 with
/// RGB, 8 with near-infrared), wave packets and extra bytes as extra dimensions.
#[test]
fn export_gives_back_every_attribute_in_every_point_format() {
    let Some(python) = test_python(&["laspy", "lazrs"], "tests/python/requirements.txt") else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    for format in 0..=10u8 {
        let source = write_format(dir.path(), format);
        let expected = match format {
            8 | 10 => 8,
            f if has_color(f) => 7,
            _ => 6,
        };
        assert_round_trip(&python, &source, dir.path(), expected);
    }
}

/// The real scans (autzen, format 3; lone star, format 1) come back point for point with
/// every attribute.
#[test]
fn export_gives_back_every_attribute_of_the_real_scans() {
    let Some(python) = test_python(&["laspy", "lazrs"], "tests/python/requirements.txt") else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    for (file, format) in [("autzen_trim.laz", 7), ("lone-star.laz", 6)] {
        let Some(scan) = shared_data(file) else {
            return;
        };
        assert_round_trip(&python, &scan, dir.path(), format);
    }
}
