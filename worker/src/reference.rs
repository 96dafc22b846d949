//! The CPU reference renderer: the oracle that every GPU mode is tested against.
//!
//! Written for clarity, not speed, and independently of the GPU passes: it shares only the
//! camera convention (`camera::CameraTransform`) and computes in f64. Every point in the view
//! covers a `point_size`-pixel square. Depths are compared as the f32 the GPU stores.
//!
//! - Basic mode: per pixel, the point with the smallest (depth, colour) pair wins. That is the
//!   documented contract of the GPU's basic mode, so where depths are distinct the images
//!   must agree exactly.
//! - High-quality mode: per pixel, the rounded average colour of every point whose depth is
//!   at most `(1 + depth_band)` times the nearest depth.

use image::RgbaImage;

use crate::cloud::PointCloud;
use crate::raster::{FrameSettings, Quality};

/// The reference's output: an image and the depth of the nearest point of each pixel.
#[derive(Debug, Clone)]
pub struct ReferenceFrame {
    pub image: RgbaImage,
    /// Linear depth per pixel, row-major; +infinity where no point landed.
    pub depth: Vec<f32>,
}

/// Renders `cloud` as `settings.quality` defines it.
pub fn render(cloud: &PointCloud, settings: &FrameSettings) -> ReferenceFrame {
    match settings.quality {
        Quality::Basic => render_basic(cloud, settings),
        Quality::High { depth_band } => render_high_quality(cloud, settings, depth_band),
    }
}

/// Calls `visit(pixel index, depth, colour)` for every pixel that every visible point covers.
fn for_each_covered_pixel(
    cloud: &PointCloud,
    settings: &FrameSettings,
    mut visit: impl FnMut(usize, f32, u32),
) {
    let (width, height) = (settings.width as i64, settings.height as i64);
    let transform = settings
        .camera
        .transform(cloud.origin, settings.width, settings.height);
    let size = settings.point_size as i64;
    for (position, &colour) in cloud.positions.iter().zip(&cloud.colors) {
        let Some((px, py, depth)) = transform.project(position.as_dvec3()) else {
            continue;
        };
        let x0 = px.floor() as i64 - (size - 1) / 2;
        let y0 = py.floor() as i64 - (size - 1) / 2;
        for y in (y0..y0 + size).filter(|y| (0..height).contains(y)) {
            for x in (x0..x0 + size).filter(|x| (0..width).contains(x)) {
                visit((y * width + x) as usize, depth as f32, colour);
            }
        }
    }
}

/// The nearest depth of each pixel (+infinity where no point landed).
fn nearest_depths(cloud: &PointCloud, settings: &FrameSettings) -> Vec<f32> {
    let mut nearest = vec![f32::INFINITY; (settings.width * settings.height) as usize];
    for_each_covered_pixel(cloud, settings, |pixel, depth, _| {
        nearest[pixel] = nearest[pixel].min(depth);
    });
    nearest
}

fn frame_from(
    settings: &FrameSettings,
    colours: Vec<Option<u32>>,
    depth: Vec<f32>,
) -> ReferenceFrame {
    let background = u32::from_le_bytes(settings.background);
    let mut image = RgbaImage::new(settings.width, settings.height);
    for (pixel, colour) in image.pixels_mut().zip(colours) {
        pixel.0 = colour.unwrap_or(background).to_le_bytes();
    }
    ReferenceFrame { image, depth }
}

/// Basic mode: the nearest point's colour; at equal depths the smallest colour word.
pub fn render_basic(cloud: &PointCloud, settings: &FrameSettings) -> ReferenceFrame {
    let mut winner: Vec<Option<(f32, u32)>> =
        vec![None; (settings.width * settings.height) as usize];
    for_each_covered_pixel(cloud, settings, |pixel, depth, colour| {
        let wins = match winner[pixel] {
            None => true,
            Some((d, c)) => depth < d || (depth == d && colour < c),
        };
        if wins {
            winner[pixel] = Some((depth, colour));
        }
    });
    let depth = winner
        .iter()
        .map(|w| w.map_or(f32::INFINITY, |(d, _)| d))
        .collect();
    frame_from(
        settings,
        winner.iter().map(|w| w.map(|(_, c)| c)).collect(),
        depth,
    )
}

/// High-quality mode: the average colour of the points within the depth band.
pub fn render_high_quality(
    cloud: &PointCloud,
    settings: &FrameSettings,
    depth_band: f32,
) -> ReferenceFrame {
    let nearest = nearest_depths(cloud, settings);
    // The band test in f32, as the GPU does it.
    let band = 1.0f32 + depth_band;
    let mut sums = vec![[0u64; 4]; nearest.len()];
    for_each_covered_pixel(cloud, settings, |pixel, depth, colour| {
        if depth <= nearest[pixel] * band {
            let [r, g, b, _] = colour.to_le_bytes();
            let sum = &mut sums[pixel];
            sum[0] += r as u64;
            sum[1] += g as u64;
            sum[2] += b as u64;
            sum[3] += 1;
        }
    });
    let average = |sum: &[u64; 4]| {
        let channel = |total: u64| (total as f64 / sum[3] as f64).round() as u8;
        u32::from_le_bytes([channel(sum[0]), channel(sum[1]), channel(sum[2]), 255])
    };
    let colours = sums
        .iter()
        .map(|s| (s[3] > 0).then(|| average(s)))
        .collect();
    frame_from(settings, colours, nearest)
}
