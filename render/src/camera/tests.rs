use super::*;

fn bounds() -> WorldBounds {
    WorldBounds {
        min: DVec3::new(515_000.0, 4_918_000.0, 2_000.0),
        max: DVec3::new(515_100.0, 4_918_050.0, 2_030.0),
    }
}

#[test]
fn a_camera_moved_sideways_keeps_its_direction_and_shifts_the_image() {
    let camera = Camera::auto(&bounds(), 1.5);
    let moved = camera.moved_sideways(3.0, -2.0);
    assert!((moved.target - moved.position).abs_diff_eq(camera.target - camera.position, 1e-9));
    assert!(((moved.position - camera.position).length() - 13f64.sqrt()).abs() < 1e-9);
    // The old target now shows left of the image centre and above it.
    let origin = bounds().center();
    let (x, y, _) = moved
        .transform(origin, 300, 200)
        .project(camera.target - origin)
        .expect("in view");
    assert!(x < 150.0 && y < 100.0, "{x} {y}");
}

#[test]
fn auto_camera_sees_every_corner_of_the_bounds() {
    let b = bounds();
    for (w, h) in [(1280, 720), (720, 1280), (512, 512)] {
        let camera = Camera::auto(&b, w as f64 / h as f64);
        camera.validate().expect("auto camera is valid");
        let transform = camera.transform(b.center(), w, h);
        for (i, corner) in box_corners(&b).into_iter().enumerate() {
            let (px, py, _) = transform
                .project(corner - b.center())
                .expect("inside near/far");
            assert!(
                (0.0..w as f64).contains(&px) && (0.0..h as f64).contains(&py),
                "{w}x{h}: corner {i} at ({px}, {py})"
            );
        }
    }
}

#[test]
fn a_fitted_view_centres_the_bounds_and_fills_the_frame_to_its_margin() {
    let b = bounds();
    let perspective = Projection::Perspective { fov_y_deg: 50.0 };
    let orthographic = Projection::Orthographic { height: 1.0 };
    for (w, h) in [(1280, 720), (720, 1280)] {
        for (azimuth, elevation) in [(-60.0, 30.0), (-90.0, 90.0), (0.0, 0.0), (-45.0, 35.26)] {
            for projection in [perspective, orthographic] {
                let what = format!("{w}x{h} from {azimuth}/{elevation} {projection:?}");
                let camera =
                    Camera::fitted(&b, w as f64 / h as f64, azimuth, elevation, projection);
                camera.validate().expect(&what);
                let transform = camera.transform(b.center(), w, h);
                let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
                for (i, corner) in box_corners(&b).into_iter().enumerate() {
                    let (px, py, _) = transform
                        .project(corner - b.center())
                        .unwrap_or_else(|| panic!("{what}: corner {i} clipped"));
                    lo = [lo[0].min(px), lo[1].min(py)];
                    hi = [hi[0].max(px), hi[1].max(py)];
                }
                let size = [w as f64, h as f64];
                for axis in 0..2 {
                    // Centred: as much room on both sides.
                    let (before, after) = (lo[axis], size[axis] - hi[axis]);
                    assert!(
                        (before - after).abs() < 1e-6 * size[axis],
                        "{what}: {lo:?} {hi:?}"
                    );
                    assert!(before > 0.0, "{what}: in view");
                }
                // Tight: the limiting axis leaves exactly the margin, 5% of the extent.
                let fill = (0..2)
                    .map(|axis| (hi[axis] - lo[axis]) / size[axis])
                    .fold(0.0, f64::max);
                assert!((fill - 1.0 / 1.05).abs() < 1e-6, "{what}: fills {fill}");
            }
        }
    }
}

#[test]
fn target_projects_to_the_image_centre_with_its_distance_as_depth() {
    let b = bounds();
    for projection in [
        Projection::Perspective { fov_y_deg: 40.0 },
        Projection::Orthographic { height: 10.0 },
    ] {
        let camera = Camera::framing(&b, 2.0, 10.0, 20.0, projection);
        let t = camera.transform(b.min, 200, 100);
        let (px, py, depth) = t.project(camera.target - b.min).expect("target is in view");
        assert!(
            (px - 100.0).abs() < 1e-6 && (py - 50.0).abs() < 1e-6,
            "({px}, {py})"
        );
        assert!((depth - camera.position.distance(camera.target)).abs() < 1e-6);
    }
}

#[test]
fn a_window_transform_puts_points_at_their_pixel_less_the_windows_corner() {
    let b = bounds();
    let origin = b.center();
    let (width, height) = (1000, 600);
    let window = ImageWindow {
        x0: 730,
        y0: 41,
        width: 270,
        height: 119,
    };
    for projection in [
        Projection::Perspective { fov_y_deg: 50.0 },
        Projection::Orthographic { height: 80.0 },
    ] {
        let camera = Camera::framing(&b, 1000.0 / 600.0, -60.0, 30.0, projection);
        let whole = camera.transform(origin, width, height);
        let part = camera.window_transform(origin, width, height, window);
        assert_eq!((part.width, part.height), (270, 119));
        for i in 0..8 {
            let p = DVec3::new(
                if i & 1 == 0 { -40.0 } else { 45.0 },
                if i & 2 == 0 { -20.0 } else { 22.0 },
                if i & 4 == 0 { -12.0 } else { 14.0 },
            );
            let (x, y, depth) = whole.project(p).expect("in depth range");
            let (wx, wy, window_depth) = part.project(p).expect("in depth range");
            assert!(
                (wx - (x - 730.0)).abs() < 1e-9 && (wy - (y - 41.0)).abs() < 1e-9,
                "{projection:?}: ({x}, {y}) became ({wx}, {wy})"
            );
            assert_eq!(depth, window_depth);
        }
        // The whole image as its own window is the plain transform.
        let same =
            camera.window_transform(origin, width, height, ImageWindow::whole(width, height));
        assert!(same.view_proj.abs_diff_eq(whole.view_proj, 1e-12));
    }
}

#[test]
fn up_is_up_in_the_image() {
    let b = bounds();
    let camera = Camera::auto(&b, 1.0);
    let t = camera.transform(b.center(), 100, 100);
    let (_, low_y, _) = t.project(DVec3::ZERO).expect("centre");
    let (_, high_y, _) = t.project(DVec3::new(0.0, 0.0, 5.0)).expect("above centre");
    assert!(high_y < low_y, "higher points must be nearer the top row");
}

#[test]
fn invalid_cameras_are_rejected_with_the_reason() {
    let good = Camera::auto(&bounds(), 1.0);
    let mut nan = good;
    nan.position.y = f64::NAN;
    assert_eq!(
        nan.validate(),
        Err(CameraError::NotFinite { field: "position" })
    );
    let mut same = good;
    same.target = same.position;
    assert_eq!(same.validate(), Err(CameraError::NoViewDirection));
    let mut up = good;
    up.up = good.target - good.position;
    assert_eq!(up.validate(), Err(CameraError::DegenerateUp));
    let mut depth = good;
    depth.near = 0.0;
    assert!(matches!(
        depth.validate(),
        Err(CameraError::DepthRange { .. })
    ));
    let mut fov = good;
    fov.projection = Projection::Perspective { fov_y_deg: 180.0 };
    assert_eq!(fov.validate(), Err(CameraError::FieldOfView(180.0)));
}
