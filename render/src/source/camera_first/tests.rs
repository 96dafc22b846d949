use glam::DVec3;

use super::*;
use crate::request::{Interpolation, Keyframe, Lens, Point3, PointSize, RenderOptions};

/// Tiles of 100 x 100 m, 10 m deep, `side` x `side` of them.
fn tile_boxes(side: usize) -> Vec<WorldBounds> {
    let mut boxes = Vec::new();
    for y in 0..side {
        for x in 0..side {
            let min = DVec3::new(
                500_000.0 + 100.0 * x as f64,
                4_900_000.0 + 100.0 * y as f64,
                0.0,
            );
            boxes.push(WorldBounds {
                min,
                max: min + DVec3::new(100.0, 100.0, 10.0),
            });
        }
    }
    boxes
}

fn point(p: DVec3) -> Point3 {
    Point3 {
        x: p.x,
        y: p.y,
        z: p.z,
    }
}

/// A low flight over the first row of tiles, looking along it and down.
fn flight(frames: u32, size: PointSize) -> RenderRequest {
    let key = |x: f64| Keyframe {
        position: point(DVec3::new(500_000.0 + x, 4_899_990.0, 60.0)),
        target: point(DVec3::new(500_060.0 + x, 4_900_020.0, 0.0)),
        up: point(DVec3::Z),
        fov_y_deg: 50.0,
    };
    RenderRequest {
        width: 160,
        height: 90,
        camera_path: CameraPath::Keyframes {
            keyframes: vec![key(0.0), key(150.0)],
            frames,
            interpolation: Interpolation::Linear,
        },
        lens: Lens {
            far: Some(400.0),
            ..Lens::default()
        },
        render: RenderOptions {
            point_size: size,
            ..RenderOptions::default()
        },
    }
}

#[test]
fn a_low_flight_sees_the_tiles_before_it_and_not_those_behind_or_past_the_far_plane() {
    let boxes = tile_boxes(10);
    let order = FileOrder::of(&flight(4, PointSize::Fixed(2)), &boxes).expect("a part seen");
    assert!(order.first.contains(&0), "{order:?}");
    assert!(!order.path.is_empty(), "the flight moves on: {order:?}");
    // The far row lies past the far plane.
    assert!(order.unseen.contains(&99), "{order:?}");
    assert!(order.unseen.len() > 50, "{order:?}");
    let mut all: Vec<usize> = [&order.first, &order.path, &order.unseen]
        .into_iter()
        .flatten()
        .copied()
        .collect();
    all.sort_unstable();
    assert_eq!(all, (0..100).collect::<Vec<_>>(), "each file once");
    let stages = order.stages(BuildUnseen::Never);
    assert_eq!(stages.len(), 2);
    assert_eq!(order.stages(BuildUnseen::After)[2].1.len(), 100);
}

#[test]
fn files_without_points_go_with_the_first_frame_and_frame_nothing() {
    let boxes = tile_boxes(10);
    let request = flight(4, PointSize::Fixed(2));
    let alone = FileOrder::of(&request, &boxes).expect("a part seen");
    // Two empty files, one first, where they would otherwise widen the extent the
    // frames are framed in.
    let mut with_empty = vec![WorldBounds::NOWHERE];
    with_empty.extend(boxes.iter().copied());
    with_empty.push(WorldBounds::NOWHERE);
    let order = FileOrder::of(&request, &with_empty).expect("a part seen");
    let shifted = |places: &[usize]| places.iter().map(|p| p + 1).collect::<Vec<_>>();
    let mut first = vec![0];
    first.extend(shifted(&alone.first));
    first.push(101);
    assert_eq!(order.first, first);
    assert_eq!(order.path, shifted(&alone.path));
    assert_eq!(order.unseen, shifted(&alone.unseen));
    // Empty files alone are seen by no frame and give no order: the whole store first.
    assert_eq!(FileOrder::of(&request, &[WorldBounds::NOWHERE; 3]), None);
}

/// Points of `bounds`: its corners, centre and a grid through it.
fn points_of(bounds: &WorldBounds) -> Vec<DVec3> {
    let steps = 6;
    let mut points = Vec::new();
    for i in 0..=steps {
        for j in 0..=steps {
            for k in 0..=steps {
                let t = DVec3::new(i as f64, j as f64, k as f64) / steps as f64;
                points.push(bounds.min + t * bounds.size());
            }
        }
    }
    points
}

/// Whether a point at `p` covers a pixel of the frame: within near..far, and its square of
/// `side` pixels reaching into the image.
fn draws(settings: &FrameSettings, p: DVec3, side: u32) -> bool {
    let transform = settings
        .camera
        .transform(DVec3::ZERO, settings.width, settings.height);
    let Some((x, y, _)) = transform.project(p) else {
        return false;
    };
    let half = f64::from(side) / 2.0;
    x + half >= 0.0
        && y + half >= 0.0
        && x - half <= f64::from(settings.width)
        && y - half <= f64::from(settings.height)
}

#[test]
fn no_point_of_an_unseen_file_draws_a_pixel_of_any_frame() {
    let boxes = tile_boxes(10);
    for size in [
        PointSize::Fixed(1),
        PointSize::Fixed(9),
        PointSize::Adaptive,
    ] {
        let request = flight(6, size);
        let order = FileOrder::of(&request, &boxes).expect("a part seen");
        let all = union(&boxes).expect("boxes");
        let side = match size {
            PointSize::Fixed(side) => side,
            PointSize::Adaptive => MAX_ADAPTIVE_POINT_SIZE,
        };
        let mut drawn_seen = 0;
        for index in 0..request.frames() {
            let settings = request.frame_settings(index, &Extent::whole(all), None);
            for (place, bounds) in boxes.iter().enumerate() {
                let drawing = points_of(bounds)
                    .into_iter()
                    .filter(|p| draws(&settings, *p, side))
                    .count();
                if order.unseen.contains(&place) {
                    assert_eq!(drawing, 0, "tile {place} of frame {index} at {size:?}");
                } else {
                    drawn_seen += drawing;
                }
                if index == 0 && drawing > 0 {
                    assert!(order.first.contains(&place), "tile {place} at {size:?}");
                }
            }
        }
        assert!(drawn_seen > 0);
    }
}

#[test]
fn a_path_the_headers_do_not_fix_builds_the_whole_store_first() {
    let boxes = tile_boxes(4);
    let turntable = RenderRequest::turntable(64, 48, 4);
    assert_eq!(FileOrder::of(&turntable, &boxes), None);
    let mut stretched = flight(2, PointSize::Fixed(2));
    stretched.render.color_mode = ColorMode::Elevation;
    assert_eq!(FileOrder::of(&stretched, &boxes), None, "percentiles");
    stretched.render.color_range = Some(crate::color::ColorRange {
        min: 0.0,
        max: 10.0,
    });
    assert!(FileOrder::of(&stretched, &boxes).is_some(), "a fixed range");
}

#[test]
fn the_unseen_option_reads_back_its_names() {
    for name in BuildUnseen::NAMES {
        assert_eq!(BuildUnseen::parse(name).map(BuildUnseen::name), Ok(name));
    }
    assert!(BuildUnseen::parse("later").is_err());
    assert_eq!(BuildUnseen::default(), BuildUnseen::After);
}
