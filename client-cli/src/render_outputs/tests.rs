use pointfarm_render::encode::video::DEFAULT_VIDEO_QUALITY;

use super::*;

#[test]
fn a_turntable_writes_into_a_folder_or_a_pattern_never_over_one_file() {
    let folder = FrameFiles::sequence(Path::new("out/frames/")).expect("folder");
    assert_eq!(folder.frame(7), Path::new("out/frames/frame_00007.png"));
    assert_eq!(
        folder.depth(7),
        Path::new("out/frames/frame_00007.depth.png")
    );
    let bare = FrameFiles::sequence(Path::new("frames")).expect("no extension");
    assert_eq!(bare.frame(0), Path::new("frames/frame_00000.png"));
    let jpeg = FrameFiles::sequence(Path::new("shots/orbit_{:03}.JPG")).expect("pattern");
    assert_eq!(jpeg.frame(12), Path::new("shots/orbit_012.JPG"));
    assert_eq!(jpeg.format(), FrameFormat::Jpeg);
    let plain = FrameFiles::sequence(Path::new("t{}.webp")).expect("unpadded");
    assert_eq!(plain.frame(123), Path::new("./t123.webp"));

    for (out, says) in [
        ("foo.png", "names one file"),
        ("a/{:05}/f.png", "not in a folder's"),
        ("f_{:05}_{}.png", "names one file"),
        ("f_{:x}.png", "names one file"),
        ("f_{:05}.gif", "not an image format"),
    ] {
        let error = FrameFiles::sequence(Path::new(out)).expect_err(out);
        assert!(format!("{error:#}").contains(says), "{out}: {error:#}");
    }
}

#[test]
fn a_still_is_one_file_in_the_format_its_extension_names() {
    let still = FrameFiles::still(Path::new("views/top.webp")).expect("still");
    assert_eq!(still.frame(0), Path::new("views/top.webp"));
    assert_eq!(still.depth(0), Path::new("views/top.depth.png"));
    assert_eq!(still.format(), FrameFormat::WebP);
    let error = FrameFiles::still(Path::new("f_{:05}.png")).expect_err("pattern");
    assert!(error.to_string().contains("pattern"), "{error}");
    let error = FrameFiles::still(Path::new("frames/")).expect_err("a folder not made yet");
    assert!(
        error
            .to_string()
            .contains("is a folder; give an image file"),
        "{error}"
    );
    let jpeg = FrameFiles::still(Path::new("a.jpg")).expect("jpeg");
    assert!(jpeg.check_background([0, 0, 0, 0]).is_err());
    assert!(jpeg.check_background([0, 0, 0, 255]).is_ok());
}

fn request(path: &Path) -> VideoRequest {
    VideoRequest {
        path: path.to_path_buf(),
        fps: 30,
        codec: None,
        quality: DEFAULT_VIDEO_QUALITY,
        preset: VideoPreset::default(),
    }
}

#[test]
fn a_video_that_cannot_be_made_is_refused_before_anything_renders() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cases = [
        (request(&dir.path().join("turn.avi")), ".webm or .gif"),
        (
            request(&dir.path().join("absent/turn.mp4")),
            "does not exist",
        ),
        (request(dir.path()), "give a file ending"),
        (
            VideoRequest {
                codec: Some(VideoCodec::H264),
                ..request(&dir.path().join("turn.webm"))
            },
            "VP9 or AV1",
        ),
        (
            VideoRequest {
                codec: Some(VideoCodec::Vp9),
                ..request(&dir.path().join("turn.gif"))
            },
            "does not apply to a GIF",
        ),
        (
            VideoRequest {
                quality: 60,
                ..request(&dir.path().join("turn.mp4"))
            },
            "--video-quality",
        ),
        (
            VideoRequest {
                fps: 0,
                ..request(&dir.path().join("turn.mp4"))
            },
            "--fps",
        ),
    ];
    for (request, says) in cases {
        let shown = request.path.display().to_string();
        let error = request.check().expect_err(&shown);
        assert!(error.to_string().contains(says), "{shown}: {error}");
    }
}

#[test]
fn the_video_preset_given_reaches_the_videos_settings() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("turn.mp4");
    let plan = VideoRequest {
        preset: VideoPreset::Slow,
        ..request(&path)
    }
    .check_output()
    .expect("checked");
    assert_eq!(plan.settings.preset, VideoPreset::Slow);
    let default = request(&path).check_output().expect("checked");
    assert_eq!(default.settings.preset, VideoPreset::default());
}
