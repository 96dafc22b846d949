//! A turntable of a real scan holds its frame 0's gain, and a job's frame rendered first
//! measures it on frame 0: the frames match whatever order they come in.

use std::path::PathBuf;

use image::RgbaImage;

use super::*;
use crate::raster::Renderer;
use crate::request::{
    CameraPath, Interpolation, Keyframe, Lens, Point3, RenderOptions, Turntable, DEFAULT_UP,
};
use crate::source::quiet;
use crate::testing::{gpu, shared_data};

const FRAMES: u32 = 5;

/// An EDL turntable of `FRAMES` small frames, as `pointfarm render` draws by default.
fn turntable() -> RenderRequest {
    RenderRequest {
        width: 160,
        height: 120,
        camera_path: CameraPath::Turntable(Turntable::around_the_cloud(FRAMES)),
        lens: Lens::default(),
        render: RenderOptions::default(),
    }
}

fn open(renderer: Renderer, file: &PathBuf, request: &RenderRequest) -> FrameSource {
    FrameSource::resident(
        renderer,
        std::slice::from_ref(file),
        None,
        &request.render,
        &quiet,
    )
    .expect("the scan resident")
}

/// Every frame of `request` rendered in order, as the command line renders a turntable.
fn in_order(source: &mut FrameSource, request: &RenderRequest) -> Vec<SourceFrame> {
    (0..request.frames())
        .map(|index| {
            let settings = source.frame_settings(request, index);
            source.render(&settings, &quiet).expect("a frame")
        })
        .collect()
}

/// The real scan's turntable rendered in order from a resident source, with frame 0's gain.
struct ScanTurntable {
    file: PathBuf,
    request: RenderRequest,
    source: FrameSource,
    frames: Vec<SourceFrame>,
    gain: f32,
}

/// The scan's turntable in order, or None (having said so) where the real scans are absent.
fn scan_turntable() -> Option<ScanTurntable> {
    let file = shared_data("autzen_trim.laz")?;
    let request = turntable();
    let mut source = open(Renderer::new(gpu()), &file, &request);
    let frames = in_order(&mut source, &request);
    let gain = frames[0].frame.gain.expect("frame 0 measured its gain");
    Some(ScanTurntable {
        file,
        request,
        source,
        frames,
        gain,
    })
}

fn image(frame: &SourceFrame) -> &RgbaImage {
    &frame.frame.image
}

#[test]
fn a_turntable_rendered_in_order_holds_the_gain_of_its_frame_0() {
    let Some(ScanTurntable {
        file,
        request,
        source,
        frames,
        gain,
    }) = scan_turntable()
    else {
        return;
    };
    for (index, frame) in frames.iter().enumerate() {
        assert_eq!(frame.frame.gain, Some(gain), "frame {index}");
    }

    // Each frame measuring its own, as the first of a source of its own: the turntable's
    // views measure other gains, which the held one replaces.
    let mut renderer = source.into_renderer();
    let mut own = Vec::new();
    for index in 0..FRAMES {
        let mut alone = open(renderer, &file, &request);
        let settings = alone.frame_settings(&request, index);
        let frame = alone.render(&settings, &quiet).expect("a frame");
        own.push(frame.frame.gain.expect("its own gain"));
        if index == 0 {
            assert!(image(&frame) == image(&frames[0]), "frame 0 measures alike");
        } else if own[index as usize] != gain {
            assert!(
                image(&frame) != image(&frames[index as usize]),
                "frame {index}: another gain, the same picture"
            );
        }
        renderer = alone.into_renderer();
    }
    eprintln!("held gain {gain}; each frame's own: {own:?}");
    assert_eq!(own[0], gain);
    assert!(
        own.iter().any(|&g| g != gain),
        "every view measures the same gain: the test shows nothing"
    );

    // Another view (another size) of the same source measures its own gain; an unshaded
    // frame has none.
    let mut source = open(renderer, &file, &request);
    let _ = in_order(&mut source, &request);
    let wide = RenderRequest {
        width: 200,
        ..turntable()
    };
    let settings = source.frame_settings(&wide, 1);
    let other = source.render(&settings, &quiet).expect("another view");
    let renderer = source.into_renderer();
    let mut alone = open(renderer, &file, &wide);
    let measured = alone.render(&settings, &quiet).expect("measured alone");
    assert_eq!(other.frame.gain, measured.frame.gain);
    assert!(image(&other) == image(&measured));
    let unshaded = FrameSettings {
        shading: Shading::None,
        ..settings
    };
    assert_eq!(
        alone
            .render(&unshaded, &quiet)
            .expect("unshaded")
            .frame
            .gain,
        None
    );
}

#[test]
fn a_job_frame_rendered_first_is_exposed_with_the_gain_of_frame_0() {
    let Some(ScanTurntable {
        file,
        request,
        source: local,
        frames,
        gain,
    }) = scan_turntable()
    else {
        return;
    };

    // A worker whose first lease of the job is frame 3, then frame 1 with the gain it kept.
    let mut worker = open(local.into_renderer(), &file, &request);
    let third = worker
        .render_job_frame(&request, 3, None, &quiet)
        .expect("frame 3");
    assert_eq!(third.frame.gain, Some(gain));
    assert!(image(&third) == image(&frames[3]), "frame 3 differs");
    assert!(
        third.opened.is_some(),
        "opening the source is reported with the frame kept, not with frame 0 measured"
    );
    let first = worker
        .render_job_frame(&request, 1, Some(gain), &quiet)
        .expect("frame 1");
    assert!(image(&first) == image(&frames[1]), "frame 1 differs");
    let zero = worker
        .render_job_frame(&request, 0, None, &quiet)
        .expect("frame 0");
    assert!(image(&zero) == image(&frames[0]), "frame 0 differs");
    assert_eq!(zero.frame.gain, Some(gain));
}

#[test]
fn a_path_that_zooms_holds_one_gain_though_its_points_change_size() {
    let Some(file) = shared_data("autzen_trim.laz") else {
        return;
    };
    let mut request = turntable();
    let mut source = open(Renderer::new(gpu()), &file, &request);
    let bounds = source.bounds().all;
    let (center, radius) = (bounds.center(), bounds.radius());
    let key = |dx: f64, fov_y_deg: f64| Keyframe {
        position: Point3 {
            x: center.x + dx * radius,
            y: center.y - 2.0 * radius,
            z: center.z + radius,
        },
        target: center.into(),
        up: DEFAULT_UP,
        fov_y_deg,
    };
    request.camera_path = CameraPath::Keyframes {
        keyframes: vec![key(-0.5, 60.0), key(0.5, 25.0)],
        frames: 3,
        interpolation: Interpolation::Linear,
    };
    // Adaptive points are sized by the focal length: the frames' point sizes differ.
    let sizes: Vec<Option<f32>> = (0..3)
        .map(|index| source.frame_settings(&request, index).adaptive_size)
        .collect();
    assert!(sizes[0] != sizes[2], "{sizes:?}");
    let frames = in_order(&mut source, &request);
    let gain = frames[0].frame.gain.expect("frame 0's gain");
    for (index, frame) in frames.iter().enumerate() {
        assert_eq!(frame.frame.gain, Some(gain), "frame {index}");
    }
}
