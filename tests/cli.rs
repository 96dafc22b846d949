//! `pointfarm render` and `pointfarm sample`, run as a user would.

use std::path::Path;

use pointfarm_tests::{own_stderr_lines, pointfarm, shared_data};

fn stdout(output: &std::process::Output) -> String {
    String::from_utf8_lossy(&output.stdout).into_owned()
}

fn assert_ok(output: &std::process::Output) {
    assert!(
        output.status.success(),
        "pointfarm failed:\n{}\n{}",
        stdout(output),
        String::from_utf8_lossy(&output.stderr)
    );
}

/// Fails unless the PNG has the size and shows something other than its background.
fn assert_rendered(path: &Path, width: u32, height: u32) {
    let image = image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgba8();
    assert_eq!(image.dimensions(), (width, height), "{}", path.display());
    let background = *image.get_pixel(0, 0);
    let drawn = image.pixels().filter(|p| **p != background).count();
    assert!(
        drawn > 1000,
        "{}: only {drawn} pixels drawn",
        path.display()
    );
}

#[test]
fn renders_a_sample_cloud_to_a_png_and_prints_the_stage_timings() {
    let dir = tempfile::tempdir().expect("tempdir");
    let laz = dir.path().join("sample.laz");
    assert_ok(&pointfarm(&[
        "sample",
        laz.to_str().expect("utf-8"),
        "--points",
        "50000",
    ]));
    let png = dir.path().join("frame.png");
    let output = pointfarm(&[
        "render",
        laz.to_str().expect("utf-8"),
        "--out",
        png.to_str().expect("utf-8"),
        "--size",
        "320x200",
        "--point-size",
        "2",
    ]);
    assert_ok(&output);
    assert_rendered(&png, 320, 200);
    let text = stdout(&output);
    for stage in ["upload", "rasterize", "resolve", "readback", "encode"] {
        assert!(text.contains(stage), "no {stage} timing in:\n{text}");
    }
}

#[test]
fn renders_a_turntable_into_a_directory() {
    let dir = tempfile::tempdir().expect("tempdir");
    let laz = dir.path().join("sample.las");
    assert_ok(&pointfarm(&[
        "sample",
        laz.to_str().expect("utf-8"),
        "--points",
        "20000",
    ]));
    let frames = dir.path().join("frames");
    let output = pointfarm(&[
        "render",
        laz.to_str().expect("utf-8"),
        "--turntable",
        "3",
        "--size",
        "160x120",
        "--atomics",
        "32",
        "--out",
        frames.to_str().expect("utf-8"),
    ]);
    assert_ok(&output);
    for i in 0..3 {
        assert_rendered(&frames.join(format!("frame_{i:04}.png")), 160, 120);
    }
    let first = std::fs::read(frames.join("frame_0000.png")).expect("frame 0");
    let second = std::fs::read(frames.join("frame_0001.png")).expect("frame 1");
    assert_ne!(
        first, second,
        "the camera must move between turntable frames"
    );
    assert!(stdout(&output).contains("median per stage"));
}

#[test]
fn renders_a_real_scan_from_a_given_camera() {
    let Some(laz) = shared_data("autzen_trim.laz") else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let png = dir.path().join("autzen.png");
    let output = pointfarm(&[
        "render",
        laz.to_str().expect("utf-8"),
        "--out",
        png.to_str().expect("utf-8"),
        "--size",
        "400x300",
        "--camera-pos",
        "636590,848300,1400",
        "--camera-target",
        "636590,849216,430",
        "--fov",
        "60",
    ]);
    assert_ok(&output);
    assert_rendered(&png, 400, 300);
}

#[test]
fn bad_input_fails_with_one_line_that_names_the_problem() {
    let dir = tempfile::tempdir().expect("tempdir");
    let not_las = dir.path().join("notes.las");
    std::fs::write(&not_las, "these are not points").expect("write");
    let out = dir.path().join("x.png");
    let out = out.to_str().expect("utf-8");
    let sample = dir.path().join("s.laz");
    assert_ok(&pointfarm(&[
        "sample",
        sample.to_str().expect("utf-8"),
        "--points",
        "1000",
    ]));
    let sample = sample.to_str().expect("utf-8");

    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec!["render", not_las.to_str().expect("utf-8"), "--out", out],
            "notes.las",
        ),
        (
            vec!["render", "/nonexistent/scan.laz", "--out", out],
            "scan.laz",
        ),
        (
            vec!["render", sample, "--out", out, "--size", "100000x100000"],
            "100000x100000",
        ),
        (
            vec!["render", sample, "--out", out, "--point-size", "0"],
            "point size",
        ),
        (
            vec![
                "render",
                sample,
                "--out",
                out,
                "--camera-pos",
                "1,2,3",
                "--camera-target",
                "1,2,3",
            ],
            "same point",
        ),
        (
            vec!["render", sample, "--out", out, "--turntable", "0"],
            "turntable",
        ),
    ];
    for (args, needle) in cases {
        let output = pointfarm(&args);
        assert!(!output.status.success(), "{args:?} succeeded");
        let lines = own_stderr_lines(&output);
        let errors: Vec<&String> = lines.iter().filter(|l| l.starts_with("error:")).collect();
        assert_eq!(
            errors.len(),
            1,
            "{args:?}: expected one error line, got {lines:?}"
        );
        assert!(
            errors[0].contains(needle),
            "{args:?}: '{}' does not mention {needle}",
            errors[0]
        );
        assert!(
            !lines.iter().any(|l| l.contains("panicked")),
            "{args:?} panicked: {lines:?}"
        );
    }

    // A NaN in a camera is refused by the argument parser, also with a clear message.
    let output = pointfarm(&["render", sample, "--out", out, "--camera-pos", "1,NaN,3"]);
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("not a finite number"));
}
