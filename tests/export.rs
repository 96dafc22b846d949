//! `pointfarm export --copc` and `pointfarm dataset export --copc` as a user runs them: the
//! file read back by the `las` crate's COPC reader and by laspy's (an implementation
//! independent of pointfarm's crates), an existing file refused without `--force`, a missing
//! folder refused, an unknown dataset NOT_FOUND through the API.
//!
//! laspy runs in the virtualenv `deploy/test.sh` makes (`POINTFARM_PYTHON`, else
//! `target/python-venv`), with `tests/python/requirements.txt`; where there is none that part
//! skips, saying so, as the Python client test does.

use std::path::Path;
use std::process::Command;

use las::copc::{BoundsSelection, CopcReader, LodSelection};
use pointfarm_proto::v1 as pb;

use pointfarm_tests::{
    assert_fails_saying, assert_ok, json_lines, pointfarm, run_ok, shared_data, stdout,
    test_python, ServeProcess,
};

fn arg(path: &Path) -> &str {
    path.to_str().expect("temporary paths are UTF-8")
}

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

#[test]
fn export_writes_a_copc_file_that_laspy_and_the_las_crate_read_as_the_scan() {
    let Some(scan) = shared_data("autzen_trim.laz") else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("autzen.copc.laz");
    let cache = dir.path().join("cache");
    let export = |extra: &[&str]| {
        let mut args = vec!["export", arg(&scan), "--copc", arg(&out)];
        args.extend(["--cache-dir", arg(&cache)]);
        args.extend(extra);
        pointfarm(&args)
    };
    let output = export(&["--json"]);
    assert_ok(&output);
    let lines = json_lines(&output);
    let [report] = lines.as_slice() else {
        panic!("one object:\n{}", stdout(&output));
    };
    assert_eq!(report["file"], arg(&out), "{report}");
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
        arg(&scan),
        "--copc",
        arg(&nowhere),
        "--cache-dir",
        arg(&cache),
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
    let added = pointfarm(&["dataset", "add", arg(&scan), "--server", &address, "--json"]);
    assert_ok(&added);
    let dataset: pb::Dataset = serde_json::from_str(stdout(&added).trim()).expect("a Dataset");

    // `pointfarm dataset export ID --copc OUT` through the server, and `more` flags.
    let export = |id: &str, out: &Path, more: &[&str]| {
        let mut args = vec!["dataset", "export", id, "--copc", arg(out), "--server"];
        args.push(&address);
        args.extend_from_slice(more);
        pointfarm(&args)
    };
    let out = dir.path().join("lone-star.copc.laz");
    let output = export(&dataset.id, &out, &["--json"]);
    assert_ok(&output);
    let lines = json_lines(&output);
    let [report] = lines.as_slice() else {
        panic!("one object:\n{}", stdout(&output));
    };
    assert_eq!(report["file"], arg(&out), "{report}");
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
