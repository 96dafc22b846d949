//! Every render option, rendered here with the render crate and through a daemon (real gRPC
//! over a loopback socket, its embedded worker) from the same request, converted as
//! `pointfarm render --server` converts it. The images must be identical: the same renderer
//! draws them on the same adapter with the same settings, so any difference is an option lost
//! or changed on the way. Each option must also change the picture, so that a dropped option
//! cannot pass.

use std::path::Path;

use image::RgbaImage;
use pointfarm_daemon::access::Access;
use pointfarm_proto::v1 as pb;
use pointfarm_render::cloud::PointCloud;
use pointfarm_render::color::{ColorMode, ColorRamp, ColorRange};
use pointfarm_render::filter::{ClipBox, CodeSet, IntensityRange};
use pointfarm_render::ingest::{load_point_cloud, write_las, LasWriteOptions};
use pointfarm_render::raster::{FillSettings, Quality, Renderer, Shading};
use pointfarm_render::request::{
    CameraPath, Interpolation, Keyframe, Lens, Point3, PointSize, RenderOptions, RenderRequest,
    StillCamera, Turntable, DEFAULT_UP,
};
use pointfarm_render::sample::sample_scene;
use pointfarm_render::source::{quiet, FrameSource};
use pointfarm_tests::service::{fetch_images, gpu, run_job, upload_file, write_sample, TestDaemon};

const WIDTH: u32 = 64;
const HEIGHT: u32 = 48;

fn still() -> RenderRequest {
    RenderRequest {
        width: WIDTH,
        height: HEIGHT,
        camera_path: CameraPath::Still(StillCamera::default()),
        lens: Lens::default(),
        render: RenderOptions::default(),
    }
}

fn with_options(change: impl FnOnce(&mut RenderOptions)) -> RenderRequest {
    let mut request = still();
    change(&mut request.render);
    request
}

/// One request per option (and per value where an option has kinds).
fn cases(cloud: &PointCloud) -> Vec<(&'static str, RenderRequest)> {
    let bounds = &cloud.bounds;
    let fitted = still().camera(0, bounds);
    let depth = fitted.far - fitted.near;
    let center = bounds.center();
    let mut intensities = cloud.intensity.clone();
    intensities.sort_unstable();
    let median_intensity = intensities[intensities.len() / 2];
    let key = |dx: f64, fov_y_deg: f64| Keyframe {
        position: Point3 {
            x: center.x + dx,
            y: center.y - 2.0 * bounds.radius(),
            z: center.z + bounds.radius(),
        },
        target: center.into(),
        up: DEFAULT_UP,
        fov_y_deg,
    };
    let keyframes = |interpolation| {
        let mut r = still();
        r.camera_path = CameraPath::Keyframes {
            keyframes: vec![key(-50.0, 40.0), key(0.0, 50.0), key(80.0, 30.0)],
            frames: 4,
            interpolation,
        };
        r
    };
    let colors = [
        ("color intensity", ColorMode::Intensity),
        ("color elevation", ColorMode::Elevation),
        ("color classification", ColorMode::Classification),
        ("color return number", ColorMode::ReturnNumber),
        ("color fixed", ColorMode::Fixed([255, 128, 0])),
    ];
    let mut cases: Vec<(&'static str, RenderRequest)> = colors
        .into_iter()
        .map(|(name, mode)| (name, with_options(|o| o.color_mode = mode)))
        .collect();
    let low = bounds.min.z + 0.2 * (bounds.max.z - bounds.min.z);
    cases.extend([
        (
            "elevation over a fixed range through a ramp",
            with_options(|o| {
                o.color_mode = ColorMode::Elevation;
                o.color_range = Some(ColorRange {
                    min: low,
                    max: bounds.max.z,
                });
                o.color_ramp = Some(ColorRamp::Turbo);
            }),
        ),
        (
            "intensity over a fixed range through a ramp",
            with_options(|o| {
                o.color_mode = ColorMode::Intensity;
                o.color_range = Some(ColorRange {
                    min: 100.0,
                    max: 2000.0,
                });
                o.color_ramp = Some(ColorRamp::Inferno);
            }),
        ),
        ("no shading", with_options(|o| o.shading = Shading::None)),
        (
            "fixed point size",
            with_options(|o| o.point_size = PointSize::Fixed(3)),
        ),
        (
            "round points",
            with_options(|o| {
                o.point_size = PointSize::Fixed(6);
                o.round_points = true;
            }),
        ),
        (
            "background",
            with_options(|o| o.background = [32, 64, 96, 255]),
        ),
        (
            "transparent background",
            with_options(|o| o.background = [0, 0, 0, 0]),
        ),
        (
            "high quality with a depth band",
            with_options(|o| {
                o.point_size = PointSize::Fixed(2);
                o.quality = Quality::High { depth_band: 0.2 };
            }),
        ),
        (
            "fill with a kernel",
            with_options(|o| o.fill = Some(FillSettings { kernel: 5 })),
        ),
        (
            "edl with parameters",
            with_options(|o| {
                o.shading = Shading::Edl {
                    strength: 3.0,
                    radius: 2.0,
                }
            }),
        ),
        (
            "pintus with parameters",
            with_options(|o| {
                o.shading = Shading::Pintus {
                    levels: 4,
                    exponent: 2.0,
                }
            }),
        ),
        ("supersample", with_options(|o| o.supersample = 2)),
        ("orthographic", {
            let mut r = still();
            r.lens.orthographic = true;
            r
        }),
        ("orthographic with a height", {
            let mut r = still();
            r.lens.orthographic = true;
            r.lens.ortho_height = Some(bounds.radius());
            r
        }),
        ("near and far", {
            let mut r = still();
            r.lens.near = Some(fitted.near + 0.3 * depth);
            r.lens.far = Some(fitted.far - 0.3 * depth);
            r
        }),
        ("a turntable", {
            let mut r = still();
            r.camera_path = CameraPath::Turntable(Turntable {
                elevation_deg: 45.0,
                degrees: 180.0,
                fov_y_deg: 40.0,
                ..Turntable::around_the_cloud(3)
            });
            r
        }),
        ("a turntable from a given camera", {
            let mut r = still();
            r.camera_path = CameraPath::Turntable(Turntable {
                center: Some(center.into()),
                start: Some(key(0.0, 50.0).position),
                ..Turntable::around_the_cloud(2)
            });
            r
        }),
        ("linear keyframes", keyframes(Interpolation::Linear)),
        ("spline keyframes", keyframes(Interpolation::Spline)),
        ("a given still camera", {
            let mut r = still();
            r.camera_path = CameraPath::Still(StillCamera {
                position: Some(key(30.0, 50.0).position),
                target: Some(center.into()),
                up: Point3 {
                    x: 0.2,
                    y: 0.0,
                    z: 1.0,
                },
                fov_y_deg: 35.0,
                ..StillCamera::default()
            });
            r
        }),
        (
            "filter by class",
            with_options(|o| o.filter.classes = Some(CodeSet::of([2, 11]))),
        ),
        (
            "filter by return number",
            with_options(|o| o.filter.return_numbers = Some(CodeSet::of([1, 3]))),
        ),
        (
            "filter by intensity",
            with_options(|o| {
                o.filter.intensity = Some(IntensityRange {
                    min: 0,
                    max: median_intensity,
                })
            }),
        ),
        (
            "filter by a clip box",
            with_options(|o| {
                o.filter.clip = Some(ClipBox {
                    min: bounds.min.to_array(),
                    max: [center.x, center.y, bounds.max.z],
                })
            }),
        ),
        ("the automatic view from above", {
            let mut r = still();
            r.camera_path = CameraPath::Still(StillCamera {
                azimuth_deg: -90.0,
                elevation_deg: 90.0,
                ..StillCamera::default()
            });
            r
        }),
    ]);
    cases
}

/// Every frame of `request` of the dataset of `file`, rendered here as `pointfarm render`
/// renders it: through the frame source, resident.
fn render_here(
    renderer: Renderer,
    file: &Path,
    request: &RenderRequest,
) -> (Vec<RgbaImage>, Renderer) {
    request.validate().expect("a valid request");
    let files = [file.to_path_buf()];
    let mut source = FrameSource::resident(renderer, &files, None, &request.render, &quiet)
        .expect("the dataset resident");
    let images = (0..request.frames())
        .map(|index| {
            let settings = source.frame_settings(request, index);
            source
                .render(&settings, &quiet)
                .expect("render")
                .frame
                .image
        })
        .collect();
    (images, source.into_renderer())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_option_renders_the_same_here_and_through_the_service() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let file = scratch.path().join("sample.las");
    let mut sample = sample_scene(20_000, 11);
    // First to third returns, for the return filter.
    for (i, number) in sample.return_number.iter_mut().enumerate() {
        *number = 1 + (i % 3) as u8;
    }
    write_las(&file, &sample, &LasWriteOptions::default()).expect("write the sample");
    let cloud = load_point_cloud(&file).expect("load the sample");
    let daemon = TestDaemon::start(|_| {}, Access::default()).await;
    let dataset = upload_file(&mut daemon.datasets().await, "sample.las", &file).await;
    let mut jobs = daemon.jobs().await;
    let (mut plain, mut renderer) = render_here(Renderer::new(gpu()), &file, &still());
    let plain = plain.remove(0);

    for (name, request) in cases(&cloud) {
        let (here, used) = render_here(renderer, &file, &request);
        renderer = used;
        assert!(
            here.iter().all(|image| *image != plain),
            "{name}: the option does not change the picture"
        );
        let finished = run_job(&mut jobs, &dataset.id, name, request).await;
        assert_eq!(
            finished.state,
            pb::JobState::Succeeded as i32,
            "{name}: {}",
            finished.error
        );
        let there = fetch_images(&mut jobs, &finished.id, 0).await;
        assert_eq!(there.len(), here.len(), "{name}: frames");
        for ((index, image), local) in there.iter().zip(&here) {
            assert!(
                image == local,
                "{name}: frame {index} from the service differs from the local one"
            );
        }
    }
    daemon.stop().await;
}

#[test]
fn the_depth_image_is_rendered_here() {
    // The service has no depth output: `pointfarm render --server` refuses --depth (tested
    // in cli.rs); here the request's option reaches the renderer.
    let scratch = tempfile::tempdir().expect("tempdir");
    let file = scratch.path().join("sample.las");
    write_sample(&file, 5_000, 12);
    let cloud = load_point_cloud(&file).expect("load the sample");
    let request = with_options(|o| o.depth = true);
    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(&cloud).expect("upload");
    let frame = renderer
        .render(
            &resident,
            &request.frame_settings(0, &cloud.bounds, cloud.spacing()),
        )
        .expect("render");
    let depth = frame.depth.expect("a depth image");
    assert_eq!(depth.len(), (WIDTH * HEIGHT) as usize);
    let camera = request.camera(0, &cloud.bounds);
    let seen = |d: &f32| d.is_finite() && (camera.near..=camera.far).contains(&(*d as f64));
    assert!(depth.iter().any(seen), "no point in the depth image");
}
