//! The workloads: which scenes a run measures (uniform cubes, the overdraw cuboid, the real
//! scans), their names, and the views of each with their cameras.

use std::path::{Path, PathBuf};

use glam::DVec3;
use pointfarm_render::camera::{Camera, Projection};
use pointfarm_render::cloud::PointCloud;
use pointfarm_render::ingest::load_point_cloud;
use pointfarm_render::raster::FrameSettings;

use crate::clouds::{cube_bounds, shuffled_cuboid, uniform_cube, CUBE_SIDE};
use crate::{BenchError, BenchOptions};

/// Points of the uniform cloud that the targets are stated for.
pub const UNIFORM_POINTS: usize = 10_000_000;
/// The uniform clouds of the scaling series (all in view); the headline cloud is one of them.
pub const UNIFORM_SERIES: [usize; 4] = [1_000_000, 3_000_000, UNIFORM_POINTS, 30_000_000];
/// Points of the opt-in huge workload unless the run names another count.
pub const HUGE_POINTS: usize = 100_000_000;
/// Plane counts of the overdraw cuboid.
pub const CUBOID_PLANES: [usize; 4] = [1, 4, 16, 64];
/// The real scans measured when present in the data directory.
pub const REAL_SCANS: [&str; 2] = ["lone-star.laz", "autzen_trim.laz"];
/// Name of the workload whose speed-up is the headline figure.
pub const HEADLINE_WORKLOAD: &str = "uniform-10m";

/// The scenes of a run, built one at a time.
pub(crate) enum SceneSpec {
    Uniform(usize),
    Cuboid(usize),
    RealScan(PathBuf),
}

/// Name of the uniform workload of `points` points: `uniform-10m`.
pub fn uniform_workload(points: usize) -> String {
    if points.is_multiple_of(1_000_000) {
        format!("uniform-{}m", points / 1_000_000)
    } else {
        format!("uniform-{points}")
    }
}

impl SceneSpec {
    pub(crate) fn name(&self) -> String {
        match self {
            SceneSpec::Uniform(points) => uniform_workload(*points),
            SceneSpec::Cuboid(planes) => format!("cuboid-k{planes}"),
            SceneSpec::RealScan(path) => path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
        }
    }

    /// The scene, or `None` for a real scan that is not there.
    pub(crate) fn build(&self, options: &BenchOptions) -> Result<Option<Scene>, BenchError> {
        let aspect = options.rounds.width as f64 / options.rounds.height as f64;
        Ok(Some(match self {
            SceneSpec::Uniform(points) => uniform_scene(*points, aspect, 1),
            SceneSpec::Cuboid(planes) => cuboid_scene(
                *planes,
                options.cuboid_side,
                options.rounds.width,
                options.rounds.height,
                2,
            ),
            SceneSpec::RealScan(path) => return real_scene(path, aspect),
        }))
    }
}

/// A cloud and the views of it that are measured.
pub(crate) struct Scene {
    pub(crate) name: String,
    pub(crate) cloud: PointCloud,
    pub(crate) views: Vec<View>,
}

/// One measured view of a scene: its workload name and camera.
pub(crate) struct View {
    pub(crate) workload: String,
    pub(crate) description: String,
    pub(crate) camera: Camera,
}

/// Points of `cloud` that project into the image of `settings` (counted on the CPU).
pub(crate) fn points_in_view(cloud: &PointCloud, settings: &FrameSettings) -> usize {
    let t = settings
        .camera
        .transform(cloud.origin, settings.width, settings.height);
    let (w, h) = (settings.width as f64, settings.height as f64);
    cloud
        .positions
        .iter()
        .filter(|p| {
            t.project(p.as_dvec3())
                .is_some_and(|(x, y, _)| x >= 0.0 && y >= 0.0 && x < w && y < h)
        })
        .count()
}

/// `points` uniform random points in a cube, colored by position; viewed whole by the
/// automatic camera of the cube's box (the same for every cloud of the series), and, for the
/// headline cloud, from above with ~10% of the points in view.
fn uniform_scene(points: usize, aspect: f64, seed: u64) -> Scene {
    uniform_scene_with(points, aspect, seed, points == UNIFORM_POINTS)
}

fn uniform_scene_with(points: usize, aspect: f64, seed: u64, with_partial: bool) -> Scene {
    let cloud = uniform_cube(points, seed);
    let (_, bounds) = cube_bounds();
    let centre = bounds.center();
    let name = uniform_workload(points);
    let mut views = vec![View {
        workload: name.clone(),
        description: format!("{points} uniform random points in a cube, all in view"),
        camera: Camera::auto(&bounds, aspect),
    }];
    if with_partial {
        // The automatic camera moved sideways, seeing a corner of the cube: points fall as
        // densely per pixel as in the full view, so this view measures the culling alone.
        views.push(View {
            workload: format!("{name}-corner"),
            description:
                "the same cloud and camera distance, panned to a corner, ~10% of it in view".into(),
            camera: panned_to_fraction(&cloud, views[0].camera, aspect, 0.1),
        });
        // Orthographic, straight down: the view rectangle covers 10% of the cube's top face,
        // so 10% of the points (at every depth) are in view and 90% are culled. They spread
        // over the whole image, ~0.5 per pixel: nearly every one passes the depth test.
        let view_height = CUBE_SIDE * (0.1 / aspect).sqrt();
        views.push(View {
            workload: format!("{name}-partial"),
            description: "the same cloud, orthographic from above, ~10% of it in view".into(),
            camera: Camera {
                position: centre + DVec3::Z * CUBE_SIDE,
                target: centre,
                up: DVec3::Y,
                projection: Projection::Orthographic {
                    height: view_height,
                },
                near: CUBE_SIDE * 0.25,
                far: CUBE_SIDE * 1.75,
            },
        });
    }
    Scene { name, views, cloud }
}

/// `camera` moved without turning, along the diagonal of its image, until about `fraction` of
/// the points of `cloud` are in view (bisection on a sample of the points).
fn panned_to_fraction(cloud: &PointCloud, camera: Camera, aspect: f64, fraction: f64) -> Camera {
    let sample: Vec<usize> = (0..cloud.len())
        .step_by(cloud.len().div_ceil(20_000))
        .collect();
    let sample = cloud.select(&sample);
    // Towards the image's lower right corner.
    let panned = |distance: f64| {
        let step = distance * std::f64::consts::FRAC_1_SQRT_2;
        camera.moved_sideways(step, -step)
    };
    let height = 1000;
    let width = (f64::from(height) * aspect).round() as u32;
    let seen = |distance: f64| {
        let settings = FrameSettings::new(width, height, panned(distance));
        points_in_view(&sample, &settings) as f64 / sample.len().max(1) as f64
    };
    // Far enough that nothing is in view: the camera's distance to the cloud's far side.
    let (mut near, mut far) = (0.0, (camera.target - camera.position).length() * 4.0);
    for _ in 0..40 {
        let middle = 0.5 * (near + far);
        if seen(middle) > fraction {
            near = middle;
        } else {
            far = middle;
        }
    }
    panned(0.5 * (near + far))
}

/// `planes` planes of `side` x `side` points, one unit apart in every direction, in shuffled
/// order; seen face-on by an orthographic camera at one point per pixel, so every covered
/// pixel is drawn `planes` times (the overdraw workload of Schütz et al.). The upload
/// Morton-orders the points, for both methods alike.
pub(crate) fn cuboid_scene(
    planes: usize,
    side: usize,
    width: u32,
    height: u32,
    seed: u64,
) -> Scene {
    let cloud = shuffled_cuboid(planes, side, seed);
    let centre = cloud.bounds.center();
    let camera = Camera {
        position: centre + DVec3::Z * (planes as f64 + 10.0),
        target: centre,
        up: DVec3::Y,
        // One world unit per pixel.
        projection: Projection::Orthographic {
            height: height as f64,
        },
        near: 1.0,
        far: 2.0 * planes as f64 + 20.0,
    };
    let name = format!("cuboid-k{planes}");
    Scene {
        views: vec![View {
            workload: name.clone(),
            description: format!(
                "{planes} planes of {side}x{side} points, face-on, {planes}x overdraw \
                 ({width}x{height} image)"
            ),
            camera,
        }],
        name,
        cloud,
    }
}

/// A real scan from the data directory, viewed by the automatic camera; `None` if absent.
fn real_scene(path: &Path, aspect: f64) -> Result<Option<Scene>, BenchError> {
    if !path.is_file() {
        return Ok(None);
    }
    let cloud = load_point_cloud(path)?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    Ok(Some(Scene {
        views: vec![View {
            workload: name.clone(),
            description: "real scan, automatic camera".into(),
            camera: Camera::auto(&cloud.bounds, aspect),
        }],
        name,
        cloud,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cuboid_view_draws_each_pixel_once_per_plane() {
        let scene = cuboid_scene(4, 16, 64, 48, 3);
        let settings = FrameSettings::new(64, 48, scene.views[0].camera);
        // Every point is in view, on its own pixel of the 16x16 square.
        assert_eq!(points_in_view(&scene.cloud, &settings), 4 * 16 * 16);
    }

    #[test]
    fn partial_views_see_about_a_tenth_of_the_uniform_cloud() {
        let scene = uniform_scene_with(50_000, 16.0 / 9.0, 4, true);
        let full = FrameSettings::new(160, 90, scene.views[0].camera);
        assert_eq!(points_in_view(&scene.cloud, &full), 50_000);
        let names: Vec<&str> = scene.views.iter().map(|v| v.workload.as_str()).collect();
        assert_eq!(
            names,
            [
                "uniform-50000",
                "uniform-50000-corner",
                "uniform-50000-partial"
            ]
        );
        for view in &scene.views[1..] {
            let settings = FrameSettings::new(160, 90, view.camera);
            let fraction = points_in_view(&scene.cloud, &settings) as f64 / 50_000.0;
            assert!(
                (0.09..0.11).contains(&fraction),
                "{}: {fraction}",
                view.workload
            );
        }
        // The corner view keeps the full view's distance and direction: the same density of
        // points per pixel.
        let (full, corner) = (scene.views[0].camera, scene.views[1].camera);
        assert!((full.position - full.target).abs_diff_eq(corner.position - corner.target, 1e-9));
    }
}
