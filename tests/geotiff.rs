//! TIFF frames as GIS tools read them: GDAL (`gdalinfo -json`) places an orthographic top view
//! of a real scan where the camera saw it, in the scan's CRS (EPSG keys, or the WKT beside
//! it), with four 8-bit bands whose fourth is alpha, compressed, and its depth image beside it
//! in 16 bits; other views are not placed.

use std::path::{Path, PathBuf};
use std::process::Command;

use pointfarm_tests::{assert_ok, installed_or_skip, path_arg, pointfarm, shared_data, stdout};
use serde_json::Value;

fn gdal_installed() -> bool {
    installed_or_skip("gdalinfo", "--version", "deploy/test.sh installs gdal-bin")
}

/// The six numbers of the geotransform `gdalinfo -json` reports in `info`.
fn geotransform_of(info: &Value) -> Vec<f64> {
    info["geoTransform"]
        .as_array()
        .unwrap_or_else(|| panic!("no geotransform: {info}"))
        .iter()
        .map(|v| v.as_f64().expect("number"))
        .collect()
}

/// `gdalinfo -json` of `path`.
fn gdalinfo(path: &Path) -> Value {
    let output = Command::new("gdalinfo")
        .arg("-json")
        .arg(path)
        .output()
        .expect("gdalinfo runs");
    assert!(
        output.status.success(),
        "gdalinfo {}: {}",
        path.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).expect("gdalinfo prints JSON")
}

/// A top view of `scan` looking straight down at (x, y), `height` file units tall, rendered
/// at `size` into `out`, with `extra` options (north up the image unless they give an up).
fn render_top(
    scan: &Path,
    out: &Path,
    size: &str,
    (x, y): (f64, f64),
    height: f64,
    extra: &[&str],
) -> String {
    let (target, position) = (format!("{x},{y},0"), format!("{x},{y},5000"));
    let height = height.to_string();
    let mut args = vec![
        "render",
        path_arg(scan),
        "--local",
        "--size",
        size,
        "--ortho",
        "--ortho-height",
        &height,
        "--camera-target",
        &target,
        "--camera-pos",
        &position,
        "--out",
        path_arg(out),
    ];
    // North up the image unless `extra` says otherwise.
    if !extra.contains(&"--camera-up") {
        args.extend(["--camera-up", "0,1,0"]);
    }
    args.extend(extra);
    let output = pointfarm(&args);
    assert_ok(&output);
    stdout(&output)
}

/// Checks the image GDAL reads: `width` x `height` RGBA, 8 bits a band with the fourth
/// declared alpha, Deflate-compressed, placed by `geotransform`.
fn assert_placed_rgba(info: &Value, (width, height): (u64, u64), geotransform: [f64; 6]) {
    assert_eq!(info["size"], serde_json::json!([width, height]), "{info}");
    let bands = info["bands"].as_array().expect("bands");
    assert_eq!(bands.len(), 4, "{info}");
    for band in bands {
        // The renderer's colors are 8 bits; the TIFF holds them as they are.
        assert_eq!(band["type"], "Byte", "{band}");
    }
    assert_eq!(bands[3]["colorInterpretation"], "Alpha", "{info}");
    assert_eq!(
        info["metadata"]["IMAGE_STRUCTURE"]["COMPRESSION"], "DEFLATE",
        "{info}"
    );
    let read = geotransform_of(info);
    for (read, expected) in read.iter().zip(geotransform) {
        // Survey coordinates of six figures, placed to a millionth of a unit.
        assert!(
            (read - expected).abs() < 1e-6,
            "{read:?} != {geotransform:?}"
        );
    }
}

/// The real scan `name` and a scratch folder, where the scan and GDAL are both here (each
/// missing one is said where it is looked for).
fn scan_with_gdal(name: &str) -> Option<(PathBuf, tempfile::TempDir)> {
    let scan = shared_data(name)?;
    gdal_installed().then(|| (scan, tempfile::tempdir().expect("tempdir")))
}

#[test]
fn a_top_view_of_a_scan_with_a_wkt_crs_is_placed_in_it_by_gdal() {
    let Some((scan, dir)) = scan_with_gdal("autzen_trim.laz") else {
        return;
    };
    let out = dir.path().join("top.tif");
    let center = (636_590.49, 849_216.55);
    render_top(&scan, &out, "200x150", center, 600.0, &[]);
    // 600 feet over 150 rows: 4 feet a pixel; the top-left corner of the top-left pixel lies
    // half the image west and north of the target.
    let origin = (center.0 - 100.0 * 4.0, center.1 + 75.0 * 4.0);
    let info = gdalinfo(&out);
    assert_placed_rgba(&info, (200, 150), [origin.0, 4.0, 0.0, origin.1, 0.0, -4.0]);
    // The scan's WKT has no EPSG code, so it lies beside the TIFF, where GDAL finds it.
    let wkt = info["coordinateSystem"]["wkt"].as_str().expect("a CRS");
    assert!(
        wkt.contains("NAD_1983_HARN_Lambert_Conformal_Conic"),
        "{wkt}"
    );
    let prj = std::fs::read_to_string(out.with_extension("prj")).expect("the .prj");
    assert!(
        prj.starts_with("PROJCS[\"NAD_1983_HARN_Lambert_Conformal_Conic\""),
        "{prj}"
    );
    let world: Vec<f64> = std::fs::read_to_string(out.with_extension("tfw"))
        .expect("the world file")
        .lines()
        .map(|l| l.parse().expect("number"))
        .collect();
    // A world file places the centre of the top-left pixel.
    let expected = [4.0, 0.0, 0.0, -4.0, origin.0 + 2.0, origin.1 - 2.0];
    assert!(
        world
            .iter()
            .zip(expected)
            .all(|(w, e)| (w - e).abs() < 1e-6),
        "{world:?}"
    );
}

/// A point near the middle of lone-star's extent, in its CRS (metres), where its top views look.
const LONE_STAR_CENTER: (f64, f64) = (515_384.5, 4_918_360.25);

/// A 96x64 top view of lone-star, 32 m high around [`LONE_STAR_CENTER`], written to `file_name`
/// in a scratch folder with `extra` options; `None` where the scan or GDAL is missing.
fn lone_star_top(file_name: &str, extra: &[&str]) -> Option<(tempfile::TempDir, PathBuf)> {
    let (scan, dir) = scan_with_gdal("lone-star.laz")?;
    let out = dir.path().join(file_name);
    render_top(&scan, &out, "96x64", LONE_STAR_CENTER, 32.0, extra);
    Some((dir, out))
}

#[test]
fn a_top_view_of_a_scan_with_epsg_keys_carries_its_code() {
    let Some((dir, out)) = lone_star_top("top.tiff", &["--depth"]) else {
        return;
    };
    let center = LONE_STAR_CENTER;
    let info = gdalinfo(&out);
    let origin = (center.0 - 48.0 * 0.5, center.1 + 32.0 * 0.5);
    assert_placed_rgba(&info, (96, 64), [origin.0, 0.5, 0.0, origin.1, 0.0, -0.5]);
    // The file's GeoTIFF keys claim EPSG:4326 (for UTM coordinates): what it says is carried.
    let wkt = info["coordinateSystem"]["wkt"].as_str().expect("a CRS");
    assert!(wkt.contains("ID[\"EPSG\",4326]"), "{wkt}");
    assert!(!out.with_extension("prj").exists() && !out.with_extension("tfw").exists());

    // The depth image has 16 bits of its own: one band, placed as its frame, 0 for no point.
    let depth = gdalinfo(&dir.path().join("top.depth.tif"));
    let transform = info["geoTransform"].clone();
    assert_eq!(depth["geoTransform"], transform, "{depth}");
    let bands = depth["bands"].as_array().expect("bands");
    assert_eq!(bands.len(), 1, "{depth}");
    assert_eq!(bands[0]["type"], "UInt16", "{depth}");
    assert_eq!(bands[0]["noDataValue"], 0.0, "{depth}");
    assert_eq!(
        depth["metadata"]["IMAGE_STRUCTURE"]["COMPRESSION"], "DEFLATE",
        "{depth}"
    );
    // GDAL's scale and offset give the distance of a level as the sidecar's formula does.
    let sidecar = std::fs::read_to_string(dir.path().join("top.depth.json")).expect("sidecar");
    let sidecar: Value = serde_json::from_str(&sidecar).expect("JSON");
    let (near, far) = (sidecar["near"].as_f64(), sidecar["far"].as_f64());
    let (near, far) = (near.expect("near"), far.expect("far"));
    let scale = bands[0]["scale"].as_f64().expect("a scale");
    let offset = bands[0]["offset"].as_f64().expect("an offset");
    assert!(
        (offset + scale - near).abs() < 1e-9,
        "{offset} {scale} {near}"
    );
    assert!(
        (offset + 65535.0 * scale - far).abs() < 1e-6,
        "{offset} {scale} {far}"
    );
}

#[test]
fn only_a_top_view_is_placed_and_a_cloud_without_a_crs_says_so() {
    if !gdal_installed() {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let cloud = dir.path().join("sample.laz");
    assert_ok(&pointfarm(&[
        "sample",
        path_arg(&cloud),
        "--points",
        "20000",
    ]));

    let oblique = dir.path().join("oblique.tif");
    let output = pointfarm(&[
        "render",
        path_arg(&cloud),
        "--local",
        "--size",
        "96x64",
        "--out",
        path_arg(&oblique),
    ]);
    assert_ok(&output);
    assert!(stdout(&output).contains("TIFF frames are not georeferenced"));
    let info = gdalinfo(&oblique);
    assert!(info.get("geoTransform").is_none(), "{info}");
    assert_eq!(info["bands"].as_array().map(Vec::len), Some(4));

    let top = dir.path().join("top.tif");
    let said = render_top(&cloud, &top, "96x64", (500_000.0, 4_500_000.0), 64.0, &[]);
    assert!(said.contains("without a CRS"), "{said}");
    let info = gdalinfo(&top);
    let (x, y) = (500_000.0 - 48.0, 4_500_000.0 + 32.0);
    assert_placed_rgba(&info, (96, 64), [x, 1.0, 0.0, y, 0.0, -1.0]);
    // GDAL calls a system without keys an unnamed engineering one: no place on Earth.
    let wkt = info["coordinateSystem"]["wkt"].as_str().unwrap_or("");
    assert!(
        wkt.is_empty() || wkt.starts_with("ENGCRS[\"unnamed\""),
        "{wkt}"
    );
}

#[test]
fn a_top_view_whose_up_is_not_north_is_placed_with_its_rotation() {
    let Some((_dir, out)) = lone_star_top("rotated.tif", &["--camera-up", "1,1,0"]) else {
        return;
    };
    let center = LONE_STAR_CENTER;
    let info = gdalinfo(&out);
    let read = geotransform_of(&info);
    let [x0, col_x, row_x, y0, col_y, row_y] = read[..] else {
        panic!("{read:?}");
    };
    // Half a unit a pixel, the image's up north-east: a column steps south-east, a row
    // south-west.
    let half_diagonal = 0.5 / 2f64.sqrt();
    for (read, expected) in [
        (col_x, half_diagonal),
        (col_y, -half_diagonal),
        (row_x, -half_diagonal),
        (row_y, -half_diagonal),
    ] {
        assert!((read - expected).abs() < 1e-9, "{read} != {expected}");
    }
    // The image's centre is the target.
    let (cx, cy) = (
        x0 + 48.0 * col_x + 32.0 * row_x,
        y0 + 48.0 * col_y + 32.0 * row_y,
    );
    assert!(
        (cx - center.0).abs() < 1e-6 && (cy - center.1).abs() < 1e-6,
        "{cx} {cy}"
    );
}
