use glam::DVec3;

use super::*;
use crate::camera::{Projection, AUTO_AZIMUTH_DEG, AUTO_ELEVATION_DEG, DEFAULT_FOV_Y_DEG};
use crate::cloud::WorldBounds;
use crate::raster::{FillSettings, Quality, Shading};

fn bounds() -> WorldBounds {
    WorldBounds {
        min: DVec3::new(515_000.0, 4_918_000.0, 2_000.0),
        max: DVec3::new(515_100.0, 4_918_050.0, 2_030.0),
    }
}

fn request(camera_path: CameraPath) -> RenderRequest {
    RenderRequest {
        width: 64,
        height: 48,
        camera_path,
        lens: Lens::default(),
        render: RenderOptions::default(),
    }
}

fn key(x: f64) -> Keyframe {
    Keyframe {
        position: Point3 {
            x: 515_000.0 + x,
            y: 4_917_900.0,
            z: 2_050.0,
        },
        target: Point3 {
            x: 515_000.0 + x,
            y: 4_918_025.0,
            z: 2_000.0,
        },
        up: DEFAULT_UP,
        fov_y_deg: 40.0 + x / 10.0,
    }
}

fn field_of(request: &RenderRequest) -> String {
    match request.validate() {
        Err(RequestError { field, .. }) => field,
        Ok(()) => panic!("expected an invalid field"),
    }
}

#[test]
fn the_turntable_keeps_its_distance_and_centres_every_frame() {
    let b = bounds();
    let frames = 8;
    let path = request(CameraPath::Turntable(Turntable::around_the_cloud(frames)));
    let cams: Vec<Camera> = (0..frames).map(|i| path.camera(i, &b)).collect();
    // One distance in front of the box's centre along every view direction; each view panned
    // across itself to centre the box, so each looks at its own target.
    let direction = |c: &Camera| (c.position - c.target).normalize();
    let d0 = cams[0].position.distance(cams[0].target);
    for c in &cams {
        c.validate().expect("valid camera");
        assert!((c.position.distance(c.target) - d0).abs() < 1e-6 * d0);
        let ahead = (c.position - b.center()).dot(direction(c));
        assert!((ahead - d0).abs() < 1e-6 * d0, "{ahead} {d0}");
        assert!(c.target.distance(b.center()) < b.radius());
    }
    let (first, opposite) = (direction(&cams[0]), direction(&cams[frames as usize / 2]));
    assert!((opposite.x + first.x).abs() < 1e-9 && (opposite.y + first.y).abs() < 1e-9);
    // The first frame looks from the automatic view's direction.
    let auto = Camera::auto(&b, path.aspect());
    let auto_offset = auto.position - auto.target;
    assert!(first.abs_diff_eq(auto_offset.normalize(), 1e-9));
    // Every corner is in every frame, centred, and the widest frame comes near the margin.
    let (w, h) = (f64::from(path.width), f64::from(path.height));
    let mut widest: f64 = 0.0;
    for (index, c) in cams.iter().enumerate() {
        let transform = c.transform(b.center(), path.width, path.height);
        let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
        for corner in crate::camera::box_corners(&b) {
            let (x, y, _) = transform.project(corner - b.center()).expect("in depth");
            assert!(
                x > 0.0 && x < w && y > 0.0 && y < h,
                "frame {index}: ({x}, {y})"
            );
            lo = [lo[0].min(x), lo[1].min(y)];
            hi = [hi[0].max(x), hi[1].max(y)];
        }
        for (axis, size) in [w, h].into_iter().enumerate() {
            let (before, after) = (lo[axis], size - hi[axis]);
            assert!(
                (before - after).abs() < 1e-6 * size,
                "frame {index}: {lo:?} {hi:?}"
            );
        }
        widest = widest.max(((hi[0] - lo[0]) / w).max((hi[1] - lo[1]) / h));
    }
    assert!(
        widest > 0.88 && widest < 1.0 / 1.05,
        "the widest frame fills {widest}"
    );
}

#[test]
fn a_turntable_with_its_centre_and_radius_given_orbits_there() {
    let center = Point3 {
        x: 515_010.0,
        y: 4_918_020.0,
        z: 2_003.0,
    };
    let turntable = Turntable {
        center: Some(center),
        radius: Some(10.0),
        elevation_deg: 0.0,
        degrees: 90.0,
        azimuth_deg: 0.0,
        ..Turntable::around_the_cloud(4)
    };
    let r = request(CameraPath::Turntable(turntable.clone()));
    let first = r.camera(0, &bounds());
    assert!(first
        .position
        .abs_diff_eq(DVec3::new(515_020.0, 4_918_020.0, 2_003.0), 1e-9));
    let last = r.camera(3, &bounds());
    assert!((last.position.distance(center.into()) - 10.0).abs() < 1e-9);
    // Three quarters of 90 degrees counter-clockwise from +X.
    let angle = (last.position.y - center.y).atan2(last.position.x - center.x);
    assert!((angle.to_degrees() - 67.5).abs() < 1e-9, "{angle}");
    // From a given first camera: the same orbit.
    let from_start = Turntable {
        start: Some(Point3 {
            x: 515_020.0,
            ..center
        }),
        radius: None,
        elevation_deg: 45.0,
        azimuth_deg: 123.0,
        ..turntable
    };
    let r = request(CameraPath::Turntable(from_start));
    assert!(r
        .camera(3, &bounds())
        .position
        .abs_diff_eq(last.position, 1e-9));
}

#[test]
fn keyframe_paths_pass_through_their_keyframes() {
    let keys = vec![key(0.0), key(30.0), key(100.0)];
    let path = |interpolation| {
        request(CameraPath::Keyframes {
            keyframes: keys.clone(),
            frames: 5,
            interpolation,
        })
    };
    for interpolation in [Interpolation::Linear, Interpolation::Spline] {
        let r = path(interpolation);
        let x: Vec<f64> = (0..5)
            .map(|i| r.camera(i, &bounds()).position.x - 515_000.0)
            .collect();
        assert!(x[0].abs() < 1e-9 && (x[2] - 30.0).abs() < 1e-9 && (x[4] - 100.0).abs() < 1e-9);
        for i in 0..5 {
            r.camera(i, &bounds()).validate().expect("valid camera");
        }
    }
    let linear = path(Interpolation::Linear).camera(1, &bounds()).position.x - 515_000.0;
    let spline = path(Interpolation::Spline).camera(1, &bounds()).position.x - 515_000.0;
    assert!((linear - 15.0).abs() < 1e-9);
    assert!(
        (spline - linear).abs() > 0.1,
        "the spline bends: {spline} vs {linear}"
    );
}

#[test]
fn the_automatic_still_camera_is_the_fitted_automatic_view() {
    let r = request(CameraPath::Still(StillCamera::default()));
    let camera = r.camera(0, &bounds());
    let auto = Camera::fitted(
        &bounds(),
        r.aspect(),
        AUTO_AZIMUTH_DEG,
        AUTO_ELEVATION_DEG,
        Projection::Perspective {
            fov_y_deg: DEFAULT_FOV_Y_DEG,
        },
    );
    assert!(camera.position.abs_diff_eq(auto.position, 1e-6));
    assert_eq!(camera.target, auto.target);
    assert_eq!(r.frames(), 1);
}

#[test]
fn the_lens_sets_the_projection_and_the_clipping_planes() {
    let mut r = request(CameraPath::Turntable(Turntable::around_the_cloud(3)));
    r.lens = Lens {
        orthographic: true,
        ortho_height: None,
        near: Some(2.0),
        far: Some(900.0),
    };
    let camera = r.camera(1, &bounds());
    let Projection::Orthographic { height } = camera.projection else {
        panic!("not orthographic: {camera:?}");
    };
    // Fitted: at least the cloud's 30 m height, at most its diagonal with the margin.
    assert!(height > 30.0 && height < 120.0, "{height}");
    assert_eq!((camera.near, camera.far), (2.0, 900.0));
    r.lens.ortho_height = Some(12.5);
    assert_eq!(
        r.camera(0, &bounds()).projection,
        Projection::Orthographic { height: 12.5 }
    );
}

#[test]
fn frame_settings_carry_every_option() {
    let mut r = request(CameraPath::Still(StillCamera::default()));
    r.render = RenderOptions {
        point_size: PointSize::Fixed(3),
        round_points: true,
        quality: Quality::High { depth_band: 0.02 },
        shading: Shading::Edl {
            strength: 2.0,
            radius: 1.0,
        },
        color_mode: crate::color::ColorMode::Elevation,
        color_range: Some(crate::color::ColorRange {
            min: -12.5,
            max: 340.0,
        }),
        color_ramp: Some(crate::color::ColorRamp::Turbo),
        background: [1, 2, 3, 4],
        fill: Some(FillSettings { kernel: 5 }),
        supersample: 2,
        depth: true,
        lod_error: Some(0.5),
        filter: crate::filter::PointFilter::default(),
    };
    let s = r.frame_settings(0, &bounds(), Some(0.1));
    assert_eq!((s.width, s.height, s.point_size), (64, 48, 3));
    assert_eq!((s.adaptive_size, s.round_points), (None, true));
    assert_eq!(s.quality, r.render.quality);
    assert_eq!(s.shading, r.render.shading);
    assert_eq!(s.fill, r.render.fill);
    assert_eq!(s.background, [1, 2, 3, 4]);
    assert_eq!((s.supersample, s.read_depth), (2, true));
    assert_eq!(s.camera, r.camera(0, &bounds()));
}

#[test]
fn invalid_requests_name_the_field() {
    let valid = request(CameraPath::Turntable(Turntable::around_the_cloud(4)));
    assert_eq!(valid.validate(), Ok(()));
    let with = |change: &dyn Fn(&mut RenderRequest)| {
        let mut r = valid.clone();
        change(&mut r);
        field_of(&r)
    };
    let turntable = |change: &dyn Fn(&mut Turntable)| {
        with(&|r| {
            let mut t = Turntable::around_the_cloud(4);
            change(&mut t);
            r.camera_path = CameraPath::Turntable(t);
        })
    };
    assert_eq!(with(&|r| r.width = 0), "width");
    assert_eq!(
        with(&|r| r.render.lod_error = Some(f64::NAN)),
        "render.lod_error"
    );
    assert_eq!(
        with(&|r| r.render.lod_error = Some(-0.5)),
        "render.lod_error"
    );
    assert_eq!(
        with(&|r| r.render.lod_error = Some(1e6)),
        "render.lod_error"
    );
    assert_eq!(with(&|r| r.height = 0), "height");
    assert_eq!(turntable(&|t| t.frames = 0), "camera_path.turntable.frames");
    assert_eq!(
        turntable(&|t| t.center = Some(Point3 {
            x: f64::NAN,
            y: 0.0,
            z: 0.0
        })),
        "camera_path.turntable.center"
    );
    assert_eq!(
        turntable(&|t| t.radius = Some(0.0)),
        "camera_path.turntable.radius"
    );
    assert_eq!(
        turntable(&|t| t.elevation_deg = 90.0),
        "camera_path.turntable.elevation_deg"
    );
    assert_eq!(
        turntable(&|t| t.fov_y_deg = 180.0),
        "camera_path.turntable.fov_y_deg"
    );
    assert_eq!(
        with(&|r| {
            let mut bad = key(5.0);
            bad.position.y = f64::INFINITY;
            r.camera_path = CameraPath::Keyframes {
                keyframes: vec![key(1.0), bad],
                frames: 3,
                interpolation: Interpolation::Linear,
            };
        }),
        "camera_path.keyframes.keyframes[1].position"
    );
    assert_eq!(
        with(&|r| {
            r.camera_path = CameraPath::Keyframes {
                keyframes: vec![key(1.0)],
                frames: 3,
                interpolation: Interpolation::Linear,
            }
        }),
        "camera_path.keyframes.keyframes"
    );
    assert_eq!(
        with(&|r| {
            let p = Point3 {
                x: 1.0,
                y: 2.0,
                z: 3.0,
            };
            r.camera_path = CameraPath::Still(StillCamera {
                position: Some(p),
                target: Some(p),
                ..StillCamera::default()
            })
        }),
        "camera_path.still.target"
    );
    assert_eq!(
        with(&|r| r.lens.ortho_height = Some(3.0)),
        "camera_path.lens.ortho_height"
    );
    assert_eq!(
        with(&|r| {
            r.lens.near = Some(5.0);
            r.lens.far = Some(4.0);
        }),
        "camera_path.lens.far"
    );
    assert_eq!(
        with(&|r| r.render.point_size = PointSize::Fixed(0)),
        "render.point_size"
    );
    assert_eq!(
        with(&|r| r.render.quality = Quality::High {
            depth_band: f32::NAN
        }),
        "render.depth_band"
    );
    let shadings = [
        (
            Shading::Edl {
                strength: 101.0,
                radius: 1.0,
            },
            "render.edl_strength",
        ),
        (
            Shading::Edl {
                strength: 1.0,
                radius: 0.1,
            },
            "render.edl_radius",
        ),
        (
            Shading::Pintus {
                levels: 0,
                exponent: 1.0,
            },
            "render.pintus_levels",
        ),
        (
            Shading::Pintus {
                levels: 4,
                exponent: 5.0,
            },
            "render.pintus_exponent",
        ),
    ];
    for (shading, field) in shadings {
        assert_eq!(with(&|r| r.render.shading = shading), field);
    }
    for kernel in [1, 4, 11] {
        assert_eq!(
            with(&|r| r.render.fill = Some(FillSettings { kernel })),
            "render.fill.kernel"
        );
    }
    assert_eq!(with(&|r| r.render.supersample = 5), "render.supersample");
    // Cameras that could not render are refused with the request, not when a frame fails.
    assert_eq!(
        turntable(&|t| t.radius = Some(1e300)),
        "camera_path.turntable.radius"
    );
    let far_away = Point3 {
        x: 1e13,
        y: 0.0,
        z: 0.0,
    };
    assert_eq!(
        turntable(&|t| t.center = Some(far_away)),
        "camera_path.turntable.center"
    );
    let straight_down = |r: &mut RenderRequest| {
        r.camera_path = CameraPath::Still(StillCamera {
            position: Some(Point3 {
                x: 1.0,
                y: 2.0,
                z: 30.0,
            }),
            target: Some(Point3 {
                x: 1.0,
                y: 2.0,
                z: 0.0,
            }),
            ..StillCamera::default()
        })
    };
    assert_eq!(with(&straight_down), "camera_path.still.up");
    assert_eq!(
        with(&|r| {
            let mut overhead = key(5.0);
            overhead.up = Point3 {
                x: overhead.target.x - overhead.position.x,
                y: overhead.target.y - overhead.position.y,
                z: overhead.target.z - overhead.position.z,
            };
            r.camera_path = CameraPath::Keyframes {
                keyframes: vec![key(1.0), overhead],
                frames: 3,
                interpolation: Interpolation::Linear,
            };
        }),
        "camera_path.keyframes.keyframes[1].up"
    );
    let message = with_message(&valid, |r| r.render.fill = Some(FillSettings { kernel: 4 }));
    assert!(message.contains("fill kernel 4"), "{message}");
}

fn with_message(valid: &RenderRequest, change: impl Fn(&mut RenderRequest)) -> String {
    let mut r = valid.clone();
    change(&mut r);
    r.validate().expect_err("invalid").to_string()
}

#[test]
fn options_stored_before_supersampling_and_lenses_read_with_the_defaults() {
    let stored = r#"{"width":64,"height":48,
        "camera_path":{"Turntable":{"frames":2,"center":null,"radius":null,
            "elevation_deg":30.0,"degrees":360.0,"fov_y_deg":50.0}},
        "render":{"point_size":1,"quality":"Basic","shading":"None","color_mode":"Rgb",
            "background":[24,24,28,255]}}"#;
    let r: RenderRequest = serde_json::from_str(stored).expect("today's shape reads");
    // A stored size and shading stay; newer options take their defaults.
    let render = RenderOptions {
        point_size: PointSize::Fixed(1),
        shading: Shading::None,
        ..RenderOptions::default()
    };
    assert_eq!(r.render, render);
    assert_eq!(r.lens, Lens::default());
    assert_eq!(
        r.camera_path,
        CameraPath::Turntable(Turntable::around_the_cloud(2))
    );
    let round_trip: RenderRequest =
        serde_json::from_str(&serde_json::to_string(&r).expect("encodes")).expect("decodes");
    assert_eq!(round_trip, r);
}

#[test]
fn a_color_range_is_finite_ordered_and_only_for_ramped_modes() {
    use crate::color::{ColorMode, ColorRamp, ColorRange};
    let mut valid = request(CameraPath::Still(StillCamera::default()));
    valid.render.color_mode = ColorMode::Elevation;
    valid.render.color_range = Some(ColorRange {
        min: -12.5,
        max: 340.0,
    });
    valid.render.color_ramp = Some(ColorRamp::Inferno);
    assert_eq!(valid.validate(), Ok(()));
    let range = |min, max| {
        move |r: &mut RenderRequest| r.render.color_range = Some(ColorRange { min, max })
    };
    for (min, max) in [
        (f64::NAN, 1.0),
        (0.0, f64::INFINITY),
        (5.0, 5.0),
        (6.0, 5.0),
    ] {
        let mut r = valid.clone();
        range(min, max)(&mut r);
        assert_eq!(field_of(&r), "render.color_range", "{min}..{max}");
    }
    assert!(with_message(&valid, range(f64::NAN, 1.0)).contains("finite"));
    assert!(with_message(&valid, range(6.0, 5.0)).contains("below"));
    for mode in [
        ColorMode::Rgb,
        ColorMode::Classification,
        ColorMode::ReturnNumber,
        ColorMode::Fixed([1, 2, 3]),
    ] {
        let message = with_message(&valid, |r| r.render.color_mode = mode);
        assert!(
            message.starts_with("render.color_range:") && message.contains(mode.name()),
            "{message}"
        );
        let message = with_message(&valid, |r| {
            r.render.color_mode = mode;
            r.render.color_range = None;
        });
        assert!(message.starts_with("render.color_ramp:"), "{message}");
    }
    let mut intensity = valid.clone();
    intensity.render.color_mode = ColorMode::Intensity;
    assert_eq!(intensity.validate(), Ok(()));
}
